# cython: language_level=3
# distutils: extra_compile_args = -O2 -ffp-contract=off
"""The batch engine's traces as csv bytes, compiled (canbrake.batch._write_csv).

A sweep point's signals.csv and ECU traces are written when it ends: ~10,000 rows of 50-130
values per point of a 10 s sweep at 1 ms, 121 points in the default sweep. ``csv_block``
(canbrake.nodes._trace) makes a str per value and joins them; :func:`csv_bytes` writes the same
text into one buffer. tests/test_batch_csv.py checks it against ``csv_block``.
"""
from cpython.bytes cimport PyBytes_FromStringAndSize
from cpython.mem cimport PyMem_Free, PyMem_Malloc
from libc.math cimport floor, log10
from libc.stdio cimport snprintf
from libc.string cimport memcpy, strlen

cdef extern from "Python.h":
    char* PyOS_double_to_string(double val, char format_code, int precision, int flags, int* ptype) except NULL

# 10**s, exact as doubles for s <= 22
cdef double _POW10[23]
_POW10[0] = 1.0
for _s in range(1, 23):
    _POW10[_s] = _POW10[_s - 1] * 10


cdef Py_ssize_t _g9_fast(double x, char* out) noexcept:
    """``"%.9g" % x`` into ``out`` (returns its length), or -1 where the fast path cannot be sure
    of the correctly rounded digits (the caller then asks Python). The 9 significant digits are
    x·10**s rounded, s chosen so the product is in [1e8, 1e9); 10**s is exact (|s| <= 22) and the
    product (or quotient) is rounded once, by at most half an ulp (< 1.2e-7 below 1e9), so the
    rounding to an integer is certain unless the product lies within 1e-6 of a half (ties and
    near-ties, about 2 values in a million: Python's)."""
    cdef double a = -x if x < 0 else x
    cdef double y, f
    cdef unsigned int d
    cdef int e, s, nd, i, pos = 0
    cdef char dig[9]
    if not (a >= 1e-14 and a < 1e30):  # 0, NaN, inf, tiny or huge: Python's text
        return -1
    e = <int>floor(log10(a))
    for i in range(3):
        s = 8 - e
        if s < -22 or s > 22:
            return -1
        y = a * _POW10[s] if s >= 0 else a / _POW10[-s]
        if y >= 1e9:
            e += 1
        elif y < 1e8:
            e -= 1
        else:
            break
    else:
        return -1
    f = y - floor(y)
    if f > 0.5 - 1e-6 and f < 0.5 + 1e-6:
        return -1
    d = <unsigned int>floor(y) + (1 if f > 0.5 else 0)
    if d >= 1000000000:
        d = 100000000
        e += 1
    for i in range(8, -1, -1):
        dig[i] = <char>(48 + d % 10)
        d //= 10
    nd = 9
    while nd > 1 and dig[nd - 1] == 48:
        nd -= 1
    if x < 0:
        out[pos] = b'-'
        pos += 1
    if -4 <= e < 9:
        if e >= 0:
            for i in range(e + 1):
                out[pos] = dig[i] if i < nd else 48
                pos += 1
            if nd > e + 1:
                out[pos] = b'.'
                pos += 1
                for i in range(e + 1, nd):
                    out[pos] = dig[i]
                    pos += 1
        else:
            out[pos] = 48
            out[pos + 1] = b'.'
            pos += 2
            for i in range(-e - 1):
                out[pos] = 48
                pos += 1
            for i in range(nd):
                out[pos] = dig[i]
                pos += 1
    else:
        out[pos] = dig[0]
        pos += 1
        if nd > 1:
            out[pos] = b'.'
            pos += 1
            for i in range(1, nd):
                out[pos] = dig[i]
                pos += 1
        out[pos] = b'e'
        out[pos + 1] = b'-' if e < 0 else b'+'
        pos += 2
        if e < 0:
            e = -e
        if e >= 100:
            out[pos] = <char>(48 + e // 100)
            pos += 1
        out[pos] = <char>(48 + (e // 10) % 10)
        out[pos + 1] = <char>(48 + e % 10)
        pos += 2
    return pos


def g9(double x):
    """``"%.9g" % x`` by :func:`_g9_fast` (None where it defers to Python): for the tests."""
    cdef char out[32]
    cdef Py_ssize_t n = _g9_fast(x, out)
    return None if n < 0 else out[:n].decode("ascii")


def csv_bytes(double[:, :] rows, bint last_int=False):
    """The rows of a float array as csv lines (``\\r\\n``), ASCII bytes: the first column (and
    with ``last_int`` also the last) as ``"%d" % int(v)``, the others as ``"%.9g" % v`` (the
    text of ``canbrake.nodes._trace.csv_block``, encoded)."""
    cdef Py_ssize_t i, j, n = rows.shape[0], m = rows.shape[1], pos = 0, k
    # a value's text is at most 24 characters ("%.9g": 16; an int below 2**63: 20), plus a separator
    cdef Py_ssize_t cap = n * (m * 26 + 2) + 1
    cdef char* buf
    cdef char* s
    cdef double x
    if n == 0:
        return b""
    buf = <char*>PyMem_Malloc(cap)
    if buf is NULL:
        raise MemoryError()
    try:
        for i in range(n):
            for j in range(m):
                if j:
                    buf[pos] = b','
                    pos += 1
                x = rows[i, j]
                if j == 0 or (last_int and j == m - 1):
                    if x != x:
                        raise ValueError("cannot convert float NaN to integer")
                    if -9.2e18 < x < 9.2e18:
                        pos += snprintf(buf + pos, 24, "%lld", <long long>x)
                    else:  # Python's own text (or its error for an infinity)
                        txt = int.__repr__(int(x)).encode("ascii")
                        if len(txt) > 24:
                            raise OverflowError("tick beyond 24 digits")
                        memcpy(buf + pos, <char*>txt, len(txt))
                        pos += len(txt)
                else:
                    k = _g9_fast(x, buf + pos)
                    if k >= 0:
                        pos += k
                        continue
                    s = PyOS_double_to_string(x, b'g', 9, 0, NULL)
                    k = strlen(s)
                    memcpy(buf + pos, s, k)
                    PyMem_Free(s)
                    pos += k
            buf[pos] = b'\r'
            buf[pos + 1] = b'\n'
            pos += 2
        return PyBytes_FromStringAndSize(buf, pos)
    finally:
        PyMem_Free(buf)
