# cython: language_level=3
# distutils: extra_compile_args = -O2 -ffp-contract=off
"""The batch engine's traces as csv bytes, compiled (canbrake.batch._write_csv).

A sweep point's signals.csv and ECU traces are written when it ends: ~10,000 rows of 50-130
values per point of a 10 s sweep at 1 ms, 121 points in the default sweep. :func:`csv_bytes`
writes their text into one buffer, floats by :mod:`canbrake._g9`; tests/test_batch_csv.py checks
it against Python's ``"%d"`` / ``"%.9g"`` text.
"""
from cpython.bytes cimport PyBytes_FromStringAndSize
from cpython.mem cimport PyMem_Free, PyMem_Malloc
from libc.stdio cimport snprintf
from libc.string cimport memcpy

from canbrake._g9 cimport g9_into


def csv_bytes(double[:, :] rows, bint last_int=False):
    """The rows of a float array as csv lines (``\\r\\n``), ASCII bytes: the first column (and
    with ``last_int`` also the last) as ``"%d" % int(v)``, the others as ``"%.9g" % v`` (the
    text of the csv writer with ``f"{v:.9g}"`` floats, encoded)."""
    cdef Py_ssize_t i, j, n = rows.shape[0], m = rows.shape[1], pos = 0, k
    # a value's text is at most 24 characters ("%.9g": 16; an int below 2**63: 20), plus a separator
    cdef Py_ssize_t cap = n * (m * 26 + 2) + 1
    cdef char* buf
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
                    pos += g9_into(x, buf + pos)
            buf[pos] = b'\r'
            buf[pos + 1] = b'\n'
            pos += 2
        return PyBytes_FromStringAndSize(buf, pos)
    finally:
        PyMem_Free(buf)
