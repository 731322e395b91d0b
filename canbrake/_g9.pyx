# cython: language_level=3
# distutils: extra_compile_args = -O2 -ffp-contract=off
"""``"%.9g" % x`` into a C buffer, compiled: the one float-to-text of canbrake's csv writers
(the nodes' trace rows, :mod:`canbrake.nodes._trace`; the batch engine's traces,
:mod:`canbrake._batch`), which write floats as ``f"{v:.9g}"``.

Written by hand because Python's float-to-text (``PyOS_double_to_string``, correctly rounded for
any precision) costs a heap allocation and its general algorithm per value, and a signals.csv row
of the 106-vehicle train holds ~1,100 values per period: :func:`g9_into` makes the nine digits
directly where they are certain and asks Python otherwise (ties, near-ties, magnitudes outside
[1e-14, 1e30)). ``tests/test_batch_csv.py`` checks it against Python's ``"%.9g"`` (hypothesis and
the edge cases). Also here, for the same reason: a candump line's time stamp, ``"%.6f"``
(:func:`f6_into`, exact integer arithmetic), and an integer's decimal text (:func:`i64_into`).
"""

cdef extern from *:
    ctypedef unsigned long long u128 "unsigned __int128"
from cpython.mem cimport PyMem_Free
from libc.math cimport INFINITY, floor, frexp, ldexp, log10, signbit
from libc.stdint cimport int64_t, uint64_t
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
    if a == 0.0:  # Python's "0" / "-0"
        if signbit(x):
            out[0] = b'-'
            out[1] = b'0'
            return 2
        out[0] = b'0'
        return 1
    if a != a:  # NaN (either sign): "nan"
        memcpy(out, b"nan", 3)
        return 3
    if a == INFINITY:
        if x < 0:
            memcpy(out, b"-inf", 4)
            return 4
        memcpy(out, b"inf", 3)
        return 3
    if not (a >= 1e-14 and a < 1e30):  # tiny or huge: Python's text
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


cdef inline int _digits(uint64_t u, char* out) noexcept:
    """``u``'s decimal digits into ``out`` (at least 20 bytes); returns their number."""
    cdef char dig[24]
    cdef int k = 0, pos = 0
    while True:
        dig[k] = <char>(48 + u % 10)
        u //= 10
        k += 1
        if u == 0:
            break
    while k > 0:
        k -= 1
        out[pos] = dig[k]
        pos += 1
    return pos


cdef Py_ssize_t f6_fast(double x, char* out) noexcept:
    """``"%.6f" % x`` into ``out`` (returns its length) for 0 <= x < 9e12, or -1 (the caller asks
    Python). Exact: x = m·2**e with a 53-bit integer m, so x·10**6 = m·10**6·2**e is an integer
    of at most 73 bits shifted, done in 128-bit integers, and rounded half to even on its exact
    remainder, as Python's correctly rounded float-to-text does."""
    cdef int ex, e, k, pos = 0
    cdef double mant
    cdef uint64_t m, q, ip, fp
    cdef u128 p, rem, half
    if not (x >= 0.0 and x < 9e12):  # negative, NaN, huge: Python's text
        return -1
    if x == 0.0:
        if signbit(x):
            return -1
        q = 0
    else:
        mant = frexp(x, &ex)  # x = mant·2**ex, 0.5 <= mant < 1
        m = <uint64_t>ldexp(mant, 53)  # exact: 53 bits
        e = ex - 53
        p = <u128>m * <u128>1000000
        if e >= 0:
            q = <uint64_t>(p << e)  # (x < 9e12: x·1e6 < 9e18 fits)
        elif e < -120:  # below 2**-67: far below the 6th decimal
            q = 0
        else:
            q = <uint64_t>(p >> (-e))
            rem = p - ((<u128>q) << (-e))
            half = (<u128>1) << (-e - 1)
            if rem > half or (rem == half and (q & 1)):
                q += 1
    ip = q // 1000000
    fp = q % 1000000
    pos = _digits(ip, out)
    out[pos] = b'.'
    pos += 1
    for k in range(5, -1, -1):
        out[pos + k] = <char>(48 + fp % 10)
        fp //= 10
    return pos + 6


cdef Py_ssize_t f6_into(double x, char* out) except -1:
    """``"%.6f" % x`` into ``out`` (at least 32 bytes for |x| < 1e20; returns its length):
    :func:`f6_fast`, or Python's float-to-text where that defers."""
    cdef Py_ssize_t k = f6_fast(x, out)
    cdef char* s
    if k >= 0:
        return k
    s = PyOS_double_to_string(x, b'f', 6, 0, NULL)
    try:
        k = <Py_ssize_t>strlen(s)
        if k > 31:
            raise OverflowError("f6_into: the text of %r is longer than 31 characters" % x)
        memcpy(out, s, k)
    finally:
        PyMem_Free(s)
    return k


cdef Py_ssize_t i64_into(int64_t v, char* out) noexcept:
    """``"%d" % v`` into ``out`` (at least 21 bytes; returns its length)."""
    if v < 0:
        out[0] = b'-'
        return 1 + _digits(<uint64_t>(-(v + 1)) + 1, out + 1)  # (also for the most negative value)
    return _digits(<uint64_t>v, out)


def f6(double x):
    """``"%.6f" % x`` by :func:`f6_fast` (None where it defers to Python): for the tests."""
    cdef char out[32]
    cdef Py_ssize_t n = f6_fast(x, out)
    return None if n < 0 else out[:n].decode("ascii")


def i64(int64_t v):
    """``"%d" % v`` by :func:`i64_into`: for the tests."""
    cdef char out[24]
    return out[:i64_into(v, out)].decode("ascii")
