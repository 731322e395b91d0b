"""The coupled kernel with Li 2024's draft gears, air brakes and eq. 3 resistance beside Chen's
couplers and ideal/EP brakes (issue 27): physics derived by hand, the heavy-haul model as a
reference, the assembler's choice of kernel and its one-line errors, and the shipped scenario
scenarios/mixed_three_papers.yaml."""
from __future__ import annotations

import copy
import math

import numpy as np
import pytest

from canbrake.build import build_plant_model
from canbrake.physics import heavy_haul as hh
from canbrake.physics.resistance import DavisResistance
from canbrake.physics.train import TrainPlant
from canbrake.scenario import ScenarioError, load_scenario, resolve

from conftest import SCENARIOS, component_plant, component_scenario

# a draft gear with a linear first segment: k1 = 3e5 N / 0.02 m = 1.5e7 N/m up to 20 mm
GEAR = hh.DraftGear("g", (0.0, 0.02, 0.05, 0.083), (0.0, 3.0e5, 9.0e5, 2.27e6), unloading_ratio=0.25, slack_m=0.005,
                    k_elastic_n_per_m=2.0e8, k_solid_n_per_m=2.0e8, damping_n_s_per_m=0.0)
K1 = 3.0e5 / 0.02


def _two_cars(v_front: float, h: float, gear: hh.DraftGear = GEAR, m: float = 1.0e4) -> TrainPlant:
    """Two cars of ``m`` kg joined by one draft gear, no resistance, the front one at ``v_front`` m/s."""
    z = np.zeros(2)
    return TrainPlant([m, m], [10.0, 0.0], [v_front, 0.0], resistance=DavisResistance(z, z, z), draft_gears=[gear],
                      coupler_stiffness_n_per_m=1.0, coupler_nonlinearity_per_m2=0.0, max_substep_s=h)


# --------------------------------------------------------------------------------- draft gears
def test_a_draft_gear_pulled_apart_shows_slack_then_loading_curve_then_unloading_on_the_ratio() -> None:
    """Two 10 t cars separating at v0 = 1 m/s: no force within the 5 mm slack; then the gear loads on
    f_l = k1 d; the relative motion (reduced mass μ = 5 t) stops where ½ μ v0² = ½ k1 d_m²,
    d_m = v0 √(μ/k1) (18.3 mm < 20 mm: on the first segment); it unloads first along eq. (8)'s
    stiffness k_e down to f_u (Δd = 0.75 k1 d_m / (k_e − 0.25 k1)), then on f_u = 0.25 f_l. The
    energy given back (the area under that path) sends the cars towards each other at √(2 E_r / μ)
    as the gear re-enters its slack (they then cross it and meet in compression)."""
    v0, mu = 1.0, 5.0e3
    p = _two_cars(v0, 1e-4)
    rows = []
    for _ in range(400):  # 0.2 s in 0.5 ms periods of 0.1 ms sub-steps
        p.step(5e-4, np.zeros(2))
        rows.append((float(p.deflection_m[0]), float(p.coupler_force_n[0]), float(p.speed_mps[0] - p.speed_mps[1])))
    d, f, rel = (np.array(c) for c in zip(*rows))
    slack, ke = GEAR.slack_m, GEAR.k_elastic_n_per_m
    assert np.all(f[np.abs(d) < slack] == 0.0)  # within the slack: no force
    assert (np.abs(d) < slack).sum() > 20
    g = d - slack  # gear deflection
    peak = int(np.argmax(d))
    d_m = v0 * math.sqrt(mu / K1)
    assert g[peak] == pytest.approx(d_m, rel=0.01)
    back = peak + int(np.argmax(d[peak:] < slack))  # the first sample back in the slack
    before, after = np.arange(d.size) < peak, (np.arange(d.size) > peak) & (np.arange(d.size) < back)
    loading = before & (g > 1e-4)
    assert loading.sum() > 10
    assert np.allclose(f[loading], K1 * g[loading], rtol=1e-9)  # on f_l while it loads
    dd = 0.75 * K1 * d_m / (ke - 0.25 * K1)
    unloading = after & (g > 1e-4) & (g < g[peak] - dd - 1e-4)
    assert unloading.sum() > 10
    assert np.allclose(f[unloading], 0.25 * K1 * g[unloading], rtol=1e-9)  # on f_u = 0.25 f_l
    band = after & (g > 1e-4)
    assert np.all((f[band] >= 0.25 * K1 * g[band] * (1 - 1e-9)) & (f[band] <= K1 * g[band] * (1 + 1e-9)))
    e_back = 0.5 * (K1 * d_m + 0.25 * K1 * (d_m - dd)) * dd + 0.5 * 0.25 * K1 * (d_m - dd) ** 2
    assert e_back < 0.3 * 0.5 * mu * v0 ** 2  # about a quarter: f_u = 0.25 f_l
    assert rel[back] == pytest.approx(-math.sqrt(2.0 * e_back / mu), rel=0.01)  # closing again


