"""Vehicles of one train on the coupled (Chen-coupler) kernel that differ (issue 27): a running
resistance from a table (``resistance: {model: table}``), a traction envelope per vehicle
(``traction: {model: envelope}``) and a brake lag and model per vehicle (``ideal`` beside
``electro_pneumatic``), each compared with physics derived by hand, and their bad inputs."""
from __future__ import annotations

import copy
import csv
import math
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import yaml

from conftest import component_plant, component_scenario

from canbrake.build import build_plant_model
from canbrake.consist import components as C
from canbrake.errors import ScenarioError
from canbrake.physics.actuator import ActuatorState, BrakeActuator
from canbrake.physics.heavy_haul import KMH, TractionEnvelope
from canbrake.physics.resistance import DavisResistance
from canbrake.physics.train import TrainPlant, stack_plants
from canbrake.scenario import resolve

ROOT = Path(__file__).resolve().parents[1]

#: Li 2024's HXD1 traction envelope (scenarios/li2024_*.yaml): 520 kN to 5 km/h, 551.6 − 5.7 v to 76 km/h, P/v above
HXD1 = {"traction_start_kn": 520.0, "traction_start_until_kmh": 5.0, "traction_intercept_kn": 551.6,
        "traction_slope_kn_per_kmh": 5.7, "traction_linear_until_kmh": 76.0, "brake_slope_kn_per_kmh": 10.0,
        "brake_linear_until_kmh": 46.0, "brake_max_kn": 461.0, "brake_constant_until_kmh": 76.0,
        "power_kn_kmh": 25000.0}
DAVIS = (650.0, 7.0, 0.9)  # c0 N, c1 N s/m, c2 N s²/m²


def _davis_table(c: tuple[float, float, float], top_mps: float = 45.0, step: float = 0.05) -> dict:
    v = np.round(np.arange(0.0, top_mps + step / 2, step), 10)
    return {"model": "table", "speed_mps": v.tolist(), "force_n": (c[0] + c[1] * v + c[2] * v * v).tolist()}




# --- 1. resistance tables ------------------------------------------------------------------------
def test_a_table_sampled_from_davis_coasts_like_davis() -> None:
    """One vehicle coasting 60 s from 30 m/s: a table of the Davis curve sampled every 0.05 m/s
    (interpolation error at most c2·Δv²/4 = 0.6 mN) gives the Davis run's speed and distance to
    1e-7 relative; a table 10 % off is told apart."""
    m = 40000.0
    c0, c1, c2 = DAVIS
    davis = TrainPlant([m], [0.0], [30.0], resistance=DavisResistance(np.array([c0]), np.array([c1]), np.array([c2])))
    t = _davis_table(DAVIS)
    table = TrainPlant([m], [0.0], [30.0], resistance=DavisResistance.zero(1),
                       resistance_table=[(t["speed_mps"], t["force_n"])])
    off = TrainPlant([m], [0.0], [30.0], resistance=DavisResistance.zero(1),
                     resistance_table=[(t["speed_mps"], [1.1 * f for f in t["force_n"]])])
    for _ in range(600):
        for p in (davis, table, off):
            p.step(0.1, [0.0])
    assert davis.speed_mps[0] < 28.0  # it did slow down (~2.4 m/s)
    assert table.speed_mps[0] == pytest.approx(davis.speed_mps[0], rel=1e-7, abs=0)
    assert table.position_m[0] == pytest.approx(davis.position_m[0], rel=1e-7, abs=0)
    assert abs(off.speed_mps[0] - davis.speed_mps[0]) > 0.1


