"""Cai et al. 2014: adhesion physics, the plant model, observers, the four control cases through the
node engine, the report.

Closed-form checks where the physics gives one; the case ordering asserted here is what
docs/reproduction/cai2014.md reports from the full 200 s runs (section "Claims").
"""
from __future__ import annotations

import math
import subprocess
import sys

import numpy as np
import pytest

from canbrake.control.base import Observation, make_controller
from canbrake.control.cai2014 import (
    PAPER_GAINS,
    AdhesionForceObserver,
    LumpedDisturbanceObserver,
    ResistanceObserver,
)
from canbrake.physics.wheel_adhesion import WheelSet, adhesion_coefficient, slip_ratio
from canbrake.scenario import load_scenario
from conftest import SCENARIOS

R, J, N = 0.495, 80.0, 117.6e3
CASE_FILE = str(SCENARIOS / "cai2014_case{}.yaml")


def _scenario(case: int = 1, profile: str | None = None, **overrides):
    return load_scenario(CASE_FILE.format(case), profile=profile, overrides=overrides)


def _conditions():
    from canbrake.physics.wheel_adhesion import RailCondition

    conds = _scenario(1).consist.wheel_rail.conditions
    return RailCondition(**conds["dry"].model_dump()), RailCondition(**conds["wet"].model_dump())


DRY, WET = _conditions()


# ------------------------------------------------------------------------------ adhesion physics
def test_free_rolling_wheel_has_zero_slip_and_zero_force():
    v = np.array([0.0, 1.0, 30.0, 55.6])
    lam = slip_ratio(v / R, v, R)
    assert np.all(lam == 0.0)  # also at standstill: the floored denominator avoids 0/0
    for variant in ("paper", "physical"):
        assert np.all(adhesion_coefficient(lam, v, WET, variant) == 0.0)
    ws = WheelSet(np.full(2, N), J, R, np.full(2, 20.0 / R))
    _, _, fa = ws.adhesion(20.0, DRY)
    assert np.all(fa == 0.0)


def test_slip_definition_traction_braking_and_standstill():
    assert slip_ratio(np.array([11.0 / R]), 10.0, R)[0] == pytest.approx(0.1 / 1.1 * 1.0, rel=1e-12)
    assert slip_ratio(np.array([9.0 / R]), 10.0, R)[0] == pytest.approx(-0.1, rel=1e-12)
    # standstill, wheel spinning at 0.05 m/s: denominator floored at 0.1 m/s
    assert slip_ratio(np.array([0.05 / R]), 0.0, R)[0] == pytest.approx(0.5)


@pytest.mark.parametrize("which", ["dry", "wet"])
def test_adhesion_coefficient_matches_eqs_13_to_15(which):
    cond = DRY if which == "dry" else WET
    lam, v = 0.01, 40.0
    curve = cond.b1 * (1 - math.exp(-cond.b2 * lam)) - lam / cond.b3
    speed = (cond.c1 + cond.c2 / (cond.c3 + v)) / (cond.c1 + cond.c2 / cond.c3)
    assert adhesion_coefficient(np.array(lam), v, cond, "paper") == pytest.approx(speed * curve, rel=1e-12)
    assert adhesion_coefficient(np.array(-lam), v, cond, "paper") == pytest.approx(-speed * curve, rel=1e-12)


def test_printed_curve_is_unphysical_and_physical_variant_peaks_where_chosen():
    lam = np.linspace(0, 1, 20001)
    for cond in (DRY, WET):
        mu_paper = adhesion_coefficient(lam, 0.0, cond, "paper")
        assert mu_paper.max() > 1.5  # printed peak ≈ b1: far above any wheel on rail
        mu_phys = adhesion_coefficient(lam, 0.0, cond, "physical")
        assert mu_phys.max() == pytest.approx(cond.peak_mu0, rel=1e-6)
        assert lam[np.argmax(mu_phys)] == pytest.approx(cond.peak_slip, abs=1e-4)
    assert DRY.mu_max(0.0) < WET.mu_max(0.0)  # as printed, "dry" is less adhesive than wet


def test_rail_switches_to_dry_only_inside_window():
    rail = _scenario(1).consist.wheel_rail.schedule()
    assert rail.at(49.999) == WET and rail.at(50.0) == DRY
    assert rail.at(100.0) == DRY and rail.at(100.001) == WET


