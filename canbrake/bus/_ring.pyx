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
from cpython.bytearray cimport (PyByteArray_FromStringAndSize, PyByteArray_AS_STRING, PyByteArray_GET_SIZE,
                                PyByteArray_Resize)
from cpython.bytes cimport PyBytes_AS_STRING, PyBytes_GET_SIZE, PyBytes_FromStringAndSize
from cpython.buffer cimport PyObject_GetBuffer, PyBuffer_Release, PyBUF_WRITABLE, PyBUF_SIMPLE
from cpython.object cimport PyObject
from cpython.ref cimport Py_INCREF
from libc.stdint cimport uint8_t, uint32_t, uint64_t, int64_t
from libc.stdlib cimport malloc, free
from libc.string cimport memcpy, memset, memmove, strerror
from libc.errno cimport errno, EINTR, EAGAIN
from posix.unistd cimport read as c_read, write as c_write
from posix.time cimport clock_gettime, timespec, CLOCK_MONOTONIC

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

cdef extern from "<sys/file.h>" nogil:
    int flock(int fd, int op)
    int LOCK_EX
    int LOCK_NB
    int LOCK_UN

cdef extern from "<poll.h>" nogil:
    struct pollfd:
        int fd
        short events
        short revents
    int poll(pollfd *fds, unsigned long nfds, int timeout)
    # (Linux, _GNU_SOURCE as Python.h sets it): a timeout in ns, where poll's is whole ms
    int ppoll(pollfd *fds, unsigned long nfds, const timespec *tmo_p, const void *sigmask)
    short POLLIN

cdef extern from "<sched.h>" nogil:
    int sched_yield()

cdef extern from "Python.h":
    int PyErr_CheckSignals() except -1

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

# ---- the slot format (canbrake.bus._slot: memory_shm's SLOT_HEAD "<dIIBBBB", data at 24, sequence number at 88)
from canbrake.bus._slot cimport SLOT_BYTES, DATA_OFFSET, MAX_DATA
DEF SLOT_SEQ_OFFSET = 88
DEF WRITE_SEQ_BYTE = 64        # header word H_WRITE_SEQ (8)
DEF SLEEPERS_BYTE = 160        # header word H_SLEEPERS (20)
DEF E_SLEEPING_BYTE = 72       # reader-entry words E_SLEEPING (9), E_WAKE_SEQ (10), E_WAKEUPS (11)
DEF E_WAKE_SEQ_BYTE = 80
DEF E_WAKEUPS_BYTE = 88
DEF E_WANT_BYTE = 104          # E_WANT (13): accepted frames a sleeping reader waits for
DEF E_PENDING_BYTE = 112       # E_PENDING (14): accepted frames published since it slept
DEF E_WAKE_ON_BYTE = 120       # E_WAKE_ON (15): 0, or 1 << 40 | ext << 31 | id: only that frame wakes it
DEF READER_GEN_BYTE = 128      # header word H_READER_GEN (16)
DEF TX_WAITERS_BYTE = 144      # header word H_TX_WAITERS (18)
DEF CLOSED_BYTE = 152          # header word H_CLOSED (19)
DEF E_READ_SEQ_BYTE = 64       # E_READ_SEQ (8)
DEF M_EXT = 1
DEF M_RTR = 2
DEF M_ERR = 4
DEF M_FD = 8
DEF M_BRS = 16
DEF M_ESI = 32
cdef uint64_t SLOT_INVALID = 0xFFFFFFFFFFFFFFFFULL

# Before a reader blocks, it yields the CPU and looks again, while a yield hands the CPU to
# another process (it took at least YIELD_RAN_S: someone ran) and for at most YIELD_BUDGET_S
# since the wait began, at most YIELD_MAX times. With more node processes than cores, a lockstep
# node's frames are then usually there without a sleep: a sleep costs a voluntary switch, the
# writer's FIFO write and a (cross-core) wake-up. A yield that comes straight back (nobody else
# runnable on this CPU, ~0.5-1 us) ends it at once, so an idle CPU is not spun on; the budget
# ends it when the CPU is shared with other work (a yield to a CPU-bound process lasts its time
# slice) or the frames are far off. Chen case 1 with one process per ECU on 2 cores: one yield
# ~3,700 periods/s (27 switches a period), this rule 5,300-6,800 (docs/performance.md, session 24).
DEF YIELD_MAX = 8
DEF YIELD_RAN_S = 3e-6
DEF YIELD_BUDGET_S = 200e-6


