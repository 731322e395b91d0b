"""Benchmark: control periods per wall second of Chen case 1 (6 cars, 1 ms) for each way of
running the same nodes, printed as ratios against the in-process engine measured in this same
process (the baseline), so the figures compare across noisy shared machines.

    python bench/bench_run.py [--duration 1.0] [--repeat 3]
"""
from __future__ import annotations

import argparse
import statistics
import tempfile
import time
from pathlib import Path

from canbrake.run import run_scenario
from canbrake.scenario import load_scenario

CASE1 = Path(__file__).resolve().parents[1] / "scenarios" / "chen2023_case1_fine_rail.yaml"


def ticks_per_s(backend: str, duration: float, extra: dict | None = None) -> float:
    scn = load_scenario(CASE1, overrides={"duration_s": duration, **(extra or {})})
    with tempfile.TemporaryDirectory() as d:
        s = run_scenario(scn, Path(d), backend=backend, plots=False)
        if s["status"] != "ok":
            raise SystemExit(f"{backend}: {s['message']}")
        # the plant's own loop time (process start-up excluded) where it is known
        wall = s["ticks"] * scn.control_period_s / s["real_time_factor"] if s.get("real_time_factor") else s["wall_time_s"]
        return s["ticks"] / wall


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__)
    ap.add_argument("--duration", type=float, default=1.0)
    ap.add_argument("--repeat", type=int, default=3)
    a = ap.parse_args()
    cases = [("inprocess (baseline)", "inprocess", None), ("virtual", "virtual", None),
             ("memory, 8 processes", "memory", None),
             ("inprocess + timing model", "inprocess", {"bus": {"timing": "model"}})]
    res = {}
    for name, backend, extra in cases:
        vals = [ticks_per_s(backend, a.duration, extra) for _ in range(a.repeat)]
        res[name] = statistics.median(vals)
    base = res["inprocess (baseline)"]
    print(f"{'how':28s} {'ticks/s':>9s} {'ratio':>7s}")
    for name, v in res.items():
        print(f"{name:28s} {v:9.0f} {v / base:7.2f}")


if __name__ == "__main__":
    t0 = time.time()
    main()
    print(f"({time.time() - t0:.0f} s)")
