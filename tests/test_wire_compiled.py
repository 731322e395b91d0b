"""The compiled wire bookkeeping (canbrake.bus._wire) against the bit-level reference in
canbrake.bus.timing (frame_bitstream + stuff_bit_count) and against the recorder's accounting
written out in Python."""
from __future__ import annotations

import io
import struct

import can
from hypothesis import given, settings
from hypothesis import strategies as st

from canbrake.bus._wire import LoadSeries, ideal_period, ideal_tick, stuff_bits, timed_bits_raw
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


@settings(max_examples=300, deadline=None)
@given(st.lists(st.tuples(st.integers(0, 2), frame_args(), st.booleans()), max_size=40), st.integers(0, 10**6),
       st.sampled_from([1e-3, 1e-2]), st.sampled_from([125e3, 500e3, 1e6]), st.floats(0, 1e-3),
       st.sampled_from([0.0, 1.7e9]), st.sets(st.integers(0, 0x7FF), max_size=20),
       st.sets(st.integers(0, 0x7FF), max_size=20), st.one_of(st.none(), st.floats(0, 2e9)), st.integers(1, 4))
def test_ideal_tick_is_sort_ideal_period_and_write_candump(frames, k, dt, bitrate, carry, epoch, untimed, simctl,
                                                             first, reps):
    """ideal_tick (the recorder's common case) = sorted by (phase, identifier, payload) with
    arrival order among equal keys + ideal_period + write_candump, frames as messages or slot
    images; repeated frames (equal keys) must come out in arrival order (the images differ in
    their sequence number, so a swap changes nothing but identity: checked by id)."""
    from canbrake.bus._candump import write_candump

    kept = []
    for n, (phase, (aid, ext, dlc, data, _r), as_image) in enumerate(frames * reps):
        m = can.Message(arbitration_id=aid, is_extended_id=ext, dlc=dlc, data=data)
        if as_image:
            m = struct.pack("<dIIBBBxxxxx", 0.0, aid, 0, int(ext), dlc, len(data)) + data + bytes(64 - len(data)) \
                + struct.pack("<Q", n)
        kept.append((phase, aid, data, m))
    u = {a: True for a in untimed}
    u.update({a: False for a in range(0, 0x800, 7) if a not in untimed})
    s = {a: True for a in simctl}
    t_k = k * dt
    want_w = can.CanutilsLogWriter(io.StringIO(), channel="vcan0")
    got_w = can.CanutilsLogWriter(io.StringIO(), channel="vcan0")
    want_w.last_timestamp = got_w.last_timestamp = first
    ordered = sorted(kept, key=lambda f: f[:3])
    want = ideal_period(ordered, u, s, t_k + carry, t_k, dt, bitrate, epoch)
    write_candump(want_w, want[4], "can0")
    series = LoadSeries(None, dt)
    got = ideal_tick(list(kept), u, s, t_k + carry, t_k, dt, bitrate, epoch, got_w, "can0", series)
    assert got == want[:4]
    assert (series.n, series.sum, series.errors) == (1, want[1] / dt, 0)
    assert got_w.file.getvalue() == want_w.file.getvalue()
    assert got_w.last_timestamp == want_w.last_timestamp or (first is None and not want[4])
    assert ideal_tick(list(kept), u, s, t_k + carry, t_k, dt, bitrate, epoch, None, "can0", series) == want[:4]


def test_ideal_tick_keeps_arrival_order_of_equal_keys():
    """Equal (phase, identifier, payload): the frames stay in arrival order (the sort key is the
    three fields, never the whole entry), seen in the candump lines by their channel-free ids."""
    import io as _io

    a = can.Message(arbitration_id=0x10, data=b"\x01", is_extended_id=False)
    b = can.Message(arbitration_id=0x10, data=b"\x01", is_extended_id=True)  # same key, other line
    c = can.Message(arbitration_id=0x08, data=b"\x02", is_extended_id=False)
    for kept, lines in ([(1, 0x10, b"\x01", a), (1, 0x10, b"\x01", b), (1, 0x08, b"\x02", c)], "008 010 00000010"), \
                       ([(1, 0x10, b"\x01", b), (1, 0x10, b"\x01", a), (0, 0x08, b"\x02", c)], "008 00000010 010"):
        w = can.CanutilsLogWriter(_io.StringIO(), channel="vcan0")
        ideal_tick(kept, {}, {}, 0.0, 0.0, 1e-3, 500e3, 0.0, w, "can0", LoadSeries(None, 1e-3))
        assert " ".join(line.split()[2].split("#")[0] for line in w.file.getvalue().splitlines()) == lines


