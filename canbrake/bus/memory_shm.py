"""Shared-memory layout and channel files of the canbrake in-memory bus (:mod:`canbrake.bus.memory`).

A channel ``NAME`` is one file, ``<dir>/canbrake-NAME.bus``, that every bus on the channel maps
with ``mmap``, plus two FIFOs per open bus, ``<dir>/canbrake-NAME@<token>.rx`` and ``.tx``, used
only to wake a process blocked in ``recv`` (rx) or in a ``send`` waiting for ring space (tx).
``<dir>`` is the ``shm_dir`` argument, else ``$CANBRAKE_SHM_DIR``, else ``/dev/shm``.

The writer lock is ``flock(LOCK_EX)`` on the channel file: the kernel releases it when a
process dies, so a crashed writer can never wedge the channel.

File layout (little endian; every shared index is an aligned 8-byte word, read and written
through a ``memoryview`` cast to ``'Q'`` so no reader ever sees a torn value)::

    [0, 4096)            header: magic, layout version, geometry, write_seq (own cache line),
                         reader_gen, token counter, tx-waiter count, closed flag, sleeper count
    [4096, +256*512)     reader table: one 512-byte entry per open bus (token, pid, process
                         start time, flags, read_seq, sleeping, wake_seq, wake-up counter,
                         tx_waiting, pushed-down filters)
    [ring_off, ...)      ring of ``ring_size`` 96-byte frame slots: timestamp (f64, s),
                         arbitration id (u32), sender token (u32), flags, dlc, length, data[64],
                         sequence number (u64, at byte 88; layout 3)
"""
from __future__ import annotations

import errno
import fcntl
import os
import re
import struct
from dataclasses import dataclass
from typing import Optional

import can
from can.exceptions import CanInitializationError, CanOperationError

# ---------------------------------------------------------------- geometry
MAGIC = int.from_bytes(b"CANBRAKE", "little")
LAYOUT_VERSION = 3
HEADER_BYTES = 4096
ENTRY_BYTES = 512
MAX_READERS = 256  # 1 + 105 vehicles with an ECU each, the plant, the recorder and listeners
MAX_PUSHED_FILTERS = 16
SLOT_BYTES = 96
DATA_OFFSET = 24
MAX_DATA = 64
#: byte offset of a slot's sequence number (u64): the writer stores SLOT_INVALID first, then the
#: frame, then its sequence number, so a reader that finds its expected number after copying a
#: frame knows the copy is whole (a per-slot seqlock)
SLOT_SEQ_OFFSET = 88
SLOT_INVALID = (1 << 64) - 1
DEFAULT_RING_SIZE = 16384

#: a frame slot's head (``<dIIBBBB``): timestamp (s), arbitration id, sender token, flags, dlc,
#: data length, pad; written and read by the compiled ring (:mod:`canbrake.bus._ring`)

# header words (index into the 'Q' view)
H_MAGIC, H_VERSION, H_RING, H_SLOT, H_READERS, H_ENTRY = 0, 1, 2, 3, 4, 5
H_WRITE_SEQ = 8  # byte 64: its own cache line
H_READER_GEN = 16  # byte 128
H_TOKEN = 17
H_TX_WAITERS = 18
H_CLOSED = 19
H_SLEEPERS = 20  # number of entries with E_SLEEPING set: writers skip the wake scan when 0

# reader-entry words (relative to the entry's first word)
E_TOKEN, E_PID, E_START, E_FLAGS, E_NFILT = 0, 1, 2, 3, 4
E_READ_SEQ = 8
E_SLEEPING = 9
E_WAKE_SEQ = 10
E_WAKEUPS = 11
E_TX_WAITING = 12
E_WANT = 13  # accepted frames a sleeping reader waits for before it is woken (0 or 1: the first)
E_PENDING = 14  # accepted frames published since it went to sleep (counted by the writers)
E_WAKE_ON = 15  # 0, or WAKE_ON_SET | extended << 31 | identifier: only that frame wakes it
WAKE_ON_SET = 1 << 40
E_FILTERS = 16  # MAX_PUSHED_FILTERS x (can_id & mask, mask, mode)

# reader-entry flags
F_OWN = 1  # receive_own_messages
F_BACKPRESSURE = 2
F_ACCEPT_ALL = 4  # no filters pushed down: every frame concerns this reader
F_PROTECT = 8  # backpressure="accepted": writers never overwrite a frame it accepts and has not read

# frame flags
M_EXT, M_RTR, M_ERR, M_FD, M_BRS, M_ESI = 1, 2, 4, 8, 16, 32

