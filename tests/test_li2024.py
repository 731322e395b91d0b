"""Li 2024 heavy haul: physics against hand calculations (the train as the scenarios give it), the
plant contract, the engine controllers.

Closed-loop runs through the node engine are in tests/test_li2024_engine.py; results of the full
runs are in docs/reproduction/li2024.md (canbrake report li2024).
"""
from __future__ import annotations

import math
from pathlib import Path
from types import SimpleNamespace

import numpy as np
import pytest
import yaml

from canbrake.consist.base import DataFileError
from canbrake.consist.components import TrainSpec
from canbrake.control.base import Observation, make_controller
from canbrake.control.li2024 import (LiDriver, LiSlidingMode, Obs, electric_brake_envelope_kn, saturate_control_n,
                                     tansig, traction_envelope_kn, traction_envelope_n)
from canbrake.control.li2024 import make_controller as make_law
from canbrake.physics import heavy_haul as hh
from canbrake.physics.contract import PlantModel
from canbrake.physics.rail import disturbance_n

KMH = hh.KMH
SCENARIOS = Path(__file__).resolve().parents[1] / "scenarios"
SCENARIO = SCENARIOS / "li2024_smc.yaml"


def train_data() -> dict:
    return yaml.safe_load(SCENARIO.read_text())["train"]


def train(**over) -> TrainSpec:
    """The scenario's train as written (components; ``route``: train.track.route); ``.kernel`` is
    its lowering onto the coupled plant (:class:`canbrake.consist.coupled.TrainConfig`)."""
    d = train_data()
    if "route" in over:
        d["track"] = {"route": over.pop("route")}
    d.update(over)
    return TrainSpec.model_validate(d)


def _short(n_wagons: int | None) -> dict:
    if n_wagons is None:
        return {}
    dist = train_data()["disturbance"]
    dist["vehicles"] = [v for v in dist["vehicles"] if v <= n_wagons + 1]
    return {"vehicles": [{"type": "hxd1"}, {"type": "c80", "count": n_wagons}], "disturbance": dist}


def short_train(n_wagons: int, **over) -> TrainSpec:
    return train(**_short(n_wagons), **over)


def plant(n_wagons: int | None = None, speed_kmh: float = 50.0, **over):
    """The scenario's plant (:class:`canbrake.build.CoupledPlant` over TrainPlant) with ``n_wagons``
    C80 (None: 105), starting at ``speed_kmh``, ``over``: train fields replaced."""
    from canbrake.scenario import load_scenario

    ov = {"initial.speed_kmh": speed_kmh, **{f"train.{k}": v for k, v in {**_short(n_wagons), **over}.items()}}
    scn = load_scenario(SCENARIO, overrides=ov)
    return scn.train.assemble(scn, scn.data_dir())


def resistance_n(p, v: np.ndarray) -> np.ndarray:
    """Eq. (3)'s basic running resistance magnitude (N) per vehicle of TrainPlant ``p`` at speeds ``v``."""
    speed = np.abs(v)
    return p._c_static + speed * (p.resistance.c1_n_per_mps + p.resistance.c2_n_per_mps2 * speed)


# ------------------------------------------------------------------------------ envelopes
@pytest.mark.parametrize("v, ft", [(0.0, 760.0), (5.0, 760.0), (10.0, 741.0), (65.0, 532.0), (80.0, 432.0),
                                   (120.0, 288.0)])
def test_traction_envelope_breakpoints(v, ft):
    assert float(traction_envelope_kn(v)) == pytest.approx(ft, abs=1e-9)
    assert float(traction_envelope_n(v * KMH)) == pytest.approx(1000 * ft, rel=1e-12)


@pytest.mark.parametrize("v, fb", [(0.0, 0.0), (2.0, 184.4), (5.0, 461.0), (75.0, 461.0), (96.0, 360.0)])
def test_electric_brake_envelope_breakpoints(v, fb):
    assert float(electric_brake_envelope_kn(v)) == pytest.approx(fb, abs=1e-9)


def test_saturation_uses_the_envelope():
    v = 40 * KMH
    assert saturate_control_n(1e9, v) == pytest.approx(1000 * (779 - 3.8 * 40))
    assert saturate_control_n(-1e9, v) == pytest.approx(-461e3)
    assert saturate_control_n(1234.0, v) == 1234.0


