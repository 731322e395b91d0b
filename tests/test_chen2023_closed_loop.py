"""Closed-loop tests of Chen 2023 on Table 2, through the node engine (plant node, one ECU node per
car, every value over CAN frames of the generated DBC) at the paper's 1 ms period.

Table 2 comes from scenarios/chen2023_case*.yaml. With the in-process bus and no impairment the
ECUs see the state of the same tick (ideal communication, as in the paper) quantised by the DBC:
speeds 1e-4 m/s, positions 1e-4 m, brake forces 10 N.
"""
from __future__ import annotations

import math

import numpy as np
import pytest

from canbrake.build import build_controller, build_plant_model
from canbrake.bus.signals import signal_format
from canbrake.scenario import KMH

from chen_runs import ChenTrace, chen_scenario, run_engine

CASE1 = chen_scenario(1, duration_s=0.5)
M = CASE1.vehicle_masses_kg()
DT = CASE1.control_period_s
A_REF = CASE1.reference.decel_mps2
K = CASE1.controller.params["k"]  # Chen's tracking gain (1/s)
Q_SPEED = signal_format("speed_mps").scale  # m/s per bit of a speed on the bus
_OBS = build_controller(CASE1, 1)._obs
#: the observer's gain on its speed error inside the boundary layer, γ2/b (1/s): it turns the ECU's
#: speed quantisation (±Q_SPEED/2) into an estimate error of up to γ2/b · Q_SPEED/2 (m/s²)
OBS_GAIN = _OBS.gamma2_mps2 / _OBS.boundary_vel_mps


def run(params=None, *, ctrl=None, duration=1.0, case=1, **overrides) -> ChenTrace:
    """Chen case ``case`` for ``duration`` s; ``params`` replace the file's controller params
    (``ctrl``: another controller) or, without ``ctrl``, are merged into them."""
    sets = dict(overrides.pop("set", {}))
    if ctrl is not None:
        sets["controller"] = {"name": ctrl, "params": params or {}}
    else:
        sets.update({f"controller.params.{k}": v for k, v in (params or {}).items()})
    return run_engine(chen_scenario(case, duration_s=duration, set=sets, **overrides))


@pytest.fixture(scope="module")
def case1(tmp_path_factory) -> ChenTrace:
    return run_engine(CASE1, tmp_path_factory.mktemp("case1"))


def true_disturbance_mps2(r: ChenTrace) -> np.ndarray:
    """φ_i/m_i = (Φ_{i−1} − Φ_i − f_i(v_i)) / m_i from the trace (f: the plant's running resistance)."""
    resistance = build_plant_model(r.scn).plant.resistance
    z = np.zeros((r.t_s.size, 1))
    f = np.array([resistance.magnitude_n(v) for v in r.speed_mps])
    return (np.hstack([z, r.coupler_force_n]) - np.hstack([r.coupler_force_n, z]) - f) / r.mass_kg


def test_case1_paper_profile_meets_the_claims(case1):
    assert case1.max_abs_deflection_m() < 0.01  # ±1 cm throughout
    t_conv = case1.convergence_time_s(0.5 * KMH)
    assert t_conv < 0.04  # paper: < 0.04 s (we get ≈ 0.012 s to 0.5 km/h)
    assert case1.convergence_time_s(0.1 * KMH) < 0.1
    # Final error: the ideal loop (exact state) reached < 0.001 km/h. Over CAN the ECU reads its speed
    # to ±Q/2, and the observer turns that into φ̂ noise of up to OBS_GAIN·Q/2 (0.025 m/s²) that the
    # tracking loop (gain k) leaves as a speed error of up to OBS_GAIN·Q/2/k: the floor is
    # Q/2 + OBS_GAIN·Q/2/k ≈ 7e-4 m/s (0.0027 km/h; ~3e-4 m/s seen). Without the observer the
    # running resistance alone leaves 1.8e-3 m/s (the ablation test).
    floor = Q_SPEED / 2 + OBS_GAIN * Q_SPEED / 2 / K
    assert np.max(np.abs(case1.speed_error_mps[-1])) < floor
    # the price: an ideal actuator braking at hundreds of m/s²
    assert np.nanmax(np.abs(case1.command_n) / M) > 100.0


