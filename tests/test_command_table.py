"""The brake units' compiled command table (canbrake.bus._codec.CommandTable) against an
interpreted oracle of the rules it implements: E2E profile 1's CRC and counter continuity
(canbrake.bus.e2e), the origin window of FrameGuard.origin (canbrake.bus.guard), the decode of
the page into the per-vehicle command arrays (FieldCodec.decode)."""
from __future__ import annotations

import struct

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from canbrake.bus import dbc
from canbrake.bus._codec import (CMD_BAD_COUNTER, CMD_BAD_CRC, CMD_FRESH, CMD_OLD, CMD_OUT_OF_SEQUENCE,
                                 CMD_SLOT_COMPLETE, CommandTable)
from canbrake.bus.codec import FrameCodec
from canbrake.bus.e2e import e2e_crc

CODEC = FrameCodec(dbc.build_database(3))
MSG = CODEC["BRAKE_CMD_C2"]
MAX_LAG = 7


class Oracle:
    """One page's receiver, interpreted: what the plant did before the table was compiled."""

    def __init__(self) -> None:
        self.last_counter: int | None = None
        self.origin = -1
        self.newest = -1
        self.fresh_pages = 0

    def take(self, data: bytes, k: int) -> tuple[int, float | None]:
        fid = MSG.frame_id
        if len(data) < 2 or data[0] != e2e_crc(fid, data):
            return CMD_BAD_CRC, None
        c = data[1] & 0x0F
        oos = 0
        if c >= 15:
            oos = CMD_OUT_OF_SEQUENCE
        else:
            if self.last_counter is not None and (c - self.last_counter) % 15 > 3:
                oos = CMD_OUT_OF_SEQUENCE
            self.last_counter = c
        lag = (k - c) % 15
        origin = k - lag
        if c >= 15 or lag > MAX_LAG or origin <= self.origin:
            return oos | CMD_BAD_COUNTER, None
        self.origin = origin
        self.newest = max(self.newest, origin)
        value = MSG.decode(data)["BrakeForce"]
        if origin != k:
            return oos | CMD_OLD, value
        self.fresh_pages += 1
        return oos | CMD_FRESH | (CMD_SLOT_COMPLETE if self.fresh_pages == 1 else 0), value


events = st.lists(st.tuples(st.integers(0, 3),            # ticks the receiver advances first
                            st.integers(0, 15),           # counter in the frame (15: invalid)
                            st.sampled_from(["ok", "crc", "short"]),
                            st.floats(-4e5, 4e5, allow_nan=False)), max_size=60)


@given(events)
@settings(max_examples=300, deadline=None)
def test_take_equals_the_rules(evs: list[tuple[int, int, str, float]]) -> None:
    force = np.full(3, np.nan)
    fresh_pages, pages, fresh, newest = (np.zeros(3, np.int64), np.ones(3, np.int64), np.zeros(3, bool),
                                         np.full(3, -1, np.int64))
    table = CommandTable(fresh_pages, pages, fresh, newest, MAX_LAG)
    table.add_page(MSG.frame_id, 1, MSG._c, [("BrakeForce", force, 1)], None)
    ref = Oracle()
    k = 0
    for dk, counter, how, f in evs:
        if dk:
            k += dk
            fresh_pages[:] = 0
            fresh[:] = False
            ref.fresh_pages = 0
        data = bytearray(MSG.encode({"BrakeForce": f, "Status": 0}, counter=min(counter, 14)))
        data[1] = (data[1] & 0xF0) | counter
        data[0] = e2e_crc(MSG.frame_id, data)
        if how == "crc":
            data[3] ^= 0x10
        elif how == "short":
            data = data[:1]
        expect, value = ref.take(bytes(data), k)
        before = force[1]
        got = table.take(MSG.frame_id, bytes(data), k)
        assert got == expect
        if value is not None:
            assert force[1] == value
        else:
            assert force[1] == before or (np.isnan(before) and np.isnan(force[1]))
        assert newest[1] == ref.newest and table.page_origin(MSG.frame_id) == ref.origin
        assert fresh_pages[1] == ref.fresh_pages and bool(fresh[1]) == (ref.fresh_pages >= 1)
        assert newest[0] == newest[2] == -1  # other slots untouched


