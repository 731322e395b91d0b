"""The compiled wire bookkeeping (canbrake.bus._wire) against the bit-level reference in
canbrake.bus.timing (frame_bitstream + stuff_bit_count) and against the recorder's accounting
written out in Python."""
from __future__ import annotations

import struct

import can
from hypothesis import given, settings
from hypothesis import strategies as st

from canbrake.bus._wire import ideal_period, stuff_bits, timed_bits_raw
from canbrake.bus.timing import IFS_BITS, frame_bits, frame_bitstream, stuff_bit_count


@st.composite
def frame_args(draw):
    ext = draw(st.booleans())
    aid = draw(st.integers(0, 0x1FFFFFFF if ext else 0x7FF))
    dlc = draw(st.integers(0, 8))
    data = draw(st.one_of(st.binary(min_size=dlc, max_size=dlc),
                          st.lists(st.sampled_from([0x00, 0xFF, 0x0F, 0xF0, 0x55, 0x1F, 0xF8]), min_size=dlc,
                                   max_size=dlc).map(bytes)))
    return aid, ext, dlc, data, draw(st.booleans())


@settings(max_examples=2000, deadline=None)
@given(frame_args())
def test_stuff_bits_equal_the_reference(args):
    aid, ext, dlc, data, remote = args
    ref = frame_bitstream(aid, ext, dlc, data, is_remote=remote)
    assert stuff_bits(aid, ext, dlc, b"" if remote else data, remote) == stuff_bit_count(ref)
    assert frame_bits(aid, ext, dlc, data, "actual", is_remote=remote) == len(ref) + stuff_bit_count(ref) + 10 + IFS_BITS


def _reference_period(ordered, untimed, sim_control, t, t_k, dt, bitrate, epoch):
    """The recorder's accounting as it was written in Python before it was compiled."""
    durs = [0.0 if untimed.get(f[1]) else
            frame_bits(f[1], f[3].is_extended_id, f[3].dlc, f[2], stuffing="actual",
                       is_remote=f[3].is_remote_frame) / bitrate for f in ordered]
    wire = sum(durs)
    scale = min(1.0, dt / wire) if wire > 0 else 1.0
    busy = in_period = 0.0
    lats, out, n_timed = [], [], 0
    for f, dur in zip(ordered, durs):
        if not untimed.get(f[1]):
            t += dur
            busy += dur
            n_timed += 1
            lats.append(t - t_k)
        in_period += dur
        if not sim_control.get(f[1]):
            out.append((epoch + (t_k + in_period * scale), f[3]))
    return t, busy, n_timed, lats, out


@settings(max_examples=300, deadline=None)
@given(st.lists(frame_args(), max_size=40), st.integers(0, 10**6), st.sampled_from([1e-3, 1e-2, 2.5e-3]),
       st.sampled_from([125e3, 250e3, 500e3, 1e6]), st.floats(0, 1e-3), st.sampled_from([0.0, 1.7e9]),
       st.sets(st.integers(0, 0x7FF), max_size=20), st.sets(st.integers(0, 0x7FF), max_size=20))
def test_ideal_period_is_bit_identical_to_the_python_accounting(frames, k, dt, bitrate, carry, epoch, untimed, simctl):
    ordered = sorted(((i % 3, aid, b"" if r else data, can.Message(arbitration_id=aid, is_extended_id=ext, dlc=dlc,
                                                                   data=b"" if r else data, is_remote_frame=r))
                      for i, (aid, ext, dlc, data, r) in enumerate(frames)), key=lambda f: f[:3])
    u = {a: True for a in untimed}
    u.update({a: False for a in range(0, 0x800, 7) if a not in untimed})
    s = {a: True for a in simctl}
    t_k = k * dt
    got = ideal_period(ordered, u, s, t_k + carry, t_k, dt, bitrate, epoch)
    want = _reference_period(ordered, u, s, t_k + carry, t_k, dt, bitrate, epoch)
    assert got[:4] == want[:4]
    assert [(ts, id(m)) for ts, m in got[4]] == [(ts, id(m)) for ts, m in want[4]]


def _image(m: can.Message, ts: float = 0.0) -> bytes:
    """A memory-bus slot image of ``m`` (canbrake.bus._slot: flags bit 0 extended, 1 remote, 2 error)."""
    flags = int(m.is_extended_id) | 2 * int(m.is_remote_frame) | 4 * int(m.is_error_frame)
    data = bytes(m.data)
    return struct.pack("<dIIBBBxxxxx", ts, m.arbitration_id, 0, flags, m.dlc, len(data)) + data + bytes(72 - len(data))


@settings(max_examples=300, deadline=None)
@given(st.lists(st.tuples(frame_args(), st.booleans()), max_size=40), st.sets(st.integers(0, 0x7FF), max_size=20),
       st.integers(0, 40), st.integers(0, 40))
def test_timed_bits_raw_sums_frame_bits_of_the_timed_frames(frames, untimed, a, b):
    """The realtime recorder's bits of a run of slot images: frame_bits (actual stuffing, remote
    frames without a data field) summed over the frames that are neither error frames nor untimed."""
    msgs = [can.Message(arbitration_id=0 if err else aid, is_extended_id=ext, dlc=dlc, data=b"" if r else data,
                        is_remote_frame=r and not err, is_error_frame=err)
            for (aid, ext, dlc, data, r), err in frames]
    images = b"".join(_image(m) for m in msgs)
    u = {x: True for x in untimed}
    u.update({x: False for x in range(0, 0x800, 11) if x not in untimed})
    start, stop = min(a, b, len(msgs)), min(max(a, b), len(msgs))
    want = sum(frame_bits(m.arbitration_id, m.is_extended_id, m.dlc, bytes(m.data), stuffing="actual",
                          is_remote=m.is_remote_frame)
               for m in msgs[start:stop] if not m.is_error_frame and not u.get(m.arbitration_id))
    assert timed_bits_raw(images, start, stop, u) == want


@settings(max_examples=200, deadline=None)
@given(st.lists(frame_args(), max_size=40), st.integers(0, 10**6), st.sampled_from([1e-3, 1e-2]),
       st.sampled_from([250e3, 1e6]), st.floats(0, 1e-3), st.sets(st.integers(0, 0x7FF), max_size=20))
def test_ideal_period_of_slot_images_equals_messages(frames, k, dt, bitrate, carry, untimed):
    """Frames kept as memory-bus slot images (identifier at 8, flags at 16, DLC at 17) are
    accounted as their messages, and handed back as they came."""
    msgs = [(i % 3, aid, b"" if r else data, can.Message(arbitration_id=aid, is_extended_id=ext, dlc=dlc,
                                                        data=b"" if r else data, is_remote_frame=r))
            for i, (aid, ext, dlc, data, r) in enumerate(frames)]
    imgs = [(p, aid, data, _image(m)) for p, aid, data, m in msgs]
    u = {a: True for a in untimed}
    t_k = k * dt
    want = ideal_period(msgs, u, {}, t_k + carry, t_k, dt, bitrate, 0.0)
    got = ideal_period(imgs, u, {}, t_k + carry, t_k, dt, bitrate, 0.0)
    assert got[:4] == want[:4]
    assert [(ts, m) for ts, m in got[4]] == [(ts, f[3]) for (ts, _m), f in zip(want[4], imgs)]
