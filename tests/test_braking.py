"""Brakes as on a real train (issue 12, item 4), checked against derivations: adhesion under braking,
wheel-slide protection, easing before standstill, blending, the brake pipe, the locomotive's
adhesion limit, draft-gear end stops."""
from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pytest

from canbrake.analysis.braking import STOP_JERK_LIMIT_MPS3, decel_at_standstill_mps2, stop_jerk_mps3
from canbrake.control.base import ControlOutput, Controller, Observation
from canbrake.control.brake_functions import BrakeFunctions
from canbrake.physics import heavy_haul as hh
from canbrake.physics.actuator import BrakeActuator
from canbrake.physics.brakes import BrakeBlending, Wheelsets
from canbrake.physics.rail import RailConditions, RailEvent
from canbrake.physics.resistance import DavisResistance
from canbrake.physics.train import TrainPlant
from canbrake.physics.wheel_adhesion import RailCondition
from canbrake.scenario import load_scenario

ROOT = Path(__file__).resolve().parents[1]
G = 9.81
#: Cai's dry-rail slip curve without its speed decay (c2 = 0): μ_max is the same at every speed
FLAT = RailCondition(b1=1.786, b2=40.0, b3=10.0, c1=1.0, c2=0.0, c3=1.0, peak_mu0=1.0)


# ------------------------------------------------------------------ a single wheelset
def _wheelset_run(torque_fraction: float, mu: float = 0.2, t_end: float = 8.0) -> np.ndarray:
    """One axle carrying a body of mass m (N = m g), from 20 m/s, brake torque = fraction x the
    adhesion limit; returns the slip λ(t)."""
    m, R, J, h = 5000.0, 0.42, 120.0, 1e-2  # backward Euler: stable at the ECU period
    ws = Wheelsets(np.array([m]), 1, R, J, np.array([20.0]), curve=FLAT)
    # rolling without sliding: the rail must take F = T/R · m R² / (m R² + J) (the wheel's own inertia
    # decelerates with the body); it can take at most μ_peak N
    t_limit = mu * m * G * R * (m * R * R + J) / (m * R * R)
    v = np.array([20.0])
    lam = []
    for _ in range(int(t_end / h)):
        v = ws.step(h, v, np.array([m]), np.zeros(1), np.array([[torque_fraction * t_limit]]), np.zeros((1, 1)),
                    np.array([mu]))
        lam.append(float(ws.slip[0, 0]))
        if v[0] <= 1.0:
            break
    return np.asarray(lam)


def test_wheelset_below_the_adhesion_limit_rolls_and_above_it_slides():
    lam_star = math.log(FLAT.b1 * FLAT.b2 * FLAT.b3) / FLAT.b2  # peak of the slip curve, 0.164
    below = _wheelset_run(0.9)
    above = _wheelset_run(1.1)
    # below: a steady creep short of the peak (μ(λ) = 0.9 μ_peak has a root below λ*)
    assert np.max(np.abs(below)) < lam_star
    assert np.ptp(below[-50:]) < 1e-3
    # above: no creep can carry the torque, the slip runs past the peak and the wheel locks (λ = -1)
    assert np.max(np.abs(above)) == pytest.approx(1.0)
    assert abs(above[-1]) == pytest.approx(1.0)
    assert np.all(np.diff(np.abs(above)) >= -1e-12)


def test_locked_wheel_decelerates_the_body_with_the_sliding_coefficient():
    m, R, J, h, mu = 5000.0, 0.42, 120.0, 1e-2, 0.2
    ws = Wheelsets(np.array([m]), 1, R, J, np.array([20.0]), curve=FLAT)
    v = np.array([20.0])
    for _ in range(300):
        v = ws.step(h, v, np.array([m]), np.zeros(1), np.array([[1e5]]), np.zeros((1, 1)), np.array([mu]))
    assert ws.omega[0, 0] == 0.0
    # sliding μ = μ(λ = -1) scaled to the peak: (b1 (1 - e^-b2) - 1/b3) / peak · μ
    mu_slide = mu * (FLAT.b1 * (1 - math.exp(-FLAT.b2)) - 1 / FLAT.b3) / FLAT.peak_curve
    v_before = float(v[0])
    v = ws.step(h, v, np.array([m]), np.zeros(1), np.array([[1e5]]), np.zeros((1, 1)), np.array([mu]))
    assert (v_before - v[0]) / h == pytest.approx(mu_slide * G, rel=1e-3)


