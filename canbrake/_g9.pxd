# cython: language_level=3
"""canbrake._g9's ``"%.9g"``, ``"%.6f"`` and ``"%d"`` for other compiled modules (``cimport``)."""
from libc.stdint cimport int64_t

cdef Py_ssize_t g9_fast(double x, char* out) noexcept
cdef Py_ssize_t g9_into(double x, char* out) except -1
cdef Py_ssize_t f6_fast(double x, char* out) noexcept
cdef Py_ssize_t f6_into(double x, char* out) except -1
cdef Py_ssize_t i64_into(int64_t v, char* out) noexcept
