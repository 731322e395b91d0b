# cython: language_level=3
"""The memory bus's ring, compiled: frame slots in, ``can.Message`` objects out
(:mod:`canbrake.bus.memory`, layout in :mod:`canbrake.bus.memory_shm`).

One boundary, crossed once per ``send``/``send_many`` burst and once per fetch of every new frame:

- :class:`Filters`: python-can acceptance filters compiled to C (the rule of
  ``BusABC._matches_filters``, checked against it in ``tests/test_memory_ring.py``);
- :class:`Ring` over the channel's mapping: :meth:`Ring.encode` (validate and pack a burst of
  messages into slot images, before the writer lock), :meth:`Ring.write` (copy them into the ring
  with the per-slot seqlock, publish ``write_seq``; lock held), :meth:`Ring.wake` (which sleeping
  readers' filters accept the burst: their wake-up bookkeeping), :meth:`Ring.protected_hit` (does a
  ``backpressure="accepted"`` reader accept an unread frame a write would overwrite), and
  :meth:`Ring.fetch` (every new frame this bus accepts as ``can.Message``, with the seqlock
  re-check and the overrun count).

Locking, wake-ups, backpressure policy, errors and counters stay in Python (``memory.py``). Written
by hand because no library offers a cross-process CAN ring; the slot format is canbrake's own.

Memory ordering: ``write_seq`` and the slots' sequence numbers are read with acquire loads and
stored with release stores (plain ``mov`` on x86-64, whose total store order the protocol relies
on; the atomics only stop the compiler from reordering).
"""
from cpython.bytearray cimport PyByteArray_FromStringAndSize, PyByteArray_AS_STRING, PyByteArray_GET_SIZE
from cpython.bytes cimport PyBytes_AS_STRING, PyBytes_GET_SIZE, PyBytes_FromStringAndSize
from cpython.buffer cimport PyObject_GetBuffer, PyBuffer_Release, PyBUF_WRITABLE, PyBUF_SIMPLE
from cpython.object cimport PyObject
from cpython.ref cimport Py_INCREF
from libc.stdint cimport uint8_t, uint32_t, uint64_t, int64_t
from libc.stdlib cimport malloc, free
from libc.string cimport memcpy, memset

from can import Message
from can.exceptions import CanOperationError

cdef extern from *:
    """
    #include <stdint.h>
    static inline uint64_t cb_load(const char *p) {
        return __atomic_load_n((const uint64_t *)p, __ATOMIC_ACQUIRE);
    }
    static inline void cb_store(char *p, uint64_t v) {
        __atomic_store_n((uint64_t *)p, v, __ATOMIC_RELEASE);
    }
    """
    uint64_t cb_load(const char *p) noexcept nogil
    void cb_store(char *p, uint64_t v) noexcept nogil

cdef extern from "structmember.h":
    int T_OBJECT_EX

cdef extern from "Python.h":
    object PyObject_GenericGetAttr(object o, object name)
    int PyObject_GenericSetAttr(object o, object name, object value) except -1
    ctypedef struct PyMemberDef:
        int type
        Py_ssize_t offset
    ctypedef struct PyMemberDescrObject:
        PyMemberDef* d_member
    PyObject* Py_True
    PyObject* Py_False
    PyObject* PyFloat_FromDouble(double v)
    PyObject* PyLong_FromUnsignedLong(unsigned long v)