@pytest.mark.parametrize("variant", ["paper", "physical"])
def test_steady_slip_under_constant_torque_gives_analytic_mu(variant):
    """Body speed held, constant torque below the peak: ω settles where μ(λ) N R = T."""
    torque = np.array([1000.0, 2000.0, 4000.0])
    ws = WheelSet(np.full(3, N), J, R, np.full(3, 30.0 / R), variant=variant)
    for _ in range(200):
        fa = ws.step(torque, 30.0, WET, 1e-2)
    np.testing.assert_allclose(fa, torque / R, rtol=1e-6)
    lam = slip_ratio(ws.omega_radps, 30.0, R)
    mu_expected = torque / (R * N)
    np.testing.assert_allclose(adhesion_coefficient(lam, 30.0, WET, variant), mu_expected, rtol=1e-6)
    assert np.all(lam > 0) and np.all(np.diff(lam) > 0)


# ------------------------------------------------------------------------------ the plant model and the consist
def _train(variant: str = "paper"):
    return _scenario(1, "physical" if variant == "physical" else None).consist


def _fd(v: float) -> float:
    """The paper's train resistance F_d(v) = 407 + 291.6 v + 6.7 v² N (v > 0)."""
    return 407.0 + 291.6 * v + 6.7 * v * v


class _Rigid:
    """The paper's train as a run builds it (the coupled plant's rigid coupling with driven axles,
    behind the plant contract), with the body's state as numbers."""

    def __init__(self, variant: str = "paper", speed_mps: float = 0.0, substeps: int = 1, dt_s: float = 1e-3) -> None:
        """``dt_s``: the control period, the length of each step (s), in ``substeps`` sub-steps."""
        from canbrake.build import build_plant_model

        scn = _scenario(1, "physical" if variant == "physical" else None, control_period_s=dt_s,
                        **{"initial.speed_kmh": speed_mps * 3.6, "plant.substeps": substeps})
        self.model = build_plant_model(scn)
        self.plant = self.model.plant  # canbrake.physics.train.TrainPlant
        self.command_names = self.model.command_names
        self.wheels = self.plant.driven  # the driven axles' WheelSet

    def step(self, dt_s: float, commands: dict) -> None:
        self.model.step(dt_s, commands)

    def measurements(self) -> dict:
        return self.model.measurements()

    @property
    def speed_mps(self) -> float:
        return float(self.plant.speed_mps[0])

    @property
    def position_m(self) -> float:
        return float(self.plant.position_m[0])

    @property
    def time_s(self) -> float:
        return self.plant.time_s


def test_consist_describes_the_papers_train():
    cfg = _train()
    assert cfg.vehicle_count() == 2 and cfg.axle_counts() == [4, 0] and cfg.rigid
    np.testing.assert_array_equal(cfg.vehicle_masses_kg(), [48e3, 48e3])
    plant = _Rigid()
    assert plant.command_names == tuple(f"axle{j}_torque_nm" for j in range(1, 5))
    np.testing.assert_allclose(plant.wheels.normal_load_n, 117.6e3 * (1 + np.array([0.015, -0.015, 0.025, -0.025])))
    # the train's resistance is the paper's 407 + 291.6 v + 6.7 v² N, split over two vehicles
    res = plant.measurements()["resistance_n"]
    assert res.tolist() == [0.0, 0.0]  # at standstill: the constant term opposes motion only
    plant = _Rigid(speed_mps=10.0)
    assert plant.measurements()["resistance_n"].sum() == pytest.approx(_fd(10.0), rel=1e-12)


def test_scenario_errors_name_the_field(tmp_path):
    import yaml

    from canbrake.scenario import ScenarioError

    data = yaml.safe_load(open(CASE_FILE.format(1)).read())
    data["train"]["wheel_rail"]["windows"][0]["condition"] = "icy"
    p = tmp_path / "bad.yaml"
    p.write_text(yaml.safe_dump(data))
    with pytest.raises(ScenarioError, match=r"bad.yaml: train.wheel_rail: windows.0.condition: unknown rail condition 'icy'"):
        load_scenario(p)
    data = yaml.safe_load(open(CASE_FILE.format(1)).read())
    del data["train"]["vehicle_types"]["locomotive"]["wheels"]["wheel"]
    p.write_text(yaml.safe_dump(data))
    with pytest.raises(ScenarioError, match=r"locomotive.*axles.0: no wheel"):
        load_scenario(p)