def test_scenario_envelope_is_the_controllers_eqs_1_2():
    from canbrake.control.li2024 import HXD1_ENVELOPE
    assert train().kernel.traction_envelope[0].physics() == HXD1_ENVELOPE  # type: ignore[union-attr]


def test_the_plant_clips_the_locomotive_force_to_its_envelope():
    m = plant(2)
    v0 = float(m.plant.speed_mps[0])
    m.step(0.01, {"brake_force_n": np.array([-1e9, np.nan, np.nan])})
    assert -m.plant.applied_force_n[0] == pytest.approx(1000 * float(traction_envelope_kn(v0 / KMH)))
    assert m.measurements()["applied_brake_n"][0] == pytest.approx(m.plant.applied_force_n[0])
    m.step(0.01, {"brake_force_n": np.array([np.nan, 5e5, 5e5])})  # NaN: no force; wagons have none
    assert np.all(m.plant.applied_force_n == 0.0)


# ------------------------------------------------------------------------------ resistance, route
def test_basic_resistance_matches_hand_calculation():
    p = plant(3).plant
    r = resistance_n(p, np.full(p.n_cars, 60 * KMH))
    loco = (1.20 + 0.0065 * 60 + 0.000279 * 3600) * 184_000 * 9.81 / 1000
    wagon = (0.92 + 0.0048 * 60 + 0.000125 * 3600) * 100_000 * 9.81 / 1000
    assert r[0] == pytest.approx(loco, rel=1e-12)
    assert r[1:] == pytest.approx([wagon] * 3, rel=1e-12)


def test_long_downgrade_ahead_is_the_former_rule_everywhere_on_the_line():
    # its long downgrades are found once per rule; the answer is the former per-call numpy rule's
    route = train().kernel.load_route(SCENARIOS)
    starts = route.grade_start_m
    ends = np.append(starts[1:], route.length_m)
    rules = [(2500.0, 8.0, 500.0), (100.0, 10.5, 5000.0), (0.0, 2.0, 0.0), (1000.0, 30.0, 500.0)]
    seen = set()
    for look, g, length in rules:
        steep = (route.grade_permille < -g) & ((ends - starts) >= length)
        edges = np.concatenate([starts, ends, starts - look, ends + 1.5e3])
        for front in np.concatenate([np.linspace(-3e3, 5e4, 1201), edges, np.nextafter(edges, np.inf),
                                     np.nextafter(edges, -np.inf)]):
            rear = front - 1500.0
            old = bool(np.any(steep & (ends > rear) & (starts < front + look)))
            assert route.long_downgrade_ahead(float(front), float(rear), look, g, length) == old, (front, look, g)
            seen.add(old)
    assert seen == {True, False}


def test_consist_of_the_paper():
    c = train().kernel
    assert c.n_cars == 106 and sum(e is not None for e in c.traction_envelope) == 1
    assert sum(c.mass_kg) == pytest.approx(184_000 + 105 * 100_000)
    assert sum(c.length_m) == pytest.approx(35.222 + 105 * 12)


def test_route_grade_and_curve():
    route = train().kernel.load_route(SCENARIOS)
    assert route.grade_at(np.array([-5.0, 1000.0, 20_000.0, 33_000.0])) == pytest.approx([0, 0, -10, -11])
    assert route.curve_permille_at(np.array([26_500.0]))[0] == pytest.approx(600 / 800)
    assert route.total_permille_at(np.array([26_500.0]))[0] == pytest.approx(-3 + 0.75)
    assert route.long_downgrade_ahead(16_000.0, 14_700.0)       # 18 km downgrade within 2.5 km
    assert not route.long_downgrade_ahead(10_000.0, 8_700.0)
    # the 31-36 km downgrade has a curve in its middle: rows split it, it is still one 5 km segment
    assert list(route.grade_start_m / 1000) == [0, 5, 10, 15, 18, 23.5, 28, 31, 36, 37.5, 41.5]
    assert route.length_m == 45_000.0


def test_route_table_errors_name_the_file(tmp_path):
    (tmp_path / "r.csv").write_text("position_m,grade_permille,curve_radius_m\n5,0,0\n10,1,0\n")
    with pytest.raises(ValueError, match="r.csv: route table: position_m must start at 0"):
        train(route={"file": "r.csv"}).kernel.load_route(tmp_path)
    with pytest.raises(DataFileError, match="no such data file"):
        train(route={"file": "missing.csv"}).kernel.load_route(tmp_path)


