"""The default canbrake bus: an in-memory, cross-process CAN bus, python-can interface ``canbrake``.

    with can.Bus(interface="canbrake", channel="train0") as bus:   # any process on this machine
        bus.send(can.Message(arbitration_id=0x123, data=b"\\x01", is_extended_id=False))

``python -m can.logger -i canbrake -c train0`` and ``python -m can.player -i canbrake -c train0 f.log``
work as on any python-can interface. Loopback only: shared memory and FIFOs, no network.

Design
  * One shared ring per channel (``/dev/shm/canbrake-<channel>.bus``, see
    :mod:`canbrake.bus.memory_shm`). A sender takes the writer lock (``flock``, released by the
    kernel if the process dies), copies its frame(s) into the ring and publishes ``write_seq``
    with an aligned 8-byte store. The ring is the bus medium: every reader sees one global
    order, so runs are reproducible.
  * Each bus registers a reader entry with its filters (pushed down by ``_apply_filters``).
    A reader with nothing to read marks itself *sleeping* under the writer lock (after
    re-checking ``write_seq`` under that lock) and blocks in ``ppoll`` on its own FIFO. A writer,
    under the same lock, clears the flag of each sleeping reader whose filters accept one of its
    frames, records where that frame is (``wake_seq``) and, after unlocking, writes one byte to
    that reader's FIFO. Check-and-sleep and publish-and-wake are both done under the one lock and
    the FIFO keeps the byte until it is read, so a wake-up cannot be lost; a frame that a
    reader's filters reject never wakes it; a burst wakes a sleeping reader once.
  * A reader may ask to sleep until n frames it accepts have come (``recv_batch(min_frames=n)``,
    ``E_WANT``): the writers count them (``E_PENDING``) and wake it at the n-th, so a lockstep
    node that needs every ECU's frame before it can go on is woken once, not at each frame;
    or to be woken by one identifier alone (``wake_on``, ``E_WAKE_ON``: the lockstep recorder,
    by SYNC). Either way the frames it accepts while it sleeps stay unread for the writers (its
    position is its ``wake_seq``), and a writer they hold back wakes it to read them.
  * Frames that went by while a reader slept were checked against its filters by the writers,
    so on waking it starts at ``wake_seq`` (or at ``write_seq`` after a timeout) and never
    scans, or overruns on, traffic it does not want.
  * Before blocking, ``recv`` yields the CPU (``sched_yield``; ``yield_before_sleep``) and looks
    again, while a yield hands the CPU to another process, for at most 200 us and 8 yields: with
    more node processes than cores, the frames are usually there by then, which saves the
    expensive sleep and cross-core wake-up. A yield that comes straight back (nothing else
    runnable on that CPU) ends it: an idle CPU is not spun on.

Slow readers (choice: per bus, default overrun)
  * ``backpressure=False`` (default, like a CAN controller's receive FIFO): writers never wait.
    A reader that falls a whole ring (``ring_size`` frames, default 16384) behind loses the
    oldest frames; its next ``recv`` raises :class:`BusOverrunError` (a ``can.CanOperationError``) saying how many
    were lost (also in :meth:`MemoryBus.stats`), then continues with the oldest frame still in
    the ring. Frames are never dropped silently.
  * ``backpressure="accepted"`` (for lockstep nodes, which must see every frame they filter
    for, but need not slow down for frames they filter out — as a CAN controller's acceptance
    filter keeps a flood on other identifiers out of its receive FIFO): a writer waits, as for
    ``backpressure=True``, only when it would overwrite a frame this reader *accepts* and has not
    read yet; frames it does not accept are overwritten freely and never raise an overrun. A
    flood on identifiers the node filters out then costs it nothing; a flood on identifiers it
    accepts is held back to the pace at which the node reads (and counted by the node's checks).
    A writer blocked this way keeps copying its own bus's accepted frames into its local queue
    while it waits, so two such nodes can never wait for each other.
  * ``backpressure=True`` (for recorders that must see every frame): a writer that would
    overwrite a frame this reader has not read waits (blocking, woken by the reader; in a rare race, after one 0.1 s wait slice) for up to
    ``send`` ``timeout`` or else ``send_timeout`` seconds, then raises
    :class:`can.CanTimeoutError` naming the slow reader's pid. Every wait slice (0.1 s) checks
    whether that reader's process is still alive; a dead one is reaped and the writer goes on.

Lifecycle: the first bus on a channel creates its file (and fixes its ``ring_size``), the last
``shutdown`` removes it.
Entries of crashed processes are found by pid and process start time and reaped (on open,
shutdown, a failed wake-up, a blocked send, :func:`channel_pids`, :func:`remove_channel`).
:func:`remove_channel` cleans up after a run. A bus must not be used across ``fork()``: open a
new one in the child (``spawn`` start method is fine). Any thread may send; one thread at a
time may receive (python-can's ``Notifier`` thread is fine).

Memory ordering relies on x86-64's total store order for the lock-free reads of ``write_seq``
and the frame slots (readers re-check ``write_seq`` after copying, a seqlock-style check).

Compiled part (:mod:`canbrake.bus._ring`, one implementation): the slot write of a burst and its
wake-up bookkeeping (which sleeping readers' filters accept it), the fetch loop (token and filter
checks, seqlock checks, the ``can.Message`` objects) and the filters themselves. The lock, the
FIFO wake-ups, backpressure policy, errors and counters are here. A FIFO byte costs no more than a
futex wake between two processes (measured, ~5 us of CPU per side per round trip either way: the
cost is the context switch), so the wake-up stays a FIFO, which any process can open by name.

:meth:`MemoryBus.recv_batch` hands a reader every accepted frame pending in one list (what
repeated :meth:`MemoryBus.recv_filtered` calls would return, overrun errors at the same place).

The node path (a lockstep ECU, the plant and the recorder, :func:`canbrake.nodes.driver.drive`
to any node with ``handle_raw``): :meth:`MemoryBus.recv_raw`
is ``recv_batch`` done in one compiled call (:meth:`canbrake.bus._ring.Ring.recv_raw`: the
fetch, the filters, the yield, the sleep under the writer lock, ``ppoll`` and the FIFO drain)
that returns the frames as slot images, which the ECU's and the plant's compiled feeds
(``PeerTable.feed_raw``, ``CommandTable.take_batch_raw``) read without a ``can.Message`` per
frame (the recorder makes one per frame, :meth:`MemoryBus.raw_message`); the read position and the FIFO state live in the ring for both ways
of reading. A send that no reader holds back and that finds the reader table unchanged is one
compiled call too (:meth:`~canbrake.bus._ring.Ring.send_fast`: lock, the backpressure checks,
write, wake-up marks, FIFO bytes); anything else (a reader in the way, new readers, a FIFO not
yet open, errors) takes the Python path below.
"""
from __future__ import annotations

