# cython: language_level=3
"""One candump -L line (the text ``can.CanutilsLogWriter.on_message_received`` writes) into a
growing buffer, one definition for ``_candump.write_candump`` and ``_wire.ideal_tick`` (the
recorder's per-period writers of ``frames.log``)."""
from cpython.mem cimport PyMem_Free
from libc.stdlib cimport realloc
from libc.string cimport memcpy, strlen

from canbrake._g9 cimport f6_into
from canbrake.bus._ring cimport MSG_DATA, MSG_ERR, MSG_EXT, MSG_ID, MSG_RTR, msg_get

cdef extern from "Python.h":
    char* PyOS_double_to_string(double val, char format_code, int precision, int flags, int* ptype) except NULL

cdef enum:
    CANDUMP_ERR_ID = 0x20000080   # can.io.canutils: CAN_ERR_FLAG | CAN_ERR_BUSERROR (tests check it)


cdef struct Buf:
    char* p
    Py_ssize_t n
    Py_ssize_t cap


cdef inline int buf_reserve(Buf* b, Py_ssize_t more) except -1:
    """Room for ``more`` bytes after ``b.n`` (the buffer grows by doubling; ``free(b.p)`` at the end)."""
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


cdef inline int _hex_id(Buf* b, unsigned long v, int width) except -1:
    """``f"{v:0{width}X}"``: at least ``width`` digits."""
    cdef const char* HEX = b"0123456789ABCDEF"
    cdef int digits = 1, i
    cdef unsigned long w = v >> 4
    while w:
        digits += 1
        w >>= 4
    if digits < width:
        digits = width
    buf_reserve(b, digits)
    for i in range(digits - 1, -1, -1):
        b.p[b.n + i] = HEX[v & 0xF]
        v >>= 4
    b.n += digits
    return 0


cdef inline int candump_line(Buf* b, double ts, const char* ch, Py_ssize_t chn, object m) except -1:
    """The line of frame ``m`` (a ``can.Message`` or its memory-bus slot image, bytes of
    ``canbrake.bus._slot``) at timestamp ``ts`` (s, already clamped to the writer's first) on
    channel ``ch`` (``chn`` bytes), received."""
    cdef const char* HEX = b"0123456789ABCDEF"
    cdef Py_ssize_t sl, k, nd = 0
    cdef const unsigned char* d = NULL
    cdef const unsigned char* img
    cdef bint err, ext, rtr
    cdef unsigned int aid32
    cdef object aid, data
    cdef char stamp[32]
    sl = f6_into(ts, stamp)  # the time stamp as "%.6f" (python-can's writer: "(%f)")
    buf_reserve(b, sl + chn + 8)
    b.p[b.n] = b'('
    memcpy(b.p + b.n + 1, stamp, sl)
    b.n += sl + 1
    b.p[b.n] = b')'
    b.p[b.n + 1] = b' '
    b.n += 2
    memcpy(b.p + b.n, ch, chn)
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
        err = msg_get(m, MSG_ERR)
        ext = msg_get(m, MSG_EXT)
        rtr = msg_get(m, MSG_RTR)
        aid = msg_get(m, MSG_ID) if not err else 0
        if not rtr:
            data = msg_get(m, MSG_DATA)
            if not isinstance(data, bytes):
                data = bytes(data)
            d = <const unsigned char*>(<char*>(<bytes>data))
            nd = len(<bytes>data)
    if err:
        _hex_id(b, CANDUMP_ERR_ID, 8)
    elif ext:
        _hex_id(b, aid, 8)
    else:
        _hex_id(b, aid, 3)
    buf_reserve(b, 4)
    b.p[b.n] = b'#'
    b.n += 1
    if rtr:
        b.p[b.n] = b'R'
        b.n += 1
    else:
        buf_reserve(b, 2 * nd + 4)
        for k in range(nd):
            b.p[b.n] = HEX[d[k] >> 4]
            b.p[b.n + 1] = HEX[d[k] & 0xF]
            b.n += 2
    buf_reserve(b, 3)
    if err:
        b.p[b.n] = b'\n'
        b.n += 1
    else:
        b.p[b.n] = b' '
        b.p[b.n + 1] = b'R'
        b.p[b.n + 2] = b'\n'
        b.n += 3
    return 0