def test_unknown_draft_gear_is_named():
    d = train_data()
    d["vehicle_types"]["c80"]["coupler"]["gear"] = "MT-3"
    with pytest.raises(ValueError, match="vehicle_types.c80.coupler.gear: unknown draft gear 'MT-3'"):
        TrainSpec.model_validate(d)


def _plant_on(tmp_path: Path, grade_permille: float, n_wagons: int, v0_kmh: float, x0: float, **over):
    """``plant(n_wagons)`` on a constant grade (a route file in ``tmp_path``) from ``x0`` (m), no δ."""
    (tmp_path / "grade.csv").write_text(f"position_m,grade_permille,curve_radius_m\n0,{grade_permille},0\n"
                                        f"100000,{grade_permille},0\n")
    return plant(n_wagons, v0_kmh, track={"route": {"file": str(tmp_path / "grade.csv")}}, start_position_m=x0,
                 uncertainty=0.0, **over)


def test_steady_state_needs_exactly_resistance_plus_grade(tmp_path):
    """On a constant 5 ‰ grade at 60 km/h the train holds its speed iff the locomotive pulls with
    Σ(basic + grade) (N), the static initial state is in equilibrium."""
    v0 = 60 * KMH
    m = _plant_on(tmp_path, 5.0, 20, 60.0, 5000.0)
    p = m.plant
    need = float(np.sum(resistance_n(p, np.full(p.n_cars, v0)) + 5.0 * p.mass_kg * 9.81 / 1000.0))
    acc = m.measurements()["passive_force_n"].copy()
    acc[0] += need
    # every vehicle in equilibrium at t = 0 (to the draft gears' 2e8 N/m times the positions' rounding)
    assert np.max(np.abs(acc / p.mass_kg)) < 1e-8
    cmd = {"brake_force_n": np.r_[-need, np.full(p.n_cars - 1, np.nan)]}
    for _ in range(500):
        m.step(0.01, cmd)
    assert np.max(np.abs(p.speed_mps - v0)) / KMH < 0.01
    m2 = _plant_on(tmp_path, 5.0, 20, 60.0, 5000.0)
    for _ in range(500):
        m2.step(0.01, {"brake_force_n": 1.01 * cmd["brake_force_n"]})
    assert m2.plant.speed_mps[0] > v0 + 0.001


def test_passive_forces_sum_to_the_external_forces():
    """Couplers are internal: Σ passive_force_n = −Σ(basic resistance + grade/curve + air brake)."""
    m = plant()
    m.step(0.01, {"airbrake_apply": np.r_[1.0, np.full(105, np.nan)]})
    for _ in range(300):
        m.step(0.01, {})
    me = m.measurements()
    p = m.plant
    ext = resistance_n(p, p.speed_mps) + p._route_force_n(p.position_m) + p.air_brake.last_force_n
    assert me["applied_brake_n"][1] > 0
    assert float(me["passive_force_n"].sum()) == pytest.approx(-float(ext.sum()), rel=1e-9)


def test_plant_model_follows_the_contract():
    m = plant(4)
    assert isinstance(m, PlantModel)
    me = m.measurements()
    for k in ("position_m", "speed_mps", "accel_mps2", "applied_brake_n", "passive_force_n",
              "brake_cylinder_pressure_pa", "downgrade_ahead"):
        assert me[k].shape == (5,), k
    assert me["deflection_m"].shape == me["coupler_force_n"].shape == (4,)
    m.step(0.05, {})  # five sub-steps of the scenario's 10 ms
    assert m.plant.time_s == pytest.approx(0.05) and m.plant.max_substep_s == 0.01


def test_downgrade_ahead_is_line_data():
    m = plant(start_position_m=10_000.0)
    assert m.measurements()["downgrade_ahead"][0] == 0.0
    m2 = plant(start_position_m=16_000.0)
    assert np.all(m2.measurements()["downgrade_ahead"] == 1.0)