def test_the_slack_is_free_play_in_compression_too() -> None:
    p = _two_cars(-0.5, 1e-3)
    for _ in range(5):  # 5 ms at 0.5 m/s: 2.5 mm into the 5 mm slack
        p.step(1e-3, np.zeros(2))
    assert -GEAR.slack_m < p.deflection_m[0] < 0
    assert p.coupler_force_n[0] == 0.0
    assert np.all(p.speed_mps == [-0.5, 0.0])


ENV = hh.TractionEnvelope(traction_start_kn=300, traction_start_until_kmh=5, traction_intercept_kn=310,
                          traction_slope_kn_per_kmh=2, traction_linear_until_kmh=60, brake_slope_kn_per_kmh=10,
                          brake_linear_until_kmh=10, brake_max_kn=100, brake_constant_until_kmh=60, power_kn_kmh=6000)
GEAR_D = hh.DraftGear("d", GEAR.curve_m, GEAR.curve_n, unloading_ratio=0.25, slack_m=0.005, k_elastic_n_per_m=2.0e8,
                      k_solid_n_per_m=2.0e8, damping_n_s_per_m=1.0e5)
MASS = np.array([90e3, 60e3, 60e3])
LENGTH = np.array([20.0, 14.0, 14.0])


def _air(mode: str = "pneumatic", pipe: hh.BrakePipe | None = None) -> hh.AirBrake:
    z = np.zeros(3)
    c = hh.Consist(mass_kg=MASS, length_m=LENGTH, davis_a=z, davis_b=z, davis_c=z, is_loco=np.array([1, 0, 0], bool))
    return hh.AirBrake(c, apply_wave_mps=200.0, release_wave_mps=36.0, cylinder_tau_s=2.0, beta_c=0.8,
                       block_force_kn=np.array([20.0, 20.0, 20.0]), n_blocks=np.array([8.0, 8.0, 8.0]),
                       friction_coef=np.array([0.48, 0.48, 0.48]), cylinder_pressure_pa=np.array([4e5, 4e5, 4e5]),
                       mode=mode, pipe=pipe)


def _loco_two_wagons(h: float, v0: float = 5.0, **kw: object) -> TrainPlant:
    z = np.zeros(3)
    x = -np.concatenate([[0.0], np.cumsum(0.5 * (LENGTH[:-1] + LENGTH[1:]))])
    return TrainPlant(MASS, x, v0, resistance=DavisResistance(z, z, z), draft_gears=[GEAR_D, GEAR_D],
                      coupler_stiffness_n_per_m=1.0, coupler_nonlinearity_per_m2=0.0, traction_envelope=[ENV, None, None],
                      max_substep_s=h, **kw)  # type: ignore[arg-type]