def test_a_table_is_held_flat_beyond_its_ends_and_holds_a_vehicle_at_rest() -> None:
    """Beyond the last speed the force is the last value: a vehicle at 30 m/s on a table ending at
    10 m/s (800 N) decelerates at exactly 800 N / m; between two points it is the straight line; at
    rest the first value is static friction (a 550 N push does not move it, a 650 N one does)."""
    m = 20000.0
    tab = [([1.0, 5.0, 10.0], [600.0, 700.0, 800.0])]
    p = TrainPlant([m], [0.0], [30.0], resistance=DavisResistance.zero(1), resistance_table=tab)
    p.step(1e-3, [0.0])
    assert p.accel_mps2[0] == pytest.approx(-800.0 / m, rel=1e-9)
    p = TrainPlant([m], [0.0], [3.0], resistance=DavisResistance.zero(1), resistance_table=tab)
    p.step(1e-3, [0.0])
    assert p.accel_mps2[0] == pytest.approx(-650.0 / m, rel=1e-6)  # 600 + (3 − 1)/4 · 100 N
    for push, moves in ((-550.0, False), (-650.0, True)):  # traction below / above the breakaway (600 N at v = 0)
        p = TrainPlant([m], [0.0], [0.0], resistance=DavisResistance.zero(1), resistance_table=tab)
        p.step(0.01, [push])
        assert bool(p.speed_mps[0] > 0.0) is moves


def test_table_and_davis_vehicles_in_one_train() -> None:
    """A train of davis and table vehicles (types ``d`` and ``t``) from a scenario: where the table is
    the Davis curve, the coupled run matches the all-davis train to 1e-6 m/s per car; the table
    vehicles really run on their tables (a zero table coasts them faster)."""
    coupler = {"model": "chen", "stiffness_n_per_m": 2.0e6, "epsilon_per_m2": 0.0}
    davis = {"model": "davis", "c0_n": DAVIS[0], "c1_n_s_per_m": DAVIS[1], "c2_n_s2_per_m2": DAVIS[2]}
    vehicles = [{"type": "d"}, {"type": "t"}, {"type": "d"}, {"type": "t"}]
    base = {"mass_kg": 30000.0, "length_m": 20.0, "coupler": coupler}
    d = {**base, "resistance": davis}
    ref = component_plant(component_scenario({"d": d, "t": d}, vehicles))
    mixed = component_plant(component_scenario({"d": d, "t": {**base, "resistance": _davis_table(DAVIS)}}, vehicles))
    zero = component_plant(component_scenario(
        {"d": d, "t": {**base, "resistance": {"model": "table", "speed_mps": [0, 1], "force_n": [0, 0]}}}, vehicles))
    assert mixed.resistance_table is not None and mixed.resistance_table[0] is None
    for _ in range(300):
        for p in (ref, mixed, zero):
            p.step(0.01, np.zeros(4))
    np.testing.assert_allclose(mixed.speed_mps, ref.speed_mps, rtol=0, atol=1e-6)
    assert np.all(zero.speed_mps > ref.speed_mps + 1e-3)


# --- 2. traction envelopes -----------------------------------------------------------------------
@pytest.mark.parametrize("v0", [1.0, 12.0, 20.0, 25.0, 30.0])
def test_a_vehicle_on_its_envelope_accelerates_at_f_env_over_m(v0: float) -> None:
    """Asked for far more traction than it has, a vehicle (no resistance) accelerates at
    F_T(v)/m (Li 2024 eq. 1, every region: 520 kN, 551.6 − 5.7 v kN, 25000/v kN); its neighbour
    without an envelope gets its whole command; a brake command is not limited."""
    env = TractionEnvelope(**HXD1)
    m = 138000.0
    p = TrainPlant([m, m], [0.0, -30.0], [v0, v0], coupler_stiffness_n_per_m=1.0, coupler_nonlinearity_per_m2=0.0,
                   resistance=DavisResistance.zero(2), traction_envelope=[env, None])
    p.step(1e-3, [-5e6, -2e5])  # one sub-step of 1 ms
    f_env = 1000.0 * float(env.traction_kn(v0 / KMH))
    assert p.applied_force_n[0] == pytest.approx(-f_env, rel=1e-12)
    assert p.accel_mps2[0] == pytest.approx(f_env / m, rel=1e-6)
    assert p.applied_force_n[1] == -2e5
    p.step(1e-3, [3e5, 3e5])
    assert list(p.applied_force_n) == [3e5, 3e5]