# ---- the slot format (memory_shm: SLOT_HEAD "<dIIBBBB", data at 24, sequence number at 88)
DEF SLOT_BYTES = 96
DEF DATA_OFFSET = 24
DEF MAX_DATA = 64
DEF SLOT_SEQ_OFFSET = 88
DEF WRITE_SEQ_BYTE = 64        # header word H_WRITE_SEQ (8)
DEF SLEEPERS_BYTE = 160        # header word H_SLEEPERS (20)
DEF E_SLEEPING_BYTE = 72       # reader-entry words E_SLEEPING (9), E_WAKE_SEQ (10), E_WAKEUPS (11)
DEF E_WAKE_SEQ_BYTE = 80
DEF E_WAKEUPS_BYTE = 88
DEF E_WANT_BYTE = 104          # E_WANT (13): accepted frames a sleeping reader waits for
DEF E_PENDING_BYTE = 112       # E_PENDING (14): accepted frames published since it slept
DEF E_WAKE_ON_BYTE = 120       # E_WAKE_ON (15): 0, or 1 << 40 | ext << 31 | id: only that frame wakes it
DEF M_EXT = 1
DEF M_RTR = 2
DEF M_ERR = 4
DEF M_FD = 8
DEF M_BRS = 16
DEF M_ESI = 32
cdef uint64_t SLOT_INVALID = 0xFFFFFFFFFFFFFFFFULL
#: the slot format compiled in, checked against memory_shm's layout by memory.py at import
LAYOUT = {"SLOT_BYTES": SLOT_BYTES, "DATA_OFFSET": DATA_OFFSET, "MAX_DATA": MAX_DATA,
          "SLOT_SEQ_OFFSET": SLOT_SEQ_OFFSET, "H_WRITE_SEQ": WRITE_SEQ_BYTE // 8,
          "H_SLEEPERS": SLEEPERS_BYTE // 8, "E_SLEEPING": E_SLEEPING_BYTE // 8,
          "E_WAKE_SEQ": E_WAKE_SEQ_BYTE // 8, "E_WAKEUPS": E_WAKEUPS_BYTE // 8,
          "E_WANT": E_WANT_BYTE // 8, "E_PENDING": E_PENDING_BYTE // 8, "E_WAKE_ON": E_WAKE_ON_BYTE // 8}

# python-can's Message has __slots__ and an __init__ that, given a bytearray and a dlc, only
# stores its arguments. Setting the slots directly on a new object gives the same object for
# a fraction of the cost; if a python-can release adds a slot, the constructor is used instead.
_SLOTS = ("timestamp", "arbitration_id", "is_extended_id", "is_remote_frame", "is_error_frame",
          "channel", "is_fd", "is_rx", "bitrate_switch", "error_state_indicator", "data", "dlc")
cdef bint _FAST_MSG = set(getattr(Message, "__slots__", ())) - {"__weakref__"} == set(_SLOTS)
cdef object _new = object.__new__


def fast_messages(on=None) -> bool:
    """Whether messages are built by setting their slots (else by ``can.Message(...)``); ``on``
    switches it (tests compare both ways; switching on needs python-can's known slots)."""
    global _FAST_MSG
    if on is not None:
        _FAST_MSG = bool(on) and set(getattr(Message, "__slots__", ())) - {"__weakref__"} == set(_SLOTS)
    return _FAST_MSG


# each slot's offset in a Message object (its member descriptor's), in _SLOTS' order: _message
# stores the values there, as the descriptor's set does on a new object (whose slots are empty)
cdef Py_ssize_t _OFF[12]


cdef bint _slot_offsets():
    cdef PyMemberDescrObject* d
    for i, name in enumerate(_SLOTS):
        descr = Message.__dict__.get(name)
        if type(descr).__name__ != "member_descriptor":
            return False
        d = <PyMemberDescrObject*><PyObject*>descr
        if d.d_member.type != T_OBJECT_EX:
            return False
        _OFF[i] = d.d_member.offset
    return True


cdef bint _DIRECT = _FAST_MSG and _slot_offsets()


cdef inline void _put(object m, int i, PyObject* v) noexcept:
    """Store the new reference ``v`` in slot i of the new message ``m``."""
    (<PyObject**>((<char*><PyObject*>m) + _OFF[i]))[0] = v


cdef inline PyObject* _flag(bint b) noexcept:
    cdef PyObject* r = Py_True if b else Py_False
    Py_INCREF(<object>r)
    return r


cdef object S_TS = "timestamp", S_ID = "arbitration_id", S_EXT = "is_extended_id"
cdef object S_RTR = "is_remote_frame", S_ERR = "is_error_frame", S_CH = "channel"
cdef object S_FD = "is_fd", S_RX = "is_rx", S_BRS = "bitrate_switch", S_ESI = "error_state_indicator"
cdef object S_DATA = "data", S_DLC = "dlc"


def data_frame(uint32_t arbitration_id, data) -> Message:
    """A classic data frame as ``can.Message(arbitration_id=..., data=..., is_extended_id=arbitration_id
    > 0x7FF)`` makes it (timestamp 0, received, no channel), built by :func:`_message`: the nodes
    make one per frame they send (:func:`canbrake.nodes.base.frame`)."""
    cdef bytearray d = data if type(data) is bytearray else bytearray(data)
    if len(d) > MAX_DATA:  # not a CAN frame, but what the constructor would make of it
        return Message(arbitration_id=arbitration_id, data=d, is_extended_id=arbitration_id > 0x7FF)
    return _message(0.0, arbitration_id, M_EXT if arbitration_id > 0x7FF else 0, <uint8_t>len(d), d, None, True)


cdef object _message(double ts, uint32_t aid, uint8_t flags, uint8_t dlc, bytearray data,
                     object channel, bint is_rx):
    """``can.Message(ts, aid, ext, rtr, err, channel, dlc, data, fd, is_rx, brs, esi)``."""
    if not _FAST_MSG:
        return Message(ts, aid, bool(flags & M_EXT), bool(flags & M_RTR), bool(flags & M_ERR),
                       channel, dlc, data, bool(flags & M_FD), is_rx, bool(flags & M_BRS),
                       bool(flags & M_ESI))
    m = _new(Message)
    if _DIRECT:  # the slots in _SLOTS' order
        if flags & M_RTR:  # as Message.__init__: a remote frame has no data
            data = bytearray()
        _put(m, 0, PyFloat_FromDouble(ts))
        _put(m, 1, PyLong_FromUnsignedLong(aid))
        _put(m, 2, _flag(flags & M_EXT))
        _put(m, 3, _flag(flags & M_RTR))
        _put(m, 4, _flag(flags & M_ERR))
        Py_INCREF(channel)
        _put(m, 5, <PyObject*>channel)
        _put(m, 6, _flag(flags & M_FD))
        _put(m, 7, _flag(is_rx))
        _put(m, 8, _flag(flags & M_BRS))
        _put(m, 9, _flag(flags & M_ESI))
        Py_INCREF(data)
        _put(m, 10, <PyObject*>data)
        _put(m, 11, PyLong_FromUnsignedLong(dlc))
        return m
    PyObject_GenericSetAttr(m, S_TS, ts)
    PyObject_GenericSetAttr(m, S_ID, aid)
    PyObject_GenericSetAttr(m, S_EXT, bool(flags & M_EXT))
    PyObject_GenericSetAttr(m, S_RTR, bool(flags & M_RTR))
    PyObject_GenericSetAttr(m, S_ERR, bool(flags & M_ERR))
    PyObject_GenericSetAttr(m, S_CH, channel)
    PyObject_GenericSetAttr(m, S_FD, bool(flags & M_FD))
    PyObject_GenericSetAttr(m, S_RX, is_rx)
    PyObject_GenericSetAttr(m, S_BRS, bool(flags & M_BRS))
    PyObject_GenericSetAttr(m, S_ESI, bool(flags & M_ESI))
    if flags & M_RTR:  # as Message.__init__: a remote frame has no data
        data = bytearray()
    PyObject_GenericSetAttr(m, S_DATA, data)
    PyObject_GenericSetAttr(m, S_DLC, dlc)
    return m


cdef class Filters:
    """python-can acceptance filters compiled for C: ``filters`` as
    :func:`canbrake.bus.memory_shm.compile_filters` gives them, ``(id & mask, mask, mode)`` with
    mode 0 any frame, 1 standard ids only, 2 extended ids only, 3 never."""

    cdef uint32_t *ids
    cdef uint32_t *masks
    cdef uint8_t *modes
    cdef Py_ssize_t n

    def __cinit__(self, filters):
        cdef Py_ssize_t i
        items = tuple(filters)
        self.n = len(items)
        self.ids = <uint32_t *>malloc(max(1, self.n) * sizeof(uint32_t))
        self.masks = <uint32_t *>malloc(max(1, self.n) * sizeof(uint32_t))
        self.modes = <uint8_t *>malloc(max(1, self.n) * sizeof(uint8_t))
        if not self.ids or not self.masks or not self.modes:
            raise MemoryError()
        for i, (cid, mask, mode) in enumerate(items):
            cid, mask, mode = int(cid), int(mask), int(mode)
            # an identifier has 29 bits: only the mask's low 32 bits can matter, and an id & mask
            # outside [0, 2**32) (huge or negative python ints) can never equal a frame's
            self.masks[i] = <uint32_t>(mask & 0xFFFFFFFF)
            if not 0 <= cid <= 0xFFFFFFFF or not 0 <= mode <= 3:
                self.ids[i], self.modes[i] = 0, 3
            else:
                self.ids[i], self.modes[i] = <uint32_t>cid, <uint8_t>mode

    def __dealloc__(self):
        free(self.ids)
        free(self.masks)
        free(self.modes)

    cdef inline bint _accepts(self, uint32_t aid, bint ext) noexcept nogil:
        cdef Py_ssize_t i
        cdef uint8_t mode
        for i in range(self.n):
            mode = self.modes[i]
            if mode:
                if mode == 3 or (mode == 2) != ext:
                    continue
            if aid & self.masks[i] == self.ids[i]:
                return True
        return False

    def accepts(self, arbitration_id: int, extended: bool) -> bool:
        """python-can's ``_matches_filters`` rule for one frame."""
        return self._accepts(<uint32_t>arbitration_id, bool(extended))


cdef Py_ssize_t _accepted(bytes frames, Filters filters, Py_ssize_t *first):
    """How many slot images in ``frames`` ``filters`` accept; ``first`` gets the index of the
    first of them (-1: none)."""
    cdef Py_ssize_t k = PyBytes_GET_SIZE(frames) // SLOT_BYTES, i, n = 0
    cdef const char *p = PyBytes_AS_STRING(frames)
    cdef uint32_t aid
    first[0] = -1
    for i in range(k):
        memcpy(&aid, p + i * SLOT_BYTES + 8, 4)
        if filters._accepts(aid, (<uint8_t>p[i * SLOT_BYTES + 16]) & M_EXT):
            if n == 0:
                first[0] = i
            n += 1
    return n


cdef bint _has_frame(bytes frames, uint64_t wake_on):
    """Whether ``frames`` hold the frame ``wake_on`` names (``ext << 31 | identifier``)."""
    cdef Py_ssize_t k = PyBytes_GET_SIZE(frames) // SLOT_BYTES, i
    cdef const char *p = PyBytes_AS_STRING(frames)
    cdef uint32_t aid = <uint32_t>(wake_on & 0x1FFFFFFF)
    cdef bint ext = (wake_on >> 31) & 1
    cdef uint32_t a
    for i in range(k):
        memcpy(&a, p + i * SLOT_BYTES + 8, 4)
        if a == aid and (((<uint8_t>p[i * SLOT_BYTES + 16]) & M_EXT) != 0) == ext:
            return True
    return False


cdef class Ring:
    """The ring of one channel mapping: ``buf`` (the ``mmap``, held until :meth:`release`), the
    ring's byte offset and size (slots, a power of two), this bus's sender ``token`` and the
    ``channel`` name its messages carry."""

    cdef Py_buffer view
    cdef bint held
    cdef char *mem
    cdef int64_t off
    cdef uint64_t mask
    cdef int64_t n
    cdef uint32_t token
    cdef object channel

    def __cinit__(self, buf, Py_ssize_t ring_off, Py_ssize_t ring_size, uint32_t token, channel):
        PyObject_GetBuffer(buf, &self.view, PyBUF_WRITABLE)
        self.held = True
        if self.view.len < ring_off + ring_size * SLOT_BYTES or ring_size <= 0 or ring_size & (ring_size - 1):
            PyBuffer_Release(&self.view)
            self.held = False
            raise ValueError("ring geometry does not fit the mapping")
        self.mem = <char *>self.view.buf
        self.off, self.n, self.mask = ring_off, ring_size, <uint64_t>(ring_size - 1)
        self.token = token
        self.channel = channel

    def release(self) -> None:
        """Give the mapping back (before ``mmap.close``); the ring is unusable afterwards."""
        if self.held:
            PyBuffer_Release(&self.view)
            self.held = False
            self.mem = NULL

    def __dealloc__(self):
        if self.held:
            PyBuffer_Release(&self.view)

    cdef inline char *_slot(self, int64_t seq) noexcept nogil:
        return self.mem + self.off + <int64_t>((<uint64_t>seq) & self.mask) * SLOT_BYTES

    cdef int _check(self) except -1:
        if not self.held:
            raise ValueError("the ring was released")
        return 0

    # ------------------------------------------------------------ send side
    def encode(self, msgs, bint preserve_ts, double now) -> bytes:
        """Slot images (``SLOT_BYTES`` each, sequence number not set) of ``msgs``, stamped ``now``
        (s, ``time.time()``) unless ``preserve_ts``.

        :raises can.CanOperationError: too many data bytes, id or dlc out of range.
        """
        cdef Py_ssize_t k = len(msgs), i = 0, ln
        cdef bytes out = PyBytes_FromStringAndSize(NULL, k * SLOT_BYTES)
        cdef char *p = PyBytes_AS_STRING(out)
        cdef char *s
        cdef const char *src
        cdef double ts
        cdef uint32_t aid32
        cdef uint8_t flags, dlc8
        memset(p, 0, k * SLOT_BYTES)
        for m in msgs:
            s = p + i * SLOT_BYTES
            fd = m.is_fd
            data = m.data
            if m.is_remote_frame or data is None:
                data = b""
            elif type(data) is not bytes and type(data) is not bytearray:
                data = bytes(data)
            if type(data) is bytes:
                src, ln = PyBytes_AS_STRING(data), PyBytes_GET_SIZE(data)
            else:
                src, ln = PyByteArray_AS_STRING(data), PyByteArray_GET_SIZE(data)
            if ln > (MAX_DATA if fd else 8):
                raise CanOperationError(
                    f"{'CAN FD' if fd else 'classic CAN'} frame 0x{m.arbitration_id:X} "
                    f"has {ln} data bytes (at most {MAX_DATA if fd else 8})"
                )
            aid, dlc = m.arbitration_id, m.dlc
            if not 0 <= aid <= 0x1FFFFFFF or not 0 <= dlc <= 255:
                raise CanOperationError(f"frame id 0x{aid:X} / dlc {dlc} out of range")
            aid32, dlc8 = aid, dlc
            flags = ((M_EXT if m.is_extended_id else 0) | (M_RTR if m.is_remote_frame else 0)
                     | (M_ERR if m.is_error_frame else 0) | (M_FD if fd else 0)
                     | (M_BRS if m.bitrate_switch else 0) | (M_ESI if m.error_state_indicator else 0))
            ts = m.timestamp if preserve_ts else now
            memcpy(s, &ts, 8)
            memcpy(s + 8, &aid32, 4)
            memcpy(s + 12, &self.token, 4)
            s[16] = <char>flags
            s[17] = <char>dlc8
            s[18] = <char>ln
            if ln:
                memcpy(s + DATA_OFFSET, src, ln)
            i += 1
        return out

    def write(self, bytes frames, int64_t w) -> int:
        """Copy the slot images ``frames`` into seqs ``w, w+1, ...`` (each invalid while it is
        rewritten, then stamped with its sequence number) and publish ``write_seq``; returns
        the new ``write_seq``. The writer lock must be held."""
        self._check()
        cdef Py_ssize_t k = PyBytes_GET_SIZE(frames) // SLOT_BYTES, i
        cdef const char *p = PyBytes_AS_STRING(frames)
        cdef char *s
        for i in range(k):
            s = self._slot(w + i)
            cb_store(s + SLOT_SEQ_OFFSET, SLOT_INVALID)  # per-slot seqlock
            memcpy(s, p + i * SLOT_BYTES, SLOT_SEQ_OFFSET)
            cb_store(s + SLOT_SEQ_OFFSET, <uint64_t>(w + i))
        cb_store(self.mem + WRITE_SEQ_BYTE, <uint64_t>(w + k))  # publish: aligned 8-byte store
        return w + k

    def wake(self, peers, bytes frames, int64_t w) -> list:
        """After :meth:`write` of ``frames`` at seq ``w`` (lock held): clear the *sleeping* flag
        of every sleeping reader in ``peers`` (``(entry word, token, filters or None)``) whose
        filters accept one of the frames and that now has as many accepted frames since it slept
        as it waits for (``E_WANT``, at least 1; counted in ``E_PENDING``), or, if it is woken only
        by one frame (``E_WAKE_ON``), that the frames hold, after storing where the first accepted
        one since it slept is (``wake_seq``) and counting the wake-up; returns their tokens, to be
        woken through their FIFOs once the lock is released. Awake readers find the frames
        themselves."""
        self._check()
        cdef list out = []
        cdef char *e
        cdef int64_t first
        cdef uint64_t pending, n, wake_on
        cdef Py_ssize_t i
        if cb_load(self.mem + SLEEPERS_BYTE) == 0:
            return out
        for b, tok, filt in peers:
            e = self.mem + <int64_t>b * 8
            if not cb_load(e + E_SLEEPING_BYTE):
                continue
            if filt is None:
                i = 0
                n = PyBytes_GET_SIZE(frames) // SLOT_BYTES
            else:
                n = _accepted(frames, <Filters>filt, &i)
                if n == 0:
                    continue
            pending = cb_load(e + E_PENDING_BYTE)
            if pending == 0:  # the first accepted frame since it slept: where it reads from
                cb_store(e + E_WAKE_SEQ_BYTE, <uint64_t>(w + i))
            pending += n
            cb_store(e + E_PENDING_BYTE, pending)
            wake_on = cb_load(e + E_WAKE_ON_BYTE)
            if wake_on:
                if not _has_frame(frames, wake_on):
                    continue  # kept for it (writers do not overwrite them): it reads them when woken
            elif pending < cb_load(e + E_WANT_BYTE):
                continue  # not yet as many as it waits for
            cb_store(e + E_SLEEPING_BYTE, 0)  # after wake_seq: the reader reads them in that order
            cb_store(self.mem + SLEEPERS_BYTE, cb_load(self.mem + SLEEPERS_BYTE) - 1)
            cb_store(e + E_WAKEUPS_BYTE, cb_load(e + E_WAKEUPS_BYTE) + 1)
            out.append(tok)
        return out

    def protected_hit(self, int64_t start, int64_t end, uint32_t token, bint own, Filters filters) -> bool:
        """True if seqs ``start .. end-1`` hold a frame the reader with ``token`` (receiving its
        own frames if ``own``; ``filters`` None accepts all) would be delivered."""
        self._check()
        cdef int64_t seq
        cdef const char *s
        cdef uint32_t aid, stok
        for seq in range(start, end):
            s = self._slot(seq)
            memcpy(&stok, s + 12, 4)
            if stok == token and not own:
                continue  # its own frame: never delivered to it
            if filters is None:
                return True
            memcpy(&aid, s + 8, 4)
            if filters._accepts(aid, (<uint8_t>s[16]) & M_EXT):
                return True
        return False

    def write_seq(self) -> int:
        self._check()
        return cb_load(self.mem + WRITE_SEQ_BYTE)

    # ------------------------------------------------------------ receive side
    def fetch(self, int64_t s, bint own, Filters filters, int mode, out):
        """Append to the list ``out`` every frame published after seq ``s`` that this bus
        accepts (``filters`` None: all; its own frames only if ``own``), as ``can.Message``.

        ``mode``: 0 overrun reader, 1 backpressure reader, 2 protected reader
        (``backpressure="accepted"``: each accepted frame's slot sequence number is checked, a
        frame overwritten while it was copied was one it does not accept).

        :returns: ``None`` if nothing was published after ``s``, else ``(seq, lost, passed)``:
            the new read position, frames overwritten unread (overrun; the frames after the loss
            are in ``out``), and (protected reader) frames it does not accept that went by unseen.
        """
        self._check()
        cdef int64_t w = <int64_t>cb_load(self.mem + WRITE_SEQ_BYTE)
        if w == s:
            return None
        cdef bint protect = mode == 2
        cdef int64_t slack = 0 if mode else 1
        cdef int64_t start = max(s, w - self.n + slack)
        cdef int64_t seq, valid_from, lost = 0, passed = 0
        cdef const char *p
        cdef double ts
        cdef uint32_t aid, tok
        cdef uint8_t flags, dlc, ln
        cdef bint is_rx
        cdef Py_ssize_t first = len(out), i, cut
        cdef list seqs = []
        channel = self.channel
        for seq in range(start, w):
            p = self._slot(seq)
            memcpy(&tok, p + 12, 4)
            if tok == self.token:
                if not own:
                    continue
                is_rx = False
            else:
                is_rx = True
            memcpy(&aid, p + 8, 4)
            flags = <uint8_t>p[16]
            if filters is not None and not filters._accepts(aid, flags & M_EXT):
                continue
            memcpy(&ts, p, 8)
            dlc = <uint8_t>p[17]
            ln = <uint8_t>p[18]
            if ln > MAX_DATA:
                ln = MAX_DATA
            data = PyByteArray_FromStringAndSize(p + DATA_OFFSET, ln)
            if protect and cb_load(p + SLOT_SEQ_OFFSET) != <uint64_t>seq:
                continue  # overwritten while we looked: it was a frame we do not accept
            out.append(_message(ts, aid, flags & 63, dlc, data, channel, is_rx))
            seqs.append(seq)
        # seqlock-style check: a slot may have been overwritten while we copied it
        valid_from = <int64_t>cb_load(self.mem + WRITE_SEQ_BYTE) - self.n + slack
        if protect:
            if valid_from > s:  # frames it does not accept went by unseen: no loss, as on a CAN filter
                passed = valid_from - s
        elif valid_from > s:
            lost = valid_from - s
            cut = 0
            for i in range(len(seqs)):
                if <int64_t>seqs[i] < valid_from:
                    cut += 1
            if cut:
                del out[first : first + cut]
            w = max(w, valid_from)
        return w, lost, passed