# ------------------------------------------------------------------------------ air brake
def test_air_brake_signal_reaches_wagon_k_at_distance_over_200():
    ab = train().kernel.air_brake_physics()
    dist = ab.dist
    assert dist[1] == pytest.approx((35.222 + 12) / 2)
    assert dist[-1] == pytest.approx(35.222 / 2 + 12 * 104 + 6)
    ab.command(10.0, True)
    arrive = 10.0 + dist / 200.0
    assert np.all(ab.signal(arrive[-1] + 1e-9))
    for k in (1, 30, 105):
        assert not ab.signal(arrive[k] - 1e-6)[k]
        assert ab.signal(arrive[k] + 1e-6)[k]
    assert dist[-1] / 200 == pytest.approx(6.0, abs=0.5)  # paper: "about 6 s" (for 1.3 km)
    ab.command(100.0, False)
    rel = 100.0 + dist / 36.0
    for k in (1, 52, 105):
        assert ab.signal(rel[k] - 1e-6)[k]
        assert not ab.signal(rel[k] + 1e-6)[k]
    assert dist[-1] / 36 == pytest.approx(36.1, abs=1.0)  # paper: 36.1 s for 1.3 km; ours 1.27 km centre to centre


def test_valve_command_fills_the_cylinders_with_the_lag():
    t = short_train(3)
    m = plant(3)
    ab = m.plant.air_brake
    dt, tau = 0.01, t.air_brake.cylinder_tau_s
    m.step(dt, {"airbrake_apply": np.array([1.0, np.nan, np.nan, np.nan])})
    p_full = ab.cylinder_pressure_pa
    # the command acts from t = 0: two fill updates on the locomotive (at 0 and 10 ms)
    a = 1.0 - math.exp(-dt / tau)
    assert ab.fill[0] == pytest.approx(1 - (1 - a) ** 2)
    assert m.measurements()["brake_cylinder_pressure_pa"][0] == pytest.approx(p_full[0] * ab.fill[0])
    assert np.all(ab.fill[1:] == 0.0)  # the signal needs 0.118 s to reach wagon 1
    m.step(dt, {"airbrake_apply": np.array([np.nan] * 4)})  # NaN: unchanged (still applied)
    assert ab.applied


def test_ecp_each_wagon_follows_its_own_demand_without_a_wave():
    ecp = {**train_data()["air_brake"], "mode": "ecp"}
    t = short_train(3, air_brake=ecp)
    m = plant(3, air_brake=ecp)
    ab = m.plant.air_brake
    dt, tau = 0.01, t.air_brake.cylinder_tau_s
    a = 1.0 - math.exp(-dt / tau)
    m.step(dt, {"ecp_demand": np.array([np.nan, 1.0, 0.5, 2.0]), "airbrake_apply": np.array([1.0, np.nan, np.nan, np.nan])})
    want = np.array([0.0, 1.0, 0.5, 1.0])  # clipped to 1; the valve is ignored in ECP mode
    assert ab.fill == pytest.approx(want * (1 - (1 - a) ** 2))
    m.step(dt, {"ecp_demand": np.array([np.nan, np.nan, 0.0, np.nan])})
    assert ab.ecp_target == pytest.approx([0.0, 1.0, 0.0, 1.0])


def test_shoe_force_and_friction_hand_calculation():
    k = math.pi / 4 * 254 ** 2 * 430 * 0.9 * 6.6 * (1 / 8) * 1e-6
    t = short_train(2)
    assert t.vehicle_types["c80"].brake.block_force_kn() == pytest.approx(k)
    k_h = 448 / 1250 * math.pi / 4 * 225 ** 2 * 450 * 2.4 * 0.9 * 1e-6
    assert t.vehicle_types["hxd1"].brake.block_force_kn() == pytest.approx(k_h)
    phi = 0.481 * (k + 200) / (4 * k + 200) * (2 * 60 + 150) / (3 * 60 + 150)
    assert float(hh.friction_coefficient(k, 60.0, 0.481)) == pytest.approx(phi)
    ab = t.kernel.air_brake_physics()
    ab.fill[:] = 1.0
    f = ab.force_n(np.full(ab.dist.size, 60 * KMH))
    assert f[1] == pytest.approx(1000 * t.air_brake.service_factor * 8 * phi * k)


# ------------------------------------------------------------------------------ couplers
def _gear(name: str) -> hh.DraftGear:
    return train().draft_gears[name].physics(name)


