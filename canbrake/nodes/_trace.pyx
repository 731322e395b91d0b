# cython: language_level=3
# distutils: extra_compile_args = -O2 -ffp-contract=off
"""The nodes' per-period bookkeeping, compiled: a trace row as csv text (:class:`CsvTrace`)
and its ``write(2)``, the nodes' duration histograms (:class:`LogHistogram`, re-exported by
canbrake.nodes.base) and the recorder's receive loops.

Written by hand because all of it runs every control period for every node (a signals.csv row of
the 106-vehicle train holds ~1,100 values) and neither the csv module nor numpy does it without a
Python call per value; ``tests/test_trace_compiled.py`` checks them against ``csv.writer`` with
``%.9g`` floats and against the Python ``LogHistogram.add`` they replaced (written out there).
"""
from cpython.buffer cimport PyBUF_C_CONTIGUOUS, PyBUF_FORMAT, PyBuffer_Release, PyObject_GetBuffer
from cpython.dict cimport PyDict_GetItem
from cpython.float cimport PyFloat_AS_DOUBLE
from cpython.object cimport PyObject
from cpython.long cimport PyLong_AsLongLongAndOverflow
from cpython.mem cimport PyMem_Free, PyMem_Malloc
from libc.math cimport log
from libc.stdint cimport uint8_t, uint32_t
from libc.string cimport memcpy, strlen
from canbrake.bus._ring cimport MSG_DATA, MSG_ERR, MSG_EXT, MSG_ID, msg_get

import numpy as np

cdef extern from "Python.h":
    object PyUnicode_DecodeASCII(const char* s, Py_ssize_t size, const char* errors)
    const char* PyUnicode_AsUTF8AndSize(object s, Py_ssize_t* size) except NULL

from canbrake._buffers cimport is_f64_vector, write_all
from canbrake._g9 cimport g9_into, i64_into

cdef type NP_F64 = np.float64
cdef type NP_I64 = np.int64
cdef type NP_I32 = np.int32
cdef type NP_BOOL = np.bool_
cdef object _F64_DTYPE = np.dtype(np.float64)


cdef Py_ssize_t _put(object v, char* buf) except -2:
    """One value of a row (see :func:`csv_row`) into ``buf`` (at least 32 bytes): its length, or
    -1 for a value csv_row does not write."""
    cdef type t = type(v)
    cdef long long iv
    cdef int ovf = 0
    if t is float or t is NP_F64:
        return g9_into(PyFloat_AS_DOUBLE(v), buf)
    if t is int or t is NP_I64 or t is NP_I32:
        iv = PyLong_AsLongLongAndOverflow(v if t is int else int(v), &ovf)
        if ovf:  # beyond 64 bits: Python's own text
            txt = int.__repr__(v if t is int else int(v)).encode("ascii")
            if len(txt) > 24:
                return -1
            memcpy(buf, <char*>txt, len(txt))
            return len(txt)
        return i64_into(iv, buf)
    if t is bool or t is NP_BOOL:
        if v:
            memcpy(buf, b"True", 4)
            return 4
        memcpy(buf, b"False", 5)
        return 5
    return -1


cdef int write_str(int fd, str text) except -1:
    """``text`` (a row's csv text) to the file descriptor ``fd`` with ``write(2)`` until all of
    it is written (its UTF-8 bytes, which Python keeps for an ASCII string: no copy); OSError as
    the file object's write would raise it (a full disk)."""
    cdef Py_ssize_t n
    cdef const char* p = PyUnicode_AsUTF8AndSize(text, &n)
    return write_all(fd, p, n)


def write_text(int fd, str text):
    """:func:`write_str`: a trace row handed to the OS at once (a node process's traces,
    :meth:`~canbrake.nodes.base.CsvTrace.row_fd`)."""
    write_str(fd, text)


def csv_dict_row(list head, dict values, tuple names, object default, list tail):
    """``csv_row(head + [values.get(n, default) for n in names] + tail)``, made in one buffer
    (no list, no string per value); None where csv_row is None."""
    return _csv_line(head, values, names, default, tail)