def test_check_then_apply_equals_take() -> None:
    a, b = (np.full(3, np.nan) for _ in range(2))
    tabs = []
    for arr in (a, b):
        t = CommandTable(np.zeros(3, np.int64), np.ones(3, np.int64), np.zeros(3, bool), np.full(3, -1, np.int64), 7)
        t.add_page(MSG.frame_id, 1, MSG._c, [("BrakeForce", arr, 1)], None)
        tabs.append(t)
    for k in range(20):
        data = MSG.encode({"BrakeForce": 1000.0 * k}, counter=k % 15)
        r = tabs[0].take(MSG.frame_id, data, k)
        c, origin = tabs[1].check(MSG.frame_id, data, k)
        assert not c & 3 and origin == k
        assert tabs[1].apply(MSG.frame_id, data, origin, k) | c == r
    assert a[1] == b[1] == 19000.0


# ---------------------------------------------------------------- the plant's sensor pages
from canbrake.bus._codec import SensorPages  # noqa: E402


@given(st.data())
@settings(max_examples=200, deadline=None)
def test_sensor_pages_equal_encode_of_the_finite_values(data: st.DataObject) -> None:
    """pack() == FieldCodec.encode({signal: value for the finite ones}) for every page, whatever
    the values (NaN, inf, out of range, the 0.0 of a missing coupler)."""
    names = sorted(CODEC.by_name)
    chosen = data.draw(st.lists(st.sampled_from(names), min_size=1, max_size=5, unique=True))
    n_src, length = 3, 4
    values = st.one_of(st.floats(allow_nan=True, allow_infinity=True), st.floats(-1e6, 1e6))
    sources = [np.asarray(data.draw(st.lists(values, min_size=length, max_size=length)), dtype=float)
               for _ in range(n_src)]
    pages, expect = [], []
    for name in chosen:
        mc = CODEC[name]
        sigs = [s.name for s in CODEC.db.get_message_by_name(name).signals if data.draw(st.booleans())]
        fields, vals = [], {}
        for sig in sigs:
            src = data.draw(st.integers(-1, n_src - 1))
            e = data.draw(st.integers(0, length - 1))
            fields.append((sig, src, e))
            x = 0.0 if src < 0 else float(sources[src][e])
            if np.isfinite(x):
                vals[sig] = x
        pages.append((mc._c, fields))
        try:
            expect.append(mc._c.encode(vals))
        except OverflowError as err:  # a finite value beyond the raw range's floats (e.g. 9e303 / 0.01)
            expect.append(err)
    errors = [e for e in expect if isinstance(e, Exception)]
    if errors:  # the first failing page raises, as encode does
        with pytest.raises(type(errors[0]), match=str(errors[0])):
            SensorPages(pages).pack(sources)
    else:
        assert SensorPages(pages).pack(sources) == expect


field_specs = st.lists(st.tuples(st.integers(0, 63), st.integers(1, 16), st.booleans(),
                                 st.sampled_from([1.0, 0.5, 0.01, 3.0]), st.sampled_from([0.0, -40.0, 12.5]),
                                 st.sampled_from(["value", "value", "counter", "const"]), st.booleans(),
                                 st.integers(0, 3)), min_size=1, max_size=6)


@given(field_specs, st.lists(st.floats(allow_nan=True, allow_infinity=False, width=32), min_size=6, max_size=6),
       st.booleans())
