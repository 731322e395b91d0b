# cython: language_level=3
"""canbrake.bus._ring for other compiled modules (``cimport``): a python-can message's fields
read without an attribute lookup (:func:`msg_get`)."""

# a field of can.Message, in _ring._SLOTS' order
cdef enum:
    MSG_TIMESTAMP = 0
    MSG_ID = 1
    MSG_EXT = 2
    MSG_RTR = 3
    MSG_ERR = 4
    MSG_CHANNEL = 5
    MSG_FD = 6
    MSG_RX = 7
    MSG_BRS = 8
    MSG_ESI = 9
    MSG_DATA = 10
    MSG_DLC = 11

cdef object msg_get(object m, int i)