# ------------------------------------------------------------------ controllers for plant loops
class ConstantDemand(Controller):
    """Brake demand a·m, whatever happens."""

    def __init__(self, decel_mps2: float, mass_kg: float, dt_s: float) -> None:
        super().__init__(0, 1, mass_kg, dt_s)
        self.a = decel_mps2

    def step(self, obs: Observation) -> ControlOutput:
        return ControlOutput(self.a * self.mass_kg)


def _obs(k: int, dt: float, plant: TrainPlant, sensors: dict[str, float]) -> Observation:
    v = float(plant.speed_mps[0])
    return Observation(tick=k, time_s=k * dt, speed_mps=v, position_m=float(plant.position_m[0]), ref_speed_mps=0.0,
                       ref_decel_mps2=0.0, peer_speed_mps=np.array([v]), peer_position_m=plant.position_m[:1].copy(),
                       peer_age_s=np.zeros(1), sensors=sensors)


def _closed_loop(plant: TrainPlant, ctrl: Controller, t_end: float, dt: float = 0.01) -> dict[str, np.ndarray]:
    """The plant and one ECU's controller in a loop without a bus (one period of delay-free exchange)."""
    rec: dict[str, list[float]] = {"t": [], "v": [], "a": [], "slip": [], "valve": []}
    for k in range(int(round(t_end / dt))):
        sensors = {f"axle{j + 1}_speed_radps": float(plant.wheels.omega[0, j]) for j in range(plant.wheels.p)} \
            if plant.wheels is not None else {}
        out = ctrl.step(_obs(k, dt, plant, sensors))
        wsp = np.array([out.commands["wsp_release"]]) if "wsp_release" in out.commands else None
        plant.step(dt, np.array([out.brake_force_n]), wsp_release=wsp)
        rec["t"].append((k + 1) * dt)
        rec["v"].append(float(plant.speed_mps[0]))
        rec["a"].append(float(plant.accel_mps2[0]))
        if plant.wheels is not None:
            rec["slip"].append(float(np.min(plant.wheels.slip[0])))
            rec["valve"].append(float(plant.wsp_valve[0]))
    return {k: np.asarray(v) for k, v in rec.items()}


class _Wsp:
    enabled, slip_release, slip_reapply, reapply_per_s, min_speed_kmh = True, 0.2, 0.1, 4.0, 3.0


def _wheeled_car(mu_low: float, *, substep: float = 1e-2) -> TrainPlant:
    m = 20_000.0
    ws = Wheelsets(np.array([m]), 4, 0.42, 120.0, np.array([20.0]), curve=FLAT)
    rail = RailConditions(base_adhesion_mu=0.25, events=[RailEvent(start_s=1.0, end_s=math.inf, adhesion_mu=mu_low)])
    return TrainPlant([m], [0.0], [20.0], resistance=DavisResistance.zero(1), max_substep_s=substep,
                      actuator=BrakeActuator.realistic(brake_rating_mps2=1.4), rail=rail, wheels=ws,
                      wsp_valve_lag_s=0.05)


def test_wheel_slide_protection_keeps_the_slip_below_its_threshold_on_a_low_mu_step():
    # 1.2 m/s² of demand on rail that takes 0.05 g = 0.49 m/s² from t = 1 s: without WSP the wheels lock
    dt, m = 0.01, 20_000.0
    bare = _closed_loop(_wheeled_car(0.05), ConstantDemand(1.2, m, dt), 6.0)
    assert np.min(bare["slip"]) == pytest.approx(-1.0)
    wsp = _closed_loop(_wheeled_car(0.05), BrakeFunctions(ConstantDemand(1.2, m, dt), wsp=_Wsp(), axles=4,
                                                          wheel_radius_m=0.42), 6.0)
    moving = wsp["v"] > 3.0 / 3.6
    # the valve vents as soon as |λ| passes 0.2 (seen one 10 ms period late, valve lag 50 ms): the slip
    # overshoots the threshold by at most its growth rate x (period + valve lag), a few hundredths here
    assert np.min(wsp["slip"][moving]) > -0.25
    assert wsp["valve"].max() > 0.9  # it did release ...
    late = moving & (wsp["t"] > 2.0)
    assert np.mean(np.abs(wsp["slip"][late])) < 0.2  # ... and keeps the axles near the adhesion peak
    # and it brakes at least as well as the sliding wheels (the curve's peak is above the sliding value)
    assert wsp["v"][-1] <= bare["v"][-1] + 0.05


