"""Vehicles of one train on the coupled (Chen-coupler) kernel whose brake functions differ (issue 27):
ED/friction blending per vehicle (and vehicles without blending beside blended ones), wheel-slide
protection on some vehicles and not others, easing per vehicle; each compared with physics
derived by hand, and their bad inputs."""
from __future__ import annotations

import copy
import math
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import yaml

from conftest import component_plant, component_scenario

from canbrake.build import build_controller, build_plant_model
from canbrake.errors import ScenarioError
from canbrake.physics.train import TrainPlant
from canbrake.scenario import resolve

ROOT = Path(__file__).resolve().parents[1]
KMH = 1 / 3.6




# --- 1. blending per vehicle ---------------------------------------------------------------------
_A = {"ed_max_decel_mps2": 1.0, "fade_start_kmh": 10, "fade_end_kmh": 3, "friction_lag_s": 0.2}
_B = {"ed_max_decel_mps2": 0.5, "fade_start_kmh": 20, "fade_end_kmh": 8, "friction_lag_s": 0.5}
M = 40000.0


def _mixed_blending(speed_kmh: float) -> dict:
    types = {"a": {"mass_kg": M, "brake": {"model": "ideal", "blending": _A}},
             "b": {"mass_kg": M, "brake": {"model": "ideal", "blending": _B}},
             "c": {"mass_kg": M, "brake": {"model": "ideal"}}}  # friction only
    return component_scenario(types, [{"type": "a"}, {"type": "b"}, {"type": "c"}], speed_kmh=speed_kmh)


def test_each_car_splits_its_demand_by_its_own_blending() -> None:
    """60 kN demand per car at 60 km/h (above every fade), ideal brakes, one 10-ms step of 100
    sub-steps: car a's ED brake gives m·1.0 = 40 kN and its friction brake follows the 20 kN rest
    with 0.2 s lag; car b's ED 20 kN, friction 40 kN with 0.5 s lag; car c (no blending) has no ED
    brake and its friction brake gives the 60 kN at once, as without blending."""
    p = component_plant(_mixed_blending(60.0))
    F, t = 60000.0, 0.01
    p.step(t, np.full(3, F))
    m = p.equipment_measurements()
    np.testing.assert_allclose(m["ed_brake_n"], [M * 1.0, M * 0.5, 0.0], rtol=0, atol=1e-9)
    want = [20000.0 * (1 - math.exp(-t / 0.2)), 40000.0 * (1 - math.exp(-t / 0.5)), F]
    np.testing.assert_allclose(m["friction_brake_n"], want, rtol=1e-9)
    # the rail force: ED + friction (car c: the whole demand, like a train without blending)
    np.testing.assert_allclose(p.applied_force_n, np.asarray(want) + [M, M * 0.5, 0.0], rtol=1e-9)
    alone = component_plant(component_scenario({"c": {"mass_kg": M, "brake": {"model": "ideal"}}}, [{"type": "c"}] * 3))
    alone.step(t, np.full(3, F))
    assert p.applied_force_n[2] == alone.applied_force_n[2] == F


def test_each_car_fades_by_its_own_speeds() -> None:
    """At 15 km/h (one sub-step of 1 ms, the speed it is computed at): car a (fade 10 -> 3 km/h)
    has its full ED force; car b (fade 20 -> 8 km/h) fades to (15 − 8)/(20 − 8) = 7/12 of m·0.5."""
    p = component_plant(_mixed_blending(15.0))
    p.step(0.001, np.full(3, 60000.0))
    ed = p.equipment_measurements()["ed_brake_n"]
    np.testing.assert_allclose(ed, [M * 1.0, M * 0.5 * 7 / 12, 0.0], rtol=1e-12)
    # the same split with both cars of type b's blending throughout: car a's ED is then 7/12 too
    d = _mixed_blending(15.0)
    d["train"]["vehicle_types"]["a"]["brake"]["blending"] = _B
    q = component_plant(d)
    q.step(0.001, np.full(3, 60000.0))
    np.testing.assert_allclose(q.equipment_measurements()["ed_brake_n"][:2], [M * 0.5 * 7 / 12] * 2, rtol=1e-12)