def test_four_case_scenarios_differ_only_in_the_case():
    import yaml

    docs = [yaml.safe_load(open(CASE_FILE.format(c)).read()) for c in (1, 2, 3, 4)]
    for c, d in enumerate(docs, start=1):
        assert d["ecus"][0]["controller"]["params"]["case"] == c
        assert d["profiles"]["printed_sign"]["ecus"][0]["controller"]["params"]["case"] == c
        for k in ("name", "description"):
            d.pop(k)
        d["ecus"][0]["controller"]["params"].pop("case")
        d["profiles"]["printed_sign"]["ecus"][0]["controller"]["params"].pop("case")
    assert all(d == docs[0] for d in docs[1:])


def test_plant_measurements_per_vehicle_and_rigid_coupler_force():
    """Constant torque on the locomotive: the carriage has no axles (NaN), NaN commands are no torque,
    and the rigid coupling carries what the carriage needs, C = −(m₂ a + F_d,2) (tension < 0)."""
    plant = _Rigid(speed_mps=20.0, dt_s=5e-3)
    dt = 5e-3
    for _ in range(400):
        plant.step(dt, {f"axle{j}_torque_nm": np.array([5000.0, np.nan]) for j in range(1, 5)})
    m = plant.measurements()
    assert np.isnan(m["axle1_speed_radps"][1]) and np.isfinite(m["axle4_slip"][0])
    assert m["position_m"][0] == m["position_m"][1] and m["speed_mps"][0] == m["speed_mps"][1]
    fa = np.array([m[f"axle{j}_adhesion_n"][0] for j in range(1, 5)])
    assert m["applied_brake_n"][0] == pytest.approx(-fa.sum()) and m["applied_brake_n"][1] == 0.0
    a = m["accel_mps2"][0]
    assert m["coupler_force_n"][0] == pytest.approx(-(48e3 * a + m["resistance_n"][1]), rel=1e-3)
    assert m["deflection_m"].tolist() == [0.0]
    # settled wheels: the adhesion force equals T/R minus the wheel's inertia force
    np.testing.assert_allclose(fa, 5000.0 / R - J * a / R ** 2, rtol=2e-3)


def test_constant_torque_on_flat_track_matches_analytic_acceleration():
    """Wheels + body: once slip settles, a = (Σ T/R − F_d(v)) / (m + Σ J/R²)."""
    plant = _Rigid(dt_s=5e-3)
    cmd = {f"axle{j}_torque_nm": np.array([6000.0, np.nan]) for j in range(1, 5)}
    dt, vs = 5e-3, []
    for _ in range(2000):  # 10 s
        plant.step(dt, cmd)
        vs.append(plant.speed_mps)
    v1, v2 = vs[-201], vs[-1]  # the last second
    a_meas = (v2 - v1) / 1.0
    a_expected = (4 * 6000.0 / R - _fd(0.5 * (v1 + v2))) / (96e3 + 4 * J / R ** 2)
    assert a_meas == pytest.approx(a_expected, rel=2e-3)
    lam = slip_ratio(plant.wheels.omega_radps, v2, R)
    assert np.all((lam > 0) & (lam < 0.01))  # the wheels roll with a small positive slip


def test_implicit_step_solves_its_equations_from_standstill():
    """One 5 ms step from rest with a large torque: the new (ω, v) satisfy the backward-Euler equations."""
    for variant in ("paper", "physical"):
        plant = _Rigid(variant, dt_s=5e-3)
        ws, dt = plant.wheels, 5e-3
        plant.step(dt, {f"axle{j}_torque_nm": np.array([8000.0, np.nan]) for j in range(1, 5)})
        v = plant.speed_mps
        fa = ws.adhesion(v, WET)[2]
        res_w = J * ws.omega_radps - dt * (8000.0 - fa * R)
        res_v = 96e3 * v - dt * (np.sum(fa) - _fd(v))
        assert np.max(np.abs(res_w)) < 1e-6 * J * np.max(ws.omega_radps)
        assert abs(res_v) < 1e-6 * 96e3 * v
        assert v > 0 and np.all(ws.omega_radps * R > v)
        assert plant.position_m == pytest.approx(0.5 * dt * v)  # trapezoid from rest