def test_the_envelope_follows_the_speed_within_a_period_and_under_a_lagged_brake() -> None:
    """Over 20 s of full traction the speed gain is ∫ F_T(v)/m dt (integrated here by classical RK4
    on eq. 1) to 1e-4 relative, whether the brake applies at once or with a 0.3 s lag after it
    settled; the rail force never exceeds the envelope (taken at each sub-step's starting speed, so
    at the period's end speed by at most |dF_T/dv|·a·h = 20.5 kN s/m · 2.6 m/s² · 1 ms ≈ 55 N)."""
    env = TractionEnvelope(**HXD1)
    m = 138000.0

    def a(v: float) -> float:
        return 1000.0 * float(env.traction_kn(v / KMH)) / m
    v, h = 15.0, 1e-3
    for _ in range(20000):
        k1 = a(v); k2 = a(v + h / 2 * k1); k3 = a(v + h / 2 * k2); k4 = a(v + h * k3)  # noqa: E702
        v += h / 6 * (k1 + 2 * k2 + 2 * k3 + k4)
    for act in (None, BrakeActuator(kind="realistic", time_constant_s=0.3, jerk_limit_mps3=math.inf)):
        p = TrainPlant([m], [0.0], [15.0], resistance=DavisResistance.zero(1), traction_envelope=[env], actuator=act)
        worst = 0.0
        for _ in range(2000):
            p.step(0.01, [-5e6])
            worst = max(worst, -p.applied_force_n[0] - 1000.0 * float(env.traction_kn(p.speed_mps[0] / KMH)))
        assert worst <= 60.0
        gain = p.speed_mps[0] - 15.0
        assert gain == pytest.approx(v - 15.0, rel=1e-4 if act is None else 2e-3)


def test_a_locomotive_envelope_on_chen_couplers_from_a_scenario() -> None:
    """``traction: {model: envelope}`` on one vehicle type of a Chen-coupler train: the coupled kernel
    is chosen and that vehicle's traction is capped by its envelope, the others' not."""
    coupler = {"model": "chen", "stiffness_n_per_m": 2.0e6, "epsilon_per_m2": 0.0}
    types = {"loco": {"mass_kg": 138000.0, "length_m": 20.0, "coupler": coupler, "traction": {"model": "envelope", **HXD1}},
             "car": {"mass_kg": 40000.0, "length_m": 20.0, "coupler": coupler}}
    data = component_scenario(types, [{"type": "loco"}, {"type": "car", "count": 2}], speed_kmh=72.0)
    scn = resolve(copy.deepcopy(data), "t.yaml")
    assert scn.train.kernel_name == "coupled"
    p = build_plant_model(scn).plant
    p.step(1e-3, [-1e6, -1e6, -1e6])
    assert p.applied_force_n[0] == pytest.approx(-1000.0 * (551.6 - 5.7 * 72.0), rel=1e-9)
    assert list(p.applied_force_n[1:]) == [-1e6, -1e6]


# --- 3. brake lag and model per vehicle ----------------------------------------------------------
def test_each_vehicle_follows_its_own_first_order_lag() -> None:
    """Vehicle types with lag_s 0.5 s and 1.2 s and an ideal brake in one train (no jerk limit): under
    a held step command F each vehicle's applied force is F (1 − e^(−t/τ_i)), the ideal one's F at
    once (1e-9 relative)."""
    coupler = {"model": "chen", "stiffness_n_per_m": 2.0e6, "epsilon_per_m2": 0.0}
    ep = {"model": "electro_pneumatic", "jerk_limit_mps3": None}
    types = {"slow": {"mass_kg": 30000.0, "length_m": 20.0, "coupler": coupler, "brake": {**ep, "lag_s": 1.2}},
             "fast": {"mass_kg": 30000.0, "length_m": 20.0, "coupler": coupler, "brake": {**ep, "lag_s": 0.5}},
             "ideal": {"mass_kg": 30000.0, "length_m": 20.0, "coupler": coupler, "brake": {"model": "ideal"}}}
    p = component_plant(component_scenario(types, [{"type": "slow"}, {"type": "ideal"}, {"type": "fast"}],
                                           speed_kmh=80.0, every_vehicle={"resistance": {"model": "davis"}}))
    assert p.actuator.time_constant_s == (1.2, 0.0, 0.5)
    f = np.full(3, 2.0e4)
    for k in range(1, 151):
        p.step(0.01, f)
        t = 0.01 * k
        want = f * (1.0 - np.exp(-t / np.array([1.2, 1e-300, 0.5])))
        np.testing.assert_allclose(p.applied_force_n, want, rtol=1e-9, atol=0)


