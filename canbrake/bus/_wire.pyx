# cython: language_level=3
# distutils: extra_compile_args = -O2 -ffp-contract=off
"""Per-frame wire bookkeeping of classic CAN, compiled: actual bit stuffing with the CRC-15, and
the recorder's accounting of one control period (:func:`ideal_period`; its common case's whole
period flush, :func:`ideal_tick`, and the bus load series, :class:`LoadSeries`).

Written by hand because no library models the CAN wire (python-can and cantools stop at frames;
see :mod:`canbrake.bus.timing`) and this runs for every frame of every period. The bit-level
reference (:func:`canbrake.bus.timing.frame_bitstream`, ``stuff_bit_count``) stays in Python as
the specification the tests check this against (``tests/test_wire_compiled.py``).

Floating point: ``-ffp-contract=off`` keeps ``a + b * c`` two roundings as in Python (no fused
multiply-add), so stamps and bus loads are bit-identical to the interpreter's arithmetic.
"""
from cpython.list cimport PyList_New, PyList_SET_ITEM
from cpython.long cimport PyLong_AsLongLongAndOverflow
from cpython.mem cimport PyMem_Free, PyMem_Malloc
from cpython.ref cimport Py_INCREF
from libc.stdint cimport uint8_t, uint16_t, uint32_t
from libc.stdlib cimport free, qsort
from posix.unistd cimport close as c_close, write as c_write
from libc.string cimport memcmp, memcpy, strlen

from canbrake._buffers cimport write_all
from canbrake._g9 cimport g9_into, i64_into
from canbrake.bus._ring cimport MSG_DLC, MSG_EXT, MSG_RTR, msg_get
from canbrake.bus._candump cimport Buf, PyOS_double_to_string, buf_reserve, candump_line

from operator import itemgetter

from canbrake.bus._candump import channel_name

from canbrake.bus._slot cimport (SLOT_BYTES, DATA_OFFSET, SLOT_FLAG_EXTENDED, SLOT_FLAG_REMOTE, SLOT_FLAG_ERROR, slot_id,
                                 slot_flags, slot_len)

cdef uint16_t CRC_TABLE[256]     # byte-wise MSB-first CRC-15 (poly 0x4599)
cdef uint8_t STUFF_N[16][256]    # stuff bits a byte adds from state (last level * 8 + run)
cdef uint8_t STUFF_NEXT[16][256]  # ... and the state after it


cdef inline void _bit(int b, int* last, int* run, int* n) noexcept nogil:
    """One bit through the stuffing rule: after five equal bits a stuff bit of the opposite level
    (which starts the next run)."""
    if b == last[0]:
        run[0] += 1
    else:
        last[0] = b
        run[0] = 1
    if run[0] == 5:
        n[0] += 1
        last[0] = 1 - last[0]
        run[0] = 1


cdef inline uint16_t _crc_bit(uint16_t crc, int b) noexcept nogil:
    cdef int top = ((crc >> 14) & 1) ^ (b & 1)
    crc = (crc << 1) & 0x7FFF
    if top:
        crc ^= 0x4599
    return crc


cdef void _make_tables() noexcept:
    cdef int byte, i, code, last, run, n
    cdef uint16_t crc
    for byte in range(256):
        crc = 0
        for i in range(8):
            crc = _crc_bit(crc, (byte >> (7 - i)) & 1)
        CRC_TABLE[byte] = crc  # the register after ``byte`` from 0: linear, so it XORs in
        for code in range(16):
            last, run, n = code >> 3, code & 7, 0
            if run > 4:  # unreachable state
                STUFF_N[code][byte] = 0
                STUFF_NEXT[code][byte] = code
                continue
            for i in range(8):
                _bit((byte >> (7 - i)) & 1, &last, &run, &n)
            STUFF_N[code][byte] = n
            STUFF_NEXT[code][byte] = last * 8 + run


_make_tables()