_CHANNEL_RE = re.compile(r"[A-Za-z0-9_][A-Za-z0-9_.\-]{0,63}\Z")

#: A compiled filter: (can_id & can_mask, can_mask, mode); mode 0 any frame, 1 standard ids
#: only, 2 extended ids only, 3 never (python-can's rule for an "extended" equal to neither bool).
Filter = tuple[int, int, int]


@dataclass(frozen=True)
class Layout:
    """Byte geometry of a channel file with ``ring_size`` slots."""

    ring_size: int

    @property
    def mask(self) -> int:
        return self.ring_size - 1

    @property
    def ring_offset(self) -> int:
        return HEADER_BYTES + MAX_READERS * ENTRY_BYTES

    @property
    def total_bytes(self) -> int:
        return self.ring_offset + self.ring_size * SLOT_BYTES

    @staticmethod
    def entry_word(index: int) -> int:
        """First 'Q' word of reader entry ``index``."""
        return (HEADER_BYTES + index * ENTRY_BYTES) // 8


# ---------------------------------------------------------------- names and paths
def validate_channel(channel: object) -> str:
    """Channel name as used in file names; raise :class:`can.CanInitializationError` if unsafe."""
    if isinstance(channel, int) and not isinstance(channel, bool):
        channel = str(channel)
    if not isinstance(channel, str) or not _CHANNEL_RE.match(channel):
        raise CanInitializationError(
            f"invalid canbrake channel name {channel!r}: use 1-64 characters from "
            "A-Z a-z 0-9 _ . - , not starting with '.' or '-' (the name becomes the file "
            "canbrake-<channel>.bus in the shared-memory directory)"
        )
    return channel


def resolve_dir(shm_dir: Optional[str] = None) -> str:
    """Directory holding channel files: ``shm_dir``, ``$CANBRAKE_SHM_DIR``, or ``/dev/shm``."""
    d = shm_dir or os.environ.get("CANBRAKE_SHM_DIR")
    if d:
        return os.fspath(d)
    if os.path.isdir("/dev/shm"):
        return "/dev/shm"
    import tempfile

    return tempfile.gettempdir()


def bus_path(directory: str, name: str) -> str:
    return os.path.join(directory, f"canbrake-{name}.bus")


def fifo_path(directory: str, name: str, token: int, kind: str) -> str:
    """FIFO of the bus with ``token``; ``kind`` is ``"rx"`` or ``"tx"``."""
    return os.path.join(directory, f"canbrake-{name}@{token}.{kind}")


# ---------------------------------------------------------------- processes
def proc_start_time(pid: int) -> int:
    """Start time of ``pid`` in clock ticks since boot (0 when /proc is unavailable)."""
    try:
        with open(f"/proc/{pid}/stat", "rb") as f:
            data = f.read()
        return int(data[data.rindex(b")") + 2 :].split()[19])
    except (OSError, ValueError, IndexError):
        return 0


def pid_alive(pid: int, start_time: int) -> bool:
    """True if the process ``pid`` started at ``start_time`` still runs (zombies are dead)."""
    try:
        with open(f"/proc/{pid}/stat", "rb") as f:
            data = f.read()
    except FileNotFoundError:
        return False
    except OSError:
        data = b""
    if data:
        try:
            rest = data[data.rindex(b")") + 2 :].split()
            if rest[0] in (b"Z", b"X", b"x"):
                return False
            return start_time == 0 or int(rest[19]) == start_time
        except (ValueError, IndexError):
            pass
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:
        return True
    return True


# ---------------------------------------------------------------- filters
def compile_filters(filters: Optional[can.typechecking.CanFilters]) -> Optional[tuple[Filter, ...]]:
    """python-can filter dicts to (id & mask, mask, mode) tuples; ``None`` accepts everything."""
    if not filters:
        return None
    out = []
    for f in filters:
        mask = int(f["can_mask"])
        cid = int(f["can_id"]) & mask
        if "extended" in f:
            ext = f["extended"]  # type: ignore[typeddict-item]
            # python-can compares ``extended != msg.is_extended_id``: 1 counts as True, 0 as False
            mode = 2 if ext == True else 1 if ext == False else 3  # noqa: E712
        else:
            mode = 0
        out.append((cid, mask, mode))
    return tuple(out)


#: the mask that makes a filter of each mode exact: standard (1) and extended (2) identifiers
_EXACT_MASK = {1: 0x7FF, 2: 0x1FFFFFFF}