def test_plant_step_count_time_and_substeps():
    plant = _Rigid(dt_s=0.1)
    for _ in range(500):
        plant.step(0.1, {})
    assert plant.time_s == 50.0  # counted, not summed (Σ 0.1 ≠ 50): the rail switch falls on t = 50 s
    assert sum([0.1] * 500) != 50.0
    fine = _Rigid(speed_mps=30.0, substeps=5, dt_s=5e-3)
    coarse = _Rigid(speed_mps=30.0, dt_s=5e-3)
    cmd = {"axle1_torque_nm": np.array([4000.0, np.nan])}
    for _ in range(200):
        fine.step(5e-3, cmd)
        coarse.step(5e-3, cmd)
    assert fine.speed_mps == pytest.approx(coarse.speed_mps, rel=1e-4) and fine.speed_mps != coarse.speed_mps


# ------------------------------------------------------------------------------ observers and the controller
def test_adhesion_observer_converges_with_time_constant_one_over_g():
    g, dt, force = PAPER_GAINS.g, 1e-3, 3000.0
    obs = AdhesionForceObserver(g, J, R, 1)
    torque = np.array([2000.0])
    omega = np.array([10.0])
    wdot = (torque - force * R) / J  # wheel with a known constant adhesion force
    est = []
    for _ in range(int(round(3 / g / dt))):
        new = omega + wdot * dt
        obs.update(torque, omega, new, dt)
        omega = new
        est.append(obs.estimate_n[0])
    k_tau = int(round(1 / g / dt)) - 1
    assert est[k_tau] == pytest.approx(force * (1 - math.exp(-1)), rel=1e-9)
    assert est[-1] == pytest.approx(force * (1 - math.exp(-3)), rel=1e-9)


@pytest.mark.parametrize("which", ["resistance", "lumped"])
def test_train_observers_converge_to_a_constant_disturbance(which):
    g, dt, m, dist = 10.0, 1e-3, 96e3, 5000.0
    torque = np.full(4, 4000.0)
    acc = (np.sum(torque) / R - dist) / m  # body with a constant disturbance, wheels not accelerating
    v, w = 5.0, np.full(4, 5.0 / R)
    obs = ResistanceObserver(g, m, J, R) if which == "resistance" else LumpedDisturbanceObserver(g, m, R)
    est = []
    for _ in range(int(round(1.0 / dt))):
        v_new = v + acc * dt
        if which == "resistance":
            obs.update(torque, v, v_new, w, w, dt)
        else:
            obs.update(torque, v, v_new, dt)
        v = v_new
        est.append(obs.estimate_n)
    assert est[int(round(1 / g / dt)) - 1] == pytest.approx(dist * (1 - math.exp(-1)), rel=1e-9)
    assert est[-1] == pytest.approx(dist, rel=1e-4)


def _params(**kw):
    return {**_scenario(1).placement()[0].controller.params, **kw}


def test_controller_signals_and_parameter_errors():
    from canbrake.control.base import ControllerError, check_params

    c = make_controller("cai2014", _params(), car_index=0, n_cars=1, mass_kg=48e3, dt_s=1e-3)
    assert c.sensor_names == ("ground_speed_mps", "position_m", "axle1_speed_radps", "axle2_speed_radps",
                              "axle3_speed_radps", "axle4_speed_radps")
    assert c.command_names[-1] == "axle4_torque_nm" and c.needs_ref_position
    check_params("cai2014", _params())
    for bad, name in ((dict(case=5), "case"), (dict(kp=1), "kp"), (dict(k0=-1), "k0"), (dict(davis=[1, 2]), "davis")):
        with pytest.raises(ControllerError) as e:
            check_params("cai2014", _params(**bad))
        assert name in f"{getattr(e.value, 'param', '')} {e.value}"