def test_jerk_limits_and_lags_per_vehicle_under_blending_too() -> None:
    """The numpy actuator (the path with blending and wheelsets) takes the same per-vehicle lags:
    a vehicle with τ = 0 gets its demand at once, the others 1 − e^(−h/τ) of the gap per step."""
    act = ActuatorState(BrakeActuator(kind="realistic", time_constant_s=(0.4, 0.0), jerk_limit_mps3=math.inf),
                        np.array([1e4, 1e4]))
    e = act.advance(np.array([1000.0, 1000.0]), 0.1)
    np.testing.assert_allclose(e, [1000.0 * (1.0 - math.exp(-0.25)), 1000.0], rtol=1e-12)


def test_uniform_lag_lowers_to_one_value_and_stacks_keep_per_vehicle_lags() -> None:
    """Equal lags stay one value (the former lowering, so former runs are unchanged); plants with
    per-vehicle lags still stack bit for bit (the batch engine)."""
    coupler = {"model": "chen", "stiffness_n_per_m": 2.0e6, "epsilon_per_m2": 0.0}
    same = {"a": {"mass_kg": 30000.0, "length_m": 20.0, "coupler": coupler,
                  "brake": {"model": "electro_pneumatic", "lag_s": 0.4}}}
    assert component_plant(component_scenario(same, [{"type": "a", "count": 3}])).actuator.time_constant_s == 0.4
    act = BrakeActuator(kind="realistic", time_constant_s=(0.3, 0.0, 0.9), jerk_limit_mps3=(1.0, math.inf, 2.0))
    plants = [TrainPlant([3e4, 3.1e4, 2.9e4], [0.0, -20.0, -40.0], [20.0 + i, 20.0, 20.0], actuator=act,
                         coupler_stiffness_n_per_m=2e6, coupler_nonlinearity_per_m2=0.0) for i in range(3)]
    st = stack_plants(plants)
    assert st is not None
    cmd = np.array([[2e4, -1e4, 3e4]] * 3)
    for _ in range(50):
        st.step(0.01, cmd)
        for p in plants:
            p.step(0.01, cmd[0])
    for i, p in enumerate(plants):
        assert np.array_equal(st.speed_mps[i], p.speed_mps) and np.array_equal(st.applied_force_n[i], p.applied_force_n)


# --- the schema: listing and refusals ------------------------------------------------------------
def test_kernels_and_components_list_the_new_features() -> None:
    assert "table" in C.KERNELS["coupled"]["resistance"] and "envelope" in C.KERNELS["coupled"]["traction"]
    r = subprocess.run([sys.executable, "-m", "canbrake", "components", "resistance"], capture_output=True, text=True,
                       cwd=ROOT, timeout=120)
    assert r.returncode == 0, r.stderr
    assert "  table: Running resistance from a table" in r.stdout and "speed_mps*, force_n*" in r.stdout
    assert "speed_mps*, force_n*\n      physics: coupled (TrainPlant)\n" in r.stdout


def test_brake_blending_may_differ_per_vehicle_now() -> None:
    """Blending per vehicle (kernlim2; physics in tests/test_per_vehicle_brakes.py): a blended
    vehicle beside one without blending is accepted, each car with its own."""
    types = {"a": {"mass_kg": 2e4, "brake": {"model": "ideal", "blending": {}}},
             "b": {"mass_kg": 2e4, "brake": {"model": "electro_pneumatic"}}}
    b = resolve(component_scenario(types, [{"type": "a"}, {"type": "b"}]), "t.yaml").consist.brakes
    assert b.blending is not None and [c.blending is not None for c in b.cars] == [True, False]


