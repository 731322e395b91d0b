# cython: language_level=3
"""C buffers shared by the compiled modules: the test of an exported numpy buffer for those that
read arrays through the buffer protocol (``PyObject_GetBuffer`` with ``PyBUF_FORMAT``, cheaper per
call than a typed memoryview: ``nodes._trace``'s rows, ``bus._codec``'s sensor pages,
``nodes._ecu``'s own entries), and the one ``write(2)``-until-done of a buffer to a file
descriptor (``bus._wire``'s candump lines and bus load lines, ``nodes._trace``'s trace rows)."""
from cpython.exc cimport PyErr_CheckSignals, PyErr_SetFromErrno
from libc.errno cimport EINTR, errno
from posix.unistd cimport write as c_write


cdef inline bint is_f64_vector(const Py_buffer* v) noexcept:
    """Is ``v`` a 1-D buffer of native float64 (format ``"d"``)?"""
    return v.ndim == 1 and v.itemsize == 8 and v.format is not NULL and v.format[0] == b'd' and v.format[1] == 0


cdef inline int write_all(int fd, const char* p, Py_ssize_t n) except -1:
    """``n`` bytes at ``p`` to the file descriptor ``fd`` (``write(2)`` until all are written;
    interrupted calls retried after Python's signal handlers ran); OSError as a file object's
    write would raise it (a full disk)."""
    cdef Py_ssize_t k
    while n > 0:
        k = c_write(fd, p, n)
        if k < 0:
            if errno == EINTR:
                PyErr_CheckSignals()
                continue
            PyErr_SetFromErrno(OSError)
            return -1
        p += k
        n -= k
    return 0
