# cython: language_level=3
"""canbrake.nodes._trace for other compiled modules (``cimport``)."""

cdef int write_str(int fd, str text) except -1