def _obs(k: int, dt: float, m: dict, omegas) -> Observation:
    a = 200 / 3.6 / 200.0
    t = k * dt
    return Observation(tick=k, time_s=t, speed_mps=m["speed_mps"][0], position_m=m["position_m"][0],
                       ref_speed_mps=a * t, ref_decel_mps2=-a, peer_speed_mps=np.zeros(1),
                       peer_position_m=np.zeros(1), peer_age_s=np.zeros(1), ref_position_m=0.5 * a * t * t,
                       sensors={"ground_speed_mps": m["speed_mps"][0], "position_m": m["position_m"][0],
                                **{f"axle{j + 1}_speed_radps": x for j, x in enumerate(omegas)}})


@pytest.mark.parametrize("case", [1, 2, 3, 4])
def test_one_ecu_per_powered_vehicle_sums_to_the_centralised_law(case):
    """Two ECUs with share 1/2 over axles 1–2 and 3–4 (the same measurements) against the one-ECU law
    driving the plant: equal axle torques in cases 1, 2, 4; in case 3 the total force command is equal
    (the derivation is in Cai2014Controller's docstring)."""
    dt = 1e-2
    central = make_controller("cai2014", _params(case=case), car_index=0, n_cars=1, mass_kg=48e3, dt_s=dt)
    split = [make_controller("cai2014", _params(case=case, axles=2, share=0.5), car_index=i, n_cars=2,
                             mass_kg=48e3, dt_s=dt) for i in range(2)]
    plant = _Rigid(dt_s=dt)
    for k in range(300):
        m = plant.measurements()
        w = [m[f"axle{j}_speed_radps"][0] for j in range(1, 5)]
        out = central.step(_obs(k, dt, m, w))
        parts = [split[0].step(_obs(k, dt, m, w[:2])), split[1].step(_obs(k, dt, m, w[2:]))]
        t_central = [out.commands[f"axle{j}_torque_nm"] for j in range(1, 5)]
        t_split = [p.commands[f"axle{j}_torque_nm"] for p in parts for j in (1, 2)]
        f_central = sum(out.diagnostics[f"axle{j}_force_cmd_n"] for j in range(1, 5))
        f_split = sum(p.diagnostics[f"axle{j}_force_cmd_n"] for p in parts for j in (1, 2))
        assert f_split == pytest.approx(f_central, rel=1e-9, abs=1e-6)
        if case != 3:
            np.testing.assert_allclose(t_split, t_central, rtol=1e-9, atol=1e-6)
        plant.step(dt, {f"axle{j}_torque_nm": np.array([t_central[j - 1], np.nan]) for j in range(1, 5)})
    assert plant.speed_mps > 0.5  # the train did accelerate under the centralised law


# ------------------------------------------------------------------------------ closed loop through the engine
def _engine_trace(case: int, tmp_dir, profile: str = "paper", **overrides):
    """A run through the node engine (in-process driver) read as the report reads it."""
    from canbrake.analysis.summary import read_signals
    from canbrake.report.cai2014 import CaiSetup, CaiTrace, trace_from_signals
    from canbrake.run import run_scenario

    scn = _scenario(case, profile, **overrides)
    s = run_scenario(scn, tmp_dir, backend="inprocess", plots=False)
    assert s["status"] == "ok", s.get("message")
    setup = CaiSetup.of(scn)
    return CaiTrace(case=case, params=setup, **trace_from_signals(read_signals(tmp_dir / "signals.csv"), setup, case))


@pytest.fixture(scope="module")
def short_runs(tmp_path_factory):
    """The four cases for 26 s at 10 ms over the bus (the report runs 200 s at 5 ms; the errors settle in ~20 s)."""
    d = tmp_path_factory.mktemp("cai")
    return {c: _engine_trace(c, d / f"case{c}", duration_s=26.0, control_period_s=1e-2) for c in (1, 2, 3, 4)}


@pytest.mark.slow
def test_case1_settled_error_equals_uncompensated_wheel_inertia(short_runs):
    """Case 1 ignores the wheels: m ṡ = −k0 s − (J/R) Σ ω̇, so e → −p J a*/(R² k0 β)."""
    a_ref = 1 / 3.6
    expected = -4 * J * a_ref / (R ** 2 * PAPER_GAINS.k0 * PAPER_GAINS.beta)
    e = short_runs[1].position_error_m[short_runs[1].time_s >= 20.0]
    assert np.mean(e) == pytest.approx(expected, rel=0.02)