def test_an_ed_brake_on_a_vehicle_without_blending_is_refused() -> None:
    types = {"a": {"mass_kg": M, "brake": {"model": "ideal", "blending": _A}},
             "c": {"mass_kg": M, "brake": {"model": "ideal", "ed_brake": {"model": "per_mass", "max_decel_mps2": 0.8}}}}
    with pytest.raises(ScenarioError, match=r"^t.yaml: train.vehicle_types.c.brake.ed_brake: an ED brake is blended "
                                            r"with the friction brake by brake.blending, which vehicle type c's brake "
                                            r"does not have$"):
        resolve(component_scenario(types, [{"type": "a"}, {"type": "c"}]), "t.yaml")


def test_ed_brake_under_per_vehicle_blending() -> None:
    """A vehicle's own ed_brake (per_mass 0.8 m/s²) under its blending; the other keeps its
    blending's ed_max: 60 kN demand at 60 km/h -> ED 32 kN and 20 kN."""
    types = {"a": {"mass_kg": M, "brake": {"model": "ideal", "blending": _A,
                                           "ed_brake": {"model": "per_mass", "max_decel_mps2": 0.8}}},
             "b": {"mass_kg": M, "brake": {"model": "ideal", "blending": _B}}}
    p = component_plant(component_scenario(types, [{"type": "a"}, {"type": "b"}]))
    p.step(0.001, np.full(2, 60000.0))
    np.testing.assert_allclose(p.equipment_measurements()["ed_brake_n"], [M * 0.8, M * 0.5], rtol=1e-12)


# --- 2. wheel-slide protection per vehicle --------------------------------------------------------
def _low_adhesion(tmp: Path, wsp_cars: tuple[int, ...], duration_s: float = 9.0) -> dict:
    """scenarios/chen2023_case2_low_adhesion.yaml with WSP on the cars ``wsp_cars`` (1-based) only."""
    d = yaml.safe_load((ROOT / "scenarios/chen2023_case2_low_adhesion.yaml").read_text())
    t = d["train"]
    car = t["vehicle_types"]["metro_car"]
    w = copy.deepcopy(car)
    w["brake"]["wsp"]["enabled"] = True
    del car["brake"]["wsp"]
    t["vehicle_types"]["wsp_car"] = w
    masses = [18000, 21000, 19500, 20000, 19700, 22000]
    t["vehicles"] = [{"type": "wsp_car" if i + 1 in wsp_cars else "metro_car", "mass_kg": [m]}
                     for i, m in enumerate(masses)]
    d["duration_s"] = duration_s
    d.pop("profiles")
    return d


def _run(tmp: Path, data: dict, name: str = "s") -> Path:
    path = tmp / f"{name}.yaml"
    path.write_text(yaml.safe_dump(data))
    out = tmp / f"out_{name}"
    r = subprocess.run([sys.executable, "-m", "canbrake", "run", str(path), "--bus", "inprocess", "--no-plots",
                        "--out", str(out)], capture_output=True, text=True, cwd=ROOT, timeout=300)
    assert r.returncode == 0, r.stderr
    return out


def test_a_car_with_wsp_releases_while_its_neighbour_without_slides(tmp_path: Path) -> None:
    """Poor rail from 3.5 to 8.5 s (μ 0.08 under car 1, 0.05 under car 3): WSP only on car 3. Car 3,
    on the worse rail, vents its brake (its valve opens) and its slip stays near the release
    threshold (|λ| < 0.25); car 1 has no WSP, its valve never moves and its wheels lock (λ = −1).
    Without WSP anywhere car 3 locks too; only car 3's ECU runs WSP."""
    import pandas as pd

    d = pd.read_csv(_run(tmp_path, _low_adhesion(tmp_path, (3,))) / "signals.csv")
    win = d[(d.t_s > 3.5) & (d.t_s < 8.5)]
    assert d.wsp_valve_c3.max() > 0.9 and win.axle1_slip_c3.min() > -0.25
    assert (d.wsp_valve_c1 == 0).all() and win.axle1_slip_c1.min() < -0.99
    assert "cmd_wsp_release_c3" in d and "cmd_wsp_release_c1" not in d
    base = pd.read_csv(_run(tmp_path, _low_adhesion(tmp_path, ()), "none") / "signals.csv")
    assert base.axle1_slip_c3.min() < -0.99 and (base.wsp_valve_c3 == 0).all()
    scn = resolve(_low_adhesion(tmp_path, (3,)), "t.yaml")
    assert [getattr(build_controller(scn, i), "wsp", None) is not None for i in range(1, 7)] == \
        [False, False, True, False, False, False]


