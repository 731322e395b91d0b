"""The user's own DBC (``bus.dbc``, canbrake.bus.userdbc): the mapping's rules, the supplier
example run end to end with every frame decoded by cantools with the supplier's file, the codec
on Motorola and multiplexed messages against cantools, and the physics against the same
scenario on canbrake's generated DBC."""
from __future__ import annotations

from pathlib import Path

import can
import cantools
import numpy as np
import pandas as pd
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from canbrake.cli import main
from canbrake.scenario import load_scenario

from conftest import ROOT

EXAMPLE = ROOT / "scenarios" / "chen2023_metro6_supplier_dbc.yaml"
SUPPLIER = ROOT / "dbc" / "metro6_brake_supplier.dbc"
#: the tolerances of docs/your-own-train.md ("Your own DBC"): the two runs differ only by the
#: supplier's quantisation (peer speeds in 0.01 km/h, positions in 1 mm, against canbrake's
#: 1e-4 m/s and 0.1 mm)
TOL_SPEED_MPS = 0.1 / 3.6
TOL_POSITION_M = 0.05
TOL_DEFLECTION_M = 0.005


def _run_cli(args: list[str], capsys) -> tuple[int, str]:
    rc = main(args)
    cap = capsys.readouterr()
    return rc, cap.err


def _bad(tmp_path: Path, capsys, *extra: str, scenario: Path = EXAMPLE) -> str:
    """Run the example with ``extra`` arguments: exit 2, one error line, nothing written."""
    rc, err = _run_cli(["run", str(scenario), "--bus", "inprocess", "--out", str(tmp_path / "out"), *extra], capsys)
    assert rc == 2, err
    assert "Traceback" not in err
    lines = [ln for ln in err.splitlines() if ln.startswith("canbrake: error:")]
    assert len(lines) == 1, err
    assert not (tmp_path / "out").exists()
    return lines[0]


def _variant(tmp_path: Path, old: str, new: str, dbc_name: str = "variant.dbc") -> Path:
    """The example scenario on a copy of the supplier's DBC with ``old`` replaced by ``new``."""
    text = SUPPLIER.read_text()
    assert old in text
    (tmp_path / dbc_name).write_text(text.replace(old, new))
    scn = EXAMPLE.read_text().replace("file: data/metro6_brake_supplier.dbc", f"file: {dbc_name}")
    p = tmp_path / "scenario.yaml"
    p.write_text(scn)
    return p


# ------------------------------------------------------------------------------ the rules
@pytest.mark.parametrize("sets, fragments", [
    # a missing message, a missing signal
    (["bus.dbc.sync.message=VCU_Sync2"], ["metro6_brake_supplier.dbc", "message VCU_Sync2 is missing"]),
    (["bus.dbc.each_ecu.commands.signals.brake_force_n=ForceDemand"],
     ["metro6_brake_supplier.dbc", "BCU1_BrakeDemand", "has no signal ForceDemand"]),
    # a range that cannot hold canbrake's values (4 bits for a speed)
    (["bus.dbc.each_ecu.state.signals.speed_mps=CarState{i}"],
     ["metro6_brake_supplier.dbc", "BCU1_Status", "signal CarState1", "cannot hold canbrake's speed_mps"]),
    # a cycle time that does not fit the control period
    (["control_period_s=0.02"], ["metro6_brake_supplier.dbc", "VCU_Sync", "GenMsgCycleTime 10 ms", "every 20 ms"]),
    # a DBC signal mapped to two canbrake signals; one message mapped to two roles
    (["bus.dbc.each_ecu.state.signals.position_m=CarSpeed{i}"],
     ["metro6_brake_supplier.dbc", "BCU1_Status", "signal CarSpeed1 is mapped twice"]),
    (["bus.dbc.ecus={ecu2: {heartbeat: {message: BCU1_Life, signals: {node_state: NodeState1}}}}"],
     ["metro6_brake_supplier.dbc", "BCU1_Life", "is mapped twice"]),
    # E2E: the counter where canbrake's receivers do not read it; a protected role without a CRC
    (["bus.dbc.each_ecu.state.counter=CarState{i}"],
     ["BCU1_Status", "signal CarState1", "alive counter as the low 4 bits of byte 1"]),
    (["bus.dbc.each_ecu.commands.crc=null"], ["BCU1_BrakeDemand", "map the E2E crc: and counter:"]),
    # the lockstep tick where the protocol does not read it
    (["bus.dbc.sync.signals.tick=VcuMode"], ["VCU_Sync", "signal VcuMode", "32-bit unsigned Intel field at bit 0"]),
    # multiplexed pages: none named, a signal of another page
    (["bus.dbc.each_ecu.sensors.multiplexer=null"], ["BIO1_LocalIO", "is multiplexed"]),
    (["bus.dbc.each_ecu.sensors.multiplexer=1"], ["BIO1_LocalIO", "signal VehSpeed is on multiplexer page 0, not 1"]),
    # a unit of another quantity; a canbrake signal left unmapped; a signal the role does not have
    (["bus.dbc.reference.signals={ref_speed_mps: TargetDecel, ref_decel_mps2: TargetSpeed}"],
     ["VCU_TrainRef", "signal TargetDecel", "unit 'm/s^2' is not a unit of m/s"]),
    (["bus.dbc.each_ecu.state.signals={speed_mps: \"CarSpeed{i}\"}"],
     ["bus.dbc.ecus.ecu1.state", "canbrake signal position_m of ECU ecu1 is not mapped"]),
    (["bus.dbc.each_ecu.state.signals.brake_force_n=CarState{i}"],
     ["BCU1_Status", "brake_force_n is not a signal of this role"]),
    (["bus.dbc.ecus={ecu9: {heartbeat: {message: BCU1_Life, signals: {node_state: NodeState1}}}}"],
     ["bus.dbc.ecus.ecu9", "no ECU of that name"]),
], ids=["missing_message", "missing_signal", "range", "cycle_time", "dbc_signal_twice", "message_twice",
        "counter_place", "no_crc", "tick_place", "mux_unnamed", "mux_wrong_page", "unit", "signal_unmapped",
        "foreign_signal", "unknown_ecu"])
