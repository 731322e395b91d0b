"""The coupled plant's rigid coupling with driven axles (TrainPlant, Cai 2014) against the former
adhesion plant (AdhesionTrain, deleted since): bit for bit, over the rail schedule's switches.

``tests/data/rigid_train_ref.npz`` holds AdhesionTrain's measurements of the two runs below at every
1000th step, recorded from it before its deletion (commit "TrainPlant: rigid coupling ...", where
this file's ``__main__`` recorded it and the test compared the two plants live).
"""
from __future__ import annotations

from pathlib import Path

import numpy as np

from canbrake.physics.resistance import DavisResistance
from canbrake.physics.train import TrainPlant
from canbrake.physics.wheel_adhesion import DrivenAxles, RailCondition, RailSchedule, RailWindow

REF = Path(__file__).parent / "data" / "rigid_train_ref.npz"
DRY = RailCondition(b1=1.786, b2=40.0, b3=10.0, c1=0.040, c2=3.78, c3=33.3, peak_mu0=0.35)
WET = RailCondition(b1=2.046, b2=15.0, b3=10.0, c1=0.060, c2=12.9, c3=72.2, peak_mu0=0.25)


def _axles(loads: list[float], J: float = 80.0, R: float = 0.495) -> DrivenAxles:
    k = len(loads)
    return DrivenAxles(np.asarray(loads, dtype=float), np.full(k, J), np.full(k, R))


#: (masses kg, Davis (n, 3), tables, axles per vehicle, rail, curve, initial speed m/s, position m,
#:  sub-steps, steps, torque range N·m)
CASES = {
    "cai2014": ([48e3, 48e3], [[203.5, 145.8, 3.35]] * 2, None,
                [_axles([117.6e3 * (1 + d) for d in (0.015, -0.015, 0.025, -0.025)]), None],
                RailSchedule(WET, (RailWindow(DRY, 50.0, 100.0),)), "paper", 0.0, 0.0, 1, 55_000, (-2000.0, 12000.0)),
    "mixed": ([40e3, 30e3, 45e3], [[100.0, 50.0, 2.0], [0.0, 0.0, 0.0], [150.0, 60.0, 3.0]],
              [None, ([0.0, 10.0, 40.0], [200.0, 500.0, 2500.0]), ([5.0, 30.0], [100.0, 900.0])],
              [_axles([100e3, 98e3]), None, _axles([110e3, 111e3, 109e3], J=60.0, R=0.46)],
              RailSchedule(DRY, (RailWindow(WET, 1.0, 2.0), RailWindow(DRY, 1.5, 4.0))), "physical", 20.0, 12.5, 3,
              5_000, (-9000.0, 9000.0)),
}


def _commands(rng: np.random.Generator, n: int, lo: float, hi: float) -> dict[str, np.ndarray]:
    return {f"axle{j}_torque_nm": np.where(rng.random(n) < 0.1, np.nan, rng.uniform(lo, hi, n)) for j in range(1, 4)}


def _train_plant(case: str) -> TrainPlant:
    m, davis, tables, axles, rail, curve, v0, x0, sub, _steps, _tq = CASES[case]
    d = np.asarray(davis, dtype=float)
    n = len(m)
    return TrainPlant(m, np.full(n, x0), np.full(n, v0), resistance=DavisResistance(d[:, 0], d[:, 1], d[:, 2]),
                      resistance_table=tables, rigid=True, driven_axles=axles, rail_schedule=rail,
                      adhesion_curve=curve, max_substep_s=1e-3 / sub)


def _run(case: str, step, measure) -> dict[str, np.ndarray]:
    """Rows of every measurement at every 1000th step (and the last), stacked."""
    m, *_r, steps, (lo, hi) = CASES[case]
    rng = np.random.default_rng(7)
    rows: dict[str, list[np.ndarray]] = {}
    for k in range(steps):
        step(_commands(rng, len(m), lo, hi))
        if k % 1000 == 0 or k == steps - 1:
            for name, a in measure().items():
                rows.setdefault(name, []).append(np.array(a, dtype=float))
    return {f"{case}:{name}": np.stack(v) for name, v in rows.items()}


def _rigid(case: str) -> dict[str, np.ndarray]:
    p = _train_plant(case)
    return _run(case, lambda c: p.step(1e-3, None, axle_torque_nm=p.axle_torques(c)), p.rigid_measurements)


def test_rigid_train_plant_equals_the_former_adhesion_plant_bit_for_bit():
    ref = np.load(REF)
    got: dict[str, np.ndarray] = {}
    for case in CASES:
        got.update(_rigid(case))
    assert sorted(got) == sorted(ref.files)
    for name in ref.files:
        np.testing.assert_array_equal(got[name], ref[name], err_msg=name)  # NaN equals NaN here


def test_rigid_train_restarts_from_its_initial_state():
    p = _train_plant("mixed")
    first = _run("mixed", lambda c: p.step(1e-3, None, axle_torque_nm=p.axle_torques(c)), p.rigid_measurements)
    p.reset()
    again = _run("mixed", lambda c: p.step(1e-3, None, axle_torque_nm=p.axle_torques(c)), p.rigid_measurements)
    for name in first:
        np.testing.assert_array_equal(first[name], again[name])