def test_dump_valve_watchdog_brings_the_brake_back_after_max_vent_s():
    plant = _wheeled_car(0.25)
    plant.wsp_max_vent_s = 1.0
    m = 20_000.0
    valve = []
    for _ in range(200):  # an ECU that vents for ever (or went silent while venting)
        plant.step(0.01, np.array([0.5 * m]), wsp_release=np.array([1.0]))
        valve.append(float(plant.wsp_valve[0]))
    v = np.asarray(valve)
    assert v[90] > 0.99                     # vented during the first second
    assert v[-1] < 1e-3                     # closed again: valve lag 0.05 s << the remaining 1 s


# ------------------------------------------------------------------ easing
def _stop(easing: bool, blending: BrakeBlending | None = None) -> dict[str, np.ndarray]:
    m, dt = 20_000.0, 0.01
    plant = TrainPlant([m], [0.0], [30 / 3.6], resistance=DavisResistance.uniform(1, 643.0, 6.6, 0.9),
                       max_substep_s=dt, actuator=BrakeActuator.realistic(brake_rating_mps2=1.4), blending=blending)
    ctrl: Controller = ConstantDemand(1.0, m, dt)
    if easing:
        lag = 0.3 + (blending.friction_lag_s if blending is not None else 0.0)
        ctrl = BrakeFunctions(ctrl, easing_tau_s=1.0, lag_s=lag)
    return _closed_loop(plant, ctrl, 14.0)


@pytest.mark.parametrize("blend", [None, BrakeBlending(ed_max_decel_mps2=1.0, friction_lag_s=0.2)])
def test_easing_brings_the_stop_jerk_under_the_comfort_limit(blend):
    hard, soft = _stop(False, blend), _stop(True, blend)
    r = 643.0 / 20_000.0  # c0 / m: the resistance that is left at standstill
    # without easing the car stands with the full 1 m/s² (+ r) on: a step the 0.1 s mean turns into ~10 m/s³
    assert decel_at_standstill_mps2(hard["t"], hard["v"], hard["a"]) > 0.9
    assert stop_jerk_mps3(hard["t"], hard["v"], hard["a"]) > 5.0
    # easing: decel -> v/τ_e at the lag-anticipating demand; at standstill only the resistance and a
    # remainder of the brake (lag and jerk limit are not exactly first order) are left
    assert decel_at_standstill_mps2(soft["t"], soft["v"], soft["a"]) < r + 0.05
    assert stop_jerk_mps3(soft["t"], soft["v"], soft["a"]) < STOP_JERK_LIMIT_MPS3


def test_blending_fades_the_ed_brake_and_the_friction_brake_takes_over():
    m, dt = 20_000.0, 0.01
    bl = BrakeBlending(ed_max_decel_mps2=0.8, fade_start_mps=10 / 3.6, fade_end_mps=3 / 3.6, friction_lag_s=0.2)
    plant = TrainPlant([m], [0.0], [20 / 3.6], resistance=DavisResistance.zero(1), max_substep_s=dt, blending=bl)
    seen = []
    for _ in range(int(10.0 / dt)):
        plant.step(dt, np.array([1.0 * m]))
        e = plant.equipment_measurements()
        seen.append((float(plant.speed_mps[0]), float(e["ed_brake_n"][0]), float(e["friction_brake_n"][0])))
        if plant.speed_mps[0] == 0.0:
            break
    v, ed, fr = (np.asarray(x) for x in zip(*seen))
    fast = v > 10 / 3.6
    assert ed[fast] == pytest.approx(0.8 * m)                              # ED at capacity above the fade
    assert fr[fast][-1] == pytest.approx(0.2 * m, rel=1e-3)                # friction tops up to the demand
    slow = (v < 2.5 / 3.6) & (v > 0)  # the split uses the speed at the start of each 10 ms step
    assert np.all(ed[slow] == 0.0) and fr[slow][-1] == pytest.approx(m, rel=0.05)  # friction alone at the end
    mid = (v > 4 / 3.6) & (v < 9 / 3.6)
    assert np.all(ed[mid] + fr[mid] < m)  # the friction brake lags the fade: the total dips