def test_coupler_hysteresis_dissipates_energy():
    mt2 = _gear("MT-2")
    bank = hh.CouplerBank([mt2])
    up = np.linspace(0.0, 0.07, 400)
    down = up[::-1]
    f_up = np.array([bank.step(np.array([s]), np.zeros(1))[0] for s in up])
    f_dn = np.array([bank.step(np.array([s]), np.zeros(1))[0] for s in down])
    for s in (0.02, 0.04, 0.06):
        i = np.argmin(abs(up - s))
        j = np.argmin(abs(down - s))
        assert f_up[i] > f_dn[j] + 1e5
    assert f_up[np.argmin(abs(up - 0.004))] == 0.0  # within the slack no force
    e_in = np.trapezoid(f_up, up)
    e_out = np.trapezoid(f_dn[::-1], up)
    assert e_out > 0 and (e_in - e_out) > 0.5 * e_in  # more than half of the work is dissipated
    d = 0.05 - mt2.slack_m
    assert f_up[np.argmin(abs(up - 0.05))] == pytest.approx(float(np.interp(d, mt2.curve_m, mt2.curve_n)), rel=0.02)


def test_coupler_compression_is_symmetric():
    mt2 = _gear("MT-2")
    b1, b2 = hh.CouplerBank([mt2]), hh.CouplerBank([mt2])
    for s in np.linspace(0, 0.05, 50):
        ft = b1.step(np.array([s]), np.zeros(1))[0]
        fc = b2.step(np.array([-s]), np.zeros(1))[0]
        assert fc == pytest.approx(-ft)


def test_first_coupler_takes_the_locomotive_gear():
    m = plant(3)
    assert m.plant._gears.fmax == pytest.approx([2.5e6, 2.27e6, 2.27e6])  # QKX100 behind the HXD1, then MT-2


def test_disturbance_eq40_only_on_listed_vehicles():
    m = plant(disturbance={**train_data()["disturbance"], "enabled": True}).plant
    v = np.full(106, 20.0)
    s = disturbance_n(m.mass_kg, 1.5, v, *m._li_dist)
    assert list(np.flatnonzero(s)) == [0] + list(range(10, 101, 10))
    acc = 0.002 + 0.001 * math.sin(2.5) + 0.0003 * 20 ** (1 / 3) * (math.sin(5.0) + math.cos(5.5))
    assert s[0] == pytest.approx(184_000 * acc)
    assert s[50] == pytest.approx(100_000 * acc)


# ------------------------------------------------------------------------------ control laws
def test_tansig_and_rbf_basis():
    assert tansig(0.0) == 0.0
    assert tansig(2.0) == pytest.approx(math.tanh(1.0))
    ctl = LiSlidingMode(0.01, 184e3, rbf=True)
    h = ctl.basis(0.005, -0.005)
    assert h[3] == pytest.approx(math.exp(-(0.0 ** 2 + 0.01 ** 2) / (2 * 0.005 ** 2)))
    assert h.shape == (5,)


def test_smc_cancels_the_model_on_the_surface():
    """On s = 0 with e = ė = 0 the SMC command is m0 (a_ref − f): the exact feed-forward."""
    ctl = make_law("smc", 0.01, 184e3)
    u, d = ctl.step(Obs(0.0, 100.0, 20.0, 100.0, 20.0, 0.01, -1.5))
    assert d["s"] == 0.0
    assert u == pytest.approx(184e3 * (0.01 + 1.5))


def test_ndo_estimates_a_constant_disturbance():
    """A point mass with unknown constant acceleration 0.03 m/s²: d̂ converges to it."""
    dt, m0 = 0.01, 184e3
    ctl = make_law("smc+ndo", dt, m0)
    v, x = 20.0, 0.0
    for k in range(300):
        u, d = ctl.step(Obs(k * dt, x, v, k * dt * 20.0, 20.0, 0.0, 0.0))
        v += (u / m0 + 0.03) * dt
        x += v * dt
    assert d["d_hat"] == pytest.approx(0.03, abs=1e-3)