def merge_exact(filters: Optional[tuple[Filter, ...]]) -> Optional[tuple[Filter, ...]]:
    """The same acceptance with exact-identifier filters merged: the identifiers of each mode
    (standard, extended) are split into aligned power-of-two blocks, one masked filter each
    (0x081..0x0BF: six filters instead of 63). A frame is accepted by the result if and only if
    it is by ``filters``; other filters are kept as they are. Written by hand: python-can
    matches filters one by one and has no such merge. Lets a node that filters for many
    identifiers (a plant hearing 106 ECUs' commands) keep its filters in its reader entry, so
    writers wake it only for frames it accepts."""
    if filters is None:
        return None
    ids: dict[int, set[int]] = {}
    rest: list[Filter] = []
    for cid, mask, mode in filters:
        if _EXACT_MASK.get(mode) == mask:
            ids.setdefault(mode, set()).add(cid)
        else:
            rest.append((cid, mask, mode))
    out: list[Filter] = []
    for mode, full in _EXACT_MASK.items():
        run = sorted(ids.get(mode, ()))
        i = 0
        while i < len(run):  # each run of consecutive identifiers a..b
            a = b = run[i]
            while i + 1 < len(run) and run[i + 1] == b + 1:
                i += 1
                b = run[i]
            i += 1
            while a <= b:  # the largest aligned block starting at a that ends by b
                size = (a & -a) if a else 1 << full.bit_length()
                while a + size - 1 > b:
                    size >>= 1
                out.append((a, full & ~(size - 1), mode))
                a += size
    return tuple(out + rest)


def pushable(filters: Optional[tuple[Filter, ...]]) -> bool:
    """True if ``filters`` fit in a reader entry (else the entry says "accept all")."""
    return (
        filters is not None
        and len(filters) <= MAX_PUSHED_FILTERS
        and all(0 <= c < 2**64 and 0 <= m < 2**64 for c, m, _ in filters)
    )


# ---------------------------------------------------------------- channel file
def _read_header(fd: int) -> tuple[int, ...]:
    raw = os.pread(fd, 48, 0)
    if len(raw) < 48:
        return (0,) * 6
    return struct.unpack("<6Q", raw)


def open_locked(path: str, ring_size: int, create: bool = True) -> Optional[int]:
    """Open the channel file at ``path`` and return its fd with ``flock(LOCK_EX)`` held.

    Creates and initialises the file when missing (``create``) or half-initialised (its creator
    died before writing the magic). Retries when the file was unlinked between open and lock
    (the last bus of a previous run removing it). Returns ``None`` if ``create`` is false and
    there is no file.
    """
    for _ in range(1000):
        flags = os.O_RDWR | (os.O_CREAT if create else 0)
        try:
            fd = os.open(path, flags | getattr(os, "O_NOFOLLOW", 0), 0o600)
        except FileNotFoundError:
            return None
        except OSError as e:
            if e.errno == errno.ELOOP:
                raise CanInitializationError(f"{path} is a symbolic link; refusing to use it as a canbrake channel") from None
            raise
        try:
            if create:  # opened for use (removal and listing only look)
                check_private(os.fstat(fd), path)
            fcntl.flock(fd, fcntl.LOCK_EX)
            st = os.fstat(fd)
            try:
                cur = os.stat(path)
            except FileNotFoundError:
                cur = None
            if st.st_nlink == 0 or cur is None or (cur.st_ino, cur.st_dev) != (st.st_ino, st.st_dev):
                os.close(fd)
                continue
            magic, version, ring, slot, readers, entry = _read_header(fd)
            if magic == 0:
                if not create:
                    return fd  # half-initialised: only good for removal
                _initialise(fd, ring_size)
            elif (magic, version, slot, readers, entry) != (
                MAGIC,
                LAYOUT_VERSION,
                SLOT_BYTES,
                MAX_READERS,
                ENTRY_BYTES,
            ) or st.st_size != Layout(ring).total_bytes:
                raise CanInitializationError(
                    f"{path} is not a canbrake channel of this version (layout {LAYOUT_VERSION}); "
                    "if no simulation uses it, remove it with "
                    "canbrake.bus.memory.remove_channel(name, force=True)"
                )
            return fd
        except BaseException:
            os.close(fd)
            raise
    raise CanInitializationError(f"could not open {path}: it keeps being removed and re-created")