def csv_row(list row):
    """``row`` as the line ``csv.writer`` writes (excel dialect, ``\\r\\n``) with floats as
    ``f"{v:.9g}"``, for rows of floats, ints and bools (Python's or numpy's); None for a row with
    any other value (the caller takes the csv writer). The text is made in one buffer (no string
    per value)."""
    return _csv_line(row, None, (), None, _NO_TAIL)


cdef list _NO_TAIL = []


cdef object _csv_line(list head, dict values, tuple names, object default, list tail):
    """The line of ``head``, then ``values[n]`` (``default`` where missing) for each of ``names``,
    then ``tail``, as csv_row describes; None for a value it does not write."""
    cdef Py_ssize_t nh = len(head), nn = len(names), nt = len(tail)
    cdef Py_ssize_t i, n = nh + nn + nt, pos = 0, w
    cdef char stack[1024]
    cdef char* buf = stack
    cdef PyObject* p
    if 32 * n + 2 > 1024:  # a value's text is at most 24 characters (a 64-bit int's 20)
        buf = <char*>PyMem_Malloc(32 * n + 2)
        if buf is NULL:
            raise MemoryError()
    try:
        for i in range(n):
            if i:
                buf[pos] = b','
                pos += 1
            if i < nh:
                v = head[i]
            elif i < nh + nn:
                p = PyDict_GetItem(values, names[i - nh])
                v = default if p is NULL else <object>p
            else:
                v = tail[i - nh - nn]
            w = _put(v, buf + pos)
            if w < 0:
                return None
            pos += w
        buf[pos] = b'\r'
        buf[pos + 1] = b'\n'
        return PyUnicode_DecodeASCII(buf, pos + 2, NULL)
    finally:
        if buf is not stack:
            PyMem_Free(buf)


cdef Py_ssize_t _bin(double x, Py_ssize_t bins, double lo, double log_ratio) except -1:
    """The bin of duration ``x`` (s) as ``LogHistogram.add`` finds it (its errors for NaN, inf)."""
    cdef double y
    cdef Py_ssize_t i
    if x <= lo:
        return 0
    y = log(x / lo) / log_ratio
    if not y < 1e18:  # what int() says of a NaN or an infinite duration
        raise ValueError("cannot convert float NaN to integer") if y != y else OverflowError(
            "cannot convert float infinity to integer")
    i = 1 + <Py_ssize_t>y
    return bins - 1 if i >= bins else i


cdef double _LO_S = 1e-7


cdef class LogHistogram:
    """Quantiles of positive durations (s) in bounded memory: logarithmic bins ``ratio - 1`` wide
    (default 0.1 %) from 1e-7 s to 1e4 s (~25 000 counters at the default, whatever the run
    length); a quantile is exact to that width, the maximum and the total exactly.

    Compiled because the nodes add to one several times a period (the plant: its model step's
    time, each ECU's response time; an ECU: its controller step's); ``counts`` stays a list
    (one element touched per add)."""

    LO_S, HI_S = _LO_S, 1e4
    cdef public double RATIO, _log_ratio, max, total
    cdef public Py_ssize_t bins, n
    cdef public list counts

    def __init__(self, double ratio=1.001):
        self.RATIO = ratio
        self._log_ratio = float(np.log(ratio))
        self.bins = int(np.ceil(np.log(self.HI_S / self.LO_S) / self._log_ratio)) + 2
        self.counts = [0] * self.bins
        self.n = 0
        self.max = 0.0
        self.total = 0.0  # s: the sum of every duration added

    cdef int _add(self, double x) except -1:
        cdef Py_ssize_t i = _bin(x, self.bins, _LO_S, self._log_ratio)
        self.n += 1
        self.total += x
        if x > self.max:
            self.max = x
        self.counts[i] += 1
        return 0

    def add(self, double x) -> None:
        """Add the duration ``x`` (s)."""
        self._add(x)

    def add_many(self, xs) -> None:
        """:meth:`add` for each of ``xs`` (s), in order."""
        for v in xs:
            self._add(v)

    def quantile(self, double q) -> float:
        """The ``q`` quantile (0..1), as the geometric middle of its bin (0 when empty)."""
        if not self.n:
            return 0.0
        return self.ranked(max(1, int(np.ceil(q * self.n))))

    def ranked(self, r) -> float:
        """The ``r``-th smallest duration (1 .. n), as the geometric middle of its bin."""
        k = int(np.searchsorted(np.cumsum(np.asarray(self.counts, dtype=np.int64)), r))
        if k == 0:
            return min(self.LO_S, self.max)
        return float(min(self.max, self.LO_S * self.RATIO ** (k - 0.5)))

    def figures(self) -> dict:
        """n, mean, p50, p99, max and total (s) for a JSON statistics file."""
        return {"n": self.n, "mean_s": self.total / self.n if self.n else 0.0, "p50_s": self.quantile(0.5),
                "p99_s": self.quantile(0.99), "max_s": self.max, "total_s": self.total}


