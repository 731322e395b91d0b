"""The compiled candump -L writer (canbrake.bus._candump) against python-can's CanutilsLogWriter:
every line must be what the library writes for the same message (frames.log is its contract)."""
from __future__ import annotations

import io
import struct

import can
from hypothesis import given, settings
from hypothesis import strategies as st

from canbrake.bus._candump import channel_name, write_candump


@st.composite
def frames(draw):
    ext = draw(st.booleans())
    return can.Message(
        arbitration_id=draw(st.integers(0, 0x1FFFFFFF if ext else 0x7FF)), is_extended_id=ext,
        is_remote_frame=(remote := draw(st.booleans())), is_error_frame=draw(st.booleans()) and not remote,
        data=draw(st.binary(max_size=8)), channel=draw(st.sampled_from([None, "x"])), is_rx=draw(st.booleans()))


stamps = st.one_of(st.floats(0, 1e6, allow_nan=False), st.floats(-1e3, 1e12, allow_nan=False),
                   st.integers(0, 10**6).map(lambda n: n * 1e-6), st.just(0.0))
channels = st.one_of(st.none(), st.sampled_from(["can0", "vcan0", "canbrake0", "seg_a", "0", "7", "ch ü"]),
                     st.integers(0, 9))


def library(pairs, channel, default="vcan0", first=None):
    w = can.CanutilsLogWriter(io.StringIO(), channel=default)
    w.last_timestamp = first
    for ts, m in pairs:
        w.on_message_received(can.Message(timestamp=ts, arbitration_id=m.arbitration_id, is_extended_id=m.is_extended_id,
                                          is_remote_frame=m.is_remote_frame, is_error_frame=m.is_error_frame,
                                          dlc=m.dlc, data=m.data, channel=channel, is_rx=True))
    return w.file.getvalue(), w.last_timestamp


def compiled(batches, channel, default="vcan0", first=None):
    w = can.CanutilsLogWriter(io.StringIO(), channel=default)
    w.last_timestamp = first
    for pairs in batches:
        write_candump(w, pairs, channel)
    return w.file.getvalue(), w.last_timestamp


@settings(max_examples=400, deadline=None)
@given(st.lists(st.tuples(stamps, frames()), max_size=30), channels, st.integers(1, 5),
       st.one_of(st.none(), stamps))
def test_lines_equal_python_cans_writer(pairs, channel, n_batches, first):
    # the same frames in one call or in several (the writer's state carries over between periods)
    cut = max(1, len(pairs) // n_batches)
    batches = [pairs[i:i + cut] for i in range(0, len(pairs), cut)]
    assert compiled(batches, channel, first=first) == library(pairs, channel, first=first)


def test_channel_rule_is_python_cans():
    assert channel_name(None, "vcan0") == "vcan0"
    assert channel_name(3, "vcan0") == "can3"
    assert channel_name("5", "vcan0") == "can5"
    assert channel_name("canbrake0", "vcan0") == "canbrake0"


def test_known_lines():
    m = can.Message(arbitration_id=0x0C1, is_extended_id=False, data=bytes.fromhex("DCBA037A765F00"))
    e = can.Message(arbitration_id=0x2000020C, is_extended_id=True, is_error_frame=True, data=bytes(8))
    r = can.Message(arbitration_id=0x1ABCDEF, is_extended_id=True, is_remote_frame=True, dlc=8)
    text, _ = compiled([[(0.000098, m), (0.0005, e), (0.0004, r)]], "can0")
    assert text == ("(0.000098) can0 0C1#DCBA037A765F00 R\n(0.000500) can0 20000080#0000000000000000\n"
                    "(0.000400) can0 01ABCDEF#R R\n")


def image(m):
    """The memory bus's slot image of ``m`` (canbrake.bus._slot), as the ring writes it."""
    flags = int(m.is_extended_id) | 2 * int(m.is_remote_frame) | 4 * int(m.is_error_frame)
    data = b"" if m.is_remote_frame else bytes(m.data)
    return (struct.pack("<dIIBBBxxxxx", 0.0, m.arbitration_id, 7, flags, m.dlc, len(data)) + data
            + bytes(64 - len(data)) + bytes(8))


@settings(max_examples=200, deadline=None)
@given(st.lists(st.tuples(stamps, frames()), max_size=30), channels, st.one_of(st.none(), stamps))
def test_slot_images_write_the_messages_lines(pairs, channel, first):
    """A frame given as its slot image (the recorder on the memory bus) writes python-can's line
    for its message."""
    mixed = [(ts, image(m) if i % 3 else m) for i, (ts, m) in enumerate(pairs)]
    assert compiled([mixed], channel, first=first) == library(pairs, channel, first=first)
