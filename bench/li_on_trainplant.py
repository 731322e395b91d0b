"""Experiment (issue 27, not a shipped behaviour): run one of Li 2024's scenarios with its train lowered
onto the coupled plant (TrainPlant) instead of the heavy-haul model, at the scenario's integration step
h and at h/4, and compare the locomotive's speed RMSE against v_ref and the coupler-force peaks.

    python bench/li_on_trainplant.py [--scenario li2024_pid] [--duration 60] [--out /tmp/li-tp]

The lowering is the component schema's coupled one (``TrainSpec._lower_coupled``: Li's draft gears,
air brake, per-weight resistance, envelopes, adhesion limit, route, static couplers, δ, eq. 40),
reached by choosing the coupled kernel for this process only; Li's scenarios otherwise still go to
the heavy-haul kernel. Prints one JSON object per run and a summary table.
"""
from __future__ import annotations

import argparse
import json
import time
from pathlib import Path
from typing import Any

import numpy as np


def run(scenario: str, kernel: str, h: float, duration: float, out: Path) -> dict[str, Any]:
    """One in-process run on ``kernel`` ("heavy_haul" or "coupled") at integration step ``h`` (s)."""
    from canbrake.consist import components as C
    from canbrake.report.li2024 import reduce_run
    from canbrake.run import run_scenario
    from canbrake.scenario import load_scenario

    orig = C.TrainSpec._choose_kernel
    if kernel == "coupled":
        C.TrainSpec._choose_kernel = lambda self, ex: "coupled"  # type: ignore[method-assign]
    try:
        scn = load_scenario(scenario, overrides={"duration_s": duration, "train.integration_step_s": h})
    finally:
        C.TrainSpec._choose_kernel = orig  # type: ignore[method-assign]
    assert scn.train.kernel_name == kernel, scn.train.kernel_name
    t0, c0 = time.perf_counter(), time.process_time()
    s = run_scenario(scn, out, backend="inprocess", plots=False)
    wall, cpu = time.perf_counter() - t0, time.process_time() - c0
    if s["status"] != "ok":
        raise SystemExit(f"{kernel} h={h}: {s['status']}: {s.get('message')}")
    r = reduce_run(out, scn.control_period_s)
    nan = np.array(np.nan)  # a run whose locomotive ECU tracks no speed (a brake test) has no RMSE
    return {"kernel": kernel, "h_s": h, "wall_s": round(wall, 2), "cpu_s": round(cpu, 2), "rmse_kmh": float(r.get("rmse_kmh", nan)),
            "err_min_kmh": float(r.get("err_min_kmh", nan)), "err_max_kmh": float(r.get("err_max_kmh", nan)),
            "max_tension_kn": float(r["max_tension_n"]) / 1e3, "max_compression_kn": float(r["max_compression_n"]) / 1e3,
            "max_tension_where": int(r["max_tension_where"]), "max_compression_where": int(r["max_compression_where"]),
            "_v": r["v_mps"], "_fmax": r["coupler_max_tension_n"], "_fmin": r["coupler_max_compression_n"]}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--scenario", default="li2024_pid")
    ap.add_argument("--duration", type=float, default=60.0)
    ap.add_argument("--out", type=Path, default=Path("/tmp/li-tp"))
    ap.add_argument("--h", type=float, default=0.01, help="the scenario's integration step (s)")
    a = ap.parse_args()
    res = []
    for kernel in ("heavy_haul", "coupled"):
        for h in (a.h, a.h / 4):
            r = run(a.scenario, kernel, h, a.duration, a.out / f"{kernel}-h{h * 1000:g}ms")
            res.append(r)
            print(json.dumps({k: v for k, v in r.items() if not k.startswith("_")}), flush=True)
    by = {(r["kernel"], r["h_s"]): r for r in res}
    print(f"\n{a.scenario}, {a.duration:g} s: coupled minus heavy-haul at the same step")
    print("| step | d RMSE (km/h) | d max tension (kN) | d max compression (kN) | max |dv_loco| (km/h) | "
          "max |d max tension(t)| (kN) |")
    for h in (a.h, a.h / 4):
        hh, cp = by[("heavy_haul", h)], by[("coupled", h)]
        n = min(hh["_v"].size, cp["_v"].size)
        dv = float(np.abs(hh["_v"][:n] - cp["_v"][:n]).max()) * 3.6
        dft = float(np.abs(hh["_fmax"][:n] - cp["_fmax"][:n]).max()) / 1e3
        print(f"| {h * 1000:g} ms | {cp['rmse_kmh'] - hh['rmse_kmh']:+.4g} | "
              f"{cp['max_tension_kn'] - hh['max_tension_kn']:+.4g} | "
              f"{cp['max_compression_kn'] - hh['max_compression_kn']:+.4g} | {dv:.3g} | {dft:.4g} |")


if __name__ == "__main__":
    main()