def test_the_passive_force_li_s_controllers_read_is_newton_s() -> None:
    """``passive_force_n`` (Li's nominal F_i: couplers − resistance − grade − air brake) of the
    coupled plant: by Newton's law each coasting car's momentum change over a sub-step is its
    passive force times the step (no control force; the plant stepped one sub-step at a time);
    ``downgrade_ahead`` is 0 on a level track. (Its agreement with the former heavy-haul model:
    tests/test_li_on_train_plant.py.)"""
    from canbrake.build import CoupledPlant

    newton = []
    # Newton: stepped by single sub-steps, each car's momentum change is h times its passive force
    # at the sub-step's start (the couplers' force of the state the sub-step starts from)
    plant = CoupledPlant(_loco_two_wagons(1e-3, air_brake=_air()))
    assert np.all(plant.measurements()["downgrade_ahead"] == 0.0)
    for k in range(1500):  # 0.5 s of traction to load the gears, then 1 s of coasting
        f0, v0 = plant.measurements()["passive_force_n"].copy(), plant.measurements()["speed_mps"].copy()
        plant.step(1e-3, {"brake_force_n": np.array([-2.0e5 if k < 500 else 0.0, np.nan, np.nan])})
        if k >= 500:
            newton.append((MASS * (plant.measurements()["speed_mps"] - v0), 1e-3 * f0))
    mdv, impulse = (np.array([row[i] for row in newton]) for i in (0, 1))
    assert np.abs(impulse).max() > 10.0  # the gears work: forces of 10 kN and more
    np.testing.assert_allclose(mdv, impulse, rtol=1e-9, atol=1e-9 * np.abs(impulse).max())


# --------------------------------------------------------------------------------- air brakes
def test_an_air_braked_wagon_fills_after_the_pipe_delay_to_the_air_brake_force() -> None:
    """Driver's valve at 1 s; the rear wagon's centre is D = 10 + 14 + 7 = 31 m behind the
    locomotive's: its signal arrives at 1 + D/200 = 1.155 s, then its cylinder fills as
    1 − e^(−(t − 1.155)/2) (τ = 2 s); its block force is eq. (10) at K = 20 kN × fill, 8 blocks,
    β_c = 0.8, φ of eqs. (11)-(12) with coef 0.48 at its speed."""
    h = 1e-3
    p = _loco_two_wagons(h, v0=0.0, air_brake=_air())
    t_arr = 1.0 + 31.0 / 200.0
    seen = []
    for k in range(400):  # 4 s at rest (the brake holds the train; no traction)
        if k == 100:
            p.command_air(1.0, None)
        p.step(0.01, np.zeros(3))
        seen.append((p.time_s, float(p.air_brake.fill[2]), float(p.air_brake_n[2])))  # type: ignore[attr-defined,index]
    for t, fill, force in seen:
        if t < t_arr - 1e-9:
            assert fill == 0.0 and force == 0.0
        else:
            want = 1.0 - math.exp(-(t - t_arr) / 2.0)
            assert fill == pytest.approx(want, abs=h / 2.0 + 1e-9)  # the arrival seen on the sub-step grid
            kk = 20.0 * fill
            phi = 0.48 * (kk + 200.0) / (4.0 * kk + 200.0)  # at v = 0
            assert force == pytest.approx(1000.0 * 0.8 * 8 * phi * kk, rel=1e-12)


def test_ecp_demand_fills_each_air_braked_car_without_a_wave_and_brakes_the_train_by_its_block_forces() -> None:
    """ECP: every cylinder follows its own demand at once (no wave); the block forces decelerate
    the (gear-coupled, resistance-free) train: Σ m a = −Σ F (the couplers' forces cancel; F taken
    at the start of the 10 ms step, while the cylinders still fill: within 3 %)."""
    p = _loco_two_wagons(1e-3, v0=10.0, air_brake=_air("ecp"))
    p.command_air(None, np.array([1.0, 1.0, 1.0]))  # acts from t = 0: one fill update of 1 ms at once
    p.step(0.5, np.zeros(3))
    want = 1.0 - math.exp(-0.501 / 2.0)
    assert np.allclose(p.air_brake.fill, want, rtol=1e-9)  # type: ignore[attr-defined]
    f = p.air_brake_n
    v_before = p.speed_mps.copy()
    p.step(0.01, np.zeros(3))
    a = (p.speed_mps - v_before) / 0.01
    # same block force per 90 t / 60 t car: the loco decelerates less; the gears' slack takes it up
    assert np.all(a < 0)
    assert float(np.sum(MASS * a)) == pytest.approx(-float(np.sum(f)), rel=0.03)  # type: ignore[arg-type]


