# cython: language_level=3
"""A period's frames as candump -L lines (``frames.log``), compiled: the text
``can.CanutilsLogWriter.on_message_received`` writes, for a whole period in one call.

Why not python-can's writer here: it is the contract and stays the writer of every other format
(.asc, .blf, .trc, .mf4) and of every frame outside the recorder's per-period path, but it needs
one ``can.Message`` and one Python call per frame, which was most of the recorder's cost per
period. So for the default format the recorder hands the period's (timestamp, frame) pairs here
and this writes the same bytes into the writer's own file, with the writer's own state (its
first timestamp, its default channel). ``tests/test_candump_compiled.py`` checks, with
hypothesis, that every line equals what ``can.CanutilsLogWriter`` writes for the same message.
"""
from cpython.mem cimport PyMem_Free
from libc.stdlib cimport free, malloc, realloc
from libc.string cimport memcpy, strlen

from can.io.canutils import CAN_ERR_BUSERROR, CAN_ERR_FLAG


cdef extern from "Python.h":
    char* PyOS_double_to_string(double val, char format_code, int precision, int flags, int* ptype) except NULL


cdef unsigned int ERR_ID = CAN_ERR_FLAG | CAN_ERR_BUSERROR
cdef const char* HEX = b"0123456789ABCDEF"


cdef struct Buf:
    char* p
    Py_ssize_t n
    Py_ssize_t cap


cdef int _reserve(Buf* b, Py_ssize_t more) except -1:
    cdef Py_ssize_t cap
    cdef char* q
    if b.n + more <= b.cap:
        return 0
    cap = max(2 * b.cap, b.n + more + 256)
    q = <char*>realloc(b.p, cap)
    if q == NULL:
        raise MemoryError()
    b.p, b.cap = q, cap
    return 0


cdef inline void _hex(Buf* b, unsigned long v, int digits) noexcept:
    cdef int i
    for i in range(digits - 1, -1, -1):
        b.p[b.n + i] = HEX[v & 0xF]
        v >>= 4
    b.n += digits


cdef int _hex_id(Buf* b, unsigned long v, int width) except -1:
    """``f"{v:0{width}X}"``: at least ``width`` digits."""
    cdef int digits = 1
    cdef unsigned long w = v >> 4
    while w:
        digits += 1
        w >>= 4
    if digits < width:
        digits = width
    _reserve(b, digits)
    _hex(b, v, digits)
    return 0


def channel_name(channel, default):
    """The channel text ``can.CanutilsLogWriter`` writes for a message of ``channel`` (its
    default ``default`` if None; a number ``n`` as ``can<n>``)."""
    ch = channel if channel is not None else default
    if isinstance(ch, int) or (isinstance(ch, str) and ch.isdigit()):
        ch = f"can{ch}"
    return ch


def write_candump(writer, list stamped, channel) -> None:
    """Write ``stamped`` — (timestamp s, frame) pairs, each line as for
    ``can.Message(timestamp=timestamp, arbitration_id, is_extended_id, is_remote_frame,
    is_error_frame, dlc, data=frame.data, channel=channel, is_rx=True)`` (a frame: a
    ``can.Message``, or its memory-bus slot image, bytes of ``canbrake.bus._slot``) — through
    ``writer`` (a ``can.CanutilsLogWriter``) in one write, its state kept as it keeps it."""
    cdef Py_ssize_t i, k, n = len(stamped)
    cdef Buf b
    cdef double ts, last
    cdef char* s
    cdef Py_ssize_t sl
    cdef bytes ch
    cdef const unsigned char* d
    cdef Py_ssize_t nd, chn
    cdef object pair, m, data
    cdef bint err, ext, rtr
    cdef const unsigned char* img
    cdef unsigned int aid32
    cdef object aid
    if n == 0:
        return
    ch = str(channel_name(channel, writer.channel)).encode("utf-8")
    chn = len(ch)
    if writer.last_timestamp is None:  # the very first message
        writer.last_timestamp = stamped[0][0] or 0.0
    last = writer.last_timestamp
    b.p, b.n, b.cap = NULL, 0, 0
    try:
        for i in range(n):
            pair = stamped[i]
            ts = pair[0]
            m = pair[1]
            if ts < last:
                ts = last
            s = PyOS_double_to_string(ts, b'f', 6, 0, NULL)
            try:
                sl = <Py_ssize_t>strlen(s)
                _reserve(&b, sl + chn + 8)
                b.p[b.n] = b'('
                memcpy(b.p + b.n + 1, s, sl)
                b.n += sl + 1
            finally:
                PyMem_Free(s)
            b.p[b.n] = b')'
            b.p[b.n + 1] = b' '
            b.n += 2
            memcpy(b.p + b.n, <const char*>ch, chn)
            b.n += chn
            b.p[b.n] = b' '
            b.n += 1
            if type(m) is bytes:  # a memory-bus slot image (canbrake.bus._slot)
                img = <const unsigned char*>(<char*>(<bytes>m))
                err = img[16] & 4
                ext = img[16] & 1
                rtr = img[16] & 2
                memcpy(&aid32, img + 8, 4)
                aid = aid32
                d = img + 24
                nd = img[18] if img[18] <= 64 else 64
            else:
                err = m.is_error_frame
                ext = m.is_extended_id
                rtr = m.is_remote_frame
                aid = m.arbitration_id if not err else 0
                if not rtr:
                    data = m.data
                    if not isinstance(data, bytes):
                        data = bytes(data)
                    d = <const unsigned char*>(<char*>(<bytes>data))
                    nd = len(<bytes>data)
            if err:
                _hex_id(&b, ERR_ID, 8)
            elif ext:
                _hex_id(&b, aid, 8)
            else:
                _hex_id(&b, aid, 3)
            _reserve(&b, 4)
            b.p[b.n] = b'#'
            b.n += 1
            if rtr:
                b.p[b.n] = b'R'
                b.n += 1
            else:
                _reserve(&b, 2 * nd + 4)
                for k in range(nd):
                    b.p[b.n] = HEX[d[k] >> 4]
                    b.p[b.n + 1] = HEX[d[k] & 0xF]
                    b.n += 2
            _reserve(&b, 3)
            if err:
                b.p[b.n] = b'\n'
                b.n += 1
            else:
                b.p[b.n] = b' '
                b.p[b.n + 1] = b'R'
                b.p[b.n + 2] = b'\n'
                b.n += 3
        writer.file.write(b.p[:b.n].decode("utf-8"))
    finally:
        free(b.p)