#: take_frames' events
cdef enum:
    _TAKE_END = 0      # every frame taken
    _TAKE_SYNC = 1     # msgs[i] is a SYNC (counted): the recorder's verdict, then resume at i
    _TAKE_PHASE = 2    # msgs[i]'s key has no phase yet: set phase_of[key], then resume at i
TAKE_END, TAKE_SYNC, TAKE_PHASE = _TAKE_END, _TAKE_SYNC, _TAKE_PHASE


def take_frames(list msgs, Py_ssize_t start, bint resume, dict counts, closing, object sync_id, dict phase_of,
                list tick_frames):
    """The lockstep recorder's receive loop (:meth:`canbrake.nodes.recorder.RecorderNode.handle_batch`)
    over ``msgs[start:]``: each frame counted by its :func:`frame_key`, a frame
    of ``closing`` counted as closing its tick, and kept as (phase, identifier, payload bytes,
    frame) in ``tick_frames`` with its key's phase from ``phase_of``. Returns (i, TAKE_*, closing
    frames seen); ``resume``: msgs[start] was counted already (it was returned)."""
    cdef int ev
    cdef Py_ssize_t closed = 0
    cdef Py_ssize_t i = _take_frames(msgs, start, resume, counts, closing, sync_id, phase_of, tick_frames, &ev,
                                     &closed)
    return i, ev, closed


cdef Py_ssize_t _take_frames(list msgs, Py_ssize_t start, bint resume, dict counts, closing, object sync_id,
                             dict phase_of, list tick_frames, int* ev, Py_ssize_t* closed) except -1:
    """:func:`take_frames`: the index, the event in ``ev``, the closing frames added to ``closed``."""
    cdef Py_ssize_t i, m = len(msgs)
    cdef PyObject* p
    for i in range(start, m):
        msg = msgs[i]
        aid = msg_get(msg, MSG_ID)
        p = _take_key(aid, msg_get(msg, MSG_EXT), msg_get(msg, MSG_ERR), resume and i == start, counts, closing,
                      sync_id, phase_of, closed)
        if p is NULL:
            ev[0] = _TAKE_PHASE
            return i
        if p == _SYNC_MARK:
            ev[0] = _TAKE_SYNC
            return i
        tick_frames.append((<object>p, aid, bytes(msg_get(msg, MSG_DATA)), msg))
    ev[0] = _TAKE_END
    return m