_MIN = {"model": "table", "speed_mps": [0.0, 10.0, 20.0], "force_n": [500.0, 800.0, 1500.0]}


@pytest.mark.parametrize("key, value, says", [
    ("train.vehicle_types.metro_car.resistance", {**_MIN, "speed_mps": [0.0, 20.0, 10.0]},
     "train.vehicle_types.metro_car.resistance.speed_mps.2: speeds must increase, got 10 after 20"),
    ("train.vehicle_types.metro_car.resistance", {**_MIN, "force_n": [500.0, 800.0]},
     "train.vehicle_types.metro_car.resistance.force_n: 2 values for 3 speeds (speed_mps); give one force per speed"),
    ("train.vehicle_types.metro_car.resistance", {**_MIN, "force_n": [500.0, ".nan", 1500.0]},
     "train.vehicle_types.metro_car.resistance.force_n.1: must be a finite number, got nan"),
    ("train.vehicle_types.metro_car.resistance", {**_MIN, "force_n": [500.0, -1.0, 1500.0]},
     "train.vehicle_types.metro_car.resistance.force_n.1: a resistance must be >= 0 N, got -1"),
    ("train.vehicle_types.metro_car.resistance", {**_MIN, "speed_mps": [-1.0, 10.0, 20.0]},
     "train.vehicle_types.metro_car.resistance.speed_mps.0: speeds are |v| and must be >= 0, got -1"),
    ("train.vehicle_types.metro_car.resistance", {"model": "table", "speed_mps": [0.0], "force_n": [1.0]},
     "train.vehicle_types.metro_car.resistance.speed_mps: List should have at least 2 items"),
    ("train.vehicle_types.metro_car.traction", {"model": "envelope", **HXD1, "power_kn_kmh": 0},
     "train.vehicle_types.metro_car.traction.power_kn_kmh: Input should be greater than 0"),
])
def test_bad_tables_and_envelopes_exit_2_in_one_line(tmp_path: Path, key: str, value: object, says: str) -> None:
    """Through ``canbrake run``: exit 2, one line naming the file and the field, no traceback."""
    data = yaml.safe_load((ROOT / "scenarios" / "chen2023_case1_fine_rail.yaml").read_text())
    node = data
    *path, last = key.split(".")
    for k in path:
        node = node.setdefault(k, {})
    node[last] = value
    p = tmp_path / "bad.yaml"
    p.write_text(yaml.safe_dump(data).replace("'.nan'", ".nan"))
    r = subprocess.run([sys.executable, "-m", "canbrake", "run", str(p), "--duration", "0.1", "--no-plots",
                        "--bus", "inprocess", "--out", str(tmp_path / "o")], capture_output=True, text=True, cwd=ROOT,
                       timeout=120)
    assert r.returncode == 2, (r.stdout, r.stderr)
    assert "Traceback" not in r.stderr
    err = r.stderr.strip()
    assert "\n" not in err and "bad.yaml" in err and says in err, err