def test_dump_valve_lag_per_car() -> None:
    """A vented valve opens as 1 − exp(−t/τ) with each car's own lag τ (0.05 s and 0.5 s) and
    its own watchdog: a car with max_vent_s 0.1 s shuts its valve after 0.1 s of venting."""
    p = TrainPlant([M, M, M], [0.0, -20.0, -40.0], [10.0] * 3, blending=None,
                   wheels=__import__("canbrake.physics.brakes", fromlist=["Wheelsets"]).Wheelsets(
                       np.full(3, M), 4, 0.42, 120.0, np.full(3, 10.0)),
                   wsp_valve_lag_s=(0.05, 0.5, 0.05), wsp_max_vent_s=(math.inf, math.inf, 0.1), max_substep_s=0.001)
    p.step(0.05, np.zeros(3), wsp_release=np.ones(3))
    k = [1 - math.exp(-0.001 / 0.05), 1 - math.exp(-0.001 / 0.5)]
    np.testing.assert_allclose(p.wsp_valve[:2], [1 - (1 - k[0]) ** 50, 1 - (1 - k[1]) ** 50], rtol=1e-12)
    assert p.wsp_valve[2] == p.wsp_valve[0]
    p.step(0.2, np.zeros(3), wsp_release=np.ones(3))
    assert p.wsp_valve[0] > 0.99 and p.wsp_valve[2] < 0.2  # car 3's watchdog closed it after 0.1 s


def test_wsp_parameters_per_vehicle_reach_the_plant_and_ecus(tmp_path: Path) -> None:
    d = _low_adhesion(tmp_path, (2, 3))
    d["train"]["vehicle_types"]["wsp2"] = copy.deepcopy(d["train"]["vehicle_types"]["wsp_car"])
    d["train"]["vehicle_types"]["wsp2"]["brake"]["wsp"].update(valve_lag_s=0.2, slip_release=0.3, max_vent_s=2.0)
    d["train"]["vehicles"][1]["type"] = "wsp2"
    scn = resolve(d, "t.yaml")
    p = build_plant_model(scn).plant
    # cars 2 and 3 their own; the others have no WSP (their valves are never commanded)
    assert list(p.wsp_valve_lag_s[1:3]) == [0.2, 0.05] and list(p.wsp_max_vent_s[1:3]) == [2.0, 5.0]
    assert build_controller(scn, 2).wsp.slip_release == 0.3 and build_controller(scn, 3).wsp.slip_release == 0.2


# --- 3. easing per vehicle ------------------------------------------------------------------------
def test_easing_per_vehicle() -> None:
    """Easing is an ECU function: each car's ECU caps its demand with its own time constant
    (m·v/τ_e·(1 − τ_a/τ_e), τ_a its own brake lag + friction lag) or not at all."""
    types = {"a": {"mass_kg": M, "brake": {"model": "electro_pneumatic", "lag_s": 0.3, "blending": _A,
                                           "easing": {"time_constant_s": 1.0}}},
             "b": {"mass_kg": M, "brake": {"model": "electro_pneumatic", "lag_s": 0.3, "blending": _A,
                                           "easing": {"time_constant_s": 2.0}}},
             "c": {"mass_kg": M, "brake": {"model": "electro_pneumatic", "lag_s": 0.3, "blending": _A}}}
    data = component_scenario(types, [{"type": "a"}, {"type": "b"}, {"type": "c"}])
    data["controller"] = {"name": "pi"}
    scn = resolve(data, "t.yaml")
    gains = [getattr(build_controller(scn, i), "ease_gain", None) for i in (1, 2, 3)]
    assert gains[0] == pytest.approx((1 - 0.5 / 1.0) / 1.0) and gains[1] == pytest.approx((1 - 0.5 / 2.0) / 2.0)
    assert gains[2] is None
    types["b"]["brake"]["easing"]["time_constant_s"] = 0.4
    with pytest.raises(ScenarioError, match=r"^t.yaml: train.vehicle_types.b.brake.easing.time_constant_s: must "
                                            r"exceed the brake lag it anticipates \(0.5 s"):
        resolve(component_scenario(types, [{"type": "a"}, {"type": "b"}]), "t.yaml")


