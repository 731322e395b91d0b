# cython: language_level=3
# distutils: extra_compile_args = -O2 -ffp-contract=off
"""``"%.9g" % x`` into a C buffer, compiled: the one float-to-text of canbrake's csv writers
(the nodes' trace rows, :mod:`canbrake.nodes._trace`; the batch engine's traces,
:mod:`canbrake._batch`), which write floats as ``f"{v:.9g}"``.

Written by hand because Python's float-to-text (``PyOS_double_to_string``, correctly rounded for
any precision) costs a heap allocation and its general algorithm per value, and a signals.csv row
of the 106-vehicle train holds ~1,100 values per period: :func:`g9_into` makes the nine digits
directly where they are certain and asks Python otherwise (ties, near-ties, 0, NaN, infinities,
magnitudes outside [1e-14, 1e30)). ``tests/test_batch_csv.py`` checks it against Python's
``"%.9g"`` (hypothesis and the edge cases).
"""
from cpython.mem cimport PyMem_Free
from libc.math cimport floor, log10
from libc.string cimport memcpy, strlen

cdef extern from "Python.h":
    char* PyOS_double_to_string(double val, char format_code, int precision, int flags, int* ptype) except NULL

# 10**s, exact as doubles for s <= 22
cdef double _POW10[23]
_POW10[0] = 1.0
for _s in range(1, 23):
    _POW10[_s] = _POW10[_s - 1] * 10


cdef Py_ssize_t g9_fast(double x, char* out) noexcept:
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


cdef Py_ssize_t g9_into(double x, char* out) except -1:
    """``"%.9g" % x`` into ``out`` (at least 32 bytes; returns its length): :func:`g9_fast`, or
    Python's float-to-text where that defers."""
    cdef Py_ssize_t k = g9_fast(x, out)
    cdef char* s
    if k >= 0:
        return k
    s = PyOS_double_to_string(x, b'g', 9, 0, NULL)
    k = <Py_ssize_t>strlen(s)
    memcpy(out, s, k)
    PyMem_Free(s)
    return k


def g9(double x):
    """``"%.9g" % x`` by :func:`g9_fast` (None where it defers to Python): for the tests."""
    cdef char out[32]
    cdef Py_ssize_t n = g9_fast(x, out)
    return None if n < 0 else out[:n].decode("ascii")