def test_tables_and_envelopes_under_blending_and_on_wheelsets() -> None:
    """The step with brake equipment takes the tables and envelopes too: with ED/friction blending a
    vehicle coasting on a Davis-sampled table runs as on Davis (1e-7), and one on its envelope
    accelerates at F_T(v)/m; on wheelsets (creep, backward Euler) full traction at ~90 km/h puts
    the envelope on the rail less what spins up the wheels, F_T − ΣJ·a/R² (1 %: the slip settles)."""
    from canbrake.physics.brakes import BrakeBlending, Wheelsets

    m = 40000.0
    c0, c1, c2 = DAVIS
    t = _davis_table(DAVIS)
    blend = BrakeBlending()
    davis = TrainPlant([m], [0.0], [30.0], resistance=DavisResistance(np.array([c0]), np.array([c1]), np.array([c2])),
                       blending=blend)
    table = TrainPlant([m], [0.0], [30.0], resistance=DavisResistance.zero(1),
                       resistance_table=[(t["speed_mps"], t["force_n"])], blending=blend)
    for _ in range(300):
        for p in (davis, table):
            p.step(0.1, [0.0])
    assert davis.speed_mps[0] < 29.0
    assert table.speed_mps[0] == pytest.approx(davis.speed_mps[0], rel=1e-7, abs=0)
    env = TractionEnvelope(**HXD1)
    p = TrainPlant([138000.0], [0.0], [20.0], resistance=DavisResistance.zero(1), traction_envelope=[env],
                   blending=blend)
    p.step(1e-3, [-5e6])
    f_env = 1000.0 * float(env.traction_kn(20.0 / KMH))
    assert p.applied_force_n[0] == pytest.approx(-f_env, rel=1e-12)
    assert p.accel_mps2[0] == pytest.approx(f_env / 138000.0, rel=1e-6)
    w = Wheelsets(np.array([138000.0]), 4, 0.625, 200.0, np.array([25.0]))
    p = TrainPlant([138000.0], [0.0], [25.0], resistance=DavisResistance.zero(1), traction_envelope=[env], wheels=w)
    for _ in range(50):
        p.step(0.01, [-5e6])
    f_env = 1000.0 * float(env.traction_kn(p.speed_mps[0] / KMH))  # 25000/v kN ≈ 268 kN, below μ·m·g = 406 kN
    spin = 4 * 200.0 * p.accel_mps2[0] / 0.625**2  # the part of the drive torque that spins up the wheels (≈ 4 kN)
    assert -p.applied_force_n[0] == pytest.approx(f_env - spin, rel=1e-2)  # without the envelope: μ·m·g, 406 kN


def test_easing_with_different_lags_needs_its_own_lag_and_plots_take_the_largest_rating() -> None:
    """Easing anticipates one lag: with vehicles' lags differing it is refused in one line unless
    ``easing.lag_s`` says which; a run's plot labels take the largest rating and jerk limit."""
    from canbrake.analysis.plots import plot_meta

    types = {"a": {"mass_kg": 2e4, "brake": {"model": "ideal", "max_brake_decel_mps2": 1.2}},
             "b": {"mass_kg": 2e4, "brake": {"model": "electro_pneumatic", "lag_s": 0.4, "max_brake_decel_mps2": 1.4,
                                             "jerk_limit_mps3": 0.8}}}
    data = component_scenario(types, [{"type": "a"}, {"type": "b"}])
    meta = plot_meta(resolve(copy.deepcopy(data), "t.yaml"))
    assert (meta.emergency_decel_mps2, meta.jerk_limit_mps3) == (1.4, 0.8)
    data["train"]["every_vehicle"] = {"brake": {"easing": {"time_constant_s": 1.0}}}
    with pytest.raises(ScenarioError, match=r"^t.yaml: train.every_vehicle.brake.easing.lag_s: easing anticipates one "
                                            r"brake lag, and this train's vehicles have different ones \(0, 0.4 s"):
        resolve(copy.deepcopy(data), "t.yaml")
    data["train"]["every_vehicle"]["brake"]["easing"]["lag_s"] = 0.4
    assert resolve(data, "t.yaml").actuator.lag_s == [0.0, 0.4]