def test_components_lists_the_brake_functions_per_vehicle() -> None:
    r = subprocess.run([sys.executable, "-m", "canbrake", "components"], capture_output=True, text=True, cwd=ROOT,
                       timeout=120)
    assert r.returncode == 0, r.stderr
    line = next(ln for ln in r.stdout.splitlines() if ln.strip().startswith("per vehicle: mass, resistance (davis, table or per_weight"))
    assert "blending (or none: friction only), easing, wsp" in line and "wheelsets (axles, radius, inertia," in line
    assert "slip curve b1..b3, c1..c3, v_floor_mps, or none)" in line and "once for the train: the rail conditions" in line


# --- 4. wheelsets per vehicle ---------------------------------------------------------------------
def _wheeled_plant(mu: float = 0.3, speed: float = 20.0) -> TrainPlant:
    """Three 40-t cars on (almost) no couplers, no resistance: car 1 four wheelsets (R 0.42 m, J 120
    kg·m²), car 2 no wheels, car 3 two wheelsets (R 0.46 m, J 200 kg·m²)."""
    from canbrake.physics.brakes import Wheelsets
    from canbrake.physics.rail import RailConditions
    from canbrake.physics.resistance import DavisResistance

    z = np.zeros(3)
    return TrainPlant(np.full(3, M), [0.0, -20.0, -40.0], np.full(3, speed), coupler_stiffness_n_per_m=1e-6,
                      coupler_nonlinearity_per_m2=0.0, resistance=DavisResistance(z, z.copy(), z.copy()),
                      rail=RailConditions(base_adhesion_mu=mu), max_substep_s=0.001,
                      wheels=Wheelsets(np.full(3, M), [4, 0, 2], [0.42, 1.0, 0.46], [120.0, 1.0, 200.0],
                                       np.full(3, speed)))


def test_each_car_decelerates_with_its_own_wheelsets_and_a_car_without_wheels_as_without() -> None:
    """A steady 20 kN brake on good rail: a car with p wheelsets of inertia J and radius R
    decelerates at F/(m + p·J/R²) once its wheels follow (the brake also stops the wheels): car 1
    F/(m + 4·120/0.42²), car 3 F/(m + 2·200/0.46²); car 2 without wheels at F/m exactly, its rail
    force the brake force, as a car of a train without wheelsets; its axle signals are NaN, and
    car 3's third and fourth."""
    p = _wheeled_plant()
    F = 20000.0
    for _ in range(100):
        p.step(0.01, np.full(3, F))
    v1 = p.speed_mps.copy()
    for _ in range(100):
        p.step(0.01, np.full(3, F))
    decel = (v1 - p.speed_mps) / 1.0
    want = [F / (M + 4 * 120 / 0.42 ** 2), F / M, F / (M + 2 * 200 / 0.46 ** 2)]
    np.testing.assert_allclose(decel, want, rtol=1e-3)  # the slip creeps as the speed falls
    assert decel[0] < decel[2] < decel[1]  # told apart: 1.5 % and 1.1 % of inertia
    assert p.applied_force_n[1] == F
    np.testing.assert_allclose(p.speed_mps[1], 20.0 - 2.0 * F / M, rtol=1e-9)
    m = p.equipment_measurements()
    assert np.isnan(m["axle1_slip"][1]) and np.isnan(m["axle3_slip"][2]) and not np.isnan(m["axle2_slip"][2])
    assert not np.isnan(m["axle4_speed_radps"][0])
    np.testing.assert_allclose(m["axle1_speed_radps"][2], p.speed_mps[2] / 0.46, rtol=2e-2)  # its own R
    assert -0.02 < m["axle1_slip"][2] < 0.0 and m["axle1_slip"][2] == m["axle2_slip"][2]


