"""Sweep points of trains whose vehicles differ (issue 27) run as one stack in the batch engine
(``stack_plants``): per-vehicle resistance tables, traction envelopes and per-coupler end stops are
rows the compiled kernel shares between points, so points that share them stack, and each row of
the stack equals its own plant bit for bit, with and without brake blending (the step with brake
equipment). Points whose tables, envelopes or end stops differ do not stack."""
from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from canbrake.physics.actuator import BrakeActuator
from canbrake.physics.brakes import BrakeBlending
from canbrake.physics.heavy_haul import TractionEnvelope
from canbrake.physics.resistance import DavisResistance
from canbrake.physics.train import TrainPlant, stack_plants

#: Li 2024's HXD1 traction envelope (kN, km/h)
ENV = TractionEnvelope(traction_start_kn=520.0, traction_start_until_kmh=5.0, traction_intercept_kn=551.6,
                       traction_slope_kn_per_kmh=5.7, traction_linear_until_kmh=76.0, brake_slope_kn_per_kmh=10.0,
                       brake_linear_until_kmh=46.0, brake_max_kn=461.0, brake_constant_until_kmh=76.0,
                       power_kn_kmh=25000.0)
TABLE = ([0.0, 10.0, 20.0, 40.0], [900.0, 1500.0, 2600.0, 7000.0])


def _plant(v0: float, *, blending: bool, table=TABLE, env=ENV, stop=(0.02, None, 0.03)) -> TrainPlant:
    """Four cars: a table on car 2, an envelope on car 1, an end stop on couplers 1 and 3 only."""
    m = [8.0e4, 4.0e4, 4.2e4, 3.9e4]
    return TrainPlant(m, [0.0, -20.0, -40.0, -60.0], [v0, v0, v0 - 0.5, v0], coupler_stiffness_n_per_m=2e6,
                      coupler_nonlinearity_per_m2=0.0, resistance=DavisResistance.zero(4),
                      actuator=BrakeActuator(kind="realistic", time_constant_s=(0.0, 0.3, 0.3, 0.5)),
                      end_stop_m=list(stop), end_stop_stiffness_n_per_m=4e6,
                      blending=BrakeBlending(ed_max_decel_mps2=0.8) if blending else None,
                      resistance_table=[None, table, None, None], traction_envelope=[env, None, None, None])


@pytest.mark.parametrize("blending", [False, True], ids=["kernel", "with-equipment"])
def test_points_sharing_tables_envelopes_and_end_stops_stack_and_equal_their_plants(blending: bool) -> None:
    plants = [_plant(15.0 + i, blending=blending) for i in range(3)]
    st = stack_plants(plants)
    assert st is not None
    # traction on the loco (capped by its envelope), brakes behind, and a pull that closes the stops
    cmds = [np.array([-6e5 + 1e5 * i, 3e4, 2e4 * i, 4e4]) for i in range(3)]
    cmd = np.stack(cmds)
    reached = np.zeros(3, dtype=bool)
    for k in range(300):
        st.step(0.01, cmd)
        for i, p in enumerate(plants):
            p.step(0.01, cmds[i])
            reached[i] |= bool(np.abs(p.deflection_m[0]) > 0.02)
    for i, p in enumerate(plants):
        assert np.array_equal(st.speed_mps[i], p.speed_mps) and np.array_equal(st.position_m[i], p.position_m)
        assert np.array_equal(st.applied_force_n[i], p.applied_force_n)
    assert reached.all()  # the end stop on coupler 1 was in play
    # the rows differ (the comparison can fail): each point ran its own command and speed
    assert not np.array_equal(st.speed_mps[0], st.speed_mps[1])


@pytest.mark.parametrize("other", [
    {"table": ([0.0, 10.0], [900.0, 1600.0])},
    {"env": None},
    {"stop": (0.02, None, 0.04)},
], ids=["table", "envelope", "end-stop"])
def test_points_whose_per_vehicle_parts_differ_do_not_stack(other: dict) -> None:
    assert stack_plants([_plant(15.0, blending=False), _plant(15.0, blending=False, **other)]) is None
    assert stack_plants([_plant(15.0, blending=False), _plant(16.0, blending=False)]) is not None