cdef class RecorderTaker:
    """A lockstep recorder's receive loop (:class:`~canbrake.nodes.recorder.RecorderNode`), one
    compiled call per batch: over python-can messages (calling it: ``handle_batch``, and what
    :meth:`~canbrake.nodes.recorder.RecorderNode.batch_handler` gives the in-process Router) or
    over the memory bus's slot images (:meth:`raw`: ``handle_raw``), through :func:`take_frames`
    / :func:`take_frames_raw`, and at a SYNC or a key without a phase the node's ``_on_event``."""

    cdef object node, closing, sync_id, on_event
    cdef dict counts, phase_of

    def __init__(self, node):
        self.node = node
        self.counts = node._counts
        self.phase_of = node._phase_of
        self.closing = node._closing_ids
        self.sync_id = node.layout.sync_id
        self.on_event = node._on_event

    def __call__(self, list batch, now):
        """The messages ``batch``; returns the frames to send (none)."""
        cdef Py_ssize_t i = 0, m = len(batch), closed
        cdef int ev
        cdef bint resume = False
        node = self.node
        while i < m:
            closed = 0
            i = _take_frames(batch, i, resume, self.counts, self.closing, self.sync_id, self.phase_of,
                             node._tick_frames, &ev, &closed)
            if closed:
                node._closing_seen += closed
            if ev == _TAKE_END:
                break
            if self.on_event(ev, batch[i]):
                break  # the END: the log is complete
            resume = True
        return []

    def raw(self, frames, keep, message):
        """The slot images ``frames``: each kept as ``keep(frames, i)`` (None: the image itself,
        :func:`take_frames_raw`); ``message(frames, i)`` is image i as a ``can.Message`` for
        ``_on_event``. Returns the frames to send (none)."""
        cdef const uint8_t[::1] v = frames
        cdef const uint8_t* base = &v[0] if v.shape[0] else NULL
        cdef Py_ssize_t i = 0, m = v.shape[0] // SLOT_BYTES, closed
        cdef int ev
        cdef bint resume = False
        node = self.node
        while i < m:
            closed = 0
            i = _take_frames_raw(keep, base, m, frames, i, resume, self.counts, self.closing, self.sync_id,
                                 self.phase_of, node._tick_frames, &ev, &closed)
            if closed:
                node._closing_seen += closed
            if ev == _TAKE_END:
                break
            if self.on_event(ev, message(frames, i)):
                break  # the END: the log is complete
            resume = True
        return []


# the memory bus's slot image (canbrake.bus._slot)
from canbrake.bus._slot cimport (SLOT_BYTES, DATA_OFFSET, SLOT_FLAG_EXTENDED, SLOT_FLAG_REMOTE, SLOT_FLAG_ERROR,
                                 slot_id, slot_flags, slot_len)


def take_frames_raw(object message, frames, Py_ssize_t start, bint resume, dict counts, closing, object sync_id,
                    dict phase_of, list tick_frames):
    """:func:`take_frames` for the memory bus's slot images (``MemoryBus.recv_raw``): the same
    work and result, each key read from the image; the frame kept is ``message(frames, i)``
    (``MemoryBus.raw_message``: the ``can.Message`` the bus's ``recv`` gives), or, ``message``
    None, the slot image itself (bytes, ``SLOT_BYTES``: what ``_wire.ideal_period`` and
    ``_candump.write_candump`` read as they read that message), its payload bytes from the
    image; ``i`` is the image's index."""
    cdef const uint8_t[::1] v = frames
    cdef int ev
    cdef Py_ssize_t closed = 0
    cdef Py_ssize_t i = _take_frames_raw(message, &v[0] if v.shape[0] else NULL, v.shape[0] // SLOT_BYTES, frames,
                                         start, resume, counts, closing, sync_id, phase_of, tick_frames, &ev,
                                         &closed)
    return i, ev, closed


cdef Py_ssize_t _take_frames_raw(object message, const uint8_t* base, Py_ssize_t m, object frames, Py_ssize_t start,
                                 bint resume, dict counts, closing, object sync_id, dict phase_of,
                                 list tick_frames, int* ev, Py_ssize_t* closed) except -1:
    """:func:`take_frames_raw` over the ``m`` images at ``base`` (of ``frames``): the index, the
    event in ``ev``, the closing frames added to ``closed``."""
    cdef Py_ssize_t i, n
    cdef PyObject* p
    cdef const uint8_t* q
    for i in range(start, m):
        q = base + i * SLOT_BYTES
        aid = slot_id(q)
        p = _take_key(aid, bool(slot_flags(q) & SLOT_FLAG_EXTENDED), bool(slot_flags(q) & SLOT_FLAG_ERROR),
                      resume and i == start, counts, closing, sync_id, phase_of, closed)
        if p is NULL:
            ev[0] = _TAKE_PHASE
            return i
        if p == _SYNC_MARK:
            ev[0] = _TAKE_SYNC
            return i
        n = 0 if slot_flags(q) & SLOT_FLAG_REMOTE else slot_len(q)  # a remote frame: no data
        tick_frames.append((<object>p, aid, (<const char*>q)[DATA_OFFSET:DATA_OFFSET + n],
                            (<const char*>q)[:SLOT_BYTES] if message is None else message(frames, i)))
    ev[0] = _TAKE_END
    return m