def test_adhesion_per_axle_only_on_the_cars_with_wheels() -> None:
    """μ = 0.05 and a 30 kN brake (> μ m g = 19.6 kN), 8 s: both wheeled cars' wheels lock (slip −1)
    and their rail force falls to the sliding creep force (< μ m g); the car without wheels has no
    adhesion limit and keeps its full 30 kN."""
    p = _wheeled_plant(mu=0.05)
    F = 30000.0
    for _ in range(800):
        p.step(0.01, np.full(3, F))
    m = p.equipment_measurements()
    assert m["axle1_slip"][0] == -1.0 and m["axle2_slip"][2] == -1.0
    assert p.applied_force_n[0] < 0.05 * M * 9.81 and p.applied_force_n[2] < 0.05 * M * 9.81
    assert p.applied_force_n[1] == F


def test_wheels_per_vehicle_from_the_scenario() -> None:
    types = {"m": {"mass_kg": M, "brake": {"model": "ideal", "wsp": {}},
                   "wheels": {"model": "wheelsets", "axles": 4, "radius_m": 0.42, "inertia_kgm2": 120}},
             "t": {"mass_kg": M, "brake": {"model": "ideal"},
                   "wheels": {"model": "wheelsets", "axles": 2, "radius_m": 0.46, "inertia_kgm2": 200}},
             "x": {"mass_kg": M, "brake": {"model": "ideal"}}}
    data = component_scenario(types, [{"type": "m"}, {"type": "x"}, {"type": "t"}])
    data["controller"] = {"name": "pi"}
    scn = resolve(copy.deepcopy(data), "t.yaml")
    w = build_plant_model(scn).plant.wheels
    assert w.p == 4 and list(w.active) == [4, 0, 2] and list(w.R[[0, 2]]) == [0.42, 0.46]
    assert build_controller(scn, 1).axles == 4
    assert len(w.curves) == 1 and list(w.v_floor) == [0.1]  # one slip curve: the train's
    # a slip curve and v_floor of its own (physics below): each car's wheels, its ECU's slip estimate
    data["train"]["vehicle_types"]["t"]["wheels"].update(b3=2.0, v_floor_mps=0.3)
    scn = resolve(copy.deepcopy(data), "t.yaml")
    w = build_plant_model(scn).plant.wheels
    assert [c.b3 for c in w.curves] == [10.0, 10.0, 2.0] and list(w.v_floor) == [0.1, 0.1, 0.3]
    data["train"]["vehicle_types"]["t"]["brake"]["wsp"] = {}
    scn = resolve(copy.deepcopy(data), "t.yaml")
    assert build_controller(scn, 3).v_floor == 0.3 and build_controller(scn, 1).v_floor == 0.1


def _lone_or_train(curves: list, floors: list, cars: list[int], v0: float) -> TrainPlant:
    """Cars ``cars`` of a 40-t train on (almost) no couplers, four wheelsets each (R 0.42 m, J 120
    kg·m²), braking from ``v0`` (m/s) on a rail of μ 0.3 with their own slip curves and v_floor."""
    from canbrake.physics.brakes import Wheelsets
    from canbrake.physics.rail import RailConditions
    from canbrake.physics.resistance import DavisResistance

    n = len(cars)
    z = np.zeros(n)
    return TrainPlant(np.full(n, M), [-20.0 * i for i in range(n)], np.full(n, v0), coupler_stiffness_n_per_m=1e-6,
                      coupler_nonlinearity_per_m2=0.0, resistance=DavisResistance(z, z.copy(), z.copy()),
                      rail=RailConditions(base_adhesion_mu=0.3), max_substep_s=0.001,
                      wheels=Wheelsets(np.full(n, M), 4, 0.42, 120.0, np.full(n, v0),
                                       curve=[curves[i] for i in cars], v_floor_mps=[floors[i] for i in cars]))