def test_case1_observer_converges_within_20ms(case1):
    # the last row is the final state, with no control step (no estimate)
    err = (case1.diag("observer_accel_mps2") - true_disturbance_mps2(case1))[:-1]
    k20, k50 = int(round(0.02 / DT)), int(round(0.05 / DT))
    # |φ/m| ≈ 0.07 m/s² (mostly Davis resistance). The ideal loop (exact state) held |error| < 0.003
    # after 20 ms and < 0.0005 after 50 ms; over CAN every tick's estimate carries the speed
    # quantisation, up to OBS_GAIN·Q/2 = 0.025 m/s² (≈ 0.008 seen), which averages out: the bound
    # after 20 ms is that noise bound, and the 0.0005 bound holds for the mean error of each car.
    assert np.max(np.abs(err[k20:])) < OBS_GAIN * Q_SPEED / 2
    assert np.max(np.abs(np.mean(err[k50:], axis=0))) < 0.0005


def test_sampled_loop_zero_order_hold():
    r = run({"kp": 2.0}, ctrl="pi", duration=0.01)
    cmd, app = r.command_n[:-1], r.applied_force_n
    expected = M * (A_REF + 2.0 * r.speed_error_mps[:-1])  # from the state at the same tick
    # the ECU sees v, v* and a* quantised by the DBC (half a step each: 1e-4 m/s, 1e-4 m/s²) and
    # sends the force in 10 N steps
    q = Q_SPEED  # REFERENCE's RefSpeed and RefDecel have the same 1e-4 step
    tol = M * (2.0 * q + q / 2) + signal_format("brake_force_n").scale / 2 + 1e-6
    assert np.all(np.abs(cmd - expected) <= tol)
    # the state one tick earlier would not do: m·kp·|Δv| per tick exceeds the tolerance
    assert np.any(np.abs(cmd[1:] - expected[:-1]) > 2 * tol)
    np.testing.assert_array_equal(app[1:], cmd)  # held over the next period


def test_ablation_without_observer_leaves_the_resistance_offset(case1):
    r = run({"observer": False}, duration=0.5)  # the same length as case1
    # steady error = −(f/m)/k with f the running resistance: ≈ −0.0065 km/h
    expected = np.mean(true_disturbance_mps2(r)[-1]) / K
    assert np.mean(r.speed_error_mps[-1]) == pytest.approx(expected, rel=0.05)
    assert abs(np.mean(case1.speed_error_mps[-1])) < 0.05 * abs(expected)
    # printed k_d = 50 on an acceleration behaves as no observer at all
    r_kd = run({"observer_cancellation": "kd"}, duration=0.5)
    assert np.mean(r_kd.speed_error_mps[-1]) == pytest.approx(expected, rel=0.05)


def test_ablation_potential_field_alone_loses_the_bound_without_consensus():
    """Without the consensus term the barrier alone cannot absorb Table 2's 8.5 km/h speed spread:
    |Δl| passes 1 cm within 20 ms and reaches tens of centimetres by 0.1 s. This is the converged
    result: the same to < 1 % with the plant step a quarter as long. (A plant that moved each car
    h²a/2 too far per step under the ~1000 m/s² of the ideal brake showed 0.775 cm here: an artefact.)"""
    field_only = {"consensus": False}
    r1 = run(field_only, duration=0.1)
    r4 = run(field_only, duration=0.1, set={"plant.substeps": 4})
    d1, d4 = r1.max_abs_deflection_m(), r4.max_abs_deflection_m()
    assert d1 > 0.1  # ≈ 28 cm: tens of centimetres, not within ±1 cm
    assert d1 == pytest.approx(d4, rel=0.01)
    first = [float(r.t_s[np.argmax(np.max(np.abs(r.deflection_m), axis=1) > 0.01)]) for r in (r1, r4)]
    assert first[0] < 0.03 and first[0] == pytest.approx(first[1], abs=DT)
    neither = run({"consensus": False, "potential_field": False}, duration=0.1)
    assert neither.max_abs_deflection_m() > 0.02
    # in case 1 the consensus term alone keeps |Δl| ≈ 1.3 mm: the barrier (wall at 1 cm) is never near it
    no_barrier = run({"potential_field": False}, duration=0.3)
    assert no_barrier.max_abs_deflection_m() < 0.002