@pytest.mark.slow
def test_case_ordering_as_reported(short_runs):
    # docs/reproduction/cai2014.md: case 1 worst by ≈ ka/R ≈ 4 over case 2 (not 10), case 2
    # slightly better than case 3, case 4 best.
    from canbrake.report.cai2014 import error_metrics

    err = {c: error_metrics(tr, 20.0)["mean_abs_pos_err_m"] for c, tr in short_runs.items()}
    assert 3.0 < err[1] / err[2] < 6.0
    assert err[2] < err[3] < err[1]
    assert err[4] < 0.5 * err[2]
    for tr in short_runs.values():  # every case tracks: speed within 5 cm/s after the start
        assert error_metrics(tr, 5.0)["max_abs_speed_err_mps"] < 0.05


@pytest.mark.slow
def test_quasi_steady_errors_match_the_derivation(short_runs):
    """The report's closed-form errors (wheel inertia, force loop, observer lag) against the runs at t = 25 s."""
    from canbrake.report.cai2014 import error_at, predicted_error_m

    for c, tr in short_runs.items():
        v_ref = tr.params.reference(25.0)[1]
        assert error_at(tr, 25.0) == pytest.approx(predicted_error_m(c, tr.params, v_ref), rel=0.1), c


@pytest.mark.slow
def test_observers_track_the_plant_in_closed_loop(short_runs):
    tr = short_runs[3]
    sel = tr.time_s >= 5.0
    np.testing.assert_allclose(tr.adhesion_hat_n[sel], tr.adhesion_n[sel], rtol=0.02)
    np.testing.assert_allclose(tr.resistance_hat_n[sel], tr.resistance_n[sel], atol=30.0)
    tr4 = short_runs[4]
    sel4 = tr4.time_s >= 5.0
    np.testing.assert_allclose(tr4.lumped_hat_n[sel4], tr4.lumped_n[sel4], atol=30.0)


@pytest.mark.slow
def test_bus_quantisation_is_negligible(short_runs):
    """The engine run (speeds, positions, torques and the reference through CAN frames) against the
    same plant and controller joined directly, case 4 at 10 ms: the position errors differ by far
    less than case 4's own error (≈ 0.3 mm)."""
    tr = short_runs[4]
    dt, n = 1e-2, len(tr.time_s)
    ctrl = make_controller("cai2014", _params(case=4), car_index=0, n_cars=1, mass_kg=48e3, dt_s=dt)
    plant = _Rigid(dt_s=dt)
    e_direct = []
    for k in range(n):
        m = plant.measurements()
        e_direct.append(m["position_m"][0] - 0.5 / 3.6 * (k * dt) ** 2)
        out = ctrl.step(_obs(k, dt, m, [m[f"axle{j}_speed_radps"][0] for j in range(1, 5)]))
        plant.step(dt, {name: np.array([v, np.nan]) for name, v in out.commands.items()})
    diff = tr.position_error_m - np.asarray(e_direct)
    settled = tr.time_s >= 10.0
    assert abs(np.mean(diff[settled])) < 0.01e-3        # < 10 µm systematic
    assert np.max(np.abs(diff)) < 0.05e-3               # < 50 µm at any time


@pytest.mark.slow
def test_printed_sign_of_eq_44_drives_the_train_backwards(tmp_path, short_runs):
    printed = _engine_trace(2, tmp_path, "printed_sign", duration_s=3.0, control_period_s=1e-2)
    assert printed.speed_mps[-1] < -1.0  # backwards
    assert short_runs[2].speed_mps[300] > 0.5  # the same case with eq. 20's sign, at 3 s


