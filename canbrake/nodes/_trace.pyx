# cython: language_level=3
# distutils: extra_compile_args = -O2 -ffp-contract=off
"""The nodes' per-period bookkeeping, compiled: a trace row as csv text (:class:`CsvTrace`)
and a batch of durations into a :class:`LogHistogram` (canbrake.nodes.base).

Written by hand because both run every control period for every node (a signals.csv row of the
106-vehicle train holds ~1,100 values) and neither the csv module nor numpy does either without a
Python call per value; ``tests/test_trace_compiled.py`` checks them against ``csv.writer`` with
``%.9g`` floats and against ``LogHistogram.add``.
"""
from cpython.float cimport PyFloat_AS_DOUBLE
from cpython.mem cimport PyMem_Free
from libc.math cimport log

import numpy as np

cdef extern from "Python.h":
    char* PyOS_double_to_string(double val, char format_code, int precision, int flags, int* ptype) except NULL

cdef type NP_F64 = np.float64
cdef type NP_I64 = np.int64
cdef type NP_I32 = np.int32
cdef type NP_BOOL = np.bool_


cdef str _g9(double x):
    cdef char* s = PyOS_double_to_string(x, b'g', 9, 0, NULL)
    try:
        return s.decode("ascii")
    finally:
        PyMem_Free(s)


def csv_row(list row):
    """``row`` as the line ``csv.writer`` writes (excel dialect, ``\\r\\n``) with floats as
    ``f"{v:.9g}"``, for rows of floats, ints and bools (Python's or numpy's); None for a row with
    any other value (the caller takes the csv writer)."""
    cdef Py_ssize_t i, n = len(row)
    cdef list parts = [None] * n
    cdef object v
    cdef type t
    for i in range(n):
        v = row[i]
        t = type(v)
        if t is float:
            parts[i] = _g9(PyFloat_AS_DOUBLE(v))
        elif t is int:
            parts[i] = int.__repr__(v)
        elif t is NP_F64:
            parts[i] = _g9(float(v))
        elif t is bool or t is NP_BOOL:
            parts[i] = "True" if v else "False"
        elif t is NP_I64 or t is NP_I32:
            parts[i] = int.__repr__(int(v))
        else:
            return None
    return ",".join(parts) + "\r\n"


def csv_block(double[:, :] rows, bint last_int=False):
    """The rows of a float array as csv lines (``\r\n``): the first column (and with
    ``last_int`` also the last) as ``"%d" % v``, the others as ``"%.9g" % v`` (the batch engine's
    traces, canbrake.batch; the same text as CsvTrace's rows)."""
    cdef Py_ssize_t i, j, n = rows.shape[0], m = rows.shape[1]
    cdef list lines = [None] * n
    cdef list parts = [None] * m
    cdef double x
    for i in range(n):
        for j in range(m):
            x = rows[i, j]
            if j == 0 or (last_int and j == m - 1):
                if x != x:
                    raise ValueError("cannot convert float NaN to integer")
                parts[j] = int.__repr__(int(x))
            else:
                parts[j] = _g9(x)
        lines[i] = ",".join(parts)
    return "\r\n".join(lines) + ("\r\n" if n else "")


def hist_add(list counts, xs, Py_ssize_t n, double total, double vmax, double lo, double log_ratio):
    """Add the durations ``xs`` (s) to a LogHistogram's ``counts`` as ``LogHistogram.add`` does,
    one by one; returns its new ``(n, total, max)``."""
    cdef Py_ssize_t bins = len(counts), i
    cdef double x, y
    for v in xs:
        x = v
        n += 1
        total += x
        if x > vmax:
            vmax = x
        if x <= lo:
            i = 0
        else:
            y = log(x / lo) / log_ratio
            if not y < 1e18:  # what int() says of a NaN or an infinite duration
                raise ValueError("cannot convert float NaN to integer") if y != y else OverflowError(
                    "cannot convert float infinity to integer")
            i = 1 + <Py_ssize_t>y
            if i >= bins:
                i = bins - 1
        counts[i] += 1
    return n, total, vmax
