"""The coupled plant (TrainPlant) with the heavy-haul model's remaining parts (issue 27): Li 2024's
route (grade and curvature by position) and the line data it gives, the static initial coupler
tensions, the locomotive's electric-brake envelope and adhesion limit, the model uncertainty δ and
eq. 40's disturbance: each by hand-derived physics, then all of them with the air brake's commands
against the former HeavyHaulModel's recorded run of the same train, to rounding."""
from __future__ import annotations

import math
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from canbrake.physics import heavy_haul as hh
from canbrake.physics.rail import disturbance_n
from canbrake.physics.resistance import DavisResistance
from canbrake.physics.route import Route
from canbrake.physics.train import TrainPlant

G = 9.81
ENV = hh.TractionEnvelope(traction_start_kn=300, traction_start_until_kmh=5, traction_intercept_kn=310,
                          traction_slope_kn_per_kmh=2, traction_linear_until_kmh=60, brake_slope_kn_per_kmh=10,
                          brake_linear_until_kmh=10, brake_max_kn=100, brake_constant_until_kmh=60, power_kn_kmh=6000)
GEAR = hh.DraftGear("d", (0.0, 0.02, 0.05, 0.083), (0.0, 3.0e5, 9.0e5, 2.27e6), unloading_ratio=0.25, slack_m=0.005,
                    k_elastic_n_per_m=2.0e8, k_solid_n_per_m=2.0e8, damping_n_s_per_m=1.0e5)
MASS = np.array([90e3, 60e3, 60e3])
LENGTH = np.array([20.0, 14.0, 14.0])
SPACING = 0.5 * (LENGTH[:-1] + LENGTH[1:])
# per unit weight (N/kN, v in km/h), Li eq. 3
DAVIS_A, DAVIS_B, DAVIS_C = np.array([1.2, 0.92, 0.92]), np.array([0.0065, 0.0048, 0.0048]), \
    np.array([0.000279, 0.000125, 0.000125])
# 0-300 m level, 300-900 m 12 permille down with a 500 m curve from 400 to 600 m, then 4 permille up
ROUTE = Route.from_table([0.0, 300.0, 400.0, 600.0, 900.0, 5000.0], [0.0, -12.0, -12.0, -12.0, 4.0, 4.0],
                         [0.0, 0.0, 500.0, 0.0, 0.0, 0.0])


def _single(route: Route = ROUTE, x0: float = 250.0, v0: float = 10.0, **kw: object) -> TrainPlant:
    z = np.zeros(1)
    return TrainPlant([5.0e4], [x0], [v0], resistance=DavisResistance(z, z, z), route=route,
                      max_substep_s=1e-3, **kw)  # type: ignore[arg-type]


def _davis() -> DavisResistance:
    w = MASS * G / 1000.0
    return DavisResistance(DAVIS_A * w, DAVIS_B * w * 3.6, DAVIS_C * w * 3.6 ** 2)


def _air(mode: str = "pneumatic") -> hh.AirBrake:
    return hh.AirBrake(_consist(), apply_wave_mps=200.0, release_wave_mps=36.0, cylinder_tau_s=2.0, beta_c=0.8,
                       block_force_kn=np.array([20.0, 20.0, 20.0]), n_blocks=np.array([8.0, 8.0, 8.0]),
                       friction_coef=np.array([0.48, 0.48, 0.48]), cylinder_pressure_pa=np.array([4e5, 4e5, 4e5]),
                       mode=mode)


def _consist() -> hh.Consist:
    return hh.Consist(mass_kg=MASS, length_m=LENGTH, davis_a=DAVIS_A, davis_b=DAVIS_B, davis_c=DAVIS_C,
                      is_loco=np.array([1, 0, 0], bool))


