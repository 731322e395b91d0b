"""Li 2024's shipped trains on the coupled plant (TrainPlant) against the heavy-haul model they ran
on before it was deleted (issue 27): every Li scenario's first 40 s, in-process.

``tests/data/li_hh_ref.npz`` holds, per scenario, the heavy-haul runs' speeds, coupler forces and
brake cylinder pressures of every vehicle every 2 s, recorded from main (5c9f895, HeavyHaulModel)
by this file's ``__main__`` (``PYTHONPATH=/work/main /work/venv-dev/bin/python
tests/test_li_reference.py``). The two plants integrate the same equations in the same order of
steps (bench/li_on_trainplant.py); they sum the forces in a different order, and the draft gears'
2e8 N/m stiffness and the controllers' CAN quantisation carry those rounding differences along.
Tolerances: speeds 1e-6 m/s, coupler forces 1e-5 of the run's largest |force| (at most a few N of
hundreds of kN), cylinder pressures 1 Pa (of 4.5e5).
"""
from __future__ import annotations

import sys
import tempfile
from pathlib import Path

import numpy as np
import pytest

HERE = Path(__file__).resolve().parent
REF = HERE / "data" / "li_hh_ref.npz"
SCENARIOS = ("li2024_pid", "li2024_smc", "li2024_rbfnn_smc", "li2024_rbfnn_smc_ndo", "li2024_driver",
             "li2024_ecp_over_can", "hh106_ecp_consensus")
DURATION_S, EVERY_S = 40.0, 2.0
SIGNALS = ("speed_mps", "coupler_force_n", "brake_cylinder_pressure_pa")


def record(name: str) -> dict[str, np.ndarray]:
    """``name``'s first :data:`DURATION_S` s in-process: each of :data:`SIGNALS` per vehicle (or
    coupler) every :data:`EVERY_S` s, rows (times, vehicles), from signals.csv."""
    import csv

    from canbrake.run import run_scenario
    from canbrake.scenario import load_scenario

    scn = load_scenario(str(HERE.parent / "scenarios" / f"{name}.yaml"), overrides={"duration_s": DURATION_S})
    with tempfile.TemporaryDirectory() as tmp:
        s = run_scenario(scn, Path(tmp) / "run", backend="inprocess", plots=False)
        assert s["status"] == "ok", s
        with open(Path(tmp) / "run" / "signals.csv", newline="") as f:
            r = csv.reader(f)
            head = next(r)
            rows = list(r)
    t = np.array([float(row[head.index("t_s")]) for row in rows])
    keep = [i for i, ti in enumerate(t) if abs(ti / EVERY_S - round(ti / EVERY_S)) < 1e-6 and ti > 0]
    out = {}
    for sig in SIGNALS:
        cols = [j for j, h in enumerate(head) if h.rsplit("_", 1)[0] == sig and h.rsplit("_", 1)[1][1:].isdigit()]
        out[f"{name}:{sig}"] = np.array([[float(rows[i][j]) for j in cols] for i in keep])
    return out


@pytest.mark.parametrize("name", SCENARIOS)
def test_li_scenarios_on_the_coupled_plant_agree_with_the_former_heavy_haul_model(name: str) -> None:
    ref = np.load(REF)
    got = record(name)
    for sig in SIGNALS:
        a, b = ref[f"{name}:{sig}"], got[f"{name}:{sig}"]
        assert a.shape == b.shape and a.shape[0] == round(DURATION_S / EVERY_S), (sig, a.shape, b.shape)
        tol = {"speed_mps": 1e-6, "coupler_force_n": 1e-5 * np.abs(a).max(), "brake_cylinder_pressure_pa": 1.0}[sig]
        np.testing.assert_allclose(b, a, rtol=0, atol=tol, err_msg=f"{name}: {sig}")


if __name__ == "__main__":
    data: dict[str, np.ndarray] = {}
    for n in SCENARIOS:
        data.update(record(n))
        print(n, {k: v.shape for k, v in data.items() if k.startswith(n + ":")}, file=sys.stderr)
    np.savez_compressed(REF, **data)
