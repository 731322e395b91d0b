"""`canbrake bench`: throughput of every backend on a scenario, as ratios to the in-process engine."""
from __future__ import annotations

import argparse
from typing import Any


def _cmd(a: argparse.Namespace) -> int:
    from canbrake.benchmark import run_benchmark
    from canbrake.scenario import load_scenario

    scn = load_scenario(a.scenario, overrides={"duration_s": a.duration})
    print(f"{'how':32s} {'ticks/s':>9s} {'ratio':>7s}")
    for name, tps, ratio in run_benchmark(scn, a.repeat):
        print(f"{name:32s} {tps:9.0f} {ratio:7.2f}")
    return 0


def register(sub: Any) -> None:
    p = sub.add_parser("bench", help="measure throughput of every backend",
                       description="Control periods per second of each backend, as ratios to the in-process engine.")
    p.add_argument("scenario", nargs="?", default="scenarios/chen2023_case1_fine_rail.yaml")
    p.add_argument("--duration", type=float, default=1.0, help="simulated seconds per run")
    p.add_argument("--repeat", type=int, default=3)
    p.set_defaults(func=_cmd)