cdef int _stuff_bits(uint32_t aid, bint ext, int dlc, const uint8_t* data, Py_ssize_t n_data,
                     bint remote) noexcept nogil:
    """Stuff bits of the SOF..CRC span of a classic frame (``n_data`` payload bytes)."""
    cdef int last = 1, run = 0, n = 0, i, b, code
    cdef uint16_t crc = 0
    cdef uint8_t byte
    # SOF
    b = 0
    _bit(b, &last, &run, &n)
    crc = _crc_bit(crc, b)
    if ext:
        for i in range(10, -1, -1):  # base identifier
            b = (aid >> (18 + i)) & 1
            _bit(b, &last, &run, &n)
            crc = _crc_bit(crc, b)
        for i in range(2):  # SRR, IDE (recessive)
            _bit(1, &last, &run, &n)
            crc = _crc_bit(crc, 1)
        for i in range(17, -1, -1):  # identifier extension
            b = (aid >> i) & 1
            _bit(b, &last, &run, &n)
            crc = _crc_bit(crc, b)
        b = 1 if remote else 0  # RTR, r1, r0
        _bit(b, &last, &run, &n)
        crc = _crc_bit(crc, b)
        for i in range(2):
            _bit(0, &last, &run, &n)
            crc = _crc_bit(crc, 0)
    else:
        for i in range(10, -1, -1):
            b = (aid >> i) & 1
            _bit(b, &last, &run, &n)
            crc = _crc_bit(crc, b)
        b = 1 if remote else 0  # RTR, IDE, r0
        _bit(b, &last, &run, &n)
        crc = _crc_bit(crc, b)
        for i in range(2):
            _bit(0, &last, &run, &n)
            crc = _crc_bit(crc, 0)
    for i in range(3, -1, -1):  # DLC
        b = (dlc >> i) & 1
        _bit(b, &last, &run, &n)
        crc = _crc_bit(crc, b)
    code = last * 8 + run
    if not remote:
        for i in range(n_data):  # data: CRC register and stuffing state a byte at a time
            byte = data[i]
            crc = ((crc << 8) & 0x7FFF) ^ CRC_TABLE[((crc >> 7) ^ byte) & 0xFF]
            n += STUFF_N[code][byte]
            code = STUFF_NEXT[code][byte]
    last, run = code >> 3, code & 7
    for i in range(14, -1, -1):  # the CRC-15 sequence
        _bit((crc >> i) & 1, &last, &run, &n)
    return n


def stuff_bits(unsigned int arbitration_id, bint is_extended, int dlc, const uint8_t[::1] data,
               bint is_remote=False) -> int:
    """Stuff bits CAN inserts into the SOF..CRC span of a classic frame (``data``: its payload,
    ignored for a remote frame). Unchecked: :func:`canbrake.bus.timing.frame_bits` validates."""
    cdef Py_ssize_t n = data.shape[0]
    return _stuff_bits(arbitration_id, is_extended, dlc, &data[0] if n else NULL, n, is_remote)


#: bits of a classic data frame before stuffing, IFS included: SOF..CRC (34 or 54 + 8n) + 10 + 3
cdef int _plain_bits(bint ext, int n_data) noexcept nogil:
    return (54 if ext else 34) + 8 * n_data + 13


cdef long long _actual_bits(object aid, bint ext, Py_ssize_t dlc, bint rtr, const uint8_t* data,
                            Py_ssize_t n) except -1:
    """Bits a classic frame takes on the wire, actual stuffing, IFS included (what
    ``timing.frame_bits(aid, ext, dlc, data, stuffing="actual", is_remote=rtr)`` gives): compiled
    for a data frame whose ``n`` payload bytes at ``data`` match its DLC and whose identifier
    fits; a remote frame (no data field) and anything else through that checked function, which
    says what is wrong with it."""
    if rtr or n != dlc or not 0 <= aid <= (0x1FFFFFFF if ext else 0x7FF):
        from canbrake.bus.timing import frame_bits

        return frame_bits(aid, ext, dlc, b"" if rtr else (<const char*>data)[:n], stuffing="actual",
                          is_remote=rtr)
    return _plain_bits(ext, n) + _stuff_bits(<uint32_t>aid, ext, n, data, n, False)