@settings(max_examples=300, deadline=None)
def test_sensor_pages_equal_encode_for_motorola_and_multiplexed_fields(specs: list, xs: list[float],
                                                                      protected: bool) -> None:
    """The same with a user DBC's field kinds: Intel and Motorola fields, a multiplexer (const)."""
    from canbrake.bus._codec import FieldCodec

    fields = [(f"S{i}", start, nbits, signed, scale, off, role, big, mux)
              for i, (start, nbits, signed, scale, off, role, big, mux) in enumerate(specs)]
    if protected:
        fields.insert(0, ("CRC", 0, 8, False, 1.0, 0.0, "crc", False, None))
    try:
        codec = FieldCodec(fields, 8, protected, 0x123)
    except ValueError:
        return  # a field that does not fit the frame: refused, nothing to compare
    src = np.asarray(xs, dtype=float)
    vals = {f"S{i}": float(src[i]) for i in range(len(specs)) if np.isfinite(src[i])}
    page = [(f"S{i}", 0, i) for i in range(len(specs))]
    try:
        expect = codec.encode(vals)
    except OverflowError:
        with pytest.raises(OverflowError):
            SensorPages([(codec, page)]).pack([src])
        return
    assert SensorPages([(codec, page)]).pack([src]) == [expect]


# ---------------------------------------------------------------- the plant's receive loop
from canbrake.bus._codec import (TAKE_BATCH_END, TAKE_BATCH_OTHER, TAKE_BATCH_RESULT,  # noqa: E402
                                 TAKE_BATCH_TICK)
from canbrake.bus._ring import data_frame, messages_of  # noqa: E402
from canbrake.bus.memory_shm import SLOT_BYTES  # noqa: E402

PAGES3 = [CODEC[f"BRAKE_CMD_C{i}"] for i in (1, 2, 3)]


def _table3() -> tuple[CommandTable, tuple[np.ndarray, ...]]:
    arrays = (np.zeros(3, np.int64), np.ones(3, np.int64), np.zeros(3, bool), np.full(3, -1, np.int64),
              np.full(3, np.nan))
    t = CommandTable(*arrays[:4], MAX_LAG)
    for slot, m in enumerate(PAGES3):
        t.add_page(m.frame_id, slot, m._c, [("BrakeForce", arrays[4], slot)], None)
    return t, arrays


def _expected_batch(table: CommandTable, fresh: np.ndarray, msgs: list, start: int, k: int) -> tuple:
    """take_batch by take() frame by frame (its documented events)."""
    ids = {m.frame_id for m in PAGES3}
    completed = accepted = 0
    for i in range(start, len(msgs)):
        if msgs[i].arbitration_id not in ids:
            return i, TAKE_BATCH_OTHER, 0, completed, accepted
        r = table.take(msgs[i].arbitration_id, msgs[i].data, k)
        if r & 3 in (CMD_BAD_CRC, CMD_BAD_COUNTER) or r & CMD_OUT_OF_SEQUENCE:
            return i, TAKE_BATCH_RESULT, r, completed, accepted
        accepted += 1
        if r & CMD_SLOT_COMPLETE:
            completed |= 1 << [m.frame_id for m in PAGES3].index(msgs[i].arbitration_id)
            if fresh.all():
                return i, TAKE_BATCH_TICK, r, completed, accepted
    return len(msgs), TAKE_BATCH_END, 0, completed, accepted


frames3 = st.lists(st.tuples(st.integers(-1, 2),          # page (-1: a frame that is not a command)
                             st.integers(0, 15), st.sampled_from(["ok", "ok", "crc"]),
                             st.floats(-4e5, 4e5, allow_nan=False)), max_size=12)


@pytest.fixture(scope="module")
def ring():
    """A memory bus's ring: its ``encode`` makes the slot images ``take_batch_raw`` reads."""
    import os
    import uuid

    import can

    bus = can.Bus(interface="canbrake", channel=f"cmdraw-{os.getpid()}-{uuid.uuid4().hex[:6]}")
    yield bus._ring
    bus.shutdown()