def test_each_car_has_its_own_ed_brake_a_trailer_none_a_locomotive_lis_envelope():
    """Per-car ED brakes: a per-mass car as the train-wide blending, a trailer without ED brake
    (friction takes the whole demand, after its lag), a car with Li 2024's eq. (2) envelope (ED
    force = min(demand, F_B(v)), its own ramp below v1, F_max, power/v above: checked against the
    heavy-haul physics' own TractionEnvelope at the car's speed), from 80 km/h to a stop."""
    m, dt = 20_000.0, 0.01
    env = hh.TractionEnvelope(traction_start_kn=1, traction_start_until_kmh=1, traction_intercept_kn=1,
                              traction_slope_kn_per_kmh=0, traction_linear_until_kmh=2, brake_slope_kn_per_kmh=2.0,
                              brake_linear_until_kmh=20.0, brake_max_kn=40.0, brake_constant_until_kmh=50.0,
                              power_kn_kmh=2000.0)
    row = (2.0 * 1000 * 3.6, 20 / 3.6, 40_000.0, 50 / 3.6, 2000.0 * 1000 / 3.6)
    nan = (math.nan,) * 5
    bl = BrakeBlending(ed_max_decel_mps2=(0.8, 0.0, 0.0), ed_power_w_per_kg=(math.inf, math.inf, math.inf),
                       fade_start_mps=10 / 3.6, fade_end_mps=3 / 3.6, friction_lag_s=0.2, envelope=(nan, nan, row))
    ref = BrakeBlending(ed_max_decel_mps2=0.8, fade_start_mps=10 / 3.6, fade_end_mps=3 / 3.6, friction_lag_s=0.2)
    v0 = 80 / 3.6
    # three cars joined by couplers of negligible stiffness (1e-9 N/m): each brakes as if alone
    cars = TrainPlant([m] * 3, [0.0, -100.0, -200.0], [v0] * 3, resistance=DavisResistance.zero(3),
                      coupler_stiffness_n_per_m=[1e-9, 1e-9], coupler_nonlinearity_per_m2=[0.0, 0.0],
                      max_substep_s=dt, blending=bl)
    alone = TrainPlant([m], [0.0], [v0], resistance=DavisResistance.zero(1), max_substep_s=dt, blending=ref)
    demand = np.array([1.0 * m, 1.0 * m, 1.0 * m])
    for k in range(int(12.0 / dt)):
        v_before = cars.speed_mps.copy()
        cars.step(dt, demand)
        alone.step(dt, demand[:1])
        e, er = cars.equipment_measurements(), alone.equipment_measurements()
        # car 1 has the train-wide per-mass ED brake: as the scalar blending of a car alone
        assert e["ed_brake_n"][0] == pytest.approx(er["ed_brake_n"][0], rel=1e-9, abs=1e-6)
        assert e["friction_brake_n"][0] == pytest.approx(er["friction_brake_n"][0], rel=1e-9, abs=1e-6)
        assert e["ed_brake_n"][1] == 0.0                                  # the trailer: no ED brake
        want = min(1.0 * m, 1000.0 * float(env.electric_brake_kn(abs(v_before[2]) * 3.6)))
        assert e["ed_brake_n"][2] == pytest.approx(want, rel=1e-9, abs=1e-6), k  # the envelope at the car's speed
    assert e["friction_brake_n"][1] == pytest.approx(m, rel=1e-6)        # the trailer's friction took it all