# --------------------------------------------------------------------------------- (a) the route
def test_a_car_on_the_route_feels_its_grade_and_curve_where_it_is() -> None:
    """A 50 t car coasting without resistance from 250 m at 10 m/s: level to 300 m (no force), then
    12 ‰ down (a = +0.012 g), from 400 m also a 500 m curve (600/500 = 1.2 N/kN against the motion:
    a = (0.012 − 0.0012) g). passive_force_n is that force; the route's force is not dissipative
    (the car is not held on the downgrade at rest)."""
    p = _single()
    seen = []
    for _ in range(8000):  # 80 s
        x0, v0, f = float(p.position_m[0]), float(p.speed_mps[0]), float(p.passive_force_n()[0])
        p.step(0.01, np.zeros(1))
        seen.append((x0, float(p.position_m[0]), (float(p.speed_mps[0]) - v0) / 0.01, f))
    for xa, xb, acc, f in seen:
        if xb < 300.0:
            want = 0.0
        elif 300.0 <= xa and xb < 400.0:
            want = 0.012 * G
        elif 400.0 <= xa and xb < 600.0:
            want = (0.012 - 600.0 / 500.0 / 1000.0) * G
        elif 600.0 <= xa and xb < 900.0:
            want = 0.012 * G
        elif 900.0 <= xa:
            want = -0.004 * G
        else:
            continue  # a period that crosses a break
        assert acc == pytest.approx(want, abs=1e-9)
        assert f == pytest.approx(5.0e4 * want, abs=1e-6)
    assert seen[-1][1] > 900.0  # it went over the whole downgrade
    rest = _single(x0=350.0, v0=0.0)
    rest.step(1.0, np.zeros(1))
    assert rest.speed_mps[0] == pytest.approx(0.012 * G * 1.0, rel=1e-9)  # rolls away: an ordinary force


def test_the_compiled_route_lookup_is_the_tables() -> None:
    """Route.force_n (compiled, both plants) equals the table lookup times the weights, breakpoints,
    before 0 (level) and beyond the end (the last grade) included."""
    x = np.array([-5.0, 0.0, 299.999, 300.0, 400.0, 599.0, 600.0, 900.0, 4999.0, 5000.0, 9000.0])
    w = np.linspace(500.0, 1500.0, x.size)
    np.testing.assert_array_equal(ROUTE.force_n(w, x), ROUTE.total_permille_at(x) * w)
    assert ROUTE.force_n(w, x)[[0, 3, 4, 7, 10]].tolist() == [0.0, -12.0 * w[3], (-12.0 + 1.2) * w[4], 4.0 * w[7],
                                                               4.0 * w[10]]


def test_downgrade_ahead_is_the_routes_line_data_rule() -> None:
    """1 while a downgrade steeper than 8 ‰ and at least 500 m long lies under the train or within
    the look-ahead of its front (here 100 m): the 600 m of 12 ‰ from 300 m."""
    z = np.zeros(2)
    for x0, want in ((150.0, False), (210.0, True), (600.0, True), (915.0, True), (960.0, False)):
        p = TrainPlant([5e4, 5e4], [x0, x0 - 40.0], [0.0, 0.0], resistance=DavisResistance(z, z, z), route=ROUTE,
                       line_rule=(100.0, 8.0, 500.0))
        assert p.downgrade_ahead() is want, x0  # the rear (at x0 − 40 m) leaves the downgrade at 940 m
        assert p.downgrade_ahead() == ROUTE.long_downgrade_ahead(x0, x0 - 40.0, 100.0, 8.0, 500.0)
    assert TrainPlant([5e4], [0.0], [0.0]).downgrade_ahead() is False  # no route: none


# ----------------------------------------------------------------------------- (b) static couplers
def test_static_couplers_carry_the_resistance_behind_them() -> None:
    """At 20 m/s on the route's downgrade: coupler j carries the running + line resistance of the
    cars behind it (on the draft gear's loading curve: stretched by its slack plus the curve's
    deflection at that force), and with the locomotive's force balancing the train's resistance the
    train starts in equilibrium: no car accelerates over the first step (a = 0 is the equilibrium
    these tensions describe: a start at a held speed, as the former heavy-haul model's)."""
    v0, x0 = 20.0, 700.0
    x = x0 - np.concatenate([[0.0], np.cumsum(SPACING)])
    p = TrainPlant(MASS, x, v0, resistance=_davis(), draft_gears=[GEAR, GEAR], coupler_stiffness_n_per_m=1.0,
                   coupler_nonlinearity_per_m2=0.0, route=ROUTE, static_couplers=True, max_substep_s=1e-3)
    w = MASS * G / 1000.0
    vk = v0 * 3.6
    r = (DAVIS_A + DAVIS_B * vk + DAVIS_C * vk * vk - 12.0) * w  # N/kN x kN, on the 12 permille downgrade
    assert p.coupler_force_n == pytest.approx([r[1] + r[2], r[2]], rel=1e-7)  # (k_e = 2e8 N/m times rounding)
    tension = np.array([r[1] + r[2], r[2]])  # < 0 here: the cars behind push (compression)
    stretch = np.sign(tension) * (GEAR.slack_m + np.interp(np.abs(tension), GEAR.curve_n, GEAR.curve_m))
    ref_x = x0 - np.concatenate([[0.0], np.cumsum(SPACING + stretch)])
    np.testing.assert_allclose(p.position_m, ref_x, rtol=0, atol=1e-9)
    v_before = p.speed_mps.copy()
    p.step(0.01, np.array([-r.sum(), 0.0, 0.0]))  # the locomotive holds the train (brakes: r < 0 downhill)
    assert np.abs(p.speed_mps - v_before).max() < 1e-9  # no car moves relative to another: no surge
    p.reset()  # back to the static state
    np.testing.assert_allclose(p.position_m, ref_x, rtol=0, atol=1e-9)
    chen = TrainPlant(MASS, x, v0, resistance=_davis(), coupler_stiffness_n_per_m=2.0e6,
                      coupler_nonlinearity_per_m2=-0.5, route=ROUTE, static_couplers=True)
    assert chen.coupler_force_n == pytest.approx([r[1] + r[2], r[2]], rel=1e-7)  # Chen's coupler solved for it