# ----------------------------------------------------------------------------- assembled trains
LOCO = {"mass_kg": 90000, "length_m": 20.0,
        "resistance": {"model": "davis"},
        "coupler": {"model": "draft_gear", "gear": "g"},
        "brake": {"model": "air", "kind": "shoe", "cylinder_diameter_mm": 254, "cylinder_pressure_kpa": 430,
                  "lever_ratio": 6.6, "efficiency": 0.9, "cylinders": 1, "shoes": 8, "friction_coefficient": 0.481},
        "traction": {"model": "envelope", **{k: getattr(ENV, k) for k in ENV.__dataclass_fields__}}}
CAR = {"mass_kg": 40000, "length_m": 22.0, "resistance": {"model": "davis"},
       "coupler": {"model": "chen", "stiffness_n_per_m": 2.0e6, "epsilon_per_m2": 0.0}, "brake": {"model": "ideal"}}
WAGON = {**LOCO, "mass_kg": 60000, "length_m": 14.0}
del WAGON["traction"]
GEARS = {"g": {"curve_mm": [0, 20, 50, 83], "curve_kn": [0, 300, 900, 2270], "unloading_ratio": 0.25,
               "slack_mm": 50, "k_elastic_n_per_m": 2.0e8, "k_solid_n_per_m": 2.0e8, "damping_n_s_per_m": 0.0}}
AIR = {"mode": "pneumatic", "apply_wave_mps": 200, "release_wave_mps": 36, "cylinder_tau_s": 2.0, "service_factor": 0.8}


def _mixed(**over: object) -> dict:
    types = {"loco": LOCO, "car": {**CAR, "coupler": {"model": "draft_gear", "gear": "g"}}, "chen_car": CAR,
             "wagon": WAGON}
    data = component_scenario(copy.deepcopy(types), [{"type": "loco"}, {"type": "car"}, {"type": "chen_car"}, {"type": "wagon"}],
                              speed_kmh=36.0, draft_gears=GEARS, air_brake=AIR)
    data["ecus"] = [{"name": "e{v}", "vehicles": "1-3"}]  # none on the wagon: it has no force equipment
    for k, v in over.items():
        node = data
        *path, last = k.split(".")
        for part in path:
            node = node[part]
        node[last] = v
    return data


def test_a_mixed_train_and_li_s_trains_go_to_the_coupled_kernel() -> None:
    assert resolve(_mixed(), "t.yaml").train.kernel_name == "coupled"
    for name in ("li2024_pid", "li2024_ecp_over_can", "hh106_ecp_consensus"):
        assert load_scenario(name).train.kernel_name == "coupled"
    assert load_scenario("mixed_three_papers").train.kernel_name == "coupled"


def test_per_weight_resistance_is_li_eq_3_as_davis_terms() -> None:
    """w = a + b v + c v² N/kN (v in km/h) times the weight m g / 1000 kN = c0 + c1 v + c2 v² (v in m/s)."""
    data = _mixed()
    data["train"]["vehicle_types"]["wagon"]["resistance"] = {
        "model": "per_weight", "a_n_per_kn": 0.92, "b_n_per_kn_per_kmh": 0.0048, "c_n_per_kn_per_kmh2": 0.000125}
    p = component_plant(data)
    w = 60000 * 9.81 / 1000.0
    r = p.resistance
    assert (r.c0_n[3], r.c1_n_per_mps[3], r.c2_n_per_mps2[3]) == pytest.approx((0.92 * w, 0.0048 * w * 3.6,
                                                                                 0.000125 * w * 3.6 ** 2), rel=1e-12)
    v_kmh = 72.0
    assert r.c0_n[3] + r.c1_n_per_mps[3] * 20.0 + r.c2_n_per_mps2[3] * 400.0 == pytest.approx(
        (0.92 + 0.0048 * v_kmh + 0.000125 * v_kmh ** 2) * w, rel=1e-12)