@pytest.mark.parametrize("ndo_model", ["nominal", "printed"])
def test_ndo_readings_what_d_hat_absorbs(ndo_model):
    """Plant a = (1 + δ) f + u/m0 + d (eq. 16 with ΔF = δ F): the nominal NDO's model is f alone, so
    d̂ → d + δ f; the printed one's is f + Δf (eq. 17), so d̂ → d alone."""
    dt, m0, delta, f, d = 0.01, 184e3, 0.01, -0.4, 0.03
    ctl = LiSlidingMode(dt, m0, ndo=True, ndo_model=ndo_model, model_uncertainty=delta)
    v, x = 20.0, 0.0
    for k in range(300):
        u, diag = ctl.step(Obs(k * dt, x, v, k * dt * 20.0, 20.0, 0.0, f))
        v += ((1 + delta) * f + u / m0 + d) * dt
        x += v * dt
    expected = d if ndo_model == "printed" else d + delta * f
    assert diag["d_hat"] == pytest.approx(expected, abs=1e-4)
    assert abs(expected - (d + delta * f if ndo_model == "printed" else d)) > 10 * 1e-4  # the readings differ


def test_ndo_model_is_a_validated_param():
    with pytest.raises(ValueError, match="ndo_model"):
        LiSlidingMode(0.01, 184e3, ndo=True, ndo_model="both")


# ------------------------------------------------------------------------------ engine controllers
def _obs(t: float = 0.0, v: float = 20.0, x: float = 100.0, **kw) -> Observation:
    sens = {"speed_mps": v, "position_m": x, **kw.pop("sensors", {})}
    return Observation(tick=int(round(t / 0.01)), time_s=t, speed_mps=v, position_m=x,
                       ref_speed_mps=kw.pop("ref_speed_mps", v), ref_decel_mps2=kw.pop("ref_decel_mps2", 0.0),
                       peer_speed_mps=np.array([v]), peer_position_m=np.array([x]), peer_age_s=np.zeros(1),
                       ref_position_m=kw.pop("ref_position_m", x), sensors=sens)


def _ctl(name: str, **params):
    return make_controller(name, params, car_index=0, n_cars=1, mass_kg=184e3, dt_s=0.01)


def test_engine_smc_is_the_law_with_the_engine_signs():
    """brake_force_n = −u; f(x) = passive_force_n / m0; a_ref = −a* (a* > 0 slows down)."""
    ctl = _ctl("li2024_smc")
    assert ctl.needs_ref_position and "passive_force_n" in ctl.sensor_names
    assert ctl.command_names == ("brake_force_n", "airbrake_apply")
    out = ctl.step(_obs(sensors={"passive_force_n": -1.5 * 184e3}, ref_decel_mps2=-0.01))
    assert out.brake_force_n == pytest.approx(-184e3 * (0.01 + 1.5))
    assert out.diagnostics["s"] == 0.0 and out.commands["airbrake_apply"] == 0.0
    assert list(out.diagnostics) == list(ctl.diagnostic_names)


def test_airbrake_schedule_is_replayed():
    ctl = _ctl("li2024_pid", airbrake_schedule=[[1.0, 1], [3.0, 0]])
    seen = [ctl.step(_obs(t)).commands["airbrake_apply"] for t in (0.0, 0.99, 1.0, 2.0, 3.0, 4.0)]
    assert seen == [0.0, 0.0, 1.0, 1.0, 0.0, 0.0]


@pytest.mark.parametrize("name, params, msg", [
    ("li2024_smc", {"reading": "kN"}, "reading: unknown reading"),
    ("li2024_rbfnn_smc_ndo", {"observer": "rk4"}, "observer: unknown observer reading"),
    ("li2024_pid", {"airbrake_schedule": [[2.0, 1], [1.0, 0]]}, r"airbrake_schedule.1: times must ascend"),
    ("li2024_pid", {"airbrake_schedule": [[2.0, 0.5]]}, r"airbrake_schedule.0: apply must be 1 or 0"),
    ("li2024_driver", {"envelope_share": 2}, "envelope_share"),
])
def test_bad_params_are_named(name, params, msg):
    with pytest.raises(ValueError, match=msg):
        _ctl(name, **params)


def test_unknown_param_is_an_error():
    from canbrake.control.base import ControllerError
    with pytest.raises(ControllerError) as e:
        _ctl("li2024_smc", kp=1.0)
    assert e.value.param == "kp"


def test_driver_rules_section_1_2():
    d = LiDriver(0, 1, 184e3, 0.01)
    d.rules(0.0, 58 * KMH, True)
    assert not d.applied                     # not above 60 km/h
    d.rules(1.0, 65 * KMH, False)
    assert not d.applied                     # no long downgrade near
    d.rules(2.0, 65 * KMH, True)
    assert d.applied and d.v_apply_kmh == pytest.approx(65)
    d.rules(3.0, 56 * KMH, True)
    assert d.applied                         # only 9 km/h below
    d.rules(4.0, 55 * KMH, True)
    assert not d.applied                     # 10 km/h below: released
    d.rules(100.0, 70 * KMH, True)
    assert not d.applied                     # < 160 s since the last application
    d.rules(162.0, 70 * KMH, True)
    assert d.applied
    d.rules(170.0, 34 * KMH, True)
    assert d.applied                         # never released below 35 km/h