def test_static_couplers_beyond_a_softening_couplers_peak_is_refused_in_one_line() -> None:
    z = np.zeros(2)
    with pytest.raises(ValueError, match=r"^static_couplers: coupler 1 cannot carry the 1e\+06 N behind it") as e:
        TrainPlant([5e4, 5e4], [10.0, 0.0], [1.0, 1.0], resistance=DavisResistance(np.array([0.0, 1e6]), z, z),
                   coupler_stiffness_n_per_m=8e4, coupler_nonlinearity_per_m2=-0.5, static_couplers=True)
    assert "\n" not in str(e.value)


# ------------------------------------------------------------------- (c) the locomotive's limits
def test_the_locomotives_electric_brake_and_adhesion_cap_its_force() -> None:
    """A 90 t locomotive alone at 36 km/h (10 m/s), no resistance: a 1 MN brake command gives
    F_B(36 km/h) = 100 kN (eq. 2's constant part), a 1 MN traction command F_T = 310 − 2·36 = 238 kN;
    with adhesion μ = 0.1 both are capped at μ m g = 88.29 kN; at 5 m/s = 18 km/h with
    Curtius–Kniffler's μ(v) the cap is μ(18) m g. The force is held as the speed changes within a
    period: re-evaluated every sub-step."""
    def loco(**kw: object) -> TrainPlant:
        return TrainPlant([90e3], [0.0], [10.0], resistance=DavisResistance(np.zeros(1), np.zeros(1), np.zeros(1)),
                          traction_envelope=[ENV], electric_brake_envelope=True, max_substep_s=1e-4, **kw)  # type: ignore[arg-type]

    for cmd, force in ((1e6, 1.0e5), (-1e6, -2.38e5)):
        p = loco()
        p.step(1e-4, np.array([cmd]))
        assert p.accel_mps2[0] * 90e3 == pytest.approx(-force, rel=1e-9)
        assert p.applied_force_n[0] == pytest.approx(force, rel=1e-9)
    for cmd in (1e6, -1e6):
        p = loco(loco_adhesion=[hh.LocoAdhesion(mu0=0.1)])
        p.step(1e-4, np.array([cmd]))
        assert p.applied_force_n[0] == pytest.approx(math.copysign(0.1 * 90e3 * G, cmd), rel=1e-9)
    ck = hh.LocoAdhesion(mu0=0.33, curve="curtius_kniffler")
    p = TrainPlant([90e3], [0.0], [5.0], resistance=DavisResistance(np.zeros(1), np.zeros(1), np.zeros(1)),
                   loco_adhesion=[ck], max_substep_s=1e-4)
    p.step(1e-4, np.array([-1e6]))
    assert -p.applied_force_n[0] == pytest.approx(ck.mu(5.0) * 90e3 * G, rel=1e-9)
    assert ck.mu(5.0) == pytest.approx(0.33 * (0.161 + 7.5 / 62.0) / (0.161 + 7.5 / 44.0), rel=1e-12)
    # the brake envelope follows the speed through a period: 10 -> 5 km/h region linear F_B = 10 v
    p = TrainPlant([90e3], [0.0], [2.0], resistance=DavisResistance(np.zeros(1), np.zeros(1), np.zeros(1)),
                   traction_envelope=[ENV], electric_brake_envelope=True, max_substep_s=1e-3)
    p.step(1.0, np.array([1e6]))  # dv/dt = −10·3.6 v·1000/m: v(1) = 2 e^(−36000/90000)
    assert p.speed_mps[0] == pytest.approx(2.0 * math.exp(-0.4), rel=2e-3)


