"""scenarios/emu8_example.yaml: an 8-car EMU of vehicle types (4 motor, 4 trailer cars) braking with a
realistic actuator, run briefly through the in-process node engine."""
from __future__ import annotations

import numpy as np

from canbrake.analysis.metrics import settling_time_s
from canbrake.analysis.summary import read_signals
from canbrake.run import run_scenario
from canbrake.scenario import KMH, load_scenario

from conftest import SCENARIOS


def test_emu8_example_brakes_within_its_actuator_and_tracks_the_reference(tmp_path):
    scn = load_scenario(SCENARIOS / "emu8_example.yaml", overrides={"duration_s": 2.0})
    assert scn.n_cars == scn.n_ecus == 8 and scn.control_period_s == 0.01
    masses = scn.vehicle_masses_kg()
    motor = np.array([2, 3, 6, 7]) - 1  # Tc-M-M-T-T-M-M-Tc
    assert np.all(masses[motor] > np.delete(masses, motor).max())
    s = run_scenario(scn, tmp_path, backend="inprocess", plots=False)
    assert s["status"] == "ok", s["message"]
    assert s["frames"]["commands_missed"] == 0
    c = read_signals(tmp_path / "signals.csv")
    cars = range(1, scn.n_cars + 1)
    applied = np.column_stack([c[f"brake_applied_n_c{i}"] for i in cars]) / masses  # m/s²
    speed = np.column_stack([c[f"speed_mps_c{i}"] for i in cars])
    a = scn.actuator
    # the brake never exceeds its rating nor its jerk limit
    assert np.max(applied) <= a.max_brake_decel_mps2 + 1e-9
    assert np.max(np.abs(np.diff(applied, axis=0))) <= a.jerk_limit_mps3 * scn.control_period_s + 1e-9
    # the reference decelerates from t = 0; the brake needs a*/J (jerk) plus its lag to build up, so
    # the cars fall behind, and then the controller brings every car within 0.5 km/h
    a_ref = scn.reference.decel_mps2
    build_up_s = a_ref / a.jerk_limit_mps3 + a.lag_s
    err = speed - c["ref_speed_mps"][:, None]
    assert np.max(err) > 0.5 * KMH
    t_conv = settling_time_s(c["t_s"], err, 0.5 * KMH)
    assert t_conv is not None and build_up_s < t_conv < 2 * build_up_s
    defl = np.column_stack([c[f"deflection_m_k{j}"] for j in range(1, scn.n_cars)])
    assert np.max(np.abs(defl)) < 0.01