def test_driver_commands_the_valve_and_a_rate_limited_force():
    d = _ctl("li2024_driver")
    out = d.step(_obs(0.0, v=65 * KMH, sensors={"downgrade_ahead": 1.0}))
    assert out.commands["airbrake_apply"] == 1.0
    # aims 12 km/h below 65 km/h: wants to brake, limited to 100 kN/s · 10 ms
    assert out.brake_force_n == pytest.approx(1e5 * 0.01)


# ------------------------------------------------------------------------------ ECP over CAN
def test_ecp_wagon_applies_the_locomotive_broadcast():
    w = make_controller("ecp_wagon", {}, car_index=3, n_cars=106, mass_kg=1e5, dt_s=0.05)
    assert w.command_names == ("ecp_demand",) and w.broadcast_names == ()
    base = _obs(0.0)
    nothing = Observation(**{**base.__dict__, "peer_signals": {}})
    assert w.step(nothing).commands == {"ecp_demand": 0.0}        # released until a demand arrives
    got = np.full(106, np.nan)
    got[0] = 0.7
    out = w.step(Observation(**{**base.__dict__, "peer_signals": {"ecp_demand": got}}))
    assert out.commands == {"ecp_demand": 0.7}
    got[0] = np.nan                                                 # lost frame: hold the last demand
    assert w.step(Observation(**{**base.__dict__, "peer_signals": {"ecp_demand": got}})).commands["ecp_demand"] == 0.7
    with pytest.raises(ValueError, match="source_ecu"):
        make_controller("ecp_wagon", {"source_ecu": 200}, car_index=3, n_cars=106, mass_kg=1e5, dt_s=0.05)


def test_brake_test_demands_from_its_start_time():
    b = make_controller("heavy_haul_brake_test", {"brake_at_s": 5.0, "demand": 0.8}, car_index=0, n_cars=106,
                        mass_kg=184e3, dt_s=0.05)
    assert b.step(_obs(4.95)).broadcast == {"ecp_demand": 0.0}
    out = b.step(_obs(5.0))
    assert out.broadcast == {"ecp_demand": 0.8} and out.commands == {"airbrake_apply": 1.0, "ecp_demand": 0.8}


def test_a_braked_train_stops_and_stays_at_rest(tmp_path):
    """ECP full service on level track: the train stops, no vehicle rolls backwards, and it stays at
    rest (brake and running resistance hold it; Karnopp stick-slip), and the distance run equals the
    work of the dissipative forces: ½ M v0² = Σ ∫ (brake + resistance) v dt (couplers are internal;
    their hysteresis dissipates too, so ≥)."""
    v0 = 20 * KMH
    cp = _plant_on(tmp_path, 0.0, 5, 20.0, 5000.0,
                   air_brake={**train_data()["air_brake"], "mode": "ecp", "service_factor": 0.8})
    m = cp.plant
    demand = {"ecp_demand": np.ones(m.n_cars)}  # the locomotive brakes too: a released one is pushed back by the gears
    e0 = 0.5 * float(np.sum(m.mass_kg)) * v0 ** 2
    work = 0.0
    stopped_at = None
    for k in range(6000):
        v_before = m.speed_mps.copy()
        cp.step(0.01, demand if k == 0 else {})
        vm = 0.5 * (v_before + m.speed_mps)
        work += 0.01 * float(np.sum((resistance_n(m, vm) + m.air_brake.last_force_n) * vm))
        assert np.all(m.speed_mps >= 0.0), f"a vehicle rolls backwards at t = {m.time_s:.2f} s"
        if stopped_at is None and np.all(m.speed_mps == 0.0):
            stopped_at = m.time_s
    assert stopped_at is not None and stopped_at < 40.0
    assert np.all(m.speed_mps == 0.0) and np.all(cp.measurements()["accel_mps2"] == 0.0)
    assert work == pytest.approx(e0, rel=0.05)
