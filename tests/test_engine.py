"""The one engine: consists as data, ECU placement, the identifier plan, references, hosted ECUs."""
from __future__ import annotations

import math
from pathlib import Path

import cantools
import numpy as np
import pytest

from canbrake.build import Reference, bus_layout
from canbrake.bus import dbc
from canbrake.run import run_scenario
from canbrake.scenario import ScenarioError, resolve

EMU = {
    "name": "emu",
    "duration_s": 0.2,
    "control_period_s": 0.01,
    "train": {
        "vehicle_types": {"mc": {"mass_kg": 42000.0, "length_m": 24.0,
                                 "resistance": {"model": "davis", "c0_n": 900.0, "c1_n_s_per_m": 30.0,
                                                "c2_n_s2_per_m2": 6.0}},
                          "tc": {"mass_kg": 36000.0, "length_m": 22.0}},
        "vehicles": [{"type": "mc"}, {"type": "tc", "count": 6}, {"type": "mc"}],
    },
    "initial": {"speed_kmh": 80.0},
    "reference": {"speed_kmh": 80.0, "decel_kmh_per_s": 3.0},
    "controller": {"name": "pi"},
}


def _emu(**over):
    data = {**EMU, **over}
    return resolve(data, "emu.yaml")


def test_vehicle_types_expand_to_the_consist():
    scn = _emu()
    assert scn.n_cars == 8
    np.testing.assert_array_equal(scn.vehicle_masses_kg(), [42000.0] + [36000.0] * 6 + [42000.0])
    # spacing = half of each neighbour's length; Davis only on the motor cars
    assert scn.consist.coupler.spacing_m == [23.0] + [22.0] * 5 + [23.0]
    assert scn.consist.davis.c0_n == [900.0] + [0.0] * 6 + [900.0]


@pytest.mark.parametrize("bad, needle", [
    ({"vehicles": [{"type": "nope"}]}, "unknown vehicle type 'nope'"),
    ({"vehicles": [{"type": "mc", "count": 0}]}, "count"),
    ({"mass_kg": [1.0]}, "train.mass_kg: moved to train.vehicles"),
])
def test_bad_consists_name_the_field(bad, needle):
    train = {**EMU["train"], **bad}
    with pytest.raises(ScenarioError, match=needle):
        resolve({**EMU, "train": train}, "emu.yaml")


def test_placement_ranges_listens_and_errors():
    scn = _emu(ecus=[{"vehicle": 1, "name": "lead"}, {"vehicles": "2-8", "name": "car{v}", "listens": ["lead"]}])
    placed = scn.placement()
    assert [p.name for p in placed] == ["lead"] + [f"car{v}" for v in range(2, 9)]
    specs = bus_layout(scn).ecus
    assert specs[0].listeners == tuple(range(2, 9)) and specs[0].listens == tuple(range(2, 9))
    assert specs[3].listens == (1,) and specs[3].listeners == (1,)
    for ecus, needle in [([{"vehicle": 9}], "vehicle 9, the train has 8"),
                         ([{"vehicle": 1}, {"vehicle": 1, "name": "x"}], "more than one ECU on vehicle"),
                         ([{"vehicle": 1, "listens": ["ghost"]}], "unknown ECU"),
                         ([{"vehicle": 1, "vehicles": "2-3"}], "exactly one of")]:
        with pytest.raises(ScenarioError, match=needle):
            _emu(ecus=ecus)


_PLANS = [(6, False), (63, False), (64, False), (127, False), (128, True), (200, True)]
#: cantools' DBC writer takes ~20 s for the 200-ECU database (quadratic in the messages): the
#: round trip of the large plans is in the slow test below
_ROUND_TRIP_FAST = (6, 64)


def _check_plan(n: int, ext: bool, round_trip: bool) -> None:
    layout = dbc.BusLayout(dbc.default_ecus(n))
    ids = [m.frame_id for m in layout.messages]
    assert len(set(ids)) == len(ids)
    assert all(m.extended == (m.frame_id > 0x7FF) for m in layout.messages)
    cmd, state = layout.ids("cmd"), layout.ids("state")
    assert max(cmd) < min(state), "commands outrank state frames"
    assert all(m.extended == ext for m in layout.messages if m.kind in ("cmd", "state")), n
    assert min(cmd) > dbc.REFERENCE_POS_ID
    db = layout.database()
    if round_trip:  # cantools accepts the whole database
        assert cantools.database.load_string(db.as_dbc_string(), database_format="dbc").messages


def test_identifier_plan_11_bit_up_to_127_then_29_bit():
    for n, ext in _PLANS:
        _check_plan(n, ext, round_trip=n in _ROUND_TRIP_FAST)


@pytest.mark.slow
def test_identifier_plan_databases_of_every_size_load_in_cantools():
    for n, ext in _PLANS:
        if n not in _ROUND_TRIP_FAST:
            _check_plan(n, ext, round_trip=True)


def test_dbc_has_units_value_tables_and_cycle_times():
    db = bus_layout(_emu()).database()
    for m in db.messages:
        assert m.length <= 8
        if not m.name.startswith(("STATE_DONE", "CMD_DONE")):
            assert m.cycle_time is not None, m.name
    hb = db.get_message_by_name("HEARTBEAT_C1")
    assert hb.cycle_time == 100 and hb.decode(bytes([5]))["NodeState"] == "operational"
    cmd = db.get_message_by_name("BRAKE_CMD_C1")
    assert cmd.cycle_time == 10 and cmd.get_signal_by_name("BrakeForce").unit == "N"
    assert cmd.get_signal_by_name("Status").choices[2] == "fail_safe"