cdef bint _yield_more(double t0) noexcept nogil:
    """``sched_yield`` in a wait that began at ``t0`` (monotonic s); True when looking again and
    yielding again is worth it: another process ran meanwhile and the budget is not spent."""
    cdef double t1 = _monotonic(), t2
    sched_yield()
    t2 = _monotonic()
    return t2 - t1 >= YIELD_RAN_S and t2 - t0 < YIELD_BUDGET_S


def yield_cpu(double t0) -> bool:
    """One yield of the memory bus's wait that began at ``t0`` (``time.monotonic`` s; at most
    :data:`YIELD_LIMIT` yields before it sleeps): ``sched_yield``; True when another process ran
    meanwhile and less than 200 us have passed since ``t0``, so that looking again and yielding
    again is worth it; False when it came straight back (nothing else to run on this CPU) or the
    budget is spent."""
    return _yield_more(t0)


YIELD_LIMIT = YIELD_MAX
#: the slot format compiled in, checked against memory_shm's layout by memory.py at import
LAYOUT = {"SLOT_BYTES": SLOT_BYTES, "DATA_OFFSET": DATA_OFFSET, "MAX_DATA": MAX_DATA,
          "SLOT_SEQ_OFFSET": SLOT_SEQ_OFFSET, "H_WRITE_SEQ": WRITE_SEQ_BYTE // 8,
          "H_SLEEPERS": SLEEPERS_BYTE // 8, "E_SLEEPING": E_SLEEPING_BYTE // 8,
          "E_WAKE_SEQ": E_WAKE_SEQ_BYTE // 8, "E_WAKEUPS": E_WAKEUPS_BYTE // 8,
          "E_WANT": E_WANT_BYTE // 8, "E_PENDING": E_PENDING_BYTE // 8, "E_WAKE_ON": E_WAKE_ON_BYTE // 8,
          "H_TX_WAITERS": TX_WAITERS_BYTE // 8, "H_READER_GEN": READER_GEN_BYTE // 8, "H_CLOSED": CLOSED_BYTE // 8, "E_READ_SEQ": E_READ_SEQ_BYTE // 8}

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


cdef object msg_get(object m, int i):
    """Field ``i`` (``_SLOTS``' order, ``_ring.pxd``'s ``MSG_*``) of the message ``m``: read from
    its slot where ``m`` is a python-can ``Message`` with the known slots (an attribute lookup
    through the member descriptor costs ~30 ns, the read ~2; the in-process engine reads a few
    fields of every frame in several places), else ``getattr``."""
    cdef PyObject* v
    if _DIRECT and type(m) is Message:
        v = (<PyObject**>((<char*><PyObject*>m) + _OFF[i]))[0]
        if v is not NULL:
            return <object>v
    return getattr(m, _SLOTS[i])


def message_field(m, int i):
    """:func:`msg_get` for Python (the tests)."""
    return msg_get(m, i)


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


def messages_of(images) -> list:
    """The ``can.Message`` of each slot image in ``images`` (bytes-like, ``SLOT_BYTES`` each) as
    a node's send path makes it: its time stamp, identifier, flags, DLC and data, received, no
    channel. Images of ``canbrake.bus._slot.slot_put`` give ``data_frame(identifier, data)``'s
    messages: the nodes that encode their frames as images (``canbrake.bus._codec.TickFrames``)
    hand these to buses other than the memory bus."""
    cdef const uint8_t[::1] v = images
    cdef Py_ssize_t k = v.shape[0] // SLOT_BYTES, i
    cdef const uint8_t* p
    cdef double ts
    cdef uint32_t aid
    cdef uint8_t ln
    cdef list out = []
    for i in range(k):
        p = &v[i * SLOT_BYTES]
        memcpy(&ts, p, 8)
        memcpy(&aid, p + 8, 4)
        ln = p[18] if p[18] <= MAX_DATA else MAX_DATA
        out.append(_message(ts, aid, p[16] & 63, p[17],
                            PyByteArray_FromStringAndSize(<const char*>p + DATA_OFFSET, ln), None, True))
    return out


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
    # ---- the reader (attach): memory.py's receive state lives here, read by both paths
    #: this bus's read position (the next seq it has not looked at)
    cdef public int64_t seq
    #: a wake-up byte of a past sleep may still sit in the reader's FIFO
    cdef public bint fifo_dirty
    #: a receive is blocked (or about to block) in this bus
    cdef public bint in_recv
    #: the acceptance filters (None: every frame)
    cdef public Filters filters
    cdef int64_t e_off         # the reader entry's byte offset (-1: not attached)
    cdef int lock_fd, rx_fd
    cdef int rmode             # 0 overrun, 1 backpressure, 2 protected reader
    cdef bint own, yield_first
    cdef object tlock, publish
    #: recv_raw's counters: sleeps, wake-ups that found nothing, (protected) frames passed unseen
    cdef readonly int64_t n_sleeps, n_spurious, n_passed
    #: recv_raw's last result: 0 frames (or the timeout), 1 frames were lost (``lost`` of them,
    #: the frames before byte ``lost_at`` of its result were read before the loss), 2 closed
    cdef readonly int status
    cdef readonly int64_t lost, lost_at

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
        self.e_off = -1
        self.lock_fd = self.rx_fd = -1

    def attach(self, int64_t entry_word, int lock_fd, int rx_fd, tlock, publish, int mode, bint own,
               bint yield_first):
        """Make this the receive side of a bus (:meth:`recv_raw`): its reader entry (first word),
        the channel file's descriptor (the writer lock, ``flock``) and the thread lock taken with
        it, its wake-up FIFO, ``publish()`` (publishes the read position when senders wait for
        it), the reader ``mode`` (0 overrun, 1 backpressure, 2 protected), whether it receives
        its own frames and yields the CPU before sleeping (see YIELD_MAX)."""
        self._check()
        self.e_off = entry_word * 8
        self.lock_fd, self.rx_fd = lock_fd, rx_fd
        self.tlock, self.publish = tlock, publish
        self.rmode, self.own, self.yield_first = mode, own, yield_first

    def release(self) -> None:
        """Give the mapping back (before ``mmap.close``); the ring is unusable afterwards."""
        self.publish = self.tlock = None  # (a bound method of the bus: no cycle kept)
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

    def stamp(self, images, bint preserve_ts, double now) -> bytes:
        """:meth:`encode` for frames already encoded as slot images (``canbrake.bus._slot``:
        ``images``, bytes-like, ``SLOT_BYTES`` each): a copy with this bus's sender token, stamped
        ``now`` (s, ``time.time()``) unless ``preserve_ts``.

        :raises can.CanOperationError: too many data bytes, id out of range (as :meth:`encode`).
        """
        cdef const uint8_t[::1] v = images
        cdef Py_ssize_t k = v.shape[0] // SLOT_BYTES, i
        if v.shape[0] != k * SLOT_BYTES:
            raise ValueError(f"{v.shape[0]} bytes are not whole slot images of {SLOT_BYTES}")
        cdef bytes out = PyBytes_FromStringAndSize(NULL, k * SLOT_BYTES)
        cdef char *p = PyBytes_AS_STRING(out)
        cdef char *s
        cdef uint32_t aid
        cdef uint8_t ln, flags
        if k:
            memcpy(p, &v[0], k * SLOT_BYTES)
        for i in range(k):
            s = p + i * SLOT_BYTES
            memcpy(&aid, s + 8, 4)
            flags = <uint8_t>s[16]
            ln = <uint8_t>s[18]
            if ln > (MAX_DATA if flags & M_FD else 8):
                raise CanOperationError(
                    f"{'CAN FD' if flags & M_FD else 'classic CAN'} frame 0x{aid:X} "
                    f"has {ln} data bytes (at most {MAX_DATA if flags & M_FD else 8})"
                )
            if aid > 0x1FFFFFFF:
                raise CanOperationError(f"frame id 0x{aid:X} / dlc {<uint8_t>s[17]} out of range")
            if not preserve_ts:
                memcpy(s, &now, 8)
            memcpy(s + 12, &self.token, 4)
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

    def send_fast(self, bytes frames, int64_t peers_gen, list bp, pr_floor, list peers, dict wake_fds):
        """A burst's way onto the ring when nothing holds it back, in one call (memory.py's
        ``_send_frames`` does the rest): under the writer lock, if the reader table is still
        generation ``peers_gen``, no backpressure reader in ``bp`` (entry words) would be
        overrun and no protected reader could be (``pr_floor``: the lowest position of one, None:
        there is none), write the slot images ``frames``, skip this reader past its own frames
        (as ``_send_frames``), mark the sleeping ``peers`` that accept them (:meth:`wake`); then,
        unlocked, write a wake-up byte to each one's FIFO found in ``wake_fds`` ((token, "rx") ->
        fd). Returns the tokens still to wake (no FIFO open yet, or a write that failed), or None
        if it did nothing (the channel closed, the readers changed, or a reader in the way)."""
        self._check()
        cdef int64_t k = PyBytes_GET_SIZE(frames) // SLOT_BYTES, w, pos, b
        cdef char *e
        cdef list wake
        cdef list rest = []
        cdef ssize_t r
        cdef char one = 1
        self._lock()
        try:
            if cb_load(self.mem + CLOSED_BYTE) or <int64_t>cb_load(self.mem + READER_GEN_BYTE) != peers_gen:
                return None
            w = <int64_t>cb_load(self.mem + WRITE_SEQ_BYTE)
            for bo in bp:
                b = bo
                e = self.mem + b * 8
                if cb_load(e + E_SLEEPING_BYTE):
                    pos = <int64_t>cb_load(e + E_WAKE_SEQ_BYTE) if cb_load(e + E_PENDING_BYTE) else w
                else:
                    pos = max(<int64_t>cb_load(e + E_READ_SEQ_BYTE), <int64_t>cb_load(e + E_WAKE_SEQ_BYTE))
                if w + k - pos > self.n:
                    return None
            if pr_floor is not None and w + k - self.n > <int64_t>pr_floor:
                return None
            self.write(frames, w)
            if not self.own and not self.in_recv and self.seq == w and self.e_off >= 0:
                # our reader is caught up and never receives its own frames: skip them
                self.seq = w + k
                cb_store(self.mem + self.e_off + E_READ_SEQ_BYTE, <uint64_t>(w + k))
            wake = self.wake(peers, frames, w)
        finally:
            self._unlock()
        for tok in wake:
            fd = wake_fds.get((tok, "rx"))
            if fd is None:
                rest.append(tok)
                continue
            r = c_write(<int>fd, &one, 1)
            if r < 0 and errno != EAGAIN:  # (EAGAIN: the FIFO is full, a wake-up is pending anyway)
                rest.append(tok)
        return rest

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

    # ------------------------------------------------------------ the node path: slot images
    cdef int _lock(self) except -1:
        """The writer lock (``flock``) and the bus's thread lock, as memory.py's ``_lock``; a lock
        held by another process is waited for without the GIL (its holder may be a thread of
        this process that needs the GIL to release it)."""
        cdef int r
        self.tlock.acquire()
        if flock(self.lock_fd, LOCK_EX | LOCK_NB) == 0:
            return 0
        while True:
            with nogil:
                r = flock(self.lock_fd, LOCK_EX)
            if r == 0:
                break
            if errno != EINTR:
                self.tlock.release()
                _os_error()
            try:
                PyErr_CheckSignals()
            except BaseException:
                self.tlock.release()
                raise
        return 0

    cdef int _unlock(self) except -1:
        cdef int r = flock(self.lock_fd, LOCK_UN)
        self.tlock.release()
        if r != 0:
            _os_error()
        return 0

    cdef bint _drain_fifo(self) except -1:
        cdef char b[4096]
        cdef ssize_t r
        while True:
            r = c_read(self.rx_fd, b, 4096)
            if r >= 0:
                return r > 0
            if errno == EINTR:
                PyErr_CheckSignals()
                continue
            if errno == EAGAIN:
                return False
            _os_error()

    cdef int _fetch_raw(self, bytearray acc) except -1:
        """Append the slot images of every new frame this reader accepts to ``acc`` (the slot's
        sequence word holds its seq) and move ``seq``; 0 nothing new, 1 fetched, 2 frames were
        lost (``lost``, ``lost_at``: where this fetch's frames begin), 3 the channel is closed."""
        if cb_load(self.mem + CLOSED_BYTE):
            return 3
        cdef int64_t s = self.seq
        cdef int64_t w = <int64_t>cb_load(self.mem + WRITE_SEQ_BYTE)
        if w == s:
            return 0
        cdef bint protect = self.rmode == 2
        cdef int64_t slack = 0 if self.rmode else 1
        cdef int64_t start = max(s, w - self.n + slack)
        cdef Py_ssize_t base = PyByteArray_GET_SIZE(acc), k = 0, cut = 0
        cdef int64_t seq, valid_from, lost = 0, sq
        cdef const char *p
        cdef char *dst
        cdef uint32_t aid, tok
        cdef Filters filters = self.filters
        PyByteArray_Resize(acc, base + (w - start) * SLOT_BYTES)
        dst = PyByteArray_AS_STRING(acc) + base
        for seq in range(start, w):
            p = self._slot(seq)
            memcpy(&tok, p + 12, 4)
            if tok == self.token and not self.own:
                continue
            if filters is not None:
                memcpy(&aid, p + 8, 4)
                if not filters._accepts(aid, (<uint8_t>p[16]) & M_EXT):
                    continue
            memcpy(dst + k * SLOT_BYTES, p, SLOT_SEQ_OFFSET)
            if protect and cb_load(p + SLOT_SEQ_OFFSET) != <uint64_t>seq:
                continue  # overwritten while we looked: it was a frame we do not accept
            memcpy(dst + k * SLOT_BYTES + SLOT_SEQ_OFFSET, &seq, 8)
            k += 1
        # seqlock-style check: a slot may have been overwritten while we copied it
        valid_from = <int64_t>cb_load(self.mem + WRITE_SEQ_BYTE) - self.n + slack
        if protect:
            if valid_from > s:  # frames it does not accept went by unseen: no loss, as on a CAN filter
                self.n_passed += valid_from - s
        elif valid_from > s:
            lost = valid_from - s
            while cut < k:
                memcpy(&sq, dst + cut * SLOT_BYTES + SLOT_SEQ_OFFSET, 8)
                if sq >= valid_from:
                    break
                cut += 1
            if cut:
                memmove(dst, dst + cut * SLOT_BYTES, (k - cut) * SLOT_BYTES)
                k -= cut
            w = max(w, valid_from)
        PyByteArray_Resize(acc, base + k * SLOT_BYTES)
        self.seq = w
        if self.rmode == 0 or not cb_load(self.mem + TX_WAITERS_BYTE):
            cb_store(self.mem + self.e_off + E_READ_SEQ_BYTE, <uint64_t>w)  # see memory.py
        else:
            self.publish()
        if lost:
            self.lost, self.lost_at = lost, base
            return 2
        return 1

    cdef int _sleep_raw(self, double deadline) except -1:
        """memory.py's ``_sleep``: block until a writer wakes this reader or ``deadline``
        (monotonic s; < 0 never) passes, then position ``seq``."""
        cdef char *e = self.mem + self.e_off
        cdef bint got_byte = False, events
        cdef pollfd pfd
        cdef int r
        cdef double left
        cdef timespec tmo
        cdef timespec *tp
        while True:
            if deadline < 0:
                tp = NULL
            else:
                left = deadline - _monotonic()
                if left <= 0:
                    break
                # to the deadline itself: poll's whole milliseconds would wake a realtime node up
                # to 1 ms late (a 0.3 ms wait rounded up to 1 ms: a missed 1 ms period)
                tmo.tv_sec = <long>left
                tmo.tv_nsec = <long>((left - <double>tmo.tv_sec) * 1e9) + 1
                if tmo.tv_nsec >= 1000000000:
                    tmo.tv_sec += 1
                    tmo.tv_nsec -= 1000000000
                tp = &tmo
            pfd.fd, pfd.events, pfd.revents = self.rx_fd, POLLIN, 0
            with nogil:
                r = ppoll(&pfd, 1, tp, NULL)
            if r < 0:
                if errno != EINTR:
                    _os_error()
                PyErr_CheckSignals()
                continue
            events = r > 0
            if events:
                got_byte = self._drain_fifo() or got_byte
            if not cb_load(e + E_SLEEPING_BYTE):
                # woken: the writer stored wake_seq before clearing the flag
                self.seq = max(self.seq, <int64_t>cb_load(e + E_WAKE_SEQ_BYTE))
                self.fifo_dirty = not got_byte
                return 0
            if cb_load(self.mem + CLOSED_BYTE):
                break
            if events:
                self.n_spurious += 1
        self._lock()
        try:
            if cb_load(e + E_SLEEPING_BYTE):  # never woken: nothing, or fewer frames than it waits for
                cb_store(e + E_SLEEPING_BYTE, 0)
                cb_store(self.mem + SLEEPERS_BYTE, cb_load(self.mem + SLEEPERS_BYTE) - 1)
                self.seq = max(self.seq, <int64_t>(cb_load(e + E_WAKE_SEQ_BYTE) if cb_load(e + E_PENDING_BYTE)
                                                   else cb_load(self.mem + WRITE_SEQ_BYTE)))
            else:  # woken just now: its byte may still be on its way
                self.seq = max(self.seq, <int64_t>cb_load(e + E_WAKE_SEQ_BYTE))
                self.fifo_dirty = True
        finally:
            self._unlock()
        return 0

    def sleep(self, deadline) -> None:
        """memory.py's ``_sleep`` (the reader marked sleeping under the writer lock): block until
        a writer wakes this reader or ``deadline`` (``time.monotonic`` s, None: never) passes,
        then position ``seq`` (:meth:`_sleep_raw`)."""
        self._check()
        if self.e_off < 0:
            raise ValueError("the ring has no reader attached")
        self._sleep_raw(-1.0 if deadline is None else <double>deadline)

    cdef int _wait_raw(self, bytearray acc, double deadline, bint poll_only, int64_t want) except -1:
        """memory.py's ``_recv_locked`` for slot images: fetch, else (unless ``poll_only``) yield
        (see YIELD_MAX), then sleep until ``want`` accepted frames have come or ``deadline``; the
        :meth:`_fetch_raw` result (0: the timeout)."""
        cdef Py_ssize_t before = PyByteArray_GET_SIZE(acc)
        cdef int r = self._fetch_raw(acc)
        cdef bint idle, ran
        cdef double t_w
        cdef int k
        cdef char *e = self.mem + self.e_off
        if r >= 2 or PyByteArray_GET_SIZE(acc) > before:
            return r
        if poll_only:
            return 0
        self.in_recv = True
        try:
            if self.yield_first:  # let runnable peers on this CPU produce first: often no sleep needed
                t_w = _monotonic()
                for k in range(YIELD_MAX):
                    ran = _yield_more(t_w)
                    r = self._fetch_raw(acc)
                    if r >= 2 or PyByteArray_GET_SIZE(acc) > before:
                        return r
                    if not ran:  # nobody else to run here, or the budget spent: sleep (see YIELD_MAX)
                        break
            while True:
                if self.fifo_dirty:  # a wake-up byte may still be on its way from a past sleep
                    self._drain_fifo()
                    self.fifo_dirty = False
                self._lock()
                try:
                    idle = <int64_t>cb_load(self.mem + WRITE_SEQ_BYTE) == self.seq
                    if idle:
                        cb_store(e + E_WANT_BYTE, <uint64_t>want)
                        cb_store(e + E_PENDING_BYTE, 0)
                        cb_store(e + E_SLEEPING_BYTE, 1)
                        cb_store(self.mem + SLEEPERS_BYTE, cb_load(self.mem + SLEEPERS_BYTE) + 1)
                finally:
                    self._unlock()
                if idle:
                    self.n_sleeps += 1
                    try:
                        self._sleep_raw(deadline)
                    except BaseException:
                        self.fifo_dirty = True
                        self._lock()
                        try:
                            if cb_load(e + E_SLEEPING_BYTE):
                                cb_store(e + E_SLEEPING_BYTE, 0)
                                cb_store(self.mem + SLEEPERS_BYTE, cb_load(self.mem + SLEEPERS_BYTE) - 1)
                        finally:
                            self._unlock()
                        raise
                r = self._fetch_raw(acc)
                if r >= 2 or PyByteArray_GET_SIZE(acc) > before:
                    return r
                if deadline >= 0 and _monotonic() >= deadline:
                    return 0
        finally:
            self.in_recv = False

    def recv_raw(self, double timeout, int64_t min_frames=1) -> bytearray:
        """The node path of ``MemoryBus.recv_batch``: the slot images (``SLOT_BYTES`` each, see
        :func:`slot_frame`) of every accepted frame pending, oldest first; if fewer than
        ``min_frames`` (capped at half the ring) are, sleep until they have come (the writers
        count them) or ``timeout`` s (< 0: forever, 0: poll) have passed. ``status`` says how it
        ended (see there); the caller raises for a loss or a closed channel."""
        self._check()
        if self.e_off < 0:
            raise ValueError("the ring has no reader attached")
        cdef bytearray acc = bytearray()
        cdef double deadline = -1.0 if timeout < 0 else _monotonic() + timeout
        cdef int64_t want = max(1, min(min_frames, self.n // 2)), got
        cdef int r = self._fetch_raw(acc)
        self.status = 0
        while r < 2:
            got = PyByteArray_GET_SIZE(acc) // SLOT_BYTES
            if got >= want:
                return acc
            r = self._wait_raw(acc, deadline, timeout == 0, want - got)
            if r == 0:  # the timeout
                return acc
        self.status = r - 1
        return acc

    def fetch_raw(self, bytearray acc) -> int:
        """Append the slot images of the new frames this reader accepts to ``acc``, without
        waiting: 0 nothing new, 1 fetched, 2 frames were lost (``lost``, ``lost_at``), 3 closed."""
        self._check()
        if self.e_off < 0:
            raise ValueError("the ring has no reader attached")
        return self._fetch_raw(acc)

    def message(self, frames, Py_ssize_t i):
        """Slot image ``i`` of ``frames`` (:meth:`recv_raw`) as the ``can.Message`` the bus's
        ``recv`` gives for it."""
        cdef const uint8_t[::1] v = frames
        if i < 0 or (i + 1) * SLOT_BYTES > v.shape[0]:
            raise IndexError(f"slot image {i} of {v.shape[0] // SLOT_BYTES}")
        cdef const char *p = <const char *>&v[i * SLOT_BYTES]
        cdef double ts
        cdef uint32_t aid, tok
        cdef uint8_t ln = <uint8_t>p[18]
        memcpy(&ts, p, 8)
        memcpy(&aid, p + 8, 4)
        memcpy(&tok, p + 12, 4)
        if ln > MAX_DATA:
            ln = MAX_DATA
        return _message(ts, aid, (<uint8_t>p[16]) & 63, <uint8_t>p[17],
                        PyByteArray_FromStringAndSize(p + DATA_OFFSET, ln), self.channel, tok != self.token)

    def messages(self, frames) -> list:
        """Every slot image of ``frames`` as :meth:`message` gives it."""
        return [self.message(frames, i) for i in range(len(frames) // SLOT_BYTES)]


cdef int _os_error() except -1:
    cdef int e = errno
    raise OSError(e, strerror(e).decode())


cdef inline double _monotonic() noexcept nogil:
    cdef timespec t
    clock_gettime(CLOCK_MONOTONIC, &t)
    return <double>t.tv_sec + <double>t.tv_nsec * 1e-9


def slot_frame(frames, Py_ssize_t i):
    """``(arbitration_id, extended, data)`` of slot image ``i`` of ``frames`` (tests, tools)."""
    cdef const uint8_t[::1] v = frames
    if i < 0 or (i + 1) * SLOT_BYTES > v.shape[0]:
        raise IndexError(f"slot image {i} of {v.shape[0] // SLOT_BYTES}")
    cdef const char *p = <const char *>&v[i * SLOT_BYTES]
    cdef uint32_t aid
    memcpy(&aid, p + 8, 4)
    cdef uint8_t ln = min(<uint8_t>p[18], MAX_DATA)
    return aid, bool((<uint8_t>p[16]) & M_EXT), bytes(p[DATA_OFFSET:DATA_OFFSET + ln])