import atexit
import collections
import fcntl
import math
import mmap
import os
import select
import sys
import threading
import time
import weakref
from collections.abc import Iterable, Sequence
from dataclasses import dataclass
from typing import Any, Optional

from can import BusABC, BusState, CanProtocol, Message
from can.exceptions import CanInitializationError, CanOperationError, CanTimeoutError
from can.typechecking import AutoDetectedConfig, CanFilters

from canbrake.bus import memory_shm as shm
from canbrake.bus._ring import LAYOUT as _RING_LAYOUT
from canbrake.bus._ring import YIELD_LIMIT, Filters, Ring, yield_cpu
from canbrake.bus.memory_shm import (
    DATA_OFFSET,
    DEFAULT_RING_SIZE,
    E_FILTERS,
    E_FLAGS,
    E_NFILT,
    E_PID,
    E_READ_SEQ,
    E_SLEEPING,
    E_START,
    E_TOKEN,
    E_TX_WAITING,
    E_PENDING,
    E_WAKE_ON,
    E_WAKE_SEQ,
    E_WAKEUPS,
    E_WANT,
    F_ACCEPT_ALL,
    F_BACKPRESSURE,
    F_OWN,
    F_PROTECT,
    H_CLOSED,
    H_READER_GEN,
    H_SLEEPERS,
    H_TOKEN,
    H_TX_WAITERS,
    H_WRITE_SEQ,
    MAX_DATA,
    SLOT_BYTES,
    SLOT_SEQ_OFFSET,
    Layout,
    channel_pids,
    list_channels,
    remove_channel,
)

__all__ = ["MemoryBus", "MemoryBusStats", "remove_channel", "list_channels", "channel_pids"]

if _RING_LAYOUT != {"SLOT_BYTES": SLOT_BYTES, "DATA_OFFSET": DATA_OFFSET, "MAX_DATA": MAX_DATA,
                    "SLOT_SEQ_OFFSET": SLOT_SEQ_OFFSET, "H_WRITE_SEQ": H_WRITE_SEQ, "H_SLEEPERS": H_SLEEPERS,
                    "E_SLEEPING": E_SLEEPING, "E_WAKE_SEQ": E_WAKE_SEQ, "E_WAKEUPS": E_WAKEUPS,
                    "E_WANT": E_WANT, "E_PENDING": E_PENDING, "E_WAKE_ON": E_WAKE_ON,
                    "H_TX_WAITERS": H_TX_WAITERS, "H_CLOSED": H_CLOSED, "E_READ_SEQ": E_READ_SEQ,
                    "H_READER_GEN": H_READER_GEN}:
    raise ImportError(f"canbrake.bus._ring was built for another slot layout ({_RING_LAYOUT}): "
                      "rebuild canbrake (pip install .)")
_WAIT_SLICE_S = 0.1  # a writer blocked by a backpressure reader re-checks that reader's pid this often
_open_buses: "weakref.WeakSet[MemoryBus]" = weakref.WeakSet()


def _after_fork_in_child() -> None:
    for bus in list(_open_buses):
        bus._forked = True
        bus._is_shutdown = True  # the parent owns the shared entry; never free it from here


def _shutdown_all() -> None:
    """At interpreter exit, leave every channel still open (the last bus removes its files)."""
    for bus in list(_open_buses):
        try:
            bus.shutdown()
        except Exception:  # best effort while the interpreter goes down
            pass


if hasattr(os, "register_at_fork"):
    os.register_at_fork(after_in_child=_after_fork_in_child)
atexit.register(_shutdown_all)


class BusOverrunError(CanOperationError):
    """A non-backpressure reader fell a whole ring behind: ``frames_lost`` frames were overwritten
    unread. The bus goes on with the oldest frame still in the ring; a caller that can live with
    the loss (a node under a flood) counts it and receives on."""

    def __init__(self, message: str, frames_lost: int) -> None:
        super().__init__(message)
        self.frames_lost = frames_lost


@dataclass(frozen=True)
class MemoryBusStats:
    """Counters of one :class:`MemoryBus` (this process's view)."""

    frames_sent: int
    frames_received: int  #: returned by recv (after filtering)
    wakeups: int  #: times a writer woke this bus's blocked recv (counted in shared memory)
    sleeps: int  #: times recv blocked waiting for a frame
    spurious_wakeups: int  #: wake-ups that found nothing to read
    frames_lost: int  #: frames overwritten before this (non-backpressure) reader read them
    overruns: int  #: times recv raised CanOperationError for lost frames
    send_waits: int  #: times send waited for a backpressure reader to make room
    #: backpressure="accepted": frames it does not accept, overwritten before it looked (no loss)
    frames_passed: int = 0