def test_a_mixed_trains_ideal_braked_cars_decelerate_as_f_over_m_while_the_air_wagon_coasts() -> None:
    """Loco (air brake, traction, draft gear) – car (ideal brake, Chen coupler) – car (ideal brake,
    draft gear with 50 mm slack) – wagon (air brake, no traction). brake_force_n = m a on the loco
    and the cars (the wagon ignores it: no force equipment); no resistance. The loco and cars
    decelerate at exactly a; the wagon coasts until the 50 mm slack in front of it is taken up
    (√(2 · 0.05 / a) = 0.447 s), then the gear pushes it back."""
    data = _mixed()
    data["train"]["vehicles"] = [{"type": "loco"}, {"type": "chen_car"}, {"type": "car"}, {"type": "wagon"}]
    for t in data["train"]["vehicle_types"].values():
        t["resistance"] = {"model": "davis"}
    plant = build_plant_model(resolve(copy.deepcopy(data), "t.yaml"))
    tp = plant.plant
    assert tp.air_braked.tolist() == [True, False, False, True]
    a = 0.5
    m = tp.mass_kg
    for _ in range(40):  # 0.4 s
        v0 = tp.speed_mps.copy()
        plant.step(0.01, {"brake_force_n": m * a})
        acc = (tp.speed_mps - v0) / 0.01
        assert acc[:3] == pytest.approx([-a] * 3, abs=1e-9)
        assert acc[3] == 0.0
    assert plant.measurements()["coupler_force_n"][2] == 0.0
    assert -0.05 < plant.measurements()["deflection_m"][2] < -0.035  # 0.04 m = a t² / 2 of the slack
    for _ in range(20):  # the slack is gone by 0.447 s: the wagon is pushed back now
        plant.step(0.01, {"brake_force_n": m * a})
    assert plant.measurements()["coupler_force_n"][2] < 0.0


def test_the_mixed_trains_measurements_and_commands_follow_the_plant_contract() -> None:
    plant = build_plant_model(resolve(_mixed(), "t.yaml"))
    assert {"airbrake_apply", "ecp_demand", "brake_force_n"} <= set(plant.command_names)
    plant.step(0.01, {"airbrake_apply": np.array([1.0, np.nan, np.nan, np.nan])})
    m = plant.measurements()
    for k in ("brake_cylinder_pressure_pa", "air_brake_n", "position_m", "speed_mps", "accel_mps2", "applied_brake_n"):
        assert m[k].shape == (4,)
    assert m["coupler_force_n"].shape == (3,)
    assert np.isnan(m["brake_cylinder_pressure_pa"][[1, 2]]).all()
    assert m["brake_cylinder_pressure_pa"][0] > 0 and m["brake_cylinder_pressure_pa"][3] == 0.0  # the rear: later


# ----------------------------------------------------------------------------- bad combinations
@pytest.mark.parametrize("over, fragment", [
    ({"train.air_brake": None}, "train.air_brake: vehicle type loco has an air brake, which needs the train's "
                                "brake pipe"),
    ({"train.vehicles": [{"type": "car"}, {"type": "loco"}, {"type": "wagon"}]},
     "train.vehicles.0.type: vehicle type loco has an air brake, but nothing feeds the brake pipe: the leading "
     "vehicle (car) is not a locomotive"),
    ({"train.vehicle_types.wagon.wheels": {"model": "wheelsets", "axles": 4, "radius_m": 0.42, "inertia_kgm2": 120}},
     "train.vehicle_types.wagon.wheels: an air-braked vehicle's block force acts on its body"),
    ({"train.vehicle_types.car.coupler": {"model": "draft_gear", "gear": "nope"}},
     "train.vehicle_types.car.coupler.gear: unknown draft gear 'nope'"),
    ({"train.vehicle_types.wagon.wheels": {"model": "adhesion_limit", "mu": 0.3}},
     "train.vehicle_types.wagon.wheels: adhesion on vehicle type wagon, which has no driven axles"),
    ({"train.vehicle_types.chen_car.brake": {"model": "ideal", "wsp": {"enabled": True}}},
     "train.vehicle_types.chen_car.brake.wsp: wheel-slide protection needs axles"),
])
def test_bad_mixed_trains_are_one_line(over: dict, fragment: str) -> None:
    data = _mixed()
    for k, v in over.items():
        node = data
        *path, last = k.split(".")
        for part in path:
            node = node[part]
        node[last] = v
    with pytest.raises(ScenarioError) as e:
        resolve(data, "t.yaml")
    assert "\n" not in str(e.value)
    assert fragment in str(e.value), str(e.value)