@given(st.lists(st.tuples(st.integers(0, 2), frames3), max_size=8))
@settings(max_examples=300, deadline=None)
def test_take_batch_equals_take_frame_by_frame(ring, calls: list) -> None:
    """take_batch, and take_batch_raw fed the same frames as slot images, equal take()."""
    got_t, got = _table3()
    raw_t, raw = _table3()
    ref_t, ref = _table3()
    k = 0
    for dk, frames in calls:
        if dk:
            k += dk
            got_t.new_tick()
            raw_t.new_tick()
            ref[0][:] = 0
            ref[2][:] = False
        msgs = []
        for page, counter, how, f in frames:
            if page < 0:
                msgs.append(data_frame(0x010, b"\x00\x00\x00\x00"))
                continue
            m = PAGES3[page]
            data = bytearray(m.encode({"BrakeForce": f}, counter=min(counter, 14)))
            data[1] = (data[1] & 0xF0) | counter
            data[0] = e2e_crc(m.frame_id, data)
            if how == "crc":
                data[3] ^= 0x10
            msgs.append(data_frame(m.frame_id, bytes(data)))
        images = ring.encode(msgs, True, 0.0)
        i = 0
        while True:
            res = got_t.take_batch(msgs, i, k)
            assert res == _expected_batch(ref_t, ref[2], msgs, i, k)
            assert raw_t.take_batch_raw(images, i, k) == res
            for a, b, c in zip(got, ref, raw):
                np.testing.assert_array_equal(a, b)
                np.testing.assert_array_equal(c, b)
            assert got_t.fresh_total() == ref[0].sum() and got_t.all_fresh() == ref[2].all()
            assert raw_t.fresh_total() == ref[0].sum()
            if res[1] == TAKE_BATCH_END:
                break
            i = res[0] + 1


def test_take_batch_completes_a_tick_of_many_slots() -> None:
    """The completed slots are a Python int: slots past a C int's bits (a 130-ECU train) are bits too."""
    n = dbc.MAX_CARS
    db = FrameCodec(dbc.build_database(n))
    arrays = (np.zeros(n, np.int64), np.ones(n, np.int64), np.zeros(n, bool), np.full(n, -1, np.int64),
              np.full(n, np.nan))
    t = CommandTable(*arrays[:4], MAX_LAG)
    msgs = []
    for slot in range(n):
        m = db[f"BRAKE_CMD_C{slot + 1}"]
        t.add_page(m.frame_id, slot, m._c, [("BrakeForce", arrays[4], slot)], None)
        msgs.append(data_frame(m.frame_id, m.encode({"BrakeForce": 100.0 * slot}, counter=0)))
    i, ev, r, completed, accepted = t.take_batch(msgs[::-1], 0, 0)
    assert (i, ev, accepted, completed) == (n - 1, TAKE_BATCH_TICK, n, (1 << n) - 1)
    assert r & CMD_SLOT_COMPLETE and arrays[2].all() and arrays[4][n - 1] == 100.0 * (n - 1)


# ---------------------------------------------------------------- the plant's frames of a period's start
@given(st.integers(0, 2**32 - 1), st.floats(-1e3, 1e3), st.floats(-50, 50), st.one_of(st.none(), st.floats(-1e5, 1e5)),
       st.booleans(), st.lists(st.floats(allow_nan=True, allow_infinity=True, width=32), min_size=3, max_size=3),
       st.sampled_from([float, int]), st.one_of(st.none(), st.binary(min_size=8, max_size=8)))