def test_each_broken_rule_is_one_line_and_exit_2(sets, fragments, tmp_path, capsys):
    args = [a for s in sets for a in ("--set", s)]
    line = _bad(tmp_path, capsys, *args)
    for f in fragments:
        assert f in line, (f, line)


def test_a_resolution_far_coarser_than_canbrakes_is_refused(tmp_path, capsys):
    # 0.5 km/h per bit holds the range (0..32767 km/h) but not the values: 1390 times canbrake's 1e-4 m/s
    p = _variant(tmp_path, 'SG_ CarSpeed1 : 23|16@0+ (0.01,0) [0|655.35] "km/h"',
                 'SG_ CarSpeed1 : 23|16@0+ (0.5,0) [0|32767.5] "km/h"')
    line = _bad(tmp_path, capsys, scenario=p)
    for f in ("variant.dbc", "BCU1_Status", "signal CarSpeed1", "resolution 0.5 km/h", "100 times canbrake's"):
        assert f in line, (f, line)


def test_an_identifier_of_canbrakes_barrier_frames_in_the_dbc_is_a_clash(tmp_path, capsys):
    # a gateway's 11-bit message at 0x781, canbrake's STATE_DONE_C1
    p = _variant(tmp_path, "BO_ 2298413079 VCU_Sync: 8 VCU",
                 'BO_ 1921 GW_Status: 8 VCU\n SG_ GwState : 0|8@1+ (1,0) [0|255] "" VCU\n\n'
                 "BO_ 2298413079 VCU_Sync: 8 VCU")
    line = _bad(tmp_path, capsys, scenario=p)
    for f in ("variant.dbc", "identifier clash", "STATE_DONE_C1", "0x781", "GW_Status"):
        assert f in line, (f, line)


def test_two_roles_on_pages_of_one_multiplexed_message_clash(tmp_path, capsys):
    # a second motion page on BIO1_LocalIO, mapped as ecu2's sensors: two roles, one identifier
    p = _variant(tmp_path, ' SG_ LoadPressure m1 : 31|16@0+ (0.1,0) [0|6553.5] "kPa" BCU1',
                 ' SG_ LoadPressure m1 : 31|16@0+ (0.1,0) [0|6553.5] "kPa" BCU1\n'
                 ' SG_ VehSpeedB m2 : 3|20@0+ (0.001,0) [0|1048.575] "km/h" BCU1\n'
                 ' SG_ OdometerB m2 : 31|32@0- (0.001,0) [-2147483.648|2147483.647] "m" BCU1')
    line = _bad(tmp_path, capsys, "--set", "bus.dbc.ecus={ecu2: {sensors: {message: BIO1_LocalIO, multiplexer: 2, "
                                           "signals: {speed_mps: VehSpeedB, position_m: OdometerB}}}}", scenario=p)
    for f in ("variant.dbc", "identifier clash", "ecus.ecu1.sensors", "ecus.ecu2.sensors", "0xcff1041"):
        assert f in line, (f, line)


