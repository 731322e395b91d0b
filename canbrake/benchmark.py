"""Throughput of the ways of running the same nodes, as ratios against the in-process engine
measured in the same process (so the figures compare across noisy shared machines)."""
from __future__ import annotations

import statistics
import tempfile
from pathlib import Path
from typing import Any

from canbrake.run import run_scenario
from canbrake.scenario import Scenario

CASES: list[tuple[str, str, dict[str, Any] | None]] = [
    ("inprocess (baseline)", "inprocess", None),
    ("virtual (python-can)", "virtual", None),
    ("memory, one process per node", "memory", None),
    ("inprocess + CAN timing model", "inprocess", {"timing": "model"}),
]


def ticks_per_s(scn: Scenario, backend: str, bus_overrides: dict[str, Any] | None = None) -> float:
    """Control periods per wall second of the plant's loop (process start-up excluded)."""
    if bus_overrides:
        scn = scn.model_copy(update={"bus": scn.bus.model_copy(update=bus_overrides)})
    with tempfile.TemporaryDirectory() as d:
        s = run_scenario(scn, Path(d), backend=backend, plots=False)
    if s["status"] != "ok":
        raise RuntimeError(f"{backend}: {s['message']}")
    rtf = s.get("real_time_factor")
    wall = s["ticks"] * scn.control_period_s / rtf if rtf else s["wall_time_s"]
    return s["ticks"] / wall


def run_benchmark(scn: Scenario, repeat: int = 3) -> list[tuple[str, float, float]]:
    """(name, median ticks/s, ratio to the baseline) for every case; rounds alternate the cases."""
    vals: dict[str, list[float]] = {name: [] for name, _, _ in CASES}
    for _ in range(repeat):
        for name, backend, bus in CASES:
            vals[name].append(ticks_per_s(scn, backend, bus))
    base = statistics.median(vals[CASES[0][0]])
    return [(name, statistics.median(v), statistics.median(v) / base) for name, v in vals.items()]