# ------------------------------------------------------------------ (d) δ and the disturbance
def test_uncertainty_scales_every_non_control_force_and_eq40_is_added() -> None:
    """A 50 t car at 10 m/s on the 12 ‰ downgrade (at 700 m) with Davis resistance c0 = 2 kN and an air brake
    force of 0 (none): m a = (1 + δ)(0.012 m g − c0) + σ(t, v), δ = 0.05; σ of eq. 40 with the
    paper's coefficients (on). passive_force_n stays nominal (no δ, no σ)."""
    m, c0, delta, coef = 5.0e4, 2.0e3, 0.05, (0.002, 0.001, 0.0003)
    z = np.zeros(1)

    def car(**kw: object) -> TrainPlant:
        return TrainPlant([m], [700.0], [10.0], resistance=DavisResistance(np.array([c0]), z, z), route=ROUTE,
                          max_substep_s=1e-3, **kw)  # type: ignore[arg-type]

    p = car(uncertainty=delta, li_disturbance_on=[True], li_disturbance_coef=coef)
    nominal = 0.012 * m * G - c0
    assert p.passive_force_n()[0] == pytest.approx(nominal, rel=1e-12)
    p.step(1e-3, np.zeros(1))
    sigma = disturbance_n(np.array([m]), 0.0, np.array([10.0]), np.array([True]), coef)[0]
    assert sigma == pytest.approx(m * (0.002 + 0.001 * math.sin(1.0) + 0.0003 * 10 ** (1 / 3) * (math.sin(2.0)
                                                                                                 + math.cos(1.0))))
    assert p.accel_mps2[0] * m == pytest.approx((1 + delta) * nominal + sigma, rel=1e-9)
    off = car(uncertainty=delta, li_disturbance_on=[False], li_disturbance_coef=coef)
    off.step(1e-3, np.zeros(1))
    assert off.accel_mps2[0] * m == pytest.approx((1 + delta) * nominal, rel=1e-9)
    with pytest.raises(ValueError, match=r"^uncertainty must be in \[-0.5, 0.5\], got 0.7$"):
        car(uncertainty=0.7)
    with pytest.raises(ValueError, match=r"^li_disturbance_on must have one value per car \(1\)$"):
        car(li_disturbance_on=[True, False])


# ------------------------------------------------------- all of them against the heavy-haul model
#: the former HeavyHaulModel's measurements of :func:`_run_plant` on :func:`_pair`'s train, recorded
#: before its deletion (issue 27; by this file's ``__main__`` at commit 50d85fe, ``_pair(heavy_haul=True)``
#: then built ``hh.HeavyHaulModel(_consist(), ROUTE, [GEAR, GEAR], _air(mode), envelopes=[ENV, None,
#: None], v0_mps=15.0, x0_m=250.0, uncertainty=0.02, disturbance_on=on, disturbance_coef=coef,
#: integration_step_s=h, adhesion=adh)``)
PAIR_REF = Path(__file__).parent / "data" / "li_pair_ref.npz"
PAIR_KEYS = ("speed_mps", "coupler_force_n", "passive_force_n", "brake_cylinder_pressure_pa")


def _pair(h: float, mode: str = "pneumatic") -> object:
    """Locomotive + 2 wagons with draft gears and air brakes (``mode`` pneumatic or ecp) on the
    route from 250 m at 15 m/s, static couplers, the locomotive's envelopes and adhesion (μ = 0.25),
    δ = 0.02 and eq. 40's disturbance on the locomotive and the last wagon, sub-step ``h``: the
    coupled plant behind the plant contract."""
    from canbrake.build import CoupledPlant

    on = np.array([True, False, True])
    coef = (0.002, 0.001, 0.0003)
    adh = [hh.LocoAdhesion(mu0=0.25, curve="curtius_kniffler"), None, None]
    x = 250.0 - np.concatenate([[0.0], np.cumsum(SPACING)])
    return CoupledPlant(TrainPlant(MASS, x, 15.0, resistance=_davis(), draft_gears=[GEAR, GEAR],
                                   coupler_stiffness_n_per_m=1.0, coupler_nonlinearity_per_m2=0.0,
                                   traction_envelope=[ENV, None, None], air_brake=_air(mode), route=ROUTE,
                                   static_couplers=True, electric_brake_envelope=True, loco_adhesion=adh,
                                   uncertainty=0.02, li_disturbance_on=on, li_disturbance_coef=coef, max_substep_s=h))