def take_realtime_raw(frames, Py_ssize_t start, double now, dict counts, dict sim_control, long long sync_id,
                      list stamped):
    """The realtime recorder's receive loop over the memory bus's slot images
    (:meth:`~canbrake.nodes.recorder.RecorderNode.handle_raw`): from image ``start`` up to the next
    frame with identifier ``sync_id`` (its SYNC, which the caller takes as a ``can.Message``) or the
    end, each frame counted by its :func:`frame_key` in ``counts`` and, unless
    ``sim_control`` (identifier -> bool, absent = False) marks it a barrier frame, appended to
    ``stamped`` for the log as (its sender's time stamp, or ``now`` (s) if it has none, its slot
    image). Returns (the index where it stopped, the error frames among them)."""
    cdef const uint8_t[::1] v = frames
    cdef Py_ssize_t i, m = v.shape[0] // SLOT_BYTES, errors = 0
    cdef const uint8_t* q
    cdef uint32_t aid32
    cdef uint8_t fl
    cdef double ts
    cdef PyObject* p
    for i in range(start, m):
        q = &v[i * SLOT_BYTES]
        aid32 = slot_id(q)
        if <long long>aid32 == sync_id:
            return i, errors
        fl = slot_flags(q)
        aid = aid32
        key = _frame_key(aid32, fl & SLOT_FLAG_EXTENDED, fl & SLOT_FLAG_ERROR)
        p = PyDict_GetItem(counts, key)
        counts[key] = 1 if p is NULL else <object>p + 1
        if fl & SLOT_FLAG_ERROR:
            errors += 1
        p = PyDict_GetItem(sim_control, aid)
        if p is NULL or not <object>p:
            memcpy(&ts, q, 8)
            stamped.append((ts if ts != 0.0 else now, (<const char*>q)[:SLOT_BYTES]))
    return m, errors


cdef object _SYNC_SENTINEL = object()
cdef PyObject* _SYNC_MARK = <PyObject*>_SYNC_SENTINEL


cdef inline long long _frame_key(long long aid, bint ext, bint err) noexcept:
    return (aid << 2) | (2 if ext else 0) | (1 if err else 0)


def frame_key(aid, ext, err):
    """A frame's key in the recorder's counts and phases: ``aid << 2 | extended << 1 | error``
    (an int: cheaper to make, hash and compare per frame than the tuple it replaced)."""
    return _frame_key(aid, ext, err)


def key_fields(long long key):
    """(identifier, extended, error frame) of a :func:`frame_key`."""
    return key >> 2, bool(key & 2), bool(key & 1)


cdef PyObject* _take_key(object aid, object ext, object err, bint counted, dict counts, closing, object sync_id,
                         dict phase_of, Py_ssize_t* closed) except? <PyObject*>1:
    """One frame of :func:`take_frames` (both variants), by its :func:`frame_key`: counted (unless
    ``counted`` already), its closing frame counted in ``closed``; returns its phase (borrowed
    from ``phase_of``), NULL if its key has none yet, ``_SYNC_MARK`` for a SYNC."""
    cdef PyObject* p
    key = _frame_key(aid, ext, err)
    if not counted:
        p = PyDict_GetItem(counts, key)
        counts[key] = 1 if p is NULL else <object>p + 1
        if aid in closing:
            closed[0] += 1
        elif aid == sync_id and ext == (aid > 0x7FF):
            return _SYNC_MARK
    return PyDict_GetItem(phase_of, key)


cdef bint _f64_buffer(object a, Py_buffer* view) except -1:
    """``a``'s buffer if it is a C-contiguous 1-D float64 array (True; release it), else False:
    the buffer protocol itself, not a typed memoryview (whose object and format check cost more
    than the row's nine-digit floats: the plant's row takes seven arrays per period)."""
    try:
        PyObject_GetBuffer(a, view, PyBUF_C_CONTIGUOUS | PyBUF_FORMAT)
    except (TypeError, ValueError, BufferError):
        return False
    if is_f64_vector(view):
        return True
    PyBuffer_Release(view)
    return False