def timed_bits_raw(frames, Py_ssize_t start, Py_ssize_t stop, dict untimed):
    """Bits on the wire, actual stuffing, of the memory bus's slot images ``start .. stop-1`` of
    ``frames`` (``canbrake.bus._slot``), leaving out error frames and the identifiers ``untimed``
    marks (identifier -> bool, absent = False): the realtime recorder's bus load, what
    ``timing.frame_bits(..., stuffing="actual")`` gives summed over those frames' messages."""
    cdef const uint8_t[::1] v = frames
    cdef Py_ssize_t i
    cdef const uint8_t* q
    cdef uint32_t aid32
    cdef object u
    total = 0
    for i in range(start, stop):
        q = &v[i * SLOT_BYTES]
        if slot_flags(q) & SLOT_FLAG_ERROR:  # an error frame: no frame on the wire
            continue
        aid32 = slot_id(q)
        u = untimed.get(aid32)
        if u is not None and u:
            continue
        total += _actual_bits(aid32, slot_flags(q) & SLOT_FLAG_EXTENDED, q[17], slot_flags(q) & SLOT_FLAG_REMOTE,
                              q + DATA_OFFSET, slot_len(q))
    return total


cdef tuple _account(list ordered, dict untimed, dict sim_control, double t, double t_k, double dt,
                    double bitrate, double epoch, double* stamps, char* logged):
    """:func:`ideal_period`'s accounting, its stamps in ``stamps`` (``epoch`` + s) and whether the
    log holds each frame in ``logged`` (both ``len(ordered)`` long); returns ``(t_end, busy_s,
    n_timed, latencies)``."""
    cdef Py_ssize_t i, n = len(ordered)
    cdef list durs = [0.0] * n
    cdef list lats = []
    cdef bytes data
    cdef double dur, wire, scale, busy = 0.0, in_period = 0.0
    cdef bint ext, rtr, is_untimed
    cdef Py_ssize_t dlc
    cdef int n_timed = 0
    cdef object f, msg, aid, u
    cdef list flags = [False] * n
    for i in range(n):
        f = ordered[i]
        aid = f[1]
        u = untimed.get(aid)
        if u is not None and u:
            flags[i] = True
            continue
        msg = f[3]
        data = f[2]
        if type(msg) is bytes:  # a slot image (canbrake.bus._slot): flags at 16, DLC at 17
            ext = slot_flags(<const uint8_t*>(<char*>(<bytes>msg))) & SLOT_FLAG_EXTENDED
            rtr = slot_flags(<const uint8_t*>(<char*>(<bytes>msg))) & SLOT_FLAG_REMOTE
            dlc = (<const uint8_t*>(<char*>(<bytes>msg)))[17]
        else:
            ext = msg_get(msg, MSG_EXT)
            rtr = msg_get(msg, MSG_RTR)
            dlc = msg_get(msg, MSG_DLC)
        durs[i] = _actual_bits(aid, ext, dlc, rtr, <const uint8_t*>(<char*>data), len(data)) / bitrate
    wire = sum(durs)  # Python's own sum (its rounding, whatever the Python release)
    scale = min(1.0, dt / wire) if wire > 0 else 1.0
    for i in range(n):
        dur = durs[i]
        is_untimed = flags[i]
        if not is_untimed:
            t += dur
            busy += dur
            n_timed += 1
            lats.append(t - t_k)
        in_period += dur
        stamps[i] = epoch + (t_k + in_period * scale)
        u = sim_control.get(ordered[i][1])
        logged[i] = u is None or not u
    return t, busy, n_timed, lats


def ideal_period(list ordered, dict untimed, dict sim_control, double t, double t_k, double dt,
                 double bitrate, double epoch):
    """The recorder's accounting of one control period under ``bus.timing: ideal``.

    ``ordered``: the period's frames in bus order, tuples whose [1] is the identifier, [2] the
    payload (bytes) and [3] the ``can.Message`` or its memory-bus slot image (bytes,
    ``canbrake.bus._slot``: identifier at 8, flags at 16, DLC at 17, data at 24); ``untimed`` / ``sim_control``: identifier ->
    bool (absent = False). The frames run back to back from ``t`` (s; the bus carries over from
    the last period) with actual stuffing at ``bitrate`` (bit/s); stamps are scaled into
    ``[t_k, t_k + dt]`` when the period's wire time exceeds ``dt``.

    Returns ``(t_end, busy_s, n_timed, latencies, stamped)``: the bus free time, the busy time,
    the frames that take bus time, each one's latency from ``t_k`` (s, list) and
    ``(epoch + stamp, message or image)`` for every frame the log holds (no barrier frames).
    """
    cdef Py_ssize_t i, n = len(ordered)
    cdef double* stamps = <double*>PyMem_Malloc((n + 1) * sizeof(double))
    cdef char* logged = <char*>PyMem_Malloc(n + 1)
    cdef list out = []
    if stamps is NULL or logged is NULL:
        PyMem_Free(stamps)
        PyMem_Free(logged)
        raise MemoryError()
    try:
        t_end, busy, n_timed, lats = _account(ordered, untimed, sim_control, t, t_k, dt, bitrate, epoch, stamps,
                                              logged)
        for i in range(n):
            if logged[i]:
                out.append((stamps[i], ordered[i][3]))
        return t_end, busy, n_timed, lats, out
    finally:
        PyMem_Free(stamps)
        PyMem_Free(logged)