class MemoryBus(BusABC):
    """A CAN bus shared by every process on this machine that opens the same ``channel``.

    :param channel: channel name, 1-64 characters from ``A-Za-z0-9_.-`` (an int is accepted).
    :param can_filters: python-can filters; pushed down so rejected frames never wake this bus.
    :param receive_own_messages: also receive the frames this bus sends (``is_rx`` False).
    :param preserve_timestamps: keep ``msg.timestamp`` on send (e.g. replaying a log) instead
        of stamping ``time.time()`` (s).
    :param backpressure: writers wait for this reader instead of overrunning it (recorders).
    :param send_timeout: upper bound (s) of a ``send(timeout=None)`` blocked by a backpressure
        reader; then :class:`can.CanTimeoutError`.
    :param ring_size: frames in the shared ring (power of two), used by the bus creating the channel.
    :param shm_dir: directory of the channel files (default ``$CANBRAKE_SHM_DIR`` or ``/dev/shm``).
    :param fd: report :attr:`protocol` as CAN FD (CAN FD frames are carried either way).
    :param yield_before_sleep: before blocking in ``recv``, give the CPU to processes that are
        ready to run (``sched_yield``) and look again, while a yield hands the CPU to another
        process, for at most 200 us and 8 yields: when nodes outnumber cores, the frames a
        reader waits for are often there by then, which saves a sleep and a cross-core wake-up.
        A yield that comes straight back (nothing else runnable on that CPU) ends it: never a
        spin on an idle CPU.
    :param wake_on: an identifier (29-bit if above 0x7FF): while this bus sleeps in ``recv``, only
        a frame with it wakes it; the frames it accepts before are kept for it (writers treat
        them as unread, and one held back by them wakes it). A lockstep recorder is woken once a
        period, by SYNC, instead of at each burst.
    :raises can.CanInitializationError: bad channel name, incompatible channel file, table full.
    """

    def __init__(
        self,
        channel: Any = "canbrake0",
        can_filters: Optional[CanFilters] = None,
        receive_own_messages: bool = False,
        preserve_timestamps: bool = False,
        backpressure: bool = False,
        send_timeout: float = 5.0,
        ring_size: int = DEFAULT_RING_SIZE,
        shm_dir: Optional[str] = None,
        fd: bool = False,
        yield_before_sleep: bool = True,
        wake_on: Optional[int] = None,
        **kwargs: Any,
    ) -> None:
        self._open = False
        self._forked = False
        self._name = shm.validate_channel(channel)
        self._dir = shm.resolve_dir(shm_dir)
        self._path = shm.bus_path(self._dir, self._name)
        self._own = bool(receive_own_messages)
        self._preserve_ts = bool(preserve_timestamps)
        #: backpressure="accepted": writers wait only for the frames this reader accepts
        self._protect = backpressure == "accepted"
        self._backpressure = bool(backpressure) and not self._protect
        self._send_timeout = float(send_timeout)
        self._yield = bool(yield_before_sleep) and hasattr(os, "sched_yield")
        self._wake_on = 0 if wake_on is None else (shm.WAKE_ON_SET | (int(wake_on > 0x7FF) << 31)
                                                   | (int(wake_on) & 0x1FFFFFFF))
        self._can_protocol = CanProtocol.CAN_FD if fd else CanProtocol.CAN_20
        self._state = BusState.ACTIVE
        self._tlock = threading.Lock()  # flock is per open file: also exclude our own threads
        self._txlock = threading.Lock()
        self._rxbuf: collections.deque[Message] = collections.deque()
        self._filters_c: Optional[Filters] = None  # ours, compiled; None accepts every frame
        #: readers to consider waking: (entry word, token, filters or None = all)
        self._peers: list[tuple[int, int, Optional[Filters]]] = []
        self._bp_peers: list[int] = []
        #: backpressure="accepted" readers: (entry word, token, filters or None, own frames)
        self._pr_peers: list[tuple[int, int, Optional[Filters], bool]] = []
        self._overrun_pending: Optional[BusOverrunError] = None  # see recv_batch
        self._pr_floor = -1  # no protected reader's position is below this (positions only grow)
        self._rxlock = threading.Lock()  # the receiving thread, or a sender draining (see _drain_own)
        self._n_passed = 0  # protected reader: frames it does not accept, overwritten before it looked
        self._peers_gen = -1
        self._wake_fds: dict[tuple[int, str], int] = {}
        #: recv_raw used: frames a waiting send takes in (_drain_own) are kept as slot images
        self._raw_mode = False
        self._raw_carry = bytearray()  # slot images taken but not yet returned (recv_raw)
        self._n_sent = self._n_recv = self._n_sleeps = self._n_spurious = 0
        self._n_lost = self._n_overruns = self._n_send_waits = 0
        self._wakeups_seen = 0  # last E_WAKEUPS read, so stats() still works after shutdown
        self._token = 0
        self._rx_fd = self._tx_fd = -1

        try:
            os.makedirs(self._dir, exist_ok=True)
            self._fd = shm.open_locked(self._path, ring_size)
        except OSError as e:
            raise CanInitializationError(f"cannot open canbrake channel file {self._path}: {e}") from e
        assert self._fd is not None
        try:
            self._layout = Layout(shm.ring_size_of(self._fd))
            self._mm = mmap.mmap(self._fd, self._layout.total_bytes)
            self._mv = memoryview(self._mm)
            self._q = self._mv.cast("Q")
            self._register()
            self._ring = Ring(self._mm, self._layout.ring_offset, self._layout.ring_size, self._token, self._name)
            self._ring.seq = self._seq0
            self._ring.filters = self._filters_c
            self._ring.attach(self._eb, self._fd, self._rx_fd, self._tlock, self._publish_read_seq,
                              2 if self._protect else 1 if self._backpressure else 0, self._own, self._yield)
        except BaseException:
            self._close_local()
            raise
        finally:
            if self._fd >= 0:
                fcntl.flock(self._fd, fcntl.LOCK_UN)
        self._ring_n = self._layout.ring_size
        self._tx_poll = select.poll()
        self._tx_poll.register(self._tx_fd, select.POLLIN)
        self._open = True
        _open_buses.add(self)
        self.channel_info = f"canbrake memory bus {self._name!r} ({self._path})"
        try:
            super().__init__(channel=self._name, can_filters=can_filters, **kwargs)
        except BaseException:
            self.shutdown()
            raise

    # ------------------------------------------------------------ receive state (kept by the ring)
    @property
    def _seq(self) -> int:
        """This bus's read position: the next seq it has not looked at."""
        return self._ring.seq

    @_seq.setter
    def _seq(self, v: int) -> None:
        self._ring.seq = v

    @property
    def _fifo_dirty(self) -> bool:
        """A stale wake-up byte may sit in our rx FIFO."""
        ring = getattr(self, "_ring", None)
        return ring is not None and ring.fifo_dirty

    @_fifo_dirty.setter
    def _fifo_dirty(self, v: bool) -> None:
        self._ring.fifo_dirty = v

    @property
    def _in_recv(self) -> bool:
        """A receive is blocked in this bus."""
        ring = getattr(self, "_ring", None)
        return ring is not None and ring.in_recv

    @_in_recv.setter
    def _in_recv(self, v: bool) -> None:
        self._ring.in_recv = v

    # ------------------------------------------------------------ registration (lock held)
    def _register(self) -> None:
        q = self._q
        shm.reap_dead(q, self._dir, self._name)
        free = [i for i in range(shm.MAX_READERS) if not q[Layout.entry_word(i) + E_TOKEN]]
        if not free:
            raise CanInitializationError(
                f"canbrake channel {self._name!r} already has {shm.MAX_READERS} open buses "
                f"(pids {sorted({q[e + E_PID] for e in shm.live_entries(q)})}); shut some down"
            )
        b = Layout.entry_word(free[0])
        token = (q[H_TOKEN] % 0xFFFFFFFF) + 1
        q[H_TOKEN] = token
        fds: dict[str, int] = {}
        try:
            for kind in ("rx", "tx"):
                path = shm.fifo_path(self._dir, self._name, token, kind)
                try:
                    os.unlink(path)
                except FileNotFoundError:
                    pass
                os.mkfifo(path, 0o600)
                fds[kind] = os.open(path, os.O_RDWR | os.O_NONBLOCK)
        except BaseException:
            for kind, fd in fds.items():
                os.close(fd)
            for kind in ("rx", "tx"):
                try:
                    os.unlink(shm.fifo_path(self._dir, self._name, token, kind))
                except FileNotFoundError:
                    pass
            raise
        self._rx_fd, self._tx_fd = fds["rx"], fds["tx"]
        w = q[H_WRITE_SEQ]
        q[b + E_PID] = os.getpid()
        q[b + E_START] = shm.proc_start_time(os.getpid())
        q[b + E_FLAGS] = ((F_OWN if self._own else 0) | (F_BACKPRESSURE if self._backpressure else 0)
                          | (F_PROTECT if self._protect else 0) | F_ACCEPT_ALL)
        q[b + E_NFILT] = 0
        q[b + E_READ_SEQ] = w
        q[b + E_SLEEPING] = 0
        q[b + E_WAKE_SEQ] = w
        q[b + E_WAKEUPS] = 0
        q[b + E_TX_WAITING] = 0
        q[b + E_WANT] = q[b + E_PENDING] = 0
        q[b + E_WAKE_ON] = self._wake_on
        q[b + E_TOKEN] = token
        q[H_READER_GEN] = q[H_READER_GEN] + 1
        self._eb = b
        self._token = token
        self._seq0 = w  # the read position: the ring's (_seq)

    def _apply_filters(self, filters: Optional[CanFilters]) -> None:
        """Push ``filters`` into this bus's shared entry so writers wake it only for accepted frames."""
        compiled = shm.compile_filters(filters)
        if compiled is not None and not shm.pushable(compiled):
            compiled = shm.merge_exact(compiled)  # the same acceptance in fewer filters
        self._filters_c = None if compiled is None else Filters(compiled)
        ring = getattr(self, "_ring", None)
        if ring is not None:
            ring.filters = self._filters_c
        if not self._open:
            return
        self._lock()
        try:
            q, b = self._q, self._eb
            flags = q[b + E_FLAGS] & ~F_ACCEPT_ALL
            if shm.pushable(compiled):
                assert compiled is not None
                for i, (cid, mask, mode) in enumerate(compiled):
                    base = b + E_FILTERS + 3 * i
                    q[base], q[base + 1], q[base + 2] = cid, mask, mode
                q[b + E_NFILT] = len(compiled)
            else:  # no filters, or too many to push: writers wake us for every frame
                flags |= F_ACCEPT_ALL
                q[b + E_NFILT] = 0
            q[b + E_FLAGS] = flags
            q[H_READER_GEN] = q[H_READER_GEN] + 1
        finally:
            self._unlock()

    # ------------------------------------------------------------ lock
    def _lock(self) -> None:
        self._tlock.acquire()
        try:
            fcntl.flock(self._fd, fcntl.LOCK_EX)
        except BaseException:
            self._tlock.release()
            raise

    def _unlock(self) -> None:
        try:
            fcntl.flock(self._fd, fcntl.LOCK_UN)
        finally:
            self._tlock.release()

    def _check_open(self) -> None:
        if not self._open or self._forked:
            if self._forked:
                raise CanOperationError(
                    "this canbrake MemoryBus was opened before fork(); open a new bus in the child"
                )
            raise CanOperationError(f"canbrake bus {self._name!r} is shut down")

    def _closed_error(self) -> CanOperationError:
        return CanOperationError(
            f"canbrake channel {self._name!r} was removed (remove_channel) while this bus was open"
        )

    # ------------------------------------------------------------ send
    def send(self, msg: Message, timeout: Optional[float] = None) -> None:
        """Put ``msg`` on the bus (stamped with ``time.time()`` unless ``preserve_timestamps``).

        :param timeout: s to wait for ring space if a backpressure reader is a full ring behind;
            ``None`` waits up to ``send_timeout``.
        :raises can.CanTimeoutError: no room within the timeout.
        :raises can.CanOperationError: bus shut down, passive, or the frame is malformed.
        """
        self._send_frames((msg,), timeout)

    def send_many(self, msgs: Iterable[Message], timeout: Optional[float] = None) -> None:
        """Send ``msgs`` as one burst: consecutive in the global order, one wake-up per reader.

        Same parameters and errors as :meth:`send`; bursts longer than half the ring are split.
        """
        msgs = list(msgs)
        step = max(1, self._ring_n // 2)
        for i in range(0, len(msgs), step):
            self._send_frames(msgs[i : i + step], timeout)

    def send_burst(self, msgs: list[Message] | bytes) -> None:
        """:meth:`send_many` of a node's frames of one phase (a list, possibly empty): the node
        driver's path, without copying the list. ``msgs`` may also be the frames as slot images
        (bytes, ``SLOT_BYTES`` each, from a node's compiled encoder, e.g.
        ``canbrake.bus._codec.TickFrames.images``): sent as they are, no ``Message`` made."""
        if type(msgs) is bytes:
            self._send_images(msgs)
        elif msgs:
            if len(msgs) <= self._ring_n // 2:
                self._send_frames(msgs, None)
            else:
                self.send_many(msgs)

    def _send_images(self, images: bytes) -> None:
        """Send the frames of the slot images ``images`` as one burst (split as :meth:`send_many`)."""
        step = max(1, self._ring_n // 2) * SLOT_BYTES
        for i in range(0, len(images), step):
            self._send_frames((), None, images[i : i + step])

    def _send_frames(self, msgs: Sequence[Message], timeout: Optional[float], images: bytes | None = None) -> None:
        if not self._open or self._forked:
            self._check_open()
        if self._state is BusState.PASSIVE:
            raise CanOperationError(f"canbrake bus {self._name!r} is passive (listen only)")
        ring = self._ring
        if images is not None:  # frames already encoded: this bus's token and time stamp
            frames = ring.stamp(images, self._preserve_ts, time.time())
            n = len(frames) // SLOT_BYTES
            if not n:
                return
        else:
            if not msgs:
                return
            frames = ring.encode(msgs, self._preserve_ts, time.time())  # slot images; raises if malformed
            n = len(msgs)
        with self._txlock:  # the common case in one compiled call: nothing in the way
            rest = ring.send_fast(frames, self._peers_gen, self._bp_peers,
                                  self._pr_floor if self._pr_peers else None, self._peers, self._wake_fds)
        if rest is not None:
            for ptok in rest:
                self._notify(ptok, "rx")  # opens its FIFO, or handles the error of a failed write
            self._n_sent += n
            return
        q, eb = self._q, self._eb
        deadline: Optional[float] = None
        waiting = False  # our E_TX_WAITING flag is (or may be) set
        with self._txlock:
            while True:
                wake: list[int] = []
                blocker = roused = 0
                self._lock()
                try:
                    if q[H_CLOSED]:
                        raise self._closed_error()
                    if q[H_READER_GEN] != self._peers_gen:
                        self._refresh_peers()
                    w = q[H_WRITE_SEQ]
                    if self._bp_peers:
                        blocker = self._blocking_reader(w + n)
                    if not blocker and self._pr_peers and w + n - self._ring_n > self._pr_floor:
                        blocker = self._protecting_reader(w, n)
                    if blocker:
                        if q[blocker + E_SLEEPING]:
                            # it sleeps until more frames come (E_WANT) with unread ones in the
                            # way: wake it to read them, or we would wait for each other
                            q[blocker + E_SLEEPING] = 0
                            q[H_SLEEPERS] = q[H_SLEEPERS] - 1
                            q[blocker + E_WAKEUPS] = q[blocker + E_WAKEUPS] + 1
                            roused = q[blocker + E_TOKEN]
                        if not q[eb + E_TX_WAITING]:
                            q[eb + E_TX_WAITING] = 1
                            q[H_TX_WAITERS] = q[H_TX_WAITERS] + 1
                        waiting = True
                        b_pid, b_start = q[blocker + E_PID], q[blocker + E_START]
                        b_lag = w + n - self._bp_position(blocker, w)
                    else:
                        if waiting and q[eb + E_TX_WAITING]:
                            q[eb + E_TX_WAITING] = 0
                            q[H_TX_WAITERS] = q[H_TX_WAITERS] - 1
                        ring.write(frames, w)  # the slots, then write_seq = w + n
                        if not self._own and not self._in_recv and self._seq == w:
                            # our reader is caught up and never receives its own frames: skip
                            # them, so a bus that mostly sends is not overrun by itself
                            self._seq = w + n
                            q[eb + E_READ_SEQ] = w + n
                        wake = ring.wake(self._peers, frames, w)  # sleeping readers that accept one
                finally:
                    self._unlock()
                if not blocker:
                    for ptok in wake:
                        self._notify(ptok, "rx")
                    self._n_sent += n
                    return
                # --- a backpressure reader is a full ring behind: wait for it (bounded)
                if roused:
                    self._notify(roused, "rx")
                now = time.monotonic()
                if deadline is None:
                    self._n_send_waits += 1
                    deadline = now + (self._send_timeout if timeout is None else max(0.0, timeout))
                # backpressure="accepted": take our own unread frames in (they may be what is in
                # the way), so that no other waiting sender ever waits for us
                if self._protect and self._drain_own() and blocker == eb:
                    continue
                if blocker == eb and not self._in_recv:
                    self._clear_tx_waiting()
                    raise CanOperationError(
                        f"this bus (backpressure=True) has {b_lag} unread frames on channel "
                        f"{self._name!r}: recv them before sending more"
                    )
                if not shm.pid_alive(b_pid, b_start):
                    self._reap()
                    continue
                if now >= deadline:
                    self._clear_tx_waiting()
                    raise CanTimeoutError(
                        f"send on canbrake channel {self._name!r} timed out: reader pid {b_pid} "
                        f"(backpressure=True) is {b_lag} frames behind a ring of {self._ring_n}"
                    )
                self._tx_poll.poll(math.ceil(min(deadline - now, _WAIT_SLICE_S) * 1000))
                self._drain(self._tx_fd)

    def _bp_position(self, b: int, w: int) -> int:
        """Oldest ring position backpressure reader ``b`` may still need (lock held)."""
        q = self._q
        if q[b + E_SLEEPING]:
            # everything published while it slept was checked against its filters: what it
            # accepts woke it, unless it waits for several frames (E_WANT) and some have come
            return q[b + E_WAKE_SEQ] if q[b + E_PENDING] else w
        return max(q[b + E_READ_SEQ], q[b + E_WAKE_SEQ])

    def _blocking_reader(self, end: int) -> int:
        w = self._q[H_WRITE_SEQ]
        for b in self._bp_peers:
            if end - self._bp_position(b, w) > self._ring_n:
                return b
        return 0

    def _protecting_reader(self, w: int, n: int) -> int:
        """A backpressure="accepted" reader that accepts, and has not read, a frame that writing
        seqs ``w .. w+n-1`` would overwrite (its entry word), else 0 (lock held). Also moves
        ``_pr_floor`` up to the lowest such reader position."""
        ring, size = self._ring, self._ring_n
        floor = w
        blocker = 0
        for b, tok, filt, own in self._pr_peers:
            p = self._bp_position(b, w)
            floor = min(floor, p)
            if not blocker and ring.protected_hit(max(p, w - size), w + n - size, tok, own, filt):
                blocker = b
        self._pr_floor = floor
        return blocker

    def _drain_own(self) -> bool:
        """Copy this bus's accepted frames into its local queue while a send waits; False if
        another thread is receiving right now (it does the same)."""
        if not self._rxlock.acquire(blocking=False):
            return False
        try:
            if self._raw_mode:  # kept as slot images for recv_raw (a protected reader loses none)
                if self._ring.fetch_raw(self._raw_carry) == 3:
                    raise self._closed_error()
            else:
                self._fetch()
        finally:
            self._rxlock.release()
        return True

    def _clear_tx_waiting(self) -> None:
        self._lock()
        try:
            q = self._q
            if q[self._eb + E_TX_WAITING]:
                q[self._eb + E_TX_WAITING] = 0
                q[H_TX_WAITERS] = q[H_TX_WAITERS] - 1
        finally:
            self._unlock()

    def _refresh_peers(self) -> None:
        """Re-read the reader table after a registration/filter change (lock held)."""
        q = self._q
        peers, bp, pr, live = [], [], [], set()
        for b in shm.live_entries(q):
            tok, flags = q[b + E_TOKEN], q[b + E_FLAGS]
            live.add(tok)
            if flags & F_ACCEPT_ALL:
                filt = None
            else:
                f0 = b + E_FILTERS
                filt = Filters([(q[f0 + 3 * i], q[f0 + 3 * i + 1], q[f0 + 3 * i + 2]) for i in range(q[b + E_NFILT])])
            if tok != self._token or flags & F_OWN:  # our own frames never wake our own reader
                peers.append((b, tok, filt))  # unless it receives its own messages
            if flags & F_BACKPRESSURE:
                bp.append(b)
            if flags & F_PROTECT:
                pr.append((b, tok, filt, bool(flags & F_OWN)))
        for key in [k for k in self._wake_fds if k[0] not in live]:
            os.close(self._wake_fds.pop(key))
        self._peers, self._bp_peers, self._peers_gen = peers, bp, q[H_READER_GEN]
        self._pr_peers, self._pr_floor = pr, -1

    def _notify(self, token: int, kind: str) -> None:
        """Write one wake-up byte to the ``kind`` FIFO of the bus with ``token``."""
        fd = self._wake_fds.get((token, kind))
        try:
            if fd is None:
                fd = os.open(shm.fifo_path(self._dir, self._name, token, kind), os.O_WRONLY | os.O_NONBLOCK)
                self._wake_fds[(token, kind)] = fd
            os.write(fd, b"\x01")
        except BlockingIOError:
            pass  # FIFO full: a wake-up is pending anyway
        except OSError as e:
            if not shm.is_enxio(e):
                raise CanOperationError(f"cannot wake a reader on {self._name!r}: {e}") from e
            if fd is not None:
                os.close(self._wake_fds.pop((token, kind)))
            self._reap()  # its process is gone

    def _reap(self) -> None:
        self._lock()
        try:
            shm.reap_dead(self._q, self._dir, self._name)
        finally:
            self._unlock()

    # ------------------------------------------------------------ receive
    @staticmethod
    def _drain(fd: int) -> bool:
        try:
            return bool(os.read(fd, 4096))
        except BlockingIOError:
            return False

    def _fetch(self) -> None:
        """Copy every new frame this bus accepts into the local queue.

        :raises can.CanOperationError: frames were overwritten before they were read (overrun).
        """
        if self._q[H_CLOSED]:
            raise self._closed_error()
        if self._raw_carry:  # slot images a waiting send took in (raw mode): theirs come first
            self._rxbuf.extend(self._ring.messages(self._raw_carry))
            self._raw_carry.clear()
        # backpressure and protected readers are safe one seq longer than overrun readers: writers
        # do not start seq x + ring_size before they have read x (protected: x is a frame they
        # accept; the others may be overwritten and are checked by their slot sequence number)
        msgs: list[Message] = []
        r = self._ring.fetch(self._seq, self._own, self._filters_c,
                             2 if self._protect else 1 if self._backpressure else 0, msgs)
        if r is None:
            return
        w, lost, passed = r
        self._n_passed += passed
        n = self._ring_n
        self._seq = w
        self._rxbuf.extend(msgs)
        self._publish_read_seq()
        if lost:
            self._n_lost += lost
            self._n_overruns += 1
            raise BusOverrunError(
                f"canbrake bus {self._name!r} overrun: this reader fell more than a ring "
                f"({n} frames) behind and {lost} frame(s) were overwritten unread "
                "(read faster, enlarge ring_size, or open the bus with backpressure=True)", lost
            )

    def _publish_read_seq(self) -> None:
        q, b = self._q, self._eb
        if not q[H_TX_WAITERS]:
            # No sender waits (or the reader is an overrun reader, whose read_seq is informative
            # only): a plain aligned store, which senders read under the lock. A sender that
            # starts to wait between our load of H_TX_WAITERS and this store misses its wake-up
            # byte and looks again after its wait slice (_WAIT_SLICE_S): a bounded delay in a
            # rare race, against a lock round trip on every fetch (a recorder fetches several
            # times per lockstep period; two flock calls each were most of its syscalls).
            q[b + E_READ_SEQ] = self._seq
            return
        if not self._backpressure and not self._protect:
            q[b + E_READ_SEQ] = self._seq  # informative only
            return
        waiters: list[int] = []
        self._lock()
        try:
            q[b + E_READ_SEQ] = self._seq
            if q[H_TX_WAITERS]:
                for eb in shm.live_entries(q):
                    if q[eb + E_TX_WAITING]:
                        q[eb + E_TX_WAITING] = 0
                        q[H_TX_WAITERS] = q[H_TX_WAITERS] - 1
                        waiters.append(q[eb + E_TOKEN])
        finally:
            self._unlock()
        for tok in waiters:
            self._notify(tok, "tx")

    def recv_filtered(self, timeout: Optional[float] = None) -> Optional[Message]:
        """:meth:`recv` without python-can's per-frame debug logging (this bus's frames are
        already filtered): the node driver's hot path."""
        with self._rxlock:
            buf = self._rxbuf
            if buf and self._open and not self._forked and self._overrun_pending is None:
                self._n_recv += 1  # fast path: a frame fetched before is waiting
                return buf.popleft()
            return self._recv_locked(timeout)[0]

    def recv_batch(self, timeout: Optional[float] = None, min_frames: int = 1) -> list[Message]:
        """Every accepted frame pending, oldest first; if none is, wait up to ``timeout`` s for the
        first (``None``: forever, 0: poll) and return it with any that came with it. ``[]`` after
        the timeout.

        ``min_frames``: wait until at least that many accepted frames are pending (those already
        pending count), or the timeout, then return them all. While it sleeps the writers count
        the frames it accepts and wake it once, at the last one: a lockstep node that needs n
        frames before it can go on (the plant: every ECU's command) is woken once a period, not n
        times. At the timeout it returns what has come, however few. Capped at half the ring.

        The frames, their order and attributes are those that calling :meth:`recv_filtered`
        until it has nothing pending would return, and errors come at the same place in that
        sequence: when frames were lost (:class:`BusOverrunError`), the frames read before the
        loss are returned first and the next call raises; the frames after the loss come with
        the call after that. Counters (:meth:`stats`) are the same too.
        """
        with self._rxlock:
            self._check_open()
            self._raise_pending_overrun()
            buf = self._rxbuf
            got = list(buf)
            buf.clear()
            try:
                self._fetch()
            except BusOverrunError as e:
                if not got:
                    raise  # the frames after the loss stay queued for the next call
                self._overrun_pending = e
                self._n_recv += len(got)
                return got
            got.extend(buf)
            buf.clear()
            want = max(1, min(min_frames, self._ring_n // 2))
            deadline = None if timeout is None else time.monotonic() + timeout
            while len(got) < want:  # wait for the rest, as recv does for one
                left = None if deadline is None else max(0.0, deadline - time.monotonic())
                try:
                    m = self._recv_locked(left, want - len(got))[0]  # (counted there)
                except BusOverrunError as e:
                    if not got:
                        raise
                    self._overrun_pending = e
                    break
                if m is None:  # the timeout
                    break
                self._n_recv -= 1
                got.append(m)
                got.extend(buf)
                buf.clear()
            self._n_recv += len(got)
            return got

    def recv_raw(self, timeout: Optional[float] = None, min_frames: int = 1) -> bytearray:
        """:meth:`recv_batch` for a node's compiled receive side: the frames as slot images
        (``SLOT_BYTES`` each: time stamp, identifier, sender token, flags, dlc, length at 0, 8,
        12, 16, 17, 18, data at ``DATA_OFFSET``; :meth:`raw_message` makes one a ``can.Message``),
        read, filtered and waited for in one compiled call (:meth:`canbrake.bus._ring.Ring.recv_raw`).
        Same frames, order, waits, errors and counters as :meth:`recv_batch`. Once used, a bus is
        read this way (frames fetched for it elsewhere are kept as slot images)."""
        ring = self._ring
        with self._rxlock:
            if (self._raw_mode and not self._raw_carry and self._open and not self._forked
                    and self._overrun_pending is None):  # the common case: nothing pending here
                got = ring.recv_raw(-1.0 if timeout is None else max(0.0, timeout), min_frames)
                if not ring.status:
                    self._n_recv += len(got) // SLOT_BYTES
                    return got
                return self._raw_result(got, 0)
            self._check_open()
            self._raise_pending_overrun()
            if not self._raw_mode:
                self._raw_mode = True
                if self._rxbuf:  # frames fetched as messages before: the same bytes, first
                    msgs = list(self._rxbuf)
                    images = bytearray(ring.encode(msgs, True, 0.0))  # sender: this bus
                    for i, m in enumerate(msgs):
                        if m.is_rx:  # another bus's frame: a token no bus has
                            images[i * SLOT_BYTES + 12:i * SLOT_BYTES + 16] = bytes(4)
                    self._raw_carry[:0] = images
                    self._rxbuf.clear()
            carry = len(self._raw_carry) // SLOT_BYTES  # pending already: they count
            if carry >= min_frames:
                got = ring.recv_raw(0.0, 1)
            else:
                got = ring.recv_raw(-1.0 if timeout is None else max(0.0, timeout), min_frames - carry)
            carry = len(self._raw_carry)  # bytes
            if carry:
                got[:0] = self._raw_carry
                self._raw_carry.clear()
            return self._raw_result(got, carry)

    def _raw_result(self, got: bytearray, carry: int) -> bytearray:
        """recv_raw's result after the ring's ``recv_raw`` gave ``got`` (after ``carry`` bytes
        taken before): raises for a closed channel; a loss as recv_batch does."""
        ring = self._ring
        status = ring.status
        if status == 2:
            raise self._closed_error()
        if status == 1:  # frames were lost: those before the loss now, the error next
            lost, cut = ring.lost, carry + ring.lost_at
            self._n_lost += lost
            self._n_overruns += 1
            e = BusOverrunError(
                f"canbrake bus {self._name!r} overrun: this reader fell more than a ring "
                f"({self._ring_n} frames) behind and {lost} frame(s) were overwritten unread "
                "(read faster, enlarge ring_size, or open the bus with backpressure=True)", lost)
            self._raw_carry[:] = got[cut:]
            del got[cut:]
            if not got:
                raise e
            self._overrun_pending = e
        self._n_recv += len(got) // SLOT_BYTES
        return got

    def raw_message(self, frames: bytes | bytearray, i: int) -> Message:
        """Slot image ``i`` of :meth:`recv_raw`'s ``frames`` as the ``can.Message`` that
        :meth:`recv` gives for that frame."""
        return self._ring.message(frames, i)

    def _raise_pending_overrun(self) -> None:
        e = self._overrun_pending
        if e is not None:
            self._overrun_pending = None
            raise e

    def _recv_internal(self, timeout: Optional[float]) -> tuple[Optional[Message], bool]:
        """Next accepted frame, or ``None`` after ``timeout`` s (``None``: wait forever, 0: poll)."""
        with self._rxlock:
            return self._recv_locked(timeout)

    def _recv_locked(self, timeout: Optional[float], want: int = 1) -> tuple[Optional[Message], bool]:
        self._check_open()
        self._raise_pending_overrun()
        buf = self._rxbuf
        if not buf:
            self._fetch()
        if buf:
            self._n_recv += 1
            return buf.popleft(), True
        if timeout is not None and timeout <= 0:
            return None, True
        deadline = None if timeout is None else time.monotonic() + timeout
        q, sleep_w = self._q, self._eb + E_SLEEPING
        self._in_recv = True
        try:
            if self._yield:  # let runnable peers on this CPU produce first: often no sleep needed
                t_w = time.monotonic()
                for _ in range(YIELD_LIMIT):  # the rule of the compiled wait (canbrake.bus._ring)
                    ran = yield_cpu(t_w)
                    self._fetch()
                    if buf:
                        self._n_recv += 1
                        return buf.popleft(), True
                    if not ran:
                        break
            while True:
                if self._fifo_dirty:  # a wake-up byte may still be on its way from a past sleep
                    self._drain(self._rx_fd)
                    self._fifo_dirty = False
                self._lock()
                try:
                    idle = q[H_WRITE_SEQ] == self._seq
                    if idle:
                        q[self._eb + E_WANT] = want
                        q[self._eb + E_PENDING] = 0
                        q[sleep_w] = 1
                        q[H_SLEEPERS] = q[H_SLEEPERS] + 1
                finally:
                    self._unlock()
                if idle:
                    self._n_sleeps += 1
                    try:
                        self._sleep(deadline)
                    except BaseException:
                        self._fifo_dirty = True
                        self._lock()
                        try:
                            if q[sleep_w]:
                                q[sleep_w] = 0
                                q[H_SLEEPERS] = q[H_SLEEPERS] - 1
                        finally:
                            self._unlock()
                        raise
                self._fetch()
                if buf:
                    self._n_recv += 1
                    return buf.popleft(), True
                if deadline is not None and time.monotonic() >= deadline:
                    return None, True
        finally:
            self._in_recv = False

    def _sleep(self, deadline: Optional[float]) -> None:
        """Block until a writer wakes us or ``deadline`` (``time.monotonic`` s; None: never)
        passes; then position ``self._seq``: the ring's compiled wait (``Ring.sleep``: ``ppoll``
        to the nanosecond and the FIFO drain, as the node path's receive), so a ``recv(timeout)``
        of a fraction of a millisecond ends on time."""
        self._ring.sleep(deadline)

    # ------------------------------------------------------------ state, stats
    @property
    def state(self) -> BusState:
        """ACTIVE, or PASSIVE (listen only: ``send`` raises)."""
        return self._state

    @state.setter
    def state(self, new_state: BusState) -> None:
        if new_state not in (BusState.ACTIVE, BusState.PASSIVE):
            raise ValueError(f"canbrake bus supports ACTIVE and PASSIVE, not {new_state}")
        self._state = new_state

    @property
    def channel_name(self) -> str:
        return self._name

    @property
    def path(self) -> str:
        """The channel's shared-memory file."""
        return self._path

    def stats(self) -> MemoryBusStats:
        """Counters of this bus; ``wakeups`` comes from shared memory (counted by writers)."""
        if self._open and not self._forked:
            self._wakeups_seen = self._q[self._eb + E_WAKEUPS]
        wakeups = self._wakeups_seen
        return MemoryBusStats(
            frames_sent=self._n_sent,
            frames_received=self._n_recv,
            wakeups=wakeups,
            sleeps=self._n_sleeps + self._ring.n_sleeps,
            spurious_wakeups=self._n_spurious + self._ring.n_spurious,
            frames_lost=self._n_lost,
            overruns=self._n_overruns,
            send_waits=self._n_send_waits,
            frames_passed=self._n_passed + self._ring.n_passed,
        )

    remove_channel = staticmethod(remove_channel)

    @staticmethod
    def _detect_available_configs() -> list[AutoDetectedConfig]:
        """The channels that currently have a file in the shared-memory directory."""
        return [{"interface": "canbrake", "channel": name} for name in list_channels()]

    # ------------------------------------------------------------ shutdown
    def shutdown(self) -> None:
        """Leave the channel; the last bus on it removes its files. Safe to call twice."""
        super().shutdown()
        if not self._open:
            return
        if not self._forked:
            self.stats()  # keep the final shared counters
        self._open = False
        _open_buses.discard(self)
        if not self._forked:
            try:
                self._lock()
            except OSError:
                pass
            else:
                try:
                    q = self._q
                    if q[self._eb + E_TOKEN] == self._token:
                        shm.free_entry(q, self._eb, self._dir, self._name)
                    if not sys.is_finalizing():
                        shm.reap_dead(q, self._dir, self._name)
                    if not shm.live_entries(q):
                        q[H_CLOSED] = 1
                        try:
                            st, cur = os.fstat(self._fd), os.stat(self._path)
                            ours = (st.st_ino, st.st_dev) == (cur.st_ino, cur.st_dev)
                        except FileNotFoundError:
                            ours = False  # already removed (remove_channel)
                        if ours:  # not a newer channel of the same name
                            os.unlink(self._path)
                            shm.remove_fifos(self._dir, self._name)
                finally:
                    self._unlock()
        self._close_local()

    def _close_local(self) -> None:
        for fd in self._wake_fds.values():
            os.close(fd)
        self._wake_fds.clear()
        ring = getattr(self, "_ring", None)
        if ring is not None:
            ring.release()  # its hold on the mapping, before mmap.close
        for attr in ("_q", "_mv"):
            view = getattr(self, attr, None)
            if view is not None:
                view.release()
                setattr(self, attr, None)
        mm = getattr(self, "_mm", None)
        if mm is not None:
            mm.close()
            self._mm = None
        for attr in ("_rx_fd", "_tx_fd", "_fd"):
            fd = getattr(self, attr, -1)
            if fd is not None and fd >= 0:
                os.close(fd)
                setattr(self, attr, -1)