@pytest.mark.parametrize("v0, ticks", [(20.0, 150), (0.4, 12)], ids=["sliding", "below-the-floor"])
def test_each_car_slides_on_its_own_slip_curve_and_floor(v0: float, ticks: int) -> None:
    """Three cars with different slip curves and floors (Cai's dry rail; a curve peaking at a larger
    slip with a flatter fall; dry with v_floor 1 m/s instead of 0.1) braked beyond adhesion: each car
    of the train moves, spins and slips as the same car alone on its own curve (to 1e-9: the cars
    are coupled by 1e-6 N/m), and the cars differ: at speed by their curves, below 1 m/s by their
    floors (λ = (ωR − v)/max(ωR, v, v_floor))."""
    from canbrake.physics.wheel_adhesion import RailCondition

    dry = RailCondition(b1=1.786, b2=40.0, b3=10.0, c1=0.040, c2=3.78, c3=33.3, peak_mu0=1.0)
    soft = RailCondition(b1=1.2, b2=12.0, b3=4.0, c1=0.040, c2=3.78, c3=33.3, peak_mu0=1.0)
    curves, floors = [dry, soft, dry], [0.1, 0.1, 1.0]
    train = _lone_or_train(curves, floors, [0, 1, 2], v0)
    lone = [_lone_or_train(curves, floors, [i], v0) for i in range(3)]
    cmd = np.full(3, 0.4 * M * 9.81)  # above μ m g: the wheels slide
    slips = []
    for _ in range(ticks):
        train.step(0.01, cmd)
        slips.append(train.wheels.slip[:, 0].copy())
        for i, p in enumerate(lone):
            p.step(0.01, cmd[:1])
    for i, p in enumerate(lone):
        assert train.speed_mps[i] == pytest.approx(p.speed_mps[0], rel=1e-9, abs=1e-12)
        np.testing.assert_allclose(train.wheels.omega[i], p.wheels.omega[0], rtol=1e-9, atol=1e-12)
        np.testing.assert_allclose(train.wheels.slip[i], p.wheels.slip[0], rtol=1e-7, atol=1e-12)
    d = np.abs(np.array(slips) - np.array(slips)[:, :1]).max(axis=0)  # each car's slip against car 1's
    if v0 > 1.0:
        assert d[1] > 0.01 and d[2] == 0.0  # the curve matters, the floor not at speed
    else:
        assert d[2] > 0.01  # below 1 m/s car 3's floor sets its slip


# --- 5. cleanups ----------------------------------------------------------------------------------
def test_a_bad_every_vehicle_value_is_reported_once_where_it_is_written(tmp_path: Path) -> None:
    """train.every_vehicle is merged over every vehicle type; its bad value is one line naming
    train.every_vehicle (exit 2), not one line per vehicle type."""
    data = component_scenario({"motor": {"mass_kg": M, "brake": {"model": "ideal"}},
                      "trailer": {"mass_kg": M, "brake": {"model": "ideal"}}}, [{"type": "motor"}, {"type": "trailer"}],
                     every_vehicle={"brake": {"blending": {"fade_end_kmh": 20}}})
    path = tmp_path / "ev.yaml"
    path.write_text(yaml.safe_dump(data))
    r = subprocess.run([sys.executable, "-m", "canbrake", "run", str(path), "--bus", "inprocess", "--out",
                        str(tmp_path / "out")], capture_output=True, text=True, cwd=ROOT, timeout=120)
    assert r.returncode == 2 and "Traceback" not in r.stderr
    assert r.stderr.strip().splitlines() == [f"canbrake: error: {path}: train.every_vehicle.brake.blending.fade_end_kmh: "
                                             "must be below fade_start_kmh (10), got 20"]


def test_a_driven_axle_without_wheel_is_checked_once_in_the_component() -> None:
    from canbrake.consist import adhesion

    from canbrake.consist import components

    assert "_wheels_known" in vars(adhesion.VehicleAxles) and "_wheels_known" not in vars(components.DrivenAxles)
    with pytest.raises(ValueError, match=r"@axles.0: no wheel \(give the axle's or the component's `wheel`\)"):
        from canbrake.consist.components import parse_component

        parse_component("wheels", {"model": "driven_axles", "axles": [{"load_n": 1e5}]})
