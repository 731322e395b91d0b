# cython: language_level=3
"""The compiled controllers' one read of an attribute (``cimport``ed by ``_chen`` and ``_observer``)."""
from cpython.dict cimport PyDict_GetItemWithError
from cpython.object cimport PyObject


cdef inline object attr(dict d, object o, str name):
    """``o.name``, read from its instance dict ``d`` (a controller's and an observer's parameters
    and state live there), else as any attribute."""
    cdef PyObject* p = PyDict_GetItemWithError(d, name)
    if p is NULL:
        return getattr(o, name)
    return <object>p