def test_case1_max_deflection_is_step_converged():
    """Case 1's max |Δl| over the transient (0.1 s): 0.1338 cm at one sub-step per 1 ms period and at
    four. Independent check: the old plant (plain semi-implicit Euler, first order in h) gave 0.1312 cm
    at 32 and 0.1325 cm at 64 sub-steps, whose Richardson extrapolation 2·0.1325 − 0.1312 = 0.1338 cm
    is the converged value; the trapezoidal rule for held forces reaches it with one step."""
    r1 = run(duration=0.1)
    r4 = run(duration=0.1, set={"plant.substeps": 4})
    assert r1.max_abs_deflection_m() == pytest.approx(0.001338, rel=0.005)
    assert r4.max_abs_deflection_m() == pytest.approx(r1.max_abs_deflection_m(), rel=0.002)


def test_literal_readings_fail_the_claims():
    assert run({"mass_scaled": False}, duration=0.3).max_abs_deflection_m() > 0.01
    lit = run({"feedforward": "velocity"}, duration=0.3)
    assert np.min(np.abs(lit.speed_error_mps[-1])) > 1.0 * KMH
    pi = run({}, ctrl="pi", duration=0.3)  # no communication
    assert pi.max_abs_deflection_m() > 0.02


# the paper's case 2 (skid at 3.5 s for 1 s, scenarios/chen2023_case2_poor_rail.yaml), shifted to
# 0.1 s to keep the test short
CASE2_SHIFT = {"events.0.start_s": 0.1, "events.0.stop_s": 1.1}


def test_case2_followers_track_car3_then_recover():
    r = run(duration=1.4, case=2, set=CASE2_SHIFT)
    k = int(round(1.1 / DT))
    e = r.speed_error_mps[k]
    assert np.all(e > 1.0 * KMH)  # nobody tracks v* during the skid ...
    assert np.ptp(e) < 0.05 * KMH  # ... they all follow car 3
    assert r.max_abs_deflection_m() < 0.01
    assert r.convergence_time_s(0.5 * KMH, 1.1) < 0.06  # paper: ≈ 0.03 s
    assert np.max(np.abs(r.speed_error_mps[-1])) < 0.05 * KMH
    # without the observer's state anti-windup (a limit of 1e12 m/s: none) the whole train brakes too hard for seconds
    wound = run({"observer_error_limit_mps": 1e12}, duration=1.4, case=2, set=CASE2_SHIFT)
    assert np.all(wound.speed_error_mps[-1] < -0.05 * KMH)


def test_case3_observer_rejects_the_sinusoidal_disturbance():
    # case 3's 20 kN 1 Hz disturbance (scenarios/chen2023_case3_disturbance.yaml) from 0.1 s, on
    # fine rail; judged after 0.15 s (5.4 time constants 1/k) over 0.55 s (> half a period)
    dist = chen_scenario(3, duration_s=1.0).events[1].model_dump()
    dist["start_s"] = 0.1
    with_obs = run(duration=0.8, case=3, set={"events": [dist]})
    without = run({"observer": False}, duration=0.8, case=3, set={"events": [dist]})
    w = with_obs.window(0.25)
    e_with = np.max(np.abs(with_obs.speed_error_mps[w]))
    e_without = np.max(np.abs(without.speed_error_mps[w]))
    assert e_without > 10 * e_with
    amp = dist["amplitude_n"] / np.mean(M)  # ≈ 1 m/s² per car
    w_hz = 2 * math.pi * dist["frequency_hz"]
    assert e_without == pytest.approx(amp / math.hypot(K, w_hz), rel=0.15)  # |1/(s+k)| at 1 Hz


def test_realistic_profile_runs_and_cannot_hold_one_centimetre():
    # the scenario's realistic profile: 10 ms ECU cycle, 0.3 s brake lag, 1 m/s³ jerk, ratings
    r = run(duration=1.0, profile="realistic")
    rating = r.scn.actuator.max_brake_decel_mps2
    assert np.all(np.isfinite(r.speed_mps))
    assert np.max(np.abs(r.applied_force_n) / M) <= rating + 1e-9
    assert r.max_abs_deflection_m() > 0.1  # tens of centimetres from the paper's initial speeds
    # from consistent initial speeds the same loop stays within a few millimetres
    calm = run(duration=1.0, profile="realistic", set={"initial.speed_kmh": r.scn.reference.speed_kmh})
    assert calm.max_abs_deflection_m() < 0.01