@pytest.mark.slow
def test_crh3_with_an_ecu_per_locomotive_moves_as_the_papers_train(tmp_path, short_runs):
    """scenarios/cai2014_crh3_case4.yaml: four locomotive-carriage pairs, a traction ECU (share 1/4) on
    each locomotive, gains × 4 for the 4× mass: every pair is the paper's train, so the run equals the
    paper's case 4 (the sum of the four ECUs' laws is the centralised law, see Cai2014Controller)."""
    from canbrake.run import run_scenario

    scn = load_scenario(SCENARIOS / "cai2014_crh3_case4.yaml", overrides={"duration_s": 3.0, "control_period_s": 1e-2})
    assert [p.vehicle for p in scn.placement()] == [1, 3, 5, 7]
    s = run_scenario(scn, tmp_path, backend="inprocess", plots=False)
    assert s["status"] == "ok", s.get("message")
    from canbrake.analysis.summary import read_signals

    cols = read_signals(tmp_path / "signals.csv")
    ref = short_runs[4]
    n = len(cols["t_s"]) - 1
    np.testing.assert_allclose(cols["position_m_c1"][:n] - cols["ref_position_m"][:n], ref.position_error_m[:n],
                               rtol=0, atol=1e-6)
    for v in (3, 5, 7):  # the four ECUs command the same torques
        np.testing.assert_allclose(cols[f"cmd_axle2_torque_nm_c{v}"][:n], cols["cmd_axle2_torque_nm_c1"][:n], rtol=1e-9)


# ------------------------------------------------------------------------------ on the bus
@pytest.mark.slow
def test_case4_identical_frames_and_signals_on_every_backend(tmp_path):
    from canbrake.run import run_scenario

    scn = _scenario(4, duration_s=0.5)
    for b in ("inprocess", "virtual", "memory"):
        s = run_scenario(scn, tmp_path / b, backend=b, plots=False)
        assert s["status"] == "ok", (b, s.get("message"))
    for f in ("frames.log", "signals.csv"):
        ref = (tmp_path / "inprocess" / f).read_bytes()
        assert (tmp_path / "virtual" / f).read_bytes() == ref and (tmp_path / "memory" / f).read_bytes() == ref, f
    assert len(ref) > 1000


@pytest.mark.slow
def test_cli_runs_case4_on_the_memory_bus_and_cantools_decodes_every_frame(tmp_path):
    from canbrake.cli import main

    out = tmp_path / "run"
    assert main(["run", CASE_FILE.format(4), "--bus", "memory", "--duration", "0.2", "--no-plots",
                 "--out", str(out)]) == 0
    log = (out / "frames.log").read_text()
    r = subprocess.run([sys.executable, "-m", "cantools", "decode", str(out / "canbrake.dbc")],
                       input=log, capture_output=True, text=True, timeout=120)
    assert r.returncode == 0, r.stderr
    lines = [ln for ln in r.stdout.splitlines() if ln.startswith("(")]
    assert len(lines) == len(log.splitlines()) > 1000
    decoded = [ln for ln in r.stdout.splitlines() if "::" in ln]
    assert len(decoded) == len(lines)  # every frame decoded by the run's DBC
    assert any("Axle4Torque" in ln for ln in r.stdout.splitlines())
    assert any("Axle1Speed" in ln for ln in r.stdout.splitlines())


# ------------------------------------------------------------------------------ report
@pytest.mark.slow
def test_generate_smoke(tmp_path):
    from canbrake.report import REPORTS
    from canbrake.report.cai2014 import generate, run_all, run_specs

    assert REPORTS["cai2014"] == "canbrake.report.cai2014"
    logs: list[str] = []
    doc = generate(tmp_path / "out", tmp_path / "runs", jobs=1, log=logs.append, duration_s=21.0, dt_s=0.05)
    text = doc.read_text(encoding="utf-8")
    for heading in ("## Model and parameters", "## Readings of ambiguous", "## Claims", "## What could not be reproduced"):
        assert heading in text
    assert "`canbrake run scenarios/cai2014_case4.yaml --profile paper --bus inprocess --duration 21 " \
           "--set control_period_s=0.05`" in text
    figs = sorted(p.name for p in (tmp_path / "out" / "figures").glob("cai2014_*.png"))
    assert "cai2014_tracking.png" in figs and "cai2014_adhesion.png" in figs
    assert "ran in" in " ".join(logs)
    logs.clear()
    res = run_all(run_specs(21.0, 0.05), tmp_path / "runs", False, 1, logs.append)
    assert logs and all("reused" in line for line in logs)  # runs are reused
    assert res["paper-case1"].time_s[-1] == pytest.approx(21.0 - 0.05)