def check_private(st: os.stat_result, path: str) -> None:
    """A channel file must belong to this user and be writable by no one else: another local
    user's file would let that user see and inject frames. Raises CanInitializationError."""
    if st.st_uid != os.geteuid():
        try:
            import pwd

            owner = pwd.getpwuid(st.st_uid).pw_name
        except (ImportError, KeyError):
            owner = str(st.st_uid)
        raise CanInitializationError(
            f"{path} belongs to user {owner}, not to you: refusing a channel another user controls "
            "(choose another channel name)")
    if st.st_mode & 0o022:
        raise CanInitializationError(
            f"{path} is writable by others (mode {st.st_mode & 0o777:o}): refusing it "
            "(remove it with `canbrake channels --remove-stale`, or choose another channel name)")


def check_channel_owner(channel: object, shm_dir: Optional[str] = None) -> None:
    """:func:`check_private` for the file of ``channel``, if it exists."""
    name = validate_channel(channel)
    path = bus_path(resolve_dir(shm_dir), name)
    try:
        st = os.lstat(path)
    except FileNotFoundError:
        return
    import stat as _stat

    if _stat.S_ISLNK(st.st_mode):
        raise CanInitializationError(f"{path} is a symbolic link; refusing to use it as a canbrake channel")
    check_private(st, path)


def channel_info(shm_dir: Optional[str] = None) -> list[dict]:
    """Every channel file (and FIFO group) of this user in the shared-memory directory:
    ``{"channel", "path", "pids", "stale"}``; a channel is stale when no live process has it open.
    Other users' channels are listed with ``"owner"`` and never touched."""
    directory = resolve_dir(shm_dir)
    try:
        files = os.listdir(directory)
    except FileNotFoundError:
        return []
    names: set[str] = set()
    for f in files:
        if not f.startswith("canbrake-"):
            continue
        rest = f[len("canbrake-"):]
        name = rest[:-4] if rest.endswith(".bus") else rest.split("@", 1)[0] if "@" in rest else None
        if name and _CHANNEL_RE.match(name):
            names.add(name)
    out = []
    for name in sorted(names):
        path = bus_path(directory, name)
        item: dict = {"channel": name, "path": path, "pids": [], "stale": True}
        try:
            st = os.lstat(path)
            if st.st_uid != os.geteuid():
                item.update(owner=st.st_uid, stale=None)
                out.append(item)
                continue
        except FileNotFoundError:
            pass
        try:
            item["pids"] = channel_pids(name, directory)
        except CanInitializationError as e:
            item["error"] = str(e)
        item["stale"] = not item["pids"]
        out.append(item)
    return out


def clean_stale_channels(shm_dir: Optional[str] = None) -> list[str]:
    """Remove this user's channels that no live process has open (left behind when every process
    of a run was killed); returns their names. Never touches another user's files."""
    removed = []
    for item in channel_info(shm_dir):
        if item["stale"] is True and "error" not in item:
            try:
                if remove_channel(item["channel"], shm_dir):
                    removed.append(item["channel"])
            except (CanOperationError, CanInitializationError, OSError):
                pass
    return removed


def _initialise(fd: int, ring_size: int) -> None:
    if ring_size < 16 or ring_size & (ring_size - 1):
        raise ValueError(f"ring_size must be a power of two >= 16, got {ring_size}")
    layout = Layout(ring_size)
    os.ftruncate(fd, 0)
    os.ftruncate(fd, layout.total_bytes)  # zero-filled
    head = struct.pack("<6Q", 0, LAYOUT_VERSION, ring_size, SLOT_BYTES, MAX_READERS, ENTRY_BYTES)
    os.pwrite(fd, head, 0)
    os.pwrite(fd, struct.pack("<Q", MAGIC), 0)  # magic last: the file is usable from here on


def ring_size_of(fd: int) -> int:
    return _read_header(fd)[H_RING]


def live_entries(q: memoryview) -> list[int]:
    """First words of the occupied reader entries (caller holds the lock)."""
    out = []
    for i in range(MAX_READERS):
        b = Layout.entry_word(i)
        if q[b + E_TOKEN]:
            out.append(b)
    return out