# --- 4. end stops per coupler --------------------------------------------------------------------
def test_each_coupler_has_its_own_end_stop() -> None:
    """Four cars, two pairs closing at 0.5 and 0.8 m/s: after its first impact (0.22 s, before the
    second one on the tension side of the slack) coupler 1's stop (2 cm, a = 0.6) returns
    sqrt(1 − a) of the closing speed, coupler 3's (4 cm, lossless, half as stiff) all of it (the
    buffer's law, module docstring of physics/train.py, to 3 %); coupler 2 has none and is pulled
    past either stop without force (1 s); each pair matches a two-car train with its own stop
    as one value (1e-6 m/s)."""
    m, free = 30000.0, 1e-3
    kw = dict(coupler_nonlinearity_per_m2=0.0, resistance=DavisResistance.zero(2), max_substep_s=1e-4)
    four = TrainPlant([m] * 4, [0.0, -20.0, -40.0, -60.0], [10.0, 10.5, 10.0, 10.8],
                      coupler_stiffness_n_per_m=free, coupler_nonlinearity_per_m2=0.0,
                      resistance=DavisResistance.zero(4), max_substep_s=1e-4, end_stop_m=[0.02, None, 0.04],
                      end_stop_stiffness_n_per_m=[2e7, 2e7, 1e7], end_stop_absorption=[0.6, 0.6, 0.0])
    a = TrainPlant([m] * 2, [0.0, -20.0], [10.0, 10.5], coupler_stiffness_n_per_m=free, end_stop_m=0.02,
                   end_stop_stiffness_n_per_m=2e7, end_stop_absorption=0.6, **kw)
    b = TrainPlant([m] * 2, [-40.0, -60.0], [10.0, 10.8], coupler_stiffness_n_per_m=free, end_stop_m=0.04,
                   end_stop_stiffness_n_per_m=1e7, end_stop_absorption=0.0, **kw)
    for k in range(100):
        for p in (four, a, b):
            p.step(0.01, np.zeros(p.n_cars))
        v = four.speed_mps
        if k == 21:  # t = 0.22 s
            assert abs(four.deflection_m[0]) < 0.02 and abs(four.deflection_m[2]) < 0.04  # in their travel again
            assert v[0] - v[1] == pytest.approx(math.sqrt(0.4) * 0.5, rel=0.03)
            assert v[2] - v[3] == pytest.approx(0.8, rel=0.03)
        np.testing.assert_allclose(v[:2], a.speed_mps, rtol=0, atol=1e-6)
        np.testing.assert_allclose(v[2:], b.speed_mps, rtol=0, atol=1e-6)
    assert abs(four.deflection_m[1]) > 0.1 and abs(four.coupler_force_n[1]) < 1e-2  # past both stops, no buffer
    assert stack_plants([four, four]) is not None  # shared per-coupler stops stack (test_stack_per_vehicle)


def test_vehicle_types_with_different_end_stops_lower_to_one_per_coupler() -> None:
    """Each vehicle's coupler is at its rear: types with and without an end stop give a list per
    coupler (null: none); bad values name the field."""
    chen = {"model": "chen", "stiffness_n_per_m": 2.0e6, "epsilon_per_m2": 0.0}
    types = {"a": {"mass_kg": 3e4, "length_m": 20.0, "coupler": {**chen, "end_stop_m": 0.08}},
             "b": {"mass_kg": 3e4, "length_m": 20.0, "coupler": {**chen, "end_stop_m": 0.05,
                                                                 "end_stop_absorption": 0.3}},
             "c": {"mass_kg": 3e4, "length_m": 20.0, "coupler": chen}}
    scn = resolve(component_scenario(types, [{"type": "a"}, {"type": "c"}, {"type": "b"}, {"type": "a"}]), "t.yaml")
    c = scn.consist.coupler
    assert c.end_stop_m == [0.08, None, 0.05] and c.end_stop_absorption == [0.6, 0.6, 0.3]
    assert c.end_stop_stiffness_n_per_m == 2e7
    p = build_plant_model(scn).plant
    assert p.end_stops_per_coupler and list(p.end_stop_m) == [0.08, math.inf, 0.05]
    p.step(0.01, np.zeros(4))  # runs
    types["b"]["coupler"]["end_stop_absorption"] = 1.0
    with pytest.raises(ScenarioError, match=r"train.vehicle_types.b.coupler.end_stop_absorption: Input should be less "
                                            r"than 1"):
        resolve(component_scenario(types, [{"type": "a"}, {"type": "b"}]), "t.yaml")


