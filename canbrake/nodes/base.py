"""Node state machines: transport-agnostic, event-driven.

A node never touches a bus. A driver (:mod:`canbrake.nodes.driver`) feeds it received frames
and sends the frames it returns, whether the driver is an OS process on the in-memory bus or
SocketCAN, or the in-process engine. The same node objects therefore produce the same frames on
every backend in lockstep mode.

Lockstep protocol, per control period k (T = control period)::

    plant : SYNC(k), REFERENCE, [COUPLER_Ci], SENSOR_Ci ...          (phase 0)
    ECU i : on SENSOR_Ci -> STATE_Ci, STATE_DONE_Ci(k)                (phase 1)
    ECU i : when STATE_DONE_Cj(k) seen for every peer j -> compute,
            BRAKE_CMD_Ci, CMD_DONE_Ci(k)                              (phase 2)
    plant : when CMD_DONE_Ci(k) seen for every i -> integrate to k+1

The *_DONE frames are the barrier: a CAN bus delivers frames in one order to every listener and
each sender's frames stay in order, so once STATE_DONE_Cj(k) is seen, every frame ECU j released
in phase 1 of tick k has been seen as well (including none, if its state frame was lost). They
are exempt from impairments. Frames whose latency (impairment delay, bus timing) reaches one
control period are held by the sender's send path and released in the same phase of a later
tick, so loss and delay are decided in simulated ticks and runs stay deterministic.
"""
from __future__ import annotations

import contextlib
import csv
import math
from abc import ABC, abstractmethod
from pathlib import Path
from typing import Any, Callable, Iterator, Protocol

import can
import numpy as np

from canbrake.bus._ring import data_frame
from canbrake.nodes._trace import LogHistogram, csv_dict_row, csv_row  # noqa: F401  (LogHistogram: also imported from here)


class SendPath(Protocol):
    """What a node's outgoing frames pass through (impairments, bus timing)."""

    def submit(self, msg: can.Message, t_s: float, delay_s: float = 0.0) -> list[can.Message]:
        """Frames to send now (possibly none, possibly duplicates); ``delay_s`` (s, e.g. the bus
        latency of the timing model) holds the frame until ``t_s + delay_s``."""

    def release(self, t_s: float) -> list[can.Message]:
        """Held frames that are due at simulated/wall time ``t_s``."""


class PassThrough:
    """Send path without impairments."""

    def submit(self, msg: can.Message, t_s: float, delay_s: float = 0.0) -> list[can.Message]:
        return [msg]

    def release(self, t_s: float) -> list[can.Message]:
        return []


class Node(ABC):
    """A bus participant."""

    name: str = "node"
    finished: bool = False
    #: realtime: the scheduling this node's process obtained (canbrake.nodes.rt), None otherwise
    scheduling: str | None = None
    #: the node whose end is the end of the run (the plant): once it has finished, a driver ends
    #: the others that are still waiting (e.g. for an END frame they would not trust)
    time_master: bool = False
    #: set by the memory bus's node driver (:func:`canbrake.nodes.driver.drive`), whose send
    #: takes a burst as slot images (bytes) too: a node may then return its frames that way
    #: from :meth:`on_timer` as well as from ``handle_raw`` (no ``can.Message`` made for them)
    sends_images: bool = False

    def filters(self) -> list[dict[str, Any]] | None:
        """python-can filters for the frames this node needs (None = all)."""
        return None

    def start(self, now: float) -> list[can.Message]:
        """Frames to send when the run starts (``now``: wall time, s)."""
        return []

    @abstractmethod
    def handle(self, msg: can.Message, now: float) -> list[can.Message]:
        """React to one received frame; return frames to send."""

    def handle_batch(self, msgs: list[can.Message], now: float) -> list[can.Message]:
        """React to frames received together (in bus order); return frames to send. The drivers
        deliver every frame a node accepted since its last call in one batch, so a node's Python
        side runs once per batch (a lockstep phase) rather than once per frame; a node overrides
        this where it can do a batch's work at once. Stops at the frame that finished the node."""
        out: list[can.Message] = []
        for m in msgs:
            out += self.handle(m, now)
            if self.finished:
                break
        return out

    def batch_handler(self) -> Callable[[list[can.Message], float], list[can.Message]]:
        """:meth:`handle_batch` as the in-process Router calls it (a list of frames, the time), bound
        once: a node may give a compiled callable that does the same."""
        return self.handle_batch

    def frames_wanted(self) -> int:
        """How many frames this node needs, at least, before it can go on: a driver on the memory
        bus sleeps until that many have come (``MemoryBus.recv_batch(min_frames=...)``) instead
        of waking at each. Must never exceed what will surely come; 1 by default."""
        return 1

    def after_send(self) -> None:
        """Called by a node process's driver once the frames this node returned are on the bus:
        work that need not hold them back (the plant writes its trace row here while the ECUs
        compute). Nothing by default."""

    def next_deadline(self) -> float | None:
        """Wall time (s) at which :meth:`on_timer` must run, or None (realtime mode only)."""
        return None

    def on_timer(self, now: float) -> list[can.Message]:
        """Called at or after :meth:`next_deadline`."""
        return []

    def on_rx_overrun(self, frames_lost: int) -> None:
        """The receive queue overflowed and ``frames_lost`` frames were dropped (a flood): counted
        by the node's receiver checks (``guard``, :mod:`canbrake.bus.guard`) when it has them."""
        guard = getattr(self, "guard", None)
        if guard is not None:
            guard.overrun(frames_lost)

    def close(self, status: str = "ok") -> None:
        """Flush traces and statistics; called once, also after an error."""