def test_ramp_up_and_table_reference(tmp_path: Path):
    up = Reference(_emu(reference={"speed_kmh": 0.0, "decel_kmh_per_s": -1.0, "target_kmh": 200.0}))
    assert up(100.0) == pytest.approx((100 / 3.6, -1 / 3.6))
    assert up(250.0) == (pytest.approx(200 / 3.6), 0.0)
    # x*(t) = a t^2 / 2 during the ramp, then v_end (t - t_end)
    assert up.position(200.0) == pytest.approx(0.5 * (1 / 3.6) * 200.0 ** 2)
    assert up.position(210.0) == pytest.approx(0.5 * (1 / 3.6) * 200.0 ** 2 + 10 * 200 / 3.6)
    (tmp_path / "ref.csv").write_text("# a recorded curve\ntime_s,speed_kmh\n0,36\n10,72\n20,72\n")
    scn = _emu(reference={"kind": "table", "file": "ref.csv", "position_m": 5.0}, base_dir=str(tmp_path))
    ref = Reference(scn)
    assert ref(5.0) == pytest.approx((15.0, -1.0))
    assert ref.position(10.0) == pytest.approx(5.0 + 150.0)  # trapezoid of 10 -> 20 m/s over 10 s
    assert ref.position(25.0) == pytest.approx(5.0 + 150.0 + 15 * 20.0)
    (tmp_path / "bad.csv").write_text("time_s,speed_kmh\n0,36\n0,40\n")
    with pytest.raises(ValueError, match="time_s must increase"):
        Reference(_emu(reference={"kind": "table", "file": "bad.csv"}, base_dir=str(tmp_path)))
    with pytest.raises(ValueError, match="no such data file"):
        Reference(_emu(reference={"kind": "table", "file": "missing.csv"}, base_dir=str(tmp_path)))


def test_controller_params_are_validated_by_the_controllers_signature(tmp_path: Path):
    from canbrake.control.base import ControllerError, check_params

    with pytest.raises(ControllerError) as e:
        check_params("chen2023", {"alpha9": 1.0})
    assert e.value.param == "alpha9"
    with pytest.raises(ControllerError) as e:
        check_params("chen2023", {"alpha1": "fast"})
    assert e.value.param == "alpha1"
    check_params("chen2023", {"alpha1": 2.0})
    with pytest.raises(ControllerError, match="unknown controller"):
        check_params("nope", {})


def test_eight_car_emu_with_named_ecus_runs_and_decodes(tmp_path: Path):
    scn = _emu(ecus=[{"vehicles": "1-8", "name": "brake{v}", "listens": "none"}])
    s = run_scenario(scn, tmp_path / "r", backend="inprocess", plots=False)
    assert s["status"] == "ok"
    db = cantools.database.load_file(str(tmp_path / "r" / "canbrake.dbc"))
    assert "BRAKE_CMD_BRAKE3" in [m.name for m in db.messages]
    assert not [m for m in db.messages if m.name.startswith("STATE_")]  # nobody listens: no STATE frames
    import can

    n = 0
    for msg in can.LogReader(str(tmp_path / "r" / "frames.log")):
        db.decode_message(msg.arbitration_id, msg.data)
        n += 1
    assert n > 0


def test_hosted_ecus_give_identical_frames_and_signals(tmp_path: Path):
    """Several ECUs per OS process (ecu.per_process) on the memory bus == one per process == in process."""
    base = _emu(ecus=[{"vehicles": "1-8", "listens": "all"}], duration_s=0.1,
                bus={"impairments": [{"type": "delay", "delay_s": 0.004, "ids": [0x141]}]})
    ref = run_scenario(base, tmp_path / "inproc", backend="inprocess", plots=False)
    assert ref["status"] == "ok"
    hosted = base.model_copy(update={"ecu": base.ecu.model_copy(update={"per_process": 3})})
    s = run_scenario(hosted, tmp_path / "hosted", backend="memory", plots=False)
    assert s["status"] == "ok", s["message"]
    for f in ("signals.csv", "frames.log"):
        assert (tmp_path / "hosted" / f).read_bytes() == (tmp_path / "inproc" / f).read_bytes(), f


def test_29_bit_train_runs_over_the_memory_bus(tmp_path: Path):
    """130 vehicles with an ECU each: 29-bit identifiers end to end (hosted 65 ECUs per process)."""
    train = {**EMU["train"], "vehicles": [{"type": "mc"}, {"type": "tc", "count": 128}, {"type": "mc"}]}
    scn = _emu(train=train, duration_s=0.03, ecus=[{"vehicles": "1-130", "listens": "none"}], ecu={"per_process": 65})
    s = run_scenario(scn, tmp_path / "r", backend="memory", plots=False)
    assert s["status"] == "ok", s["message"]
    ref = run_scenario(scn, tmp_path / "i", backend="inprocess", plots=False)
    assert (tmp_path / "r" / "signals.csv").read_bytes() == (tmp_path / "i" / "signals.csv").read_bytes()
    assert s["ticks"] == 3 and not math.isnan(s["ticks"])