def test_a_table_on_the_rigid_train_with_driven_axles_runs_as_its_davis_curve() -> None:
    """Cai 2014 case 1 (rigid train, driven axles: the coupled kernel's rigid coupling) with the carriage's Davis
    resistance given as a table sampled every 0.05 m/s: the body's speed and each vehicle's
    measured resistance match the Davis run's (speed 1e-6 relative; resistance to the table's own
    interpolation error c2·Δv²/4 = 2.1 mN); a table 10 % higher is told apart."""
    from canbrake.scenario import load_scenario

    c = (203.5, 145.8, 3.35)
    tab = _davis_table(c, top_mps=40.0)
    runs = {}
    for name, res in (("davis", None), ("table", tab), ("off", {**tab, "force_n": [1.1 * f for f in tab["force_n"]]})):
        over = {} if res is None else {"train.vehicle_types.carriage.resistance": res}
        scn = load_scenario("cai2014_case1", overrides=over)
        assert scn.train.kernel_name == "coupled" and scn.consist.rigid
        p = build_plant_model(scn)
        for _ in range(300):
            p.step(0.01, {"axle1_torque_nm": np.full(p.n_vehicles, 3000.0)})
        runs[name] = (p.measurements()["speed_mps"][0], p.measurements()["resistance_n"])
    assert runs["table"][0] == pytest.approx(runs["davis"][0], rel=1e-6)
    np.testing.assert_allclose(runs["table"][1], runs["davis"][1], rtol=0, atol=c[2] * 0.05**2 / 4 + 1e-9)
    assert abs(runs["off"][1][1] - runs["davis"][1][1]) > 0.05 * runs["davis"][1][1]
    assert abs(runs["off"][0] - runs["davis"][0]) > 1e-4


MIXED = """\
name: mixed_kernel_limits
duration_s: 1.0
control_period_s: 0.01
train:
  vehicle_types:
    loco:
      mass_kg: 90000
      length_m: 20
      resistance: {model: davis, c0_n: 1500, c1_n_s_per_m: 20, c2_n_s2_per_m2: 6}
      coupler: {model: chen, stiffness_n_per_m: 2.0e+6, epsilon_per_m2: 0.0, end_stop_m: 0.08}
      brake: {model: electro_pneumatic, lag_s: 0.5, max_brake_decel_mps2: 1.2}
      traction: {model: envelope, traction_start_kn: 300, traction_start_until_kmh: 5, traction_intercept_kn: 320,
                 traction_slope_kn_per_kmh: 2, traction_linear_until_kmh: 60, brake_slope_kn_per_kmh: 0,
                 brake_linear_until_kmh: 0, brake_max_kn: 0, brake_constant_until_kmh: 1, power_kn_kmh: 12000}
    car:
      mass_kg: 40000
      length_m: 20
      resistance: {model: table, speed_mps: [0, 10, 20, 30], force_n: [600, 800, 1300, 2100]}
      coupler: {model: chen, stiffness_n_per_m: 2.0e+6, epsilon_per_m2: 0.0}
      brake: {model: ideal, max_brake_decel_mps2: 1.4}
  vehicles: [{type: loco}, {type: car, count: 3}]
initial: {speed_kmh: 60}
reference: {speed_kmh: 60, decel_kmh_per_s: 2.0}
controller: {name: pi}
"""


def test_a_train_with_every_per_vehicle_feature_runs_on_the_bus(tmp_path: Path) -> None:
    """``canbrake run`` on the memory bus (one process per ECU): a locomotive with an envelope, a lag
    and an end stop at its rear, cars with table resistance and ideal brakes: exit 0, finite
    speeds, and the lowering as intended."""
    p = tmp_path / "mixed.yaml"
    p.write_text(MIXED)
    c = resolve(yaml.safe_load(MIXED), str(p)).consist
    assert c.actuator.lag_s == [0.5, 0.0, 0.0, 0.0] and c.coupler.end_stop_m == [0.08, None, None]
    assert c.resistance_table[0] is None and c.traction_envelope[1] is None
    r = subprocess.run([sys.executable, "-m", "canbrake", "run", str(p), "--bus", "memory", "--no-plots",
                        "--out", str(tmp_path / "o")], capture_output=True, text=True, cwd=ROOT, timeout=300)
    assert r.returncode == 0, r.stderr
    rows = list(csv.DictReader((tmp_path / "o" / "signals.csv").open()))
    assert len(rows) > 90
    assert all(math.isfinite(float(row[f"speed_mps_c{i}"])) for row in rows for i in range(1, 5))