def csv_pick_row(str head, list arrays, plan, flags, Py_ssize_t flags_at):
    """The plant's trace row (:meth:`canbrake.nodes.plant.PlantNode.after_send`) without a
    Python float per value: ``head`` (the row's first values as csv text, no line end), then
    per row ``j`` of ``plan`` (an (m, 2) intp array) the value ``arrays[plan[j, 0]][plan[j, 1]]``
    as ``f"{v:.9g}"``, with ``flags`` (a bool array or None) written as 0/1 before plan row
    ``flags_at``; the line ends with ``\\r\\n`` as :func:`csv_row`'s. ``arrays``: float64 arrays
    (others are converted as ``np.concatenate(..., dtype=float)`` converts them). None if an
    element is outside its array (the caller's plan is stale)."""
    cdef Py_ssize_t na = len(arrays), np_, nf = 0, i, j, a, e, pos, k, cap, held = 0
    cdef Py_buffer* views = <Py_buffer*>PyMem_Malloc((na + 2) * sizeof(Py_buffer))
    cdef Py_buffer pv
    cdef bint plan_held = False
    cdef const Py_ssize_t* pl
    cdef const uint8_t[::1] fl
    cdef bytes hb = head.encode("ascii")
    cdef char* buf = NULL
    if views is NULL:
        raise MemoryError()
    try:
        for i in range(na):
            # (another dtype or layout: a float64 copy, kept alive by its buffer)
            if not _f64_buffer(arrays[i], &views[i]) and \
                    not _f64_buffer(np.ascontiguousarray(arrays[i], dtype=np.float64), &views[i]):
                raise ValueError("csv_pick_row: the arrays must be 1-D")
            held += 1
        PyObject_GetBuffer(plan, &pv, PyBUF_C_CONTIGUOUS | PyBUF_FORMAT)
        plan_held = True
        if pv.ndim != 2 or pv.shape[1] != 2 or pv.itemsize != sizeof(Py_ssize_t):
            raise ValueError("csv_pick_row: plan must be an (m, 2) intp array")
        np_ = pv.shape[0]
        pl = <const Py_ssize_t*>pv.buf
        if flags is not None:
            fl = np.ascontiguousarray(flags, dtype=np.bool_).view(np.uint8)
            nf = fl.shape[0]
        cap = len(hb) + 32 * (np_ + nf) + 2
        buf = <char*>PyMem_Malloc(cap)
        if buf is NULL:
            raise MemoryError()
        pos = len(hb)
        memcpy(buf, <char*>hb, pos)
        for j in range(np_ + 1):
            if j == flags_at and flags is not None:
                for k in range(nf):
                    buf[pos] = b','
                    buf[pos + 1] = b'1' if fl[k] else b'0'
                    pos += 2
            if j == np_:
                break
            a = pl[2 * j]
            e = pl[2 * j + 1]
            if a < 0 or a >= na or e < 0 or e >= views[a].shape[0]:
                return None
            buf[pos] = b','
            pos += 1
            pos += g9_into((<const double*>views[a].buf)[e], buf + pos)
        buf[pos] = b'\r'
        buf[pos + 1] = b'\n'
        return PyUnicode_DecodeASCII(buf, pos + 2, NULL)
    finally:
        PyMem_Free(buf)
        for i in range(held):
            PyBuffer_Release(&views[i])
        if plan_held:
            PyBuffer_Release(&pv)
        PyMem_Free(views)


def hist_add_bits(list hists, bits, double x):
    """``hists[s].add(x)`` (:class:`LogHistogram`) for each bit ``s`` set in ``bits`` (a
    non-negative int), lowest first: the plant's response times of the ECUs whose commands a
    batch completed, in one call (the bits read from the int's bytes)."""
    cdef bytes b = bits.to_bytes((bits.bit_length() + 7) // 8, "little")
    cdef const unsigned char* p = b
    cdef Py_ssize_t j, t
    for j in range(len(b)):
        if not p[j]:
            continue
        for t in range(8):
            if (p[j] >> t) & 1:
                (<LogHistogram?>hists[8 * j + t])._add(x)