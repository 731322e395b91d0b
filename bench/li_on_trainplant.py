"""Issue 27: a Li 2024 scenario run by this tree (on TrainPlant) and by a reference tree (default
/work/main, whose Li trains ran on the heavy-haul model; ``--coupled`` forces this tree's run onto
the coupled kernel, for a tree that still had the other), compared column by column: the largest |difference| of
every signals.csv column (per-vehicle and per-coupler columns grouped under their name), and
the locomotive speed RMSE and coupler-force peaks of canbrake.report.li2024.reduce_run.

    python bench/li_on_trainplant.py [--scenario li2024_pid] [--duration 930] [--ref /work/main]
        [--ref-python /work/venv-dev/bin/python] [--out /tmp/li-tp] [--coupled]

Each run is the CLI's in-process run (``canbrake run --bus inprocess --no-plots --seed 7``), so both
trees record the same columns as far as their plants measure the same things; a column only one
of them has is listed by name. Prints one line per column group and a summary JSON line.
"""
from __future__ import annotations

import argparse
import csv
import json
import os
import re
import subprocess
import sys
import time
from pathlib import Path
from typing import Any

import numpy as np

HERE = Path(__file__).resolve().parents[1]


#: run the CLI with every train lowered onto the coupled kernel (TrainPlant), for a tree that still has another
FORCE_COUPLED = ("import sys; from canbrake.consist import components as C; "
                 "C.TrainSpec._choose_kernel = lambda self, ex: 'coupled'; "
                 "from canbrake.cli import main; sys.exit(main(sys.argv[1:]))")


def run(tree: Path, python: str, scenario: str, duration: float, out: Path, coupled: bool = False) -> float:
    """One in-process CLI run of ``scenario`` by the code in ``tree`` (``coupled``: forced onto the
    coupled kernel); returns its CPU time (s)."""
    scn = tree / "scenarios" / f"{scenario}.yaml"
    cmd = [python, *(["-c", FORCE_COUPLED] if coupled else ["-m", "canbrake"]), "run", str(scn), "--bus",
           "inprocess", "--duration", str(duration), "--no-plots", "--seed", "7", "--out", str(out)]
    env = dict(os.environ, PYTHONPATH=str(tree))
    t0 = os.times()
    p = subprocess.run(cmd, env=env, cwd="/tmp", capture_output=True, text=True)
    t1 = os.times()
    if p.returncode != 0:
        raise SystemExit(f"{tree}: {scenario} failed ({p.returncode}): {p.stderr.strip()[-500:]}")
    return (t1.children_user - t0.children_user) + (t1.children_system - t0.children_system)


def columns(path: Path) -> tuple[list[str], np.ndarray]:
    """signals.csv's header and its values (NaN where empty or not a number)."""
    with open(path, newline="") as f:
        r = csv.reader(f)
        head = next(r)
        rows = list(r)

    def num(x: str) -> float:
        try:
            return float(x)
        except ValueError:
            return float("nan")

    return head, np.array([[num(x) for x in row] for row in rows], dtype=float).reshape(len(rows), len(head))


def compare(a: Path, b: Path) -> tuple[dict[str, float], list[str], list[str]]:
    """Per column group (``speed_mps_c12`` -> ``speed_mps``, ``coupler_force_n_k3`` -> ``coupler_force_n``):
    the largest |a − b| over the common rows (NaN in both counts as equal); and the columns only in
    a, only in b."""
    ha, va = columns(a)
    hb, vb = columns(b)
    n = min(len(va), len(vb))
    out: dict[str, float] = {}
    for j, name in enumerate(ha):
        if name not in hb:
            continue
        xa, xb = va[:n, j], vb[:n, hb.index(name)]
        both = np.isnan(xa) & np.isnan(xb)
        d = np.where(both, 0.0, np.abs(xa - xb))
        group = re.sub(r"_[ck]\d+$", "", name)
        m = float(np.max(d)) if d.size else 0.0  # NaN where only one of them is NaN
        out[group] = m if np.isnan(m) or group not in out else max(out[group], m)
    return out, [h for h in ha if h not in hb], [h for h in hb if h not in ha]


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--scenario", default="li2024_pid")
    ap.add_argument("--duration", type=float, default=60.0)
    ap.add_argument("--ref", type=Path, default=Path("/work/main"), help="the reference tree (built in place)")
    ap.add_argument("--ref-python", default="/work/venv-dev/bin/python")
    ap.add_argument("--out", type=Path, default=Path("/tmp/li-tp"))
    ap.add_argument("--coupled", action="store_true", help="force this tree's run onto the coupled kernel")
    a = ap.parse_args()
    ref_out, our_out = a.out / f"{a.scenario}-ref", a.out / f"{a.scenario}-this"
    t0 = time.perf_counter()
    cpu_ref = run(a.ref, a.ref_python, a.scenario, a.duration, ref_out)
    cpu_this = run(HERE, sys.executable, a.scenario, a.duration, our_out, a.coupled)
    diff, only_ref, only_this = compare(ref_out / "signals.csv", our_out / "signals.csv")
    print(f"{a.scenario}, {a.duration:g} s: max |this - ref| per signals.csv column")
    for k, v in diff.items():
        print(f"  {k:32s} {v:.3g}")
    strip = lambda cols: sorted({re.sub(r"_[ck]\d+$", "", c) for c in cols})  # noqa: E731
    if only_ref or only_this:
        print(f"  columns only in ref: {strip(only_ref)}; only here: {strip(only_this)}")
    from canbrake.report.li2024 import reduce_run
    from canbrake.scenario import load_scenario

    period = load_scenario(str(HERE / "scenarios" / f"{a.scenario}.yaml")).control_period_s
    summary: dict[str, Any] = {"scenario": a.scenario, "duration_s": a.duration,
                               "cpu_ref_s": round(cpu_ref, 2), "cpu_this_s": round(cpu_this, 2),
                               "wall_s": round(time.perf_counter() - t0, 1),
                               "max_abs_diff": {k: v for k, v in diff.items() if v != 0.0}}
    r0, r1 = reduce_run(ref_out, period), reduce_run(our_out, period)
    for key in ("rmse_kmh", "max_tension_n", "max_compression_n"):
        if key in r0 and key in r1:
            summary[f"d_{key}"] = float(r1[key]) - float(r0[key])
    print(json.dumps(summary))


if __name__ == "__main__":
    main()