#: an EMU of our own whose motor cars have a traction envelope and whose trailers a resistance table
MIXED = """
name: emu_parts
duration_s: 1.5
control_period_s: 0.01
train:
  vehicle_types:
    motor: {mass_kg: 46000, length_m: 22.0, traction: {model: envelope, traction_start_kn: 200,
            traction_start_until_kmh: 5, traction_intercept_kn: 210, traction_slope_kn_per_kmh: 1.0,
            traction_linear_until_kmh: 76, brake_slope_kn_per_kmh: 10, brake_linear_until_kmh: 46,
            brake_max_kn: 200, brake_constant_until_kmh: 76, power_kn_kmh: 10000}}
    trailer: {mass_kg: 40000, length_m: 22.0,
              resistance: {model: table, speed_mps: [0, 10, 30], force_n: [800, 1400, 4000]}}
  vehicles: [{type: trailer}, {type: motor, count: 2}, {type: trailer, count: 2}]
  every_vehicle:
    coupler: {model: chen, stiffness_n_per_m: 2.0e6, epsilon_per_m2: 0.0}
    brake: {model: electro_pneumatic, lag_s: 0.3, jerk_limit_mps3: 1.0, max_brake_decel_mps2: 1.3,
            max_traction_accel_mps2: 1.0}
initial: {speed_kmh: 100}
reference: {speed_kmh: 100, decel_kmh_per_s: 3.0}
controller: {name: chen2023}
"""


@pytest.mark.slow
def test_a_sweep_over_a_train_with_tables_and_envelopes_runs_stacked_and_equals_per_point_runs(tmp_path) -> None:
    """The batch engine steps such points as one stack, and each point's signals.csv, metrics and
    verdict equal its own run on the node engine (delay and loss differ between the points)."""
    from test_batch_sweep import _compare, _run_both

    from canbrake import sweep as sw
    from canbrake.batch import BatchEngine, unsupported
    from canbrake.build import bus_layout
    from canbrake.scenario import load_scenario

    path = tmp_path / "emu_parts.yaml"
    path.write_text(MIXED)
    base = load_scenario(path)
    data, lay = base.model_dump(mode="json"), bus_layout(base)
    scns = [load_scenario(path, overrides={**sw.point_overrides(data, params, lay), "seed": seed})
            for params, seed in [({"delay": 0.0, "loss": 0.0}, 1), ({"delay": 0.02, "loss": 0.1}, 2),
                                 ({"delay": 0.005, "loss": 0.3}, 3)]]
    assert all(unsupported(s, 0) is None for s in scns)
    eng = BatchEngine(scns, [None] * len(scns))
    assert eng.stack is not None and eng.stack._tab is not None and eng.stack._env is not None
    sb, sp = _run_both(tmp_path, scns)
    for i in range(len(scns)):
        assert _compare(tmp_path / f"batch{i}", tmp_path / f"point{i}", sb[i], sp[i]) == [], i
    assert _compare(tmp_path / "batch0", tmp_path / "point1", sb[0], sp[1])


def _wheeled(v0: float, mu: float = 0.08):
    """Three 40-t cars (four, none and two wheelsets), blended brakes, on a rail of μ ``mu``, from v0."""
    from canbrake.physics.brakes import Wheelsets
    from canbrake.physics.rail import RailConditions

    m = np.full(3, 4.0e4)
    return TrainPlant(m, [0.0, -20.0, -40.0], [v0, v0, v0], coupler_stiffness_n_per_m=2e6,
                      coupler_nonlinearity_per_m2=0.0, resistance=DavisResistance.zero(3),
                      rail=RailConditions(base_adhesion_mu=mu), max_substep_s=0.001,
                      blending=BrakeBlending(ed_max_decel_mps2=0.8), wsp_valve_lag_s=(0.05, 0.05, 0.2),
                      wheels=Wheelsets(m, [4, 0, 2], [0.42, 1.0, 0.46], [120.0, 1.0, 200.0], np.full(3, v0)))