def test_vehicle_type_ed_brakes_need_the_blending_and_fill_it_per_car():
    from canbrake.scenario import ScenarioError

    over = {"train.vehicle_types.trailer.brake.ed_brake": {"model": "none"}}
    scn = load_scenario("emu8_low_adhesion", overrides=over)
    pc = scn.consist.brakes.blending.per_car
    assert [c is not None and c.model == "none" for c in pc] == [True, False, False, True, True, False, False, True]
    with pytest.raises(ScenarioError, match=r"train.vehicle_types.trailer.brake.ed_brake: an ED brake is blended with the "
                                            r"friction brake by brake.blending, which this train's brake does not have"):
        load_scenario("emu8_low_adhesion", overrides={**over, "train.every_vehicle.brake.blending": None})
    with pytest.raises(ScenarioError, match=r"brake_constant_until_kmh: must be at least brake_linear_until_kmh"):
        load_scenario("emu8_low_adhesion", overrides={"train.vehicle_types.motor.brake.ed_brake": {
            "model": "envelope", "brake_slope_kn_per_kmh": 1, "brake_linear_until_kmh": 30, "brake_max_kn": 30,
            "brake_constant_until_kmh": 20, "power_kn_kmh": 900}})


# ------------------------------------------------------------------ the whole train, through the bus
@pytest.mark.slow
def test_realistic_profile_stops_within_the_comfort_jerk(tmp_path):
    """Chen's realistic profile (blending and easing on) stopping the six cars, all at v*, from 30 km/h
    (the fade and the easing happen below 10 km/h, so 90 km/h ends the same; the report runs 90)."""
    import pandas as pd

    from canbrake.run import run_scenario

    scn = load_scenario(ROOT / "scenarios" / "chen2023_case1_fine_rail.yaml", profile="realistic",
                        overrides={"initial.speed_kmh": 30.0, "reference.speed_kmh": 30.0, "duration_s": 12.0})
    assert scn.consist.brakes is not None and scn.consist.brakes.easing is not None
    s = run_scenario(scn, tmp_path / "run", backend="inprocess", plots=False)
    assert s["status"] == "ok"
    d = pd.read_csv(tmp_path / "run" / "signals.csv")
    v = d[[f"speed_mps_c{i}" for i in range(1, 7)]].to_numpy()
    a = d[[f"accel_mps2_c{i}" for i in range(1, 7)]].to_numpy()
    assert np.all(v[-1] == 0.0)
    assert stop_jerk_mps3(d["t_s"].to_numpy(), v, a) < STOP_JERK_LIMIT_MPS3
    assert {"ed_brake_n_c1", "friction_brake_n_c1"} <= set(d.columns)


# ------------------------------------------------------------------ freight air brake along the train
def _pipe_brake(n: int, length: float, pipe: hh.BrakePipe | None, tau_cyl: float = 2.0) -> hh.AirBrake:
    c = hh.Consist(mass_kg=np.full(n, 1e5), length_m=np.full(n, length), davis_a=np.zeros(n), davis_b=np.zeros(n),
                   davis_c=np.zeros(n), is_loco=np.zeros(n, bool))
    return hh.AirBrake(c, apply_wave_mps=200.0, release_wave_mps=36.0, cylinder_tau_s=tau_cyl, beta_c=0.2,
                       block_force_kn=np.full(n, 30.0), n_blocks=np.full(n, 8.0), friction_coef=np.full(n, 0.48),
                       cylinder_pressure_pa=np.full(n, 450e3), pipe=pipe)


def test_brake_pipe_wave_reaches_wagon_k_after_k_lengths_over_the_wave_speed_and_cylinders_follow_the_fill_curve():
    n, length, c, dt = 60, 13.0, 200.0, 1e-3
    pipe = hh.BrakePipe(p0_pa=600e3, reduction_pa=150e3, ratio=2.6, tau_s=1.0, tau_per_km_s=4.0)  # 390 kPa < 450
    ab = _pipe_brake(n, length, pipe)
    ab.command(0.0, True)
    ks = np.array([0, 10, 30, 59])
    arrival = ks * length / c  # equal lengths: centre k is k·length behind the locomotive's
    t, rec_p, rec_c = 0.0, [], []
    for _ in range(int(8.0 / dt)):
        t += dt
        ab.step(t, dt, np.zeros(n))
        rec_p.append(ab.pipe_pressure_pa[ks].copy())
        rec_c.append((ab.fill * ab.cylinder_pressure_pa)[ks].copy())
    ts = dt * np.arange(1, len(rec_p) + 1)
    p, cyl = np.asarray(rec_p), np.asarray(rec_c)
    for i, k in enumerate(ks):
        first = ts[np.argmax(p[:, i] < 600e3)]
        assert first == pytest.approx(arrival[i], abs=1.5 * dt)  # the front of the wave
        tp, tc = 1.0 + 4.0 * k * length / 1000.0, 2.0
        s = np.clip(ts - arrival[i], 0.0, None)
        # two first-order stages (pipe then cylinder) in series: P [1 - (τp e^(-s/τp) - τc e^(-s/τc)) / (τp - τc)]
        want = 2.6 * 150e3 * (1 - (tp * np.exp(-s / tp) - tc * np.exp(-s / tc)) / (tp - tc))
        assert np.max(np.abs(cyl[:, i] - want)) < 0.01 * 390e3
    # the pressure builds up along the train: at 5 s the rear cylinder is far behind the front one
    k3 = int(5.0 / dt) - 1
    assert cyl[k3, 0] > 1.5 * cyl[k3, -1] > 0