def _commands(t: float, mode: str) -> dict[str, np.ndarray]:
    """400 kN traction (capped by the envelope and adhesion) for 10 s, 300 kN electric brake (capped
    at F_B) to 20 s, then coasting; the air brake applied at 25 s, released at 31 s and applied
    again at 34.005 s (pneumatic: the driver's valve; ECP: each car's demand, changed in steps, the
    last wagon's left unchanged (NaN) at one of them)."""
    u = -4.0e5 if t < 10 else 3.0e5 if t < 20 else 0.0
    cmd = {"brake_force_n": np.array([u, np.nan, np.nan])}
    on = 25.0 <= t < 31.0 or t >= 34.005
    if mode == "pneumatic":
        cmd["airbrake_apply"] = np.array([1.0 if on else 0.0, np.nan, np.nan])
    else:
        level = 0.0 if not on else 0.6 if t < 28.0 or t >= 34.005 else 0.9
        cmd["ecp_demand"] = np.array([level, level, np.nan if 28.0 <= t < 29.0 else level])
    return cmd


def _run_plant(mode: str) -> dict[str, np.ndarray]:
    """40 s of :func:`_commands` at a 1 ms sub-step; :data:`PAIR_KEYS` every 200 ms, (200, n)."""
    plant: Any = _pair(1e-3, mode)
    out: dict[str, list[np.ndarray]] = {k: [] for k in PAIR_KEYS}
    for k in range(4000):
        plant.step(0.01, _commands(0.01 * k, mode))
        if k % 20 == 19:
            m = plant.measurements()
            for key in PAIR_KEYS:
                out[key].append(np.array(m[key], dtype=float))
    return {f"{mode}:{k}": np.array(v) for k, v in out.items()}


@pytest.mark.parametrize("mode", ["pneumatic", "ecp"])
def test_the_coupled_plant_with_li_s_parts_agrees_with_the_heavy_haul_model_to_rounding(mode: str) -> None:
    """Route, static couplers, envelopes and adhesion, δ and σ, and the air brake's commands
    together, against the heavy-haul model's recorded run (:data:`PAIR_REF`): the two integrate
    alike (semi-implicit Euler, couplers from the positions, the locomotive's limits applied to the
    held force as the heavy-haul model did, a brake command acting from its instant: the fill update
    that reached it redone) through traction, electric braking, coasting on the route and the air
    brake applied, released and applied again. The remaining differences are the order of the
    floating-point operations (the two sum the forces differently): measured 2.8e-10 m/s and 1e-3 N
    of 1.7e5 N; tolerances 1e-9 m/s, 1e-7 of the peak coupler and passive force (the gears' 2e8 N/m
    turn 1e-13 m of position into 2e-5 N), 1e-6 Pa of cylinder pressure."""
    ref = np.load(PAIR_REF)
    got = _run_plant(mode)
    sa, fa, pa, ca = (ref[f"{mode}:{k}"] for k in PAIR_KEYS)
    sb, fb, pb, cb = (got[f"{mode}:{k}"] for k in PAIR_KEYS)
    assert sa[49, 0] * 3.6 > 70.0 and sa[99, 0] * 3.6 > 60.0 and sa[-1, 0] < sa[124, 0] - 1.0  # the phases
    peak = np.abs(fa).max()
    assert peak > 5e4 and ca.max() > 1e5  # the brake was applied
    assert np.abs(sa - sb).max() < 1e-9
    assert np.abs(fa - fb).max() < 1e-7 * peak
    assert np.abs(pa - pb).max() < 1e-7 * np.abs(pa).max()
    assert np.abs(ca - cb).max() < 1e-6


# ----------------------------------------------------------------------------- the schema
def _mixed_on_route(tmp_path, **over: object) -> dict:
    """test_mixed_kernel's mixed train (loco, draft-gear car, Chen car, air-braked wagon) on a route
    file with Li's line and disturbance parts."""
    import copy

    import test_mixed_kernel as M

    (tmp_path / "route.csv").write_text("position_m,grade_permille,curve_radius_m\n0,0,0\n300,-12,0\n400,-12,500\n"
                                        "600,-12,0\n900,4,0\n5000,4,0\n")
    data = M._mixed()
    data["train"].update(copy.deepcopy({
        "track": {"route": {"file": str(tmp_path / "route.csv"), "lookahead_m": 100, "long_downgrade_permille": 8,
                            "long_downgrade_min_length_m": 500}},
        "start_position_m": 150.0, "uncertainty": 0.02,
        "disturbance": {"enabled": True, "vehicles": [1, 4]}}))
    data["train"]["vehicle_types"]["loco"]["wheels"] = {"model": "adhesion_limit", "mu": 0.25,
                                                        "curve": "curtius_kniffler"}
    for k, v in over.items():
        node = data
        *path, last = k.split(".")
        for part in path:
            node = node[part]
        node[last] = v
    return data