#: bus order of a period's frames: phase, then identifier (arbitration), then payload
_BUS_ORDER = itemgetter(0, 1, 2)


cdef struct Entry:
    long long phase
    long long aid
    const unsigned char* data
    Py_ssize_t n
    Py_ssize_t i


cdef int _entry_cmp(const void* pa, const void* pb) noexcept nogil:
    """Bus order (phase, identifier, payload as bytes compare), then arrival: a stable sort."""
    cdef const Entry* a = <const Entry*>pa
    cdef const Entry* b = <const Entry*>pb
    cdef int c
    if a.phase != b.phase:
        return -1 if a.phase < b.phase else 1
    if a.aid != b.aid:
        return -1 if a.aid < b.aid else 1
    c = memcmp(a.data, b.data, a.n if a.n < b.n else b.n)
    if c:
        return c
    if a.n != b.n:
        return -1 if a.n < b.n else 1
    return -1 if a.i < b.i else (1 if a.i > b.i else 0)


cdef list _bus_order(list frames):
    """``sorted(frames, key=itemgetter(0, 1, 2))`` (phase, identifier, payload; equal keys keep
    their order) in C for int phases and identifiers and bytes payloads; anything else through
    ``sorted``."""
    cdef Py_ssize_t i, n = len(frames)
    cdef Entry* e = <Entry*>PyMem_Malloc((n + 1) * sizeof(Entry))
    cdef list out
    cdef object f, p, a, d
    cdef int ovf = 0
    if e is NULL:
        raise MemoryError()
    try:
        for i in range(n):
            f = frames[i]
            p, a, d = f[0], f[1], f[2]
            if type(p) is not int or type(a) is not int or type(d) is not bytes:
                return sorted(frames, key=_BUS_ORDER)
            e[i].phase = PyLong_AsLongLongAndOverflow(p, &ovf)
            if ovf:
                return sorted(frames, key=_BUS_ORDER)
            e[i].aid = PyLong_AsLongLongAndOverflow(a, &ovf)
            if ovf:
                return sorted(frames, key=_BUS_ORDER)
            e[i].data = <const unsigned char*>(<char*>(<bytes>d))
            e[i].n = len(<bytes>d)
            e[i].i = i
        qsort(e, n, sizeof(Entry), _entry_cmp)
        out = PyList_New(n)
        for i in range(n):
            f = frames[e[i].i]
            Py_INCREF(f)
            PyList_SET_ITEM(out, i, f)
        return out
    finally:
        PyMem_Free(e)


cdef object _ch_args = None
cdef bytes _ch_bytes = None


cdef bytes _channel_bytes(channel, writer_channel):
    """``channel_name(channel, writer_channel)`` as UTF-8 bytes, the last one remembered (a
    recorder asks for the same every period)."""
    global _ch_args, _ch_bytes
    if _ch_args is None or _ch_args[0] is not channel or _ch_args[1] is not writer_channel:
        _ch_bytes = str(channel_name(channel, writer_channel)).encode("utf-8")
        _ch_args = (channel, writer_channel)
    return _ch_bytes