def test_without_the_pipe_model_the_fill_is_the_signal_arrival_plus_one_first_order_curve():
    n, length, dt = 20, 13.0, 1e-3
    ab = _pipe_brake(n, length, None)
    ab.command(0.0, True)
    t = 0.0
    for _ in range(int(3.0 / dt)):
        t += dt
        ab.step(t, dt, np.zeros(n))
    s = np.clip(t - np.arange(n) * length / 200.0, 0, None)
    assert ab.fill == pytest.approx(1 - np.exp(-s / 2.0), abs=2e-3)


# ------------------------------------------------------------------ locomotive adhesion
def test_locomotive_traction_and_dynamic_brake_are_limited_by_adhesion():
    scn = load_scenario(ROOT / "scenarios" / "li2024_driver.yaml",
                        overrides={"train.vehicle_types.hxd1.wheels": {"model": "adhesion_limit", "mu": 0.1}})
    model = scn.train.assemble(scn, scn.data_dir())
    p = model.plant  # TrainPlant
    nan = np.full(model.n_vehicles, np.nan)
    m_loco = float(model.mass_kg[0])
    for demand in (-5e6, 5e6):  # traction, electric brake: far beyond the envelope and the rail
        cmd = nan.copy()
        cmd[0] = demand
        v0 = float(p.speed_mps[0])
        model.step(p.max_substep_s, {"brake_force_n": cmd})
        envelope = abs(p.traction_envelope[0].saturate_n(-demand, v0))
        assert abs(p.applied_force_n[0]) == pytest.approx(min(envelope, 0.1 * m_loco * hh.G))
    ck = hh.LocoAdhesion(mu0=0.33, curve="curtius_kniffler")
    assert ck.mu(0.0) == pytest.approx(0.33) and ck.mu(80 / 3.6) == pytest.approx(0.33 * (0.161 + 7.5 / 124) / 0.33146,
                                                                                  rel=1e-3)


# ------------------------------------------------------------------ draft gear end stops
def test_end_stop_bounds_the_deflection_by_the_stop_plus_the_solid_overrun():
    # two 20 t cars closing at 5 m/s on a soft coupler: without a stop the deflection is ~Δv·sqrt(μ/κ) = 1.6 m
    # (past the softening spring's reversal); with the stop at 0.1 m the overrun is Δv·sqrt(μ/k_stop)
    m, dv, k_stop = 20_000.0, 5.0, 2e7
    p = TrainPlant([m, m], [0.0, 10.0], [20.0, 25.0], resistance=DavisResistance.zero(2), end_stop_m=0.1,
                   end_stop_stiffness_n_per_m=k_stop, max_substep_s=1e-4)
    worst = 0.0
    for _ in range(5000):
        p.step(1e-3, np.zeros(2))
        worst = max(worst, float(np.max(np.abs(p.deflection_m))))
    overrun = dv * math.sqrt((m / 2) / k_stop)  # 0.112 m (the spring before the stop only lowers it)
    assert 0.1 < worst <= 0.1 + overrun * 1.01