def test_a_mixed_train_takes_li_s_route_limits_and_disturbance_on_the_coupled_kernel(tmp_path) -> None:
    """The route, the start position (the first vehicle's centre; the others behind at their
    nominal spacings, then moved back by the static stretches), δ, eq. 40 on vehicles 1 and 4, the
    locomotive's adhesion limit and its envelope's electric brake all reach the coupled plant; its
    downgrade_ahead follows the route as the train runs onto the downgrade."""
    from canbrake.build import build_plant_model
    from canbrake.scenario import resolve

    scn = resolve(_mixed_on_route(tmp_path), "t.yaml")
    assert scn.train.kernel_name == "coupled"
    plant = build_plant_model(scn)
    tp = plant.plant
    assert tp.route is not None and tp.static_couplers and tp.electric_brake_envelope
    assert tp.uncertainty == 0.02 and tp._li_dist[0].tolist() == [True, False, False, True]  # type: ignore[index]
    assert [a is not None for a in tp.loco_adhesion] == [True, False, False, False]  # type: ignore[union-attr]
    assert tp.position_m[0] == 150.0
    nominal = 150.0 - np.cumsum([0.0, 21.0, 22.0, 18.0])
    assert np.all(tp.position_m[1:] <= nominal[1:]) and np.all(tp.position_m[1:] > nominal[1:] - 0.2)
    assert plant.measurements()["downgrade_ahead"][0] == 0.0  # 300 m is beyond 150 + 100 m of look-ahead
    for _ in range(700):  # 7 s at about 10 m/s: the front passes 200 m
        plant.step(0.01, {"brake_force_n": np.zeros(4)})
    assert plant.measurements()["downgrade_ahead"].tolist() == [1.0] * 4


@pytest.mark.parametrize("over, fragment", [
    ({"train.track.grade_permille": 3.0}, "train.track.grade_permille: a train on a route takes its grade"),
    ({"train.disturbance": {"enabled": True, "vehicles": [1, 9]}}, "train.disturbance.vehicles: [9] outside 1..4"),
    ({"initial.position_m": [0.0, -20.0, -40.0, -60.0]},
     "initial.position_m: a train on a route is placed by train.start_position_m"),
])
def test_bad_li_parts_on_the_coupled_kernel_are_one_line(tmp_path, over: dict, fragment: str) -> None:
    from canbrake.build import build_plant_model
    from canbrake.scenario import ScenarioError, resolve

    with pytest.raises((ScenarioError, ValueError)) as e:
        build_plant_model(resolve(_mixed_on_route(tmp_path, **over), "t.yaml"))
    assert "\n" not in str(e.value)
    assert fragment in str(e.value), str(e.value)


def test_li_s_parts_without_draft_gears_or_air_brakes_are_still_refused() -> None:
    """δ, eq. 40 and the route go with Li's draft gears or air brakes; a Chen train refuses them."""
    from canbrake.scenario import ScenarioError, resolve

    from conftest import component_scenario

    car = {"mass_kg": 40000, "length_m": 22.0, "coupler": {"model": "chen"}, "brake": {"model": "ideal"}}
    data = component_scenario({"car": car}, [{"type": "car", "count": 3}], uncertainty=0.1)
    with pytest.raises(ScenarioError, match=r"train.uncertainty: used by draft-gear trains"):
        resolve(data, "t.yaml")


def test_the_integration_step_of_a_mixed_train(tmp_path) -> None:
    """train.integration_step_s, when given, is the coupled plant's sub-step (also the default's
    10 ms written out); not given, the control period over plant.substeps."""
    from canbrake.build import build_plant_model
    from canbrake.scenario import resolve

    data = _mixed_on_route(tmp_path)
    data["plant"] = {"substeps": 4}
    assert build_plant_model(resolve(data, "t.yaml")).plant.max_substep_s == pytest.approx(0.0025)
    for h in (0.01, 0.002):
        data["train"]["integration_step_s"] = h
        assert build_plant_model(resolve(data, "t.yaml")).plant.max_substep_s == h