def test_a_missing_dbc_file_is_one_line(tmp_path, capsys):
    line = _bad(tmp_path, capsys, "--set", "bus.dbc.file=nope.dbc")
    assert "nope.dbc" in line and "no such DBC file" in line


# ------------------------------------------------------------------------------ the codec
def _layouts():
    from canbrake.build import bus_layout

    scn = load_scenario(EXAMPLE)
    layout = bus_layout(scn)
    return layout, cantools.database.load_file(str(SUPPLIER))


def test_the_mapped_layout_holds_the_suppliers_identifiers_and_canbrakes_barrier_frames():
    layout, user = _layouts()
    user_ids = {m.frame_id for m in user.messages}
    kinds = {}
    for m in layout.messages:
        kinds.setdefault(m.kind, set()).add(m.frame_id in user_ids)
    # every role on the bus is the supplier's; only the barrier frames are canbrake's (11-bit)
    assert kinds.pop("state_done") == {False} and kinds.pop("cmd_done") == {False}
    assert all(v == {True} for v in kinds.values()), kinds
    assert layout.sync_id == user.get_message_by_name("VCU_Sync").frame_id
    assert layout.plan.heartbeat(3) == user.get_message_by_name("BCU3_Life").frame_id


@settings(max_examples=40, deadline=None, suppress_health_check=[HealthCheck.too_slow, HealthCheck.data_too_large])
@given(data=st.data())
def test_frames_are_the_suppliers_frames_bit_for_bit(data):
    """Every mapped message, encoded by the compiled codec (Motorola fields, multiplexer page,
    E2E CRC), is what cantools encodes with the run's database, and the supplier's DBC decodes it
    to the same physical values in its own units (km/h, kN)."""
    from canbrake.bus.codec import FrameCodec
    from canbrake.bus.e2e import e2e_crc
    from canbrake.bus.userdbc import UNITS

    layout, user = _layouts()
    db = layout.database()
    fc = FrameCodec(db)
    for spec in layout.messages:
        if spec.kind in ("state_done", "cmd_done"):
            continue
        m = db.get_message_by_frame_id(spec.frame_id)
        c = fc.by_id[spec.frame_id]
        vals = {}
        for s in m.signals:
            lo, hi = ((-(1 << (s.length - 1)), (1 << (s.length - 1)) - 1) if s.is_signed else (0, (1 << s.length) - 1))
            if s.name == "CRC":
                continue
            if s.is_multiplexer:
                vals[s.name] = next(i for x in m.signals for i in (x.multiplexer_ids or ()))
            elif s.name == "Counter":
                vals[s.name] = data.draw(st.integers(0, 14))
            else:
                vals[s.name] = data.draw(st.integers(lo, hi)) * s.scale + s.offset
        ours = c.encode(vals, counter=vals.get("Counter"))
        theirs_vals = dict(vals, **({"CRC": ours[0]} if c.protected else {}))
        assert ours == m.encode(theirs_vals, strict=False), spec.name
        if c.protected:
            assert ours[0] == e2e_crc(spec.frame_id, ours)
        assert c.decode(ours) == m.decode(ours, decode_choices=False), spec.name
        if not m.is_multiplexed():  # (random bytes of a multiplexed message may be another page)
            raw = data.draw(st.binary(min_size=m.length, max_size=m.length))
            assert c.decode(raw) == m.decode(raw, decode_choices=False), spec.name
        # the supplier's DBC reads the same frame: same values, in its units
        um = user.get_message_by_frame_id(spec.frame_id)
        got = um.decode(ours, decode_choices=False)
        dec = c.decode(ours)
        for _sig, sp in spec.signals:
            if sp.is_multiplexer:
                assert got[sp.name] == dec[sp.name]
                continue
            uname = sp.comment.split(" of ")[0].split(".")[1]
            us = um.get_signal_by_name(uname)
            k = UNITS[us.unit][1] / UNITS[sp.unit][1] if us.unit in UNITS and sp.unit in UNITS else 1.0
            assert got[uname] == pytest.approx(dec[sp.name] * k, rel=1e-12, abs=1e-9), (spec.name, uname)


