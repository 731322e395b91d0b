# cython: language_level=3
"""The memory bus's slot image, one definition for its writer (``_ring``) and the readers of
``MemoryBus.recv_raw``'s images (``_codec``'s ``feed_raw``/``take_batch_raw``, ``nodes._trace``'s
``take_frames_raw``): ``canbrake.bus.memory_shm``'s ``SLOT_HEAD "<dIIBBBB"``, i.e. time stamp at
0, identifier at 8, flags at 16 (bit 0 extended, bit 1 remote, bit 2 error frame), data length at
18, data at 24, sequence number at 88, of 96 bytes."""
from libc.stdint cimport uint8_t, uint32_t
from libc.string cimport memcpy

cdef enum:
    SLOT_BYTES = 96
    DATA_OFFSET = 24
    MAX_DATA = 64
    SLOT_FLAG_EXTENDED = 1
    SLOT_FLAG_REMOTE = 2
    SLOT_FLAG_ERROR = 4


cdef inline uint32_t slot_id(const uint8_t* p) noexcept nogil:
    """The image's arbitration identifier."""
    cdef uint32_t a
    memcpy(&a, p + 8, 4)
    return a


cdef inline uint8_t slot_flags(const uint8_t* p) noexcept nogil:
    """The image's flags (``SLOT_FLAG_*``)."""
    return p[16]


cdef inline Py_ssize_t slot_len(const uint8_t* p) noexcept nogil:
    """The image's data length, at most ``MAX_DATA`` bytes (from ``DATA_OFFSET``)."""
    return p[18] if p[18] <= MAX_DATA else MAX_DATA


cdef inline void slot_put(uint8_t* p, uint32_t aid, const uint8_t* data, uint8_t n) noexcept nogil:
    """Write a classic data frame's image into the zeroed slot ``p``: identifier ``aid``
    (extended if above 0x7FF, as ``canbrake.nodes.base.frame``), data length and DLC ``n``
    (at most ``MAX_DATA``), its ``n`` bytes of ``data``; time stamp 0 and sender token 0 (the ring's
    ``Ring.stamp`` sets them when it is sent)."""
    memcpy(p + 8, &aid, 4)
    p[16] = SLOT_FLAG_EXTENDED if aid > 0x7FF else 0
    p[17] = n
    p[18] = n
    memcpy(p + DATA_OFFSET, data, n)