#: hand every trace row to the OS as it is written (a node in its own process: SIGKILL loses at
#: most its current row); False while every node runs in one process (:func:`buffered_traces`)
_ROW_BY_ROW = [True]


@contextlib.contextmanager
def buffered_traces() -> Iterator[None]:
    """Traces opened inside are written through the file's buffer, not row by row: for the
    in-process engine, whose nodes all live and die with the one process that closes (and so
    flushes) them; a write per row and node was ~10 % of a 106-ECU period."""
    _ROW_BY_ROW.append(False)
    try:
        yield
    finally:
        _ROW_BY_ROW.pop()


def rows_by_row() -> bool:
    """True where files opened now hand each period's lines to the OS at once (a node in its
    own process); False inside :func:`buffered_traces` (the in-process engine)."""
    return _ROW_BY_ROW[-1]


class CsvTrace:
    """A CSV trace written as it goes: the header at once, then every row handed to the OS as it
    is appended (one ``write`` per row through a buffered file: one control period per row), so
    a node killed with SIGKILL loses at most its current row; inside :func:`buffered_traces` rows
    stay in the file's buffer until it fills or closes. ``flush_every`` is accepted for
    compatibility and ignored. Floats are written with 9 significant digits."""

    def __init__(self, path: Path | None, header: list[str], flush_every: int = 1) -> None:
        self.flush_every = flush_every
        self._row_by_row = _ROW_BY_ROW[-1]
        self._file = open(path, "w", newline="") if path is not None else None
        self._writer = csv.writer(self._file) if self._file is not None else None
        if self._writer is not None:
            self._writer.writerow(header)
            self._file.flush()  # type: ignore[union-attr]

    def append(self, row: list[Any]) -> None:
        if self._writer is None:
            return
        # The row's text in one compiled call (canbrake.nodes._trace.csv_row) instead of the csv
        # module's per-field work: the same bytes as csv.writer with floats as f"{v:.9g}"
        # (signals.csv of a 106-vehicle train is ~1,100 values per period). Rows with values it
        # does not write (str, None, ...) take the csv writer.
        self._write(csv_row(row) if type(row) is list else None, row)

    def append_text(self, text: str) -> None:
        """Append a row already made as csv text (a whole line, ``\\r\\n`` included)."""
        if self._writer is not None:
            self._write(text, None)

    def append_dict(self, head: list[Any], values: dict[str, Any], names: tuple[str, ...], default: Any,
                    tail: list[Any]) -> None:
        """``append(head + [values.get(n, default) for n in names] + tail)``, the row's text made
        in one compiled call (an ECU's row: its controller's diagnostics by name)."""
        if self._writer is None:
            return
        text = csv_dict_row(head, values, names, default, tail) if type(values) is dict else None
        self._write(text, None if text is not None else [*head, *[values.get(n, default) for n in names], *tail])

    def row_write(self) -> Callable[[str], Any] | None:
        """The file's ``write`` for a row's text when rows go through its buffer (inside
        :func:`buffered_traces`), to call in place of :meth:`append_text`; None when rows are
        flushed one by one or there is no file."""
        return self._file.write if self._file is not None and not self._row_by_row else None

    def row_fd(self) -> int:
        """The file's descriptor when each row is handed to the OS as it is appended (outside
        :func:`buffered_traces`): a caller may write a row's text there itself (one ``write(2)``,
        :func:`canbrake.nodes._trace.write_text`), in place of :meth:`append_text` (the file's
        buffers are empty between rows); -1 otherwise."""
        return self._file.fileno() if self._file is not None and self._row_by_row else -1

    def _write(self, text: str | None, row: list[Any] | None) -> None:
        """Write a row's text, or (None) the row through the csv writer."""
        if text is not None:
            self._file.write(text)  # type: ignore[union-attr]
        else:
            self._writer.writerow([f"{v:.9g}" if isinstance(v, float) else v for v in row])  # type: ignore[union-attr]
        if self._row_by_row:
            self._file.flush()  # type: ignore[union-attr]

    def flush(self) -> None:
        if self._file is not None:
            self._file.flush()

    def close(self) -> None:
        if self._file is not None:
            try:
                self._file.close()
            finally:
                path = self._file.name
                self._file = None
                self._writer = None
                trim_partial_line(path)  # a full disk may have cut the last row short


def trim_partial_line(path: str | Path) -> None:
    """Cut a text file after its last complete line: a write cut short (full disk, a killed
    writer) must not leave half a frame or row that a reader takes for a shorter one."""
    try:
        with open(path, "rb+") as f:
            size = f.seek(0, 2)
            if size == 0:
                return
            back = min(size, 4096)
            f.seek(size - back)
            tail = f.read()
            if tail.endswith(b"\n"):
                return
            cut = tail.rfind(b"\n")
            f.truncate(size - back + cut + 1 if cut >= 0 else (0 if back == size else size))
    except OSError:
        pass


#: frame(arbitration_id, data) -> can.Message: a classic data frame; identifiers above 0x7FF are
#: 29-bit (extended). Compiled (canbrake.bus._ring.data_frame): a node sends one per frame.
frame = data_frame


def exact_filter(arbitration_id: int, extended: bool | None = None) -> dict[str, Any]:
    """A python-can filter matching exactly one identifier (29-bit if ``extended`` or id > 0x7FF)."""
    ext = arbitration_id > 0x7FF if extended is None else extended
    return {"can_id": arbitration_id, "can_mask": 0x1FFFFFFF if ext else 0x7FF, "extended": ext}