def ideal_tick(list frames, dict untimed, dict sim_control, double t, double t_k, double dt, double bitrate,
               double epoch, writer, channel, LoadSeries series, int fd=-1):
    """A control period of the recorder's common case in one call: its frames (as kept by
    ``nodes._trace.take_frames``/``take_frames_raw``: (phase, identifier, payload, message or
    slot image), in arrival order) put in bus order (phase, identifier, payload; arrival order
    among equal keys), accounted as :func:`ideal_period` accounts them, and the lines of the ones
    the log holds written as :func:`canbrake.bus._candump.write_candump` writes them into
    ``writer`` (a ``can.CanutilsLogWriter`` or None: no log) on ``channel``, in one write (``fd``
    >= 0: the writer file's descriptor, its Python buffers empty: straight to it with
    ``write(2)``, handed to the OS now); the period's bus load (busy time / ``dt``, its timed
    frames, no error frames) added to ``series``.

    Returns ``(t_end, busy_s, n_timed, latencies)`` as :func:`ideal_period`."""
    cdef Py_ssize_t i, n = len(frames)
    cdef double* stamps = <double*>PyMem_Malloc((n + 1) * sizeof(double))
    cdef char* logged = <char*>PyMem_Malloc(n + 1)
    cdef list ordered
    cdef Buf b
    cdef bytes ch
    cdef double last, ts
    cdef object first
    if stamps is NULL or logged is NULL:
        PyMem_Free(stamps)
        PyMem_Free(logged)
        raise MemoryError()
    b.p, b.n, b.cap = NULL, 0, 0
    try:
        ordered = _bus_order(frames)
        res = _account(ordered, untimed, sim_control, t, t_k, dt, bitrate, epoch, stamps, logged)
        series.add_counts(<double>res[1] / dt, res[2], 0)
        if writer is None:
            return res
        for i in range(n):
            if logged[i]:
                break
        else:
            return res
        ch = _channel_bytes(channel, writer.channel)
        if writer.last_timestamp is None:  # the very first message
            first = stamps[i]
            writer.last_timestamp = first or 0.0
        last = writer.last_timestamp
        for i in range(i, n):
            if logged[i]:
                ts = stamps[i]
                candump_line(&b, last if ts < last else ts, ch, len(ch), ordered[i][3])
        if fd >= 0:
            write_all(fd, b.p, b.n)
        else:
            writer.file.write(b.p[:b.n].decode("utf-8"))
        return res
    finally:
        free(b.p)
        PyMem_Free(stamps)
        PyMem_Free(logged)