def _impact(absorption: float, v0: float = 1.5, m1: float = 18_000.0, m2: float = 22_000.0,
            k_b: float = 2e7, stop: float = 0.08) -> tuple[float, float, float, float]:
    """Two cars on a (nearly) force-free coupler closing at v0 into the end stop; returns the peak
    buffer force (N), the peak overrun (m), the relative speed after they separate (m/s, + = apart)
    and the reduced mass (kg)."""
    p = TrainPlant([m1, m2], [0.0, 10.0], [v0 + 5.0, 5.0], resistance=DavisResistance.zero(2),
                   coupler_stiffness_n_per_m=1e-6, coupler_nonlinearity_per_m2=0.0, end_stop_m=stop,
                   end_stop_stiffness_n_per_m=k_b, end_stop_absorption=absorption, max_substep_s=1e-3)
    f_peak = over_peak = 0.0
    for _ in range(400):  # contact at 53 ms, lasts ~70 ms; stop when the cars have parted
        p.step(1e-3, np.zeros(2))
        dl, phi = p.couplers()
        f = abs(float(phi[0] - 1e-6 * (1.0 + 0.0 * dl[0] * dl[0]) * dl[0]))  # the buffer's: Φ less the spring's
        if f_peak > 0.0 and f == 0.0:
            break
        f_peak = max(f_peak, f)
        over_peak = max(over_peak, float(np.abs(p.deflection_m)[0]) - stop)
    assert f_peak > 0.0 and f == 0.0
    return f_peak, over_peak, float(p.speed_mps[1] - p.speed_mps[0]), m1 * m2 / (m1 + m2)


@pytest.mark.parametrize("absorption", [0.0, 0.6])
def test_end_stop_impact_force_and_absorbed_energy_follow_the_two_mass_derivation(absorption):
    # loading curve elastic: peak force v0·sqrt(k_b μ), overrun v0·sqrt(μ/k_b) (μ reduced mass);
    # unloading at (1 - a)·k_b returns (1 - a) of the energy: the cars part at sqrt(1 - a)·v0
    v0, k_b = 1.5, 2e7
    f, over, v_out, mu = _impact(absorption, v0=v0, k_b=k_b)
    assert f == pytest.approx(v0 * math.sqrt(k_b * mu), rel=0.01)
    assert over == pytest.approx(v0 * math.sqrt(mu / k_b), rel=0.01)
    assert v_out == pytest.approx(math.sqrt(1.0 - absorption) * v0, rel=0.02)
    absorbed = 0.5 * mu * (v0**2 - v_out**2)
    assert absorbed == pytest.approx(absorption * 0.5 * mu * v0**2, abs=0.02 * 0.5 * mu * v0**2)


def test_the_end_stop_changes_nothing_while_it_is_not_reached():
    # the fine sub-step is taken only near the stop: a run that stays within the travel is bit-identical
    kw = dict(resistance=DavisResistance.zero(3), max_substep_s=1e-2)
    a = TrainPlant([20_000.0] * 3, [0.0, 10.0, 20.0], [20.0, 20.2, 20.1], **kw)
    b = TrainPlant([20_000.0] * 3, [0.0, 10.0, 20.0], [20.0, 20.2, 20.1], end_stop_m=0.08, **kw)
    for _ in range(300):
        a.step(0.01, np.full(3, 1e4))
        b.step(0.01, np.full(3, 1e4))
    assert np.max(np.abs(b.deflection_m)) < 0.08
    assert np.array_equal(a.position_m, b.position_m) and np.array_equal(a.speed_mps, b.speed_mps)


# ------------------------------------------------------------------ the low-adhesion scenario
@pytest.mark.slow
def test_low_adhesion_scenario_car3_locks_without_wsp_and_not_with_it(tmp_path):
    """chen2023_case2_low_adhesion.yaml with its poor rail from 0.5 s, for 3.5 s: car 3's skid comes
    from μ per car over time; the profile ``wsp`` keeps its axles near the adhesion peak. 3.5 s: with
    the end stops on, the neighbours push car 3 through their buffers and its slip passes -0.5 at ~3.1 s."""
    import pandas as pd

    from canbrake.run import run_scenario

    path = ROOT / "scenarios" / "chen2023_case2_low_adhesion.yaml"
    slips = {}
    for prof in (None, "wsp"):
        scn = load_scenario(path, profile=prof, overrides={"duration_s": 3.5, "events.0.start_s": 0.5})
        assert (scn.consist.brakes.wsp.enabled) == (prof == "wsp")
        s = run_scenario(scn, tmp_path / str(prof), backend="inprocess", plots=False)
        assert s["status"] == "ok"
        d = pd.read_csv(tmp_path / str(prof) / "signals.csv")
        slips[prof] = min(float(d[f"axle{j}_slip_c3"].min()) for j in range(1, 5))
        assert s["braking"]["wheels"][2]["car"] == 3
    assert slips[None] < -0.5  # past the adhesion peak (|λ| = 0.12 for b3 = 2) and on its way to locking
    assert slips["wsp"] > -0.25
    # the switch is an ordinary field
    assert load_scenario(path, overrides={"train.every_vehicle.brake.wsp.enabled": True}).consist.brakes.wsp.enabled


