"""The alive counter's extension (canbrake.bus.dbc CounterExt): a protected frame whose last byte
has spare bits counts the tick mod 15·2^m instead of mod 15, with the same length and the low
nibble unchanged; frames without spare bits (Chen's) keep today's layout byte for byte."""
from __future__ import annotations

import cantools

from canbrake.build import bus_layout
from canbrake.bus.codec import FrameCodec
from canbrake.bus.e2e import COUNTER_MODULO, counter_modulus, extended_counter
from canbrake.bus.guard import FrameGuard
from canbrake.run import run_scenario
from canbrake.scenario import load_scenario
from conftest import CASE1, ROOT

LI = ROOT / "scenarios" / "li2024_driver.yaml"


def test_spare_bits_extend_the_counter_and_nothing_else_moves():
    layout = bus_layout(load_scenario(LI))
    m = layout.by_name["BRAKE_CMD_LOCO"]
    used = max(s.start + s.length for name, s in m.signals if s.name != "CounterExt")
    assert layout.counter_ext() == {m.frame_id: (used, 8 * m.length - used)}  # all the spare bits
    assert bus_layout(load_scenario(CASE1)).counter_ext() == {}  # Chen's frames are full: unchanged
    db = cantools.database.load_string(layout.database().as_dbc_string())
    codec = FrameCodec(layout.database())[m.name]
    bits = 8 * m.length - used
    for tick in (0, 14, 15, 29, 15 * (1 << bits) - 1, 15 * (1 << bits), 123456):
        data = codec.encode({"BrakeForce": 1000.0}, counter=tick % COUNTER_MODULO, tick=tick)
        d = db.decode_message(m.frame_id, data)
        assert d["Counter"] == tick % 15 and d["CounterExt"] == (tick // 15) % (1 << bits)
        assert extended_counter(data, (used, bits)) == tick % counter_modulus(bits)


def test_a_frame_15_periods_old_is_dated_right_instead_of_aliasing():
    layout = bus_layout(load_scenario(LI))
    fid = layout.by_name["BRAKE_CMD_LOCO"].frame_id
    codec = FrameCodec(layout.database())["BRAKE_CMD_LOCO"]
    old = codec.encode({"BrakeForce": 1000.0}, counter=40 % 15, tick=40)
    plain = FrameGuard(max_lag=7)
    assert plain.origin(fid, old, 55, 54) == 55  # the 4-bit counter alone: taken for this period's
    ext = FrameGuard(max_lag=7)
    ext.counter_ext = layout.counter_ext()
    assert ext.origin(fid, old, 55, 54) is None and ext.last_reason == "counter"  # 15 periods old
    assert ext.origin(fid, old, 40 + 15 * 128, 0) == 40 + 15 * 128  # aliases only after 15·2^7


def test_a_copy_15_periods_later_is_dropped_on_the_extended_counter(tmp_path):
    """Li's driver scenario (10 ms period): every locomotive command repeated 14.9 periods later.
    With the 4-bit counter it would alias onto the period 15 later; the extended counter dates it
    15 periods old, so every copy is rejected and the run equals the clean one."""
    over = {"duration_s": 1.0}
    clean = run_scenario(load_scenario(LI, overrides=over), tmp_path / "clean", backend="inprocess", plots=False)
    dup = {**over, "bus": {"impairments": [{"type": "duplicate", "probability": 1.0, "gap_s": 0.149,
                                            "ids": [0x081], "start_s": 0.1}]}}
    s = run_scenario(load_scenario(LI, overrides=dup), tmp_path / "dup", backend="inprocess", plots=False)
    copies = round((1.0 - 0.1) / 0.01) - 15  # copies of the commands of ticks 10 .. 84 land in the run
    assert s["safety"]["rejected"]["counter"] == copies, s["safety"]["rejected"]
    assert clean["safety"]["verdict"] == "clean"
    assert (tmp_path / "dup" / "signals.csv").read_bytes() == (tmp_path / "clean" / "signals.csv").read_bytes()
