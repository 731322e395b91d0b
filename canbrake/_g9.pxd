# cython: language_level=3
"""canbrake._g9's ``"%.9g"`` for other compiled modules (``cimport``)."""

cdef Py_ssize_t g9_fast(double x, char* out) noexcept
cdef Py_ssize_t g9_into(double x, char* out) except -1