# ------------------------------------------------------------------------------ end to end
@pytest.fixture(scope="module")
def own_and_generated(tmp_path_factory):
    """The example (1.5 s) on the memory bus with one process per ECU, and the same scenario
    without bus.dbc (canbrake's generated DBC) in process."""
    import yaml

    from canbrake.cli import main as cli

    base = tmp_path_factory.mktemp("own_dbc")
    rc_own = cli(["run", str(EXAMPLE), "--duration", "1.5", "--out", str(base / "own"), "--no-plots"])
    data = yaml.safe_load(EXAMPLE.read_text())
    del data["bus"]["dbc"]
    gen = base / "generated.yaml"
    gen.write_text(yaml.safe_dump(data))
    rc_gen = cli(["run", str(gen), "--duration", "1.5", "--bus", "inprocess", "--out", str(base / "gen"), "--no-plots"])
    return rc_own, rc_gen, base / "own", base / "gen"


@pytest.mark.slow
def test_the_example_runs_and_cantools_decodes_every_frame_with_the_suppliers_dbc(own_and_generated):
    rc, _rc_gen, own, _gen = own_and_generated
    assert rc == 0
    assert (own / "metro6_brake_supplier.dbc").read_bytes() == SUPPLIER.read_bytes()
    db = cantools.database.load_file(str(SUPPLIER))
    names: dict[str, int] = {}
    first: dict[str, dict] = {}
    frames = list(can.LogReader(str(own / "frames.log")))
    assert len(frames) > 1000
    for f in frames:
        m = db.get_message_by_frame_id(f.arbitration_id)  # KeyError: a frame the supplier's DBC does not know
        assert f.is_extended_id == m.is_extended_frame
        first.setdefault(m.name, db.decode_message(f.arbitration_id, f.data))
        names[m.name] = names.get(m.name, 0) + 1
    # every role of the mapping travelled, at its cycle time (10 ms, heartbeats 100 ms)
    ticks = 150
    assert names["VCU_Sync"] == ticks + 1  # + the END frame
    for i in range(1, 7):
        assert names[f"BIO{i}_LocalIO"] == names[f"BCU{i}_Status"] == names[f"BCU{i}_BrakeDemand"] == ticks
        assert names[f"BCU{i}_Life"] == ticks // 10
    assert f"BCU1_DM1" not in names  # unmapped messages are not sent
    assert first["VCU_TrainRef"]["TargetSpeed"] == pytest.approx(90.0)
    assert first["BIO1_LocalIO"]["IoPage"] == "Motion"
    assert first["BIO1_LocalIO"]["VehSpeed"] == pytest.approx(88.0) and first["BIO6_LocalIO"]["VehSpeed"] == 95.5
    assert first["BIO2_LocalIO"]["Odometer"] == pytest.approx(20.0)
    assert first["BCU1_Life"]["NodeState1"] == "Operational"


@pytest.mark.slow
def test_the_physics_equals_the_generated_dbc_run_within_the_quantisation(own_and_generated):
    rc_own, rc_gen, own, gen = own_and_generated
    assert rc_own == rc_gen == 0
    a = pd.read_csv(own / "signals.csv")
    b = pd.read_csv(gen / "signals.csv")
    assert list(a.columns) == list(b.columns) and len(a) == len(b) == 151
    assert np.array_equal(a["t_s"], b["t_s"])

    def worst(prefix: str) -> float:
        cols = [c for c in a.columns if c.startswith(prefix)]
        assert cols
        return float(max(np.nanmax(np.abs(a[c] - b[c])) for c in cols))

    assert worst("speed_mps_c") <= TOL_SPEED_MPS
    assert worst("position_m_c") <= TOL_POSITION_M
    assert worst("deflection_m_k") <= TOL_DEFLECTION_M
    # and the encodings really differ (a run that ignored the mapping would be identical)
    assert worst("speed_mps_c") > 0