def test_the_driver_valve_only_on_the_leading_vehicle() -> None:
    data = _mixed()
    data["ecus"] = [{"name": "x", "vehicle": 2, "controller": {"name": "heavy_haul_brake_test"}}]
    with pytest.raises(ScenarioError, match="the valve is on the leading vehicle"):
        resolve(data, "t.yaml")


def test_a_force_controller_on_an_air_braked_wagon_is_refused_pneumatic_and_wrapped_with_ecp() -> None:
    """As on the heavy-haul kernel: a wagon has no force equipment; with ECP its ECU's force demand
    becomes its cylinder demand (EcpUnit, inverting the air brake's force law)."""
    from canbrake.build import build_controller
    from canbrake.control.ecp import EcpUnit

    data = _mixed()
    data["controller"] = {"name": "chen2023"}
    data["ecus"] = [{"name": "w", "vehicle": 4}]
    with pytest.raises(ScenarioError, match="has no force equipment"):
        resolve(copy.deepcopy(data), "t.yaml")
    data["train"]["air_brake"] = {**AIR, "mode": "ecp"}
    scn = resolve(data, "t.yaml")
    ctrl = build_controller(scn, 1)
    assert isinstance(ctrl, EcpUnit) and "ecp_demand" in ctrl.command_names
    assert scn.consist.ecp_unit_params(1) is None  # the locomotive takes brake_force_n itself
    unit = scn.consist.ecp_unit_params(4)
    assert unit["n_blocks"] == 8.0 and unit["beta_c"] == 0.8


# ----------------------------------------------------------------------------- the shipped scenario
def test_mixed_three_papers_runs_in_process_and_on_the_memory_bus_alike(tmp_path) -> None:
    """One process per ECU on the memory bus gives the in-process run's signals; the brake signal
    reaches the first C80 after (35.222/2 + 3·22 + 12/2) m / 200 m/s = 0.448 s."""
    import csv

    from canbrake.cli import main

    outs = {}
    for bus in ("inprocess", "memory"):
        out = tmp_path / bus
        assert main(["run", str(SCENARIOS / "mixed_three_papers.yaml"), "--bus", bus, "--duration", "3", "--no-plots",
                     "--out", str(out)]) == 0
        outs[bus] = (out / "signals.csv").read_text()
    assert outs["inprocess"] == outs["memory"]
    rows = list(csv.DictReader(outs["inprocess"].splitlines()))
    first = next(float(r["t_s"]) for r in rows if float(r["brake_cylinder_pressure_pa_c5"]) > 0)
    assert first == pytest.approx(1.0 + (35.222 / 2 + 66 + 6) / 200.0, abs=0.011)


def test_li_s_controller_runs_the_mixed_trains_locomotive(tmp_path) -> None:
    """li2024_smc reads passive_force_n, which the coupled plant of a train with draft gears or air
    brakes now measures, and broadcasts nothing: the EMU cars' ECUs (listening to all) do not wait
    for a STATE frame it never sends (that stalled the run's first tick), and the run ends ok; an
    ECU that names such an ECU in its listens is refused in one line."""
    from canbrake.build import bus_layout
    from canbrake.run import run_scenario

    path = SCENARIOS / "mixed_three_papers.yaml"
    scn = load_scenario(path, overrides={"ecus.0.controller.name": "li2024_smc", "duration_s": 2.0})
    lay = bus_layout(scn)
    assert all(1 not in e.listens for e in lay.ecus) and lay.ecus[1].listens == (3, 4)
    s = run_scenario(scn, tmp_path / "run", backend="inprocess", plots=False)
    assert s["status"] == "ok", s.get("message")
    head = (tmp_path / "run" / "signals.csv").read_text().splitlines()[0].split(",")
    assert "passive_force_n_c1" in head and "downgrade_ahead_c1" in head
    from canbrake.run import check_buildable

    bad = load_scenario(path, overrides={"ecus": [{"name": "loco", "vehicle": 1, "controller": {"name": "li2024_smc"}},
                                                  {"name": "emu2", "vehicle": 2, "listens": ["loco"]}]})
    with pytest.raises(ScenarioError, match=r"ECU emu2 listens to loco, whose controller li2024_smc broadcasts nothing"):
        check_buildable(bad)