def free_entry(q: memoryview, b: int, directory: str, name: str) -> None:
    """Release reader entry ``b`` and its FIFOs (caller holds the lock)."""
    token = q[b + E_TOKEN]
    if q[b + E_TX_WAITING] and q[H_TX_WAITERS]:
        q[H_TX_WAITERS] = q[H_TX_WAITERS] - 1
    if q[b + E_SLEEPING] and q[H_SLEEPERS]:
        q[H_SLEEPERS] = q[H_SLEEPERS] - 1
    for w in range(ENTRY_BYTES // 8):
        q[b + w] = 0
    q[H_READER_GEN] = q[H_READER_GEN] + 1
    for kind in ("rx", "tx"):
        try:
            os.unlink(fifo_path(directory, name, token, kind))
        except FileNotFoundError:
            pass


def reap_dead(q: memoryview, directory: str, name: str) -> list[int]:
    """Free the entries of processes that died without shutting down; return their pids."""
    dead = []
    for b in live_entries(q):
        pid, start = q[b + E_PID], q[b + E_START]
        if not pid_alive(pid, start):
            dead.append(pid)
            free_entry(q, b, directory, name)
    return dead


def channel_fifos(directory: str, name: str) -> list[str]:
    """Paths of every FIFO of channel ``name`` (live or left behind by crashed processes)."""
    prefix = f"canbrake-{name}@"
    try:
        return [os.path.join(directory, f) for f in os.listdir(directory) if f.startswith(prefix)]
    except FileNotFoundError:
        return []


def remove_fifos(directory: str, name: str) -> None:
    for p in channel_fifos(directory, name):
        try:
            os.unlink(p)
        except FileNotFoundError:
            pass


def _wake_all_fifos(directory: str, name: str) -> None:
    for p in channel_fifos(directory, name):
        try:
            wfd = os.open(p, os.O_WRONLY | os.O_NONBLOCK)
        except OSError:
            continue
        try:
            os.write(wfd, b"\x01")
        except OSError:
            pass
        finally:
            os.close(wfd)


# ---------------------------------------------------------------- public helpers
def remove_channel(channel: object, shm_dir: Optional[str] = None, force: bool = False) -> bool:
    """Remove the files of ``channel`` (for the orchestrator, after a run).

    Entries of dead processes are reaped first. If live processes still have the channel open,
    raise :class:`can.CanOperationError` naming them, unless ``force``: then their buses see the
    channel closed (``recv``/``send`` raise ``CanOperationError``). Returns True if anything was
    removed. Raises :class:`can.CanInitializationError` for an invalid name.
    """
    name = validate_channel(channel)
    directory = resolve_dir(shm_dir)
    path = bus_path(directory, name)
    fd = open_locked(path, DEFAULT_RING_SIZE, create=False)
    removed = False
    if fd is not None:
        try:
            size = os.fstat(fd).st_size
            import mmap

            if _read_header(fd)[H_MAGIC] == MAGIC and size >= HEADER_BYTES + MAX_READERS * ENTRY_BYTES:
                mm = mmap.mmap(fd, size)
                q = memoryview(mm).cast("Q")
                try:
                    reap_dead(q, directory, name)
                    pids = sorted({q[b + E_PID] for b in live_entries(q)})
                    if pids and not force:
                        raise CanOperationError(
                            f"canbrake channel {name!r} is still open in process(es) {pids}; "
                            "shut those buses down first or pass force=True"
                        )
                    q[H_CLOSED] = 1
                finally:
                    q.release()
                    mm.close()
            os.unlink(path)
            removed = True
        finally:
            os.close(fd)  # releases the lock
    before = channel_fifos(directory, name)
    if force:
        _wake_all_fifos(directory, name)
    remove_fifos(directory, name)
    return removed or bool(before)


def list_channels(shm_dir: Optional[str] = None) -> list[str]:
    """Names of the channels that have a file in the shared-memory directory."""
    directory = resolve_dir(shm_dir)
    try:
        files = os.listdir(directory)
    except FileNotFoundError:
        return []
    out = []
    for f in files:
        if f.startswith("canbrake-") and f.endswith(".bus"):
            name = f[len("canbrake-") : -len(".bus")]
            if _CHANNEL_RE.match(name):
                out.append(name)
    return sorted(out)


def channel_pids(channel: object, shm_dir: Optional[str] = None) -> list[int]:
    """Pids of the live processes with a bus open on ``channel`` (one per bus); reaps dead ones."""
    name = validate_channel(channel)
    directory = resolve_dir(shm_dir)
    fd = open_locked(bus_path(directory, name), DEFAULT_RING_SIZE, create=False)
    if fd is None:
        return []
    try:
        if _read_header(fd)[H_MAGIC] != MAGIC:
            return []
        import mmap

        mm = mmap.mmap(fd, os.fstat(fd).st_size)
        q = memoryview(mm).cast("Q")
        try:
            reap_dead(q, directory, name)
            return sorted(q[b + E_PID] for b in live_entries(q))
        finally:
            q.release()
            mm.close()
    finally:
        os.close(fd)


def is_enxio(err: OSError) -> bool:
    return err.errno in (errno.ENXIO, errno.EPIPE, errno.ENOENT)