cdef class LoadSeries:
    """Per-period bus load in constant memory: each period is written to ``bus_load.csv`` as it
    ends (handed to the OS with the frames of that period) and only running aggregates stay in
    memory — mean, peak, the peak ``window_s`` window, and at most ``max_windows`` window means
    (pairs are merged and the window doubles when there would be more), so a run of any length
    keeps the recorder's memory bounded. Compiled so that :func:`ideal_tick` adds a period
    without a Python call; the recorder's other paths call :meth:`add`. The file's lines are
    kept here until :meth:`flush` (one ``write(2)``; the recorder calls it every period in its own
    process) or until 64 KiB are pending (the in-process engine)."""

    cdef public double dt, sum, peak, window_s, _base_window_s, _acc, peak_window, _pend
    cdef public object path
    cdef int _fd
    cdef Buf _out
    cdef public long long n, errors, per_window, _acc_n, _merge, _pend_n, max_windows
    cdef public list windows

    def __init__(self, path, double dt_s, double window_s=0.1, long long max_windows=4096):
        self.dt = dt_s
        self.path = path
        self.n = 0
        self.sum = 0.0
        self.peak = 0.0
        self.errors = 0
        self.per_window = max(1, int(round(window_s / dt_s)))
        self.window_s = self.per_window * dt_s
        self._base_window_s = self.window_s
        self._acc, self._acc_n = 0.0, 0
        self.peak_window = 0.0
        self.windows = []
        self._merge = 1          # base windows per stored window
        self._pend, self._pend_n = 0.0, 0
        self.max_windows = max_windows

    def __cinit__(self):
        self._fd = -1
        self._out.p, self._out.n, self._out.cap = NULL, 0, 0

    def __dealloc__(self):
        if self._fd >= 0:  # what a Python file dropped unclosed does: its lines written, then closed
            if self._out.n:
                c_write(self._fd, self._out.p, self._out.n)
            c_close(self._fd)
        free(self._out.p)

    def add(self, double load, frames, long long errors) -> None:
        """One period: its bus load (fraction), frames (a count, or "" when not counted) and error frames."""
        cdef bytes txt = str(frames).encode("ascii")
        self._add(load, txt, len(txt), errors)

    cdef int add_counts(self, double load, long long frames, long long errors) except -1:
        """:meth:`add` with a count of frames (no Python call)."""
        cdef char txt[24]
        cdef Py_ssize_t k = i64_into(frames, txt)
        return self._add(load, txt, k, errors)

    cdef int _add(self, double load, const char* frames, Py_ssize_t nf, long long errors) except -1:
        cdef char buf[160]
        cdef Py_ssize_t pos
        cdef char* s
        cdef Py_ssize_t k
        cdef bytes head
        if self._fd < 0 and self.path is not None:  # as open(path, "w"): created or truncated
            import os

            self._fd = os.open(self.path, os.O_WRONLY | os.O_CREAT | os.O_TRUNC | getattr(os, "O_CLOEXEC", 0), 0o666)
            head = b"period,t_s,bus_load,frames,error_frames\r\n"  # csv.writer's header line
            buf_reserve(&self._out, len(head))
            memcpy(self._out.p + self._out.n, <const char*>head, len(head))
            self._out.n += len(head)
        if self._fd >= 0:  # the csv writer's line for these values (no quoting needed)
            if nf > 24:
                raise ValueError("LoadSeries.add: frames text longer than 24 characters")
            pos = i64_into(self.n, buf)  # (buf: 160 bytes; each number below at most 32 characters)
            buf[pos] = b','
            pos += 1
            pos += g9_into(<double>self.n * self.dt, buf + pos)
            buf[pos] = b','
            pos += 1
            s = PyOS_double_to_string(load, b'g', 6, 0, NULL)
            k = strlen(s)
            memcpy(buf + pos, s, k)
            PyMem_Free(s)
            pos += k
            buf[pos] = b','
            memcpy(buf + pos + 1, frames, nf)
            pos += nf + 1
            buf[pos] = b','
            pos += 1
            pos += i64_into(errors, buf + pos)
            buf[pos] = b'\r'
            buf[pos + 1] = b'\n'
            pos += 2
            buf_reserve(&self._out, pos)
            memcpy(self._out.p + self._out.n, buf, pos)
            self._out.n += pos
            if self._out.n >= 65536:
                self._write_out()
        self.n += 1
        self.sum += load
        if load > self.peak:
            self.peak = load
        self.errors += errors
        self._acc += load
        self._acc_n += 1
        if self._acc_n == self.per_window:
            self._window(self._acc / self._acc_n)
            self._acc, self._acc_n = 0.0, 0
        return 0

    def _window(self, double mean) -> None:
        cdef object last
        if mean > self.peak_window:
            self.peak_window = mean
        self._pend += mean          # sum of base-window means not stored yet
        self._pend_n += 1           # ... and how many base windows that is
        if self._pend_n < self._merge:
            return
        self.windows.append(self._pend / self._pend_n)
        self._pend, self._pend_n = 0.0, 0
        if len(self.windows) > self.max_windows:  # halve the resolution: bounded memory
            last = self.windows.pop() if len(self.windows) % 2 else None
            self.windows = [(a + b) / 2 for a, b in zip(self.windows[0::2], self.windows[1::2])]
            if last is not None:  # an odd one out waits, as base windows, for its partner
                self._pend, self._pend_n = last * self._merge, self._merge
            self._merge *= 2
            self.window_s = self._base_window_s * self._merge

    cdef int _write_out(self) except -1:
        cdef Py_ssize_t n = self._out.n
        self._out.n = 0  # a failed write loses these lines rather than repeating part of them
        return write_all(self._fd, self._out.p, n)

    def flush(self) -> None:
        """Hand the pending lines to the OS (one ``write(2)``)."""
        if self._fd >= 0 and self._out.n:
            self._write_out()

    def close(self) -> None:
        cdef int fd = self._fd
        if fd >= 0:
            try:
                self.flush()
            finally:
                self._fd = -1
                c_close(fd)

    @property
    def mean(self) -> float:
        return self.sum / self.n if self.n else 0.0

    def window_list(self) -> list:
        if self.windows:
            return list(self.windows)
        return [self._acc / self._acc_n] if self._acc_n else [self.mean]
