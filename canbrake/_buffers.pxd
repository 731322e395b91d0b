# cython: language_level=3
"""One test of an exported buffer for the compiled modules that read numpy arrays through the
buffer protocol (``PyObject_GetBuffer`` with ``PyBUF_FORMAT``, cheaper per call than a typed
memoryview): ``nodes._trace``'s rows, ``bus._codec``'s sensor pages, ``nodes._ecu``'s own entries."""


cdef inline bint is_f64_vector(const Py_buffer* v) noexcept:
    """Is ``v`` a 1-D buffer of native float64 (format ``"d"``)?"""
    return v.ndim == 1 and v.itemsize == 8 and v.format is not NULL and v.format[0] == b'd' and v.format[1] == 0