def test_points_with_wheelsets_stack_and_equal_their_plants_under_wheel_slide_protection() -> None:
    """Wheelsets with their own axles per car, on poor rail, braked beyond adhesion with the dump
    valves commanded (WSP): each stacked row's speeds, wheel speeds, slips and valves equal its own
    plant's bit for bit, and its measurements too."""
    plants = [_wheeled(15.0 + i) for i in range(3)]
    st = stack_plants(plants)
    assert st is not None and st.wheels.omega.shape == (3, 3, 4)
    rng = np.random.default_rng(3)
    for k in range(200):
        cmd = np.stack([np.array([3e4, 2.5e4, 3.5e4]) * (1.0 + 0.2 * i) for i in range(3)])
        wsp = np.where(rng.random((3, 3)) < 0.3, rng.random((3, 3)), np.nan)
        st.step(0.01, cmd, wsp_release=wsp)
        for i, p in enumerate(plants):
            p.step(0.01, cmd[i], wsp_release=wsp[i])
    sm = st.equipment_measurements()
    for i, p in enumerate(plants):
        assert np.array_equal(st.speed_mps[i], p.speed_mps) and np.array_equal(st.wheels.omega[i], p.wheels.omega)
        assert np.array_equal(st.wheels.slip[i], p.wheels.slip) and np.array_equal(st.wsp_valve[i], p.wsp_valve)
        pm = p.equipment_measurements()
        assert sm.keys() == pm.keys()
        for name, a in pm.items():
            np.testing.assert_array_equal(sm[name][i], a, err_msg=name)
    assert np.min(st.wheels.slip) < -0.05  # the wheels slid: the creep force was in play
    assert not np.array_equal(st.wheels.omega[0], st.wheels.omega[1])


def test_points_whose_wheelsets_differ_do_not_stack() -> None:
    a, b = _wheeled(15.0), _wheeled(15.0)
    assert stack_plants([a, b]) is not None
    b.wheels.J = b.wheels.J * 1.01
    assert stack_plants([a, b]) is None


@pytest.mark.slow
def test_a_sweep_over_a_train_with_wheels_runs_stacked_and_equals_per_point_runs(tmp_path) -> None:
    """emu8_low_adhesion (wheelsets on every car, blending, a low-adhesion section), without its
    end stops (they refine the sub-step by each point's state, which a stack cannot): the batch
    engine steps its points as one stack, and each equals its own node-engine run (signals.csv,
    metrics, verdict). Its WSP profile uses extended alive counters, which the batch engine does
    not run; WSP in a stack is compared at the plant above."""
    from test_batch_sweep import _compare, _run_both

    from canbrake import sweep as sw
    from canbrake.batch import BatchEngine, unsupported
    from canbrake.build import bus_layout
    from canbrake.scenario import load_scenario

    path = Path(__file__).resolve().parents[1] / "scenarios" / "emu8_low_adhesion.yaml"
    ov = {"duration_s": 7.0, "train.every_vehicle.coupler.end_stop_m": None}
    base = load_scenario(path, overrides=ov)
    data, lay = base.model_dump(mode="json"), bus_layout(base)
    scns = [load_scenario(path, overrides={**ov, **sw.point_overrides(data, params, lay), "seed": seed})
            for params, seed in [({"delay": 0.0, "loss": 0.0}, 1), ({"delay": 0.03, "loss": 0.2}, 2)]]
    assert all(unsupported(s, 0) is None for s in scns)
    eng = BatchEngine(scns, [None] * len(scns))
    assert eng.stack is not None and eng.stack.wheels is not None
    sb, sp = _run_both(tmp_path, scns)
    for i in range(len(scns)):
        assert _compare(tmp_path / f"batch{i}", tmp_path / f"point{i}", sb[i], sp[i]) == [], i
    assert _compare(tmp_path / "batch0", tmp_path / "point1", sb[0], sp[1])
    slip = np.genfromtxt(tmp_path / "batch0" / "signals.csv", delimiter=",", names=True)["axle1_slip_c1"]
    assert np.nanmin(slip) < -0.02  # car 1 slid in the low-adhesion section: the wheels were in play