class _ReferenceLoadSeries:
    """The recorder's LoadSeries as it was written in Python before it was compiled (the oracle)."""

    def __init__(self, path, dt_s, window_s=0.1, max_windows=4096):
        self.dt, self.path, self._f, self._w = dt_s, path, None, None
        self.n, self.sum, self.peak, self.errors = 0, 0.0, 0.0, 0
        self.per_window = max(1, int(round(window_s / dt_s)))
        self.window_s = self.per_window * dt_s
        self._base_window_s = self.window_s
        self._acc, self._acc_n = 0.0, 0
        self.peak_window = 0.0
        self.windows = []
        self._merge = 1
        self._pend, self._pend_n = 0.0, 0
        self.max_windows = max_windows

    def add(self, load, frames, errors):
        import csv

        if self._w is None and self.path is not None:
            self._f = open(self.path, "w", newline="")
            self._w = csv.writer(self._f)
            self._w.writerow(["period", "t_s", "bus_load", "frames", "error_frames"])
        if self._f is not None:
            self._f.write(f"{self.n},{self.n * self.dt:.9g},{load:.6g},{frames},{errors}\r\n")
        self.n += 1
        self.sum += load
        self.peak = max(self.peak, load)
        self.errors += errors
        self._acc += load
        self._acc_n += 1
        if self._acc_n == self.per_window:
            self._window(self._acc / self._acc_n)
            self._acc, self._acc_n = 0.0, 0

    def _window(self, mean):
        self.peak_window = max(self.peak_window, mean)
        self._pend += mean
        self._pend_n += 1
        if self._pend_n < self._merge:
            return
        self.windows.append(self._pend / self._pend_n)
        self._pend, self._pend_n = 0.0, 0
        if len(self.windows) > self.max_windows:
            last = self.windows.pop() if len(self.windows) % 2 else None
            self.windows = [(a + b) / 2 for a, b in zip(self.windows[0::2], self.windows[1::2])]
            if last is not None:
                self._pend, self._pend_n = last * self._merge, self._merge
            self._merge *= 2
            self.window_s = self._base_window_s * self._merge

    @property
    def mean(self):
        return self.sum / self.n if self.n else 0.0

    def window_list(self):
        if self.windows:
            return list(self.windows)
        return [self._acc / self._acc_n] if self._acc_n else [self.mean]


@settings(max_examples=200, deadline=None)
@given(st.lists(st.tuples(st.one_of(st.floats(0, 3), st.floats(0, 1e-3), st.sampled_from([0.0, 0.25, 1.5, 1e-300])),
                          st.one_of(st.integers(0, 10**12), st.just("")), st.integers(0, 1000)), max_size=300),
       st.sampled_from([1e-3, 2.5e-3, 1e-2, 0.3]), st.sampled_from([0.1, 0.01, 0.0075, 1.0]), st.integers(1, 6),
       st.sampled_from([0, 7, 10**6]))
def test_load_series_is_the_python_one(tmp_path_factory, rows, dt, window_s, max_windows, n0):
    """The compiled LoadSeries against the Python one it replaced: the same bus_load.csv bytes
    and the same aggregates (mean, peak, windows merged under a small max_windows)."""
    d = tmp_path_factory.mktemp("ls")
    got = LoadSeries(d / "got.csv", dt, window_s, max_windows)
    want = _ReferenceLoadSeries(d / "want.csv", dt, window_s, max_windows)
    got.n = want.n = n0
    for load, frames, errors in rows:
        got.add(load, frames, errors)
        want.add(load, frames, errors)
    got.close()
    if want._f is not None:
        want._f.close()
    assert (d / "got.csv").exists() == (d / "want.csv").exists()
    if rows:
        assert (d / "got.csv").read_bytes() == (d / "want.csv").read_bytes()
    for a in ("n", "sum", "peak", "errors", "per_window", "window_s", "peak_window", "windows", "mean"):
        assert getattr(got, a) == getattr(want, a), a
    assert got.window_list() == want.window_list()


def test_load_series_without_file_and_counts():
    """No path: nothing written, the aggregates kept; ideal_tick's add (a count) is add's."""
    a, b = LoadSeries(None, 1e-3, 0.002), _ReferenceLoadSeries(None, 1e-3, 0.002)
    for x in (0.5, 0.25, 1.25, 0.0, 3.0):
        a.add(x, 3, 1)
        b.add(x, 3, 1)
    assert (a.n, a.sum, a.peak, a.errors, a.windows, a.peak_window) == (b.n, b.sum, b.peak, b.errors, b.windows,
                                                                        b.peak_window)


def test_ideal_tick_to_the_descriptor_and_load_series_flush_hand_each_period_to_the_os(tmp_path):
    """ideal_tick with ``fd`` (the recorder in its own process) writes into the file at once the
    bytes it writes through the writer otherwise; LoadSeries.flush hands the lines to the OS (a
    killed recorder loses at most its current period)."""
    kept = [(p, 0x100 + i, bytes([i, 7]), can.Message(arbitration_id=0x100 + i, data=bytes([i, 7])))
            for i, p in enumerate([2, 0, 1, 1, 0])]
    ref = can.CanutilsLogWriter(io.StringIO(), channel="vcan0")
    w = can.Logger(str(tmp_path / "frames.log"))
    series = LoadSeries(tmp_path / "bus_load.csv", 1e-3)
    ref_series = _ReferenceLoadSeries(None, 1e-3)
    for k in range(3):
        want = ideal_tick(list(kept), {}, {}, k * 1e-3, k * 1e-3, 1e-3, 250e3, 0.0, ref, "can0",
                          LoadSeries(None, 1e-3))
        got = ideal_tick(list(kept), {}, {}, k * 1e-3, k * 1e-3, 1e-3, 250e3, 0.0, w, "can0", series,
                         w.file.fileno())
        assert got == want
        ref_series.add(got[1] / 1e-3, got[2], 0)
        assert (tmp_path / "frames.log").read_text() == ref.file.getvalue()  # no flush: written already
        series.flush()
        lines = (tmp_path / "bus_load.csv").read_bytes().split(b"\r\n")
        assert len(lines) == k + 3 and lines[-2].startswith(b"%d," % k)
    assert (series.n, series.sum, series.peak) == (ref_series.n, ref_series.sum, ref_series.peak)
    w.stop()
    series.close()
    assert (tmp_path / "frames.log").read_text() == ref.file.getvalue()