# ------------------------------------------------------------------------------ more of the codec
@st.composite
def _motorola_message(draw):
    """A random message of Intel and Motorola fields (non-overlapping), as DBC text."""
    length = draw(st.integers(1, 8))
    free = [True] * (8 * length)  # by the big-endian linear bit index (byte 0's MSB = 0)
    sigs = []
    for k in range(draw(st.integers(1, 6))):
        big = draw(st.booleans())
        n = draw(st.integers(1, min(32, 8 * length)))
        if big:
            msb = draw(st.integers(0, 8 * length - n))
            bits = list(range(msb, msb + n))
            start = 8 * (msb // 8) + 7 - msb % 8
        else:
            start = draw(st.integers(0, 8 * length - n))
            bits = [8 * (b // 8) + 7 - b % 8 for b in range(start, start + n)]
        if not all(free[b] for b in bits):
            continue
        for b in bits:
            free[b] = False
        signed = draw(st.booleans()) and n > 1
        scale = draw(st.sampled_from([1, 0.01, 0.5, 0.001, 2.5]))
        offset = draw(st.sampled_from([0, -10, 0.25]))
        sigs.append(f' SG_ S{k} : {start}|{n}@{0 if big else 1}{"-" if signed else "+"} ({scale},{offset}) '
                    f'[0|0] "" B')
    text = f'VERSION ""\nBU_: A B\nBO_ {0x80000000 | 0x18FF0001} M: {length} A\n' + "\n".join(sigs) + "\n"
    return text


@settings(max_examples=200, deadline=None)
@given(text=_motorola_message(), data=st.data())
def test_the_codec_encodes_and_decodes_motorola_and_intel_fields_as_cantools(text, data):
    from canbrake.bus.codec import MessageCodec

    db = cantools.database.load_string(text, database_format="dbc")
    m = db.messages[0]
    if not m.signals:
        return
    c = MessageCodec(m)
    vals = {}
    for s in m.signals:
        lo, hi = ((-(1 << (s.length - 1)), (1 << (s.length - 1)) - 1) if s.is_signed else (0, (1 << s.length) - 1))
        vals[s.name] = data.draw(st.integers(lo, hi)) * s.scale + s.offset
    assert c.encode(vals) == m.encode(vals, strict=False, scaling=True)
    raw = data.draw(st.binary(min_size=m.length, max_size=m.length))
    assert c.decode(raw) == m.decode(raw, decode_choices=False)


@pytest.mark.slow
def test_a_role_over_two_messages_runs_as_over_one(tmp_path, capsys):
    """The state broadcast split over two supplier messages (speed in one, position in the other,
    same scaling) gives the same physics as the one-message mapping, byte for byte: pages of a
    mapped role are handled as canbrake's own pages."""
    text = SUPPLIER.read_text()
    for i in range(1, 7):
        old = f' SG_ CarPosition{i} : 39|32@0- (0.001,0) [-2147483.648|2147483.647] "m"'
        assert old in text
        text = text.replace(old, f' SG_ CarSpare{i} : 39|32@0- (0.001,0) [-2147483.648|2147483.647] "m"')
        fid = 0x80000000 | (3 << 26) | (0xFF << 16) | (0x21 << 8) | (0x30 + i)
        text += (f'\nBO_ {fid} BCU{i}_Position: 8 BCU{i}\n SG_ CRC{i}_PO : 7|8@0+ (1,0) [0|255] "" BCU1\n'
                 f' SG_ AliveCounter{i}_PO : 11|4@0+ (1,0) [0|14] "" BCU1\n'
                 f' SG_ CarPosition{i} : 39|32@0- (0.001,0) [-2147483.648|2147483.647] "m" BCU1\n')
    (tmp_path / "two.dbc").write_text(text)
    scn = EXAMPLE.read_text().replace("file: data/metro6_brake_supplier.dbc", "file: two.dbc").replace(
        '''      state:     {message: "BCU{i}_Status", crc: "CRC{i}_ST", counter: "AliveCounter{i}_ST",
                  signals: {speed_mps: "CarSpeed{i}", position_m: "CarPosition{i}"}}''',
        '''      state:
        - {message: "BCU{i}_Status", crc: "CRC{i}_ST", counter: "AliveCounter{i}_ST", signals: {speed_mps: "CarSpeed{i}"}}
        - {message: "BCU{i}_Position", crc: "CRC{i}_PO", counter: "AliveCounter{i}_PO", signals: {position_m: "CarPosition{i}"}}''')
    assert "BCU{i}_Position" in scn
    (tmp_path / "two.yaml").write_text(scn)
    for name, path in (("one", EXAMPLE), ("two", tmp_path / "two.yaml")):
        rc, err = _run_cli(["run", str(path), "--bus", "inprocess", "--duration", "0.5", "--out", str(tmp_path / name),
                            "--no-plots"], capsys)
        assert rc == 0, err
    assert (tmp_path / "one" / "signals.csv").read_bytes() == (tmp_path / "two" / "signals.csv").read_bytes()
    db = cantools.database.load_file(str(tmp_path / "two.dbc"))
    seen = {db.get_message_by_frame_id(f.arbitration_id).name for f in can.LogReader(str(tmp_path / "two" / "frames.log"))}
    assert {"BCU3_Status", "BCU3_Position"} <= seen