def test_each_car_has_its_own_brake_rating_and_jerk_limit():
    """Per-car ratings and jerk limits (vehicle types with different brake equipment): under a
    command far above every rating, each car's effort ramps at its own jerk limit x its mass and
    settles at its own rating x its mass; one value for every car is the former scalar actuator,
    float for float."""
    from canbrake.physics.actuator import BrakeActuator

    m = np.array([46000.0, 40000.0, 40000.0])
    act = BrakeActuator(kind="realistic", time_constant_s=0.3, jerk_limit_mps3=(1.0, 0.5, 0.5),
                        brake_rating_mps2=(1.3, 1.1, 1.1), traction_rating_mps2=(1.0, 0.0, 0.0))
    plant = TrainPlant(m, [0.0, -22.0, -44.0], [25.0] * 3, resistance=DavisResistance.zero(3),
                       coupler_stiffness_n_per_m=[2e6, 2e6], coupler_nonlinearity_per_m2=[0.0, 0.0],
                       max_substep_s=0.01, actuator=act)
    dt, cmd = 0.01, np.full(3, 1e7)
    plant.step(dt, cmd)
    assert plant.applied_force_n == pytest.approx(np.array([1.0, 0.5, 0.5]) * m * dt, rel=1e-9)  # jerk-limited start
    for _ in range(600):
        plant.step(dt, cmd)
    assert plant.applied_force_n == pytest.approx(np.array([1.3, 1.1, 1.1]) * m, rel=1e-6)      # each at its rating
    plant.step(dt, -cmd)  # traction: the trailers have none
    assert plant._act.demand_n(-cmd)[1:] == pytest.approx([0.0, 0.0]) and plant._act.demand_n(-cmd)[0] == -m[0]
    same = [TrainPlant(m, [0.0, -22.0, -44.0], [25.0] * 3, resistance=DavisResistance.zero(3),
                       coupler_stiffness_n_per_m=[2e6, 2e6], coupler_nonlinearity_per_m2=[0.0, 0.0], max_substep_s=0.01,
                       actuator=BrakeActuator(kind="realistic", jerk_limit_mps3=j, brake_rating_mps2=b))
            for j, b in ((1.0, 1.3), ((1.0, 1.0, 1.0), (1.3, 1.3, 1.3)))]
    for _ in range(50):
        for p in same:
            p.step(dt, np.array([3e4, 6e4, 9e4]))
    assert same[0].speed_mps.tobytes() == same[1].speed_mps.tobytes()


def test_vehicle_types_with_different_brake_ratings_lower_to_per_car_ratings():
    import yaml

    from canbrake.scenario import resolve

    doc = yaml.safe_load((ROOT / "scenarios" / "emu8_example.yaml").read_text())
    ep = doc["train"]["every_vehicle"].pop("brake")
    doc["train"]["vehicle_types"]["motor"]["brake"] = ep
    doc["train"]["vehicle_types"]["trailer"]["brake"] = {**ep, "max_brake_decel_mps2": 1.1, "jerk_limit_mps3": 0.8}
    a = resolve(doc).actuator
    assert a.max_brake_decel_mps2 == [1.1, 1.3, 1.3, 1.1, 1.1, 1.3, 1.3, 1.1]
    assert a.jerk_limit_mps3 == [0.8, 1.0, 1.0, 0.8, 0.8, 1.0, 1.0, 0.8]
    assert load_scenario("emu8_example").actuator.max_brake_decel_mps2 == 1.3  # one value when the types agree