@settings(max_examples=200, deadline=None)
def test_tick_frames_equal_the_codecs_frames(k, v, a, x, heartbeat, speeds, kind, sync_payload) -> None:
    """TickFrames.frames == the frames the plant built one by one: SYNC, REFERENCE, [REFERENCE_POS],
    [heartbeat], the sensor pages (SensorPages.pack of the same arrays, converted to float64)."""
    from canbrake.bus._codec import TickFrames

    lay = dbc.BusLayout(dbc.default_ecus(3, coupler_sensors=True), ref_position=True)
    codec = FrameCodec(lay.database())
    sensors = [m for m in lay.messages if m.kind == "sensor"]
    pages = SensorPages([(codec[m.name]._c, [(sp.name, 0, m.ecu - 1) for sig, sp in m.signals if sig == "speed_mps"])
                         for m in sensors])
    ids = [m.frame_id for m in sensors]
    whole = kind is int and np.isfinite(speeds).all() and max(map(abs, speeds)) < 1e9
    meas = {"speed_mps": np.asarray(speeds).astype(int) if whole else np.asarray(speeds), "other": np.zeros(2)}
    ref_pos = codec["REFERENCE_POS"]._c if x is not None else None
    tf = TickFrames(codec["SYNC"]._c, lay.sync_id, codec["REFERENCE"]._c, lay.reference_id, ref_pos,
                    lay.reference_pos_id, codec["HEARTBEAT_PLANT"]._c, lay.plant_heartbeat_id, pages, ids,
                    ["speed_mps"], messages_of)
    expect = [(lay.sync_id, sync_payload if sync_payload is not None else codec["SYNC"].encode({"Tick": k})),
              (lay.reference_id, codec["REFERENCE"].encode({"RefSpeed": v, "RefDecel": a}))]
    if x is not None:
        expect.append((lay.reference_pos_id, codec["REFERENCE_POS"].encode({"RefPosition": x})))
    if heartbeat:
        expect.append((lay.plant_heartbeat_id, codec["HEARTBEAT_PLANT"].encode({"NodeState": 5})))
    expect += list(zip(ids, pages.pack([np.ascontiguousarray(meas["speed_mps"], dtype=float)])))
    got = tf.frames(k, v, a, x, heartbeat, meas, sync_payload)
    assert [(m.arbitration_id, bytes(m.data)) for m in got] == [(i, bytes(p)) for i, p in expect]
    # the messages are the ones the plant made one by one (data_frame), every field
    for m, (i, p) in zip(got, expect):
        want = data_frame(i, p)
        assert [(getattr(m, f), type(getattr(m, f))) for f in _MSG_FIELDS] == \
            [(getattr(want, f), type(getattr(want, f))) for f in _MSG_FIELDS]
    # the slot images hold the same frames: identifier, flags, length, data, nothing else set
    images = tf.images(k, v, a, x, heartbeat, meas, sync_payload)
    assert type(images) is bytes and len(images) == len(expect) * SLOT_BYTES
    for n, (i, p) in enumerate(expect):
        ts, aid, token, flags, dlc, ln = struct.unpack_from("<dIIBBB", images, n * SLOT_BYTES)
        assert (ts, aid, token, flags, dlc, ln) == (0.0, i, 0, int(i > 0x7FF), len(p), len(p))
        img = images[n * SLOT_BYTES:(n + 1) * SLOT_BYTES]
        assert img[24:24 + ln] == bytes(p) and img[19:24] == bytes(5) and img[24 + ln:] == bytes(SLOT_BYTES - 24 - ln)


_MSG_FIELDS = ("timestamp", "arbitration_id", "is_extended_id", "is_remote_frame", "is_error_frame", "channel",
               "dlc", "data", "is_fd", "is_rx", "bitrate_switch", "error_state_indicator")


@given(st.lists(st.tuples(st.integers(0, 0x1FFFFFFF), st.binary(max_size=8)), max_size=6))
@settings(max_examples=100, deadline=None)
def test_messages_of_images_are_data_frames(frames) -> None:
    """messages_of(slot images as slot_put writes them: memory_shm's layout, time stamp and token
    0) == data_frame(identifier, data) for each frame, every field."""
    images = b"".join(struct.pack("<dIIBBBxxxxx", 0.0, aid, 0, int(aid > 0x7FF), len(d), len(d)) + d
                      + bytes(64 - len(d)) + bytes(8) for aid, d in frames)
    got = messages_of(images)
    assert len(got) == len(frames)
    for m, (aid, d) in zip(got, frames):
        want = data_frame(aid, d)
        assert [(getattr(m, f), type(getattr(m, f))) for f in _MSG_FIELDS] == \
            [(getattr(want, f), type(getattr(want, f))) for f in _MSG_FIELDS]
