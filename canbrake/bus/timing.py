"""Wire-level timing model of one classic CAN bus (ISO 11898-1, CAN 2.0A/B).

Two layers, both pure (no processes, no bus I/O):

* :func:`frame_bits` — how many bit times one classic CAN data or remote frame takes on the
  wire, with the bit-stuffing rule applied worst-case, exactly (``"actual"``: the real bit
  stream including the CRC-15 is built and stuffed) or not at all.
* :class:`BusTimingModel` — a deterministic discrete-event model of one bus in *simulated*
  seconds: per-node transmit queues, non-preemptive transmission, arbitration by identifier
  when the bus goes idle, bus load and per-message latency statistics.

Why our own code: python-can and cantools describe frames (identifier, DLC, payload, DBC
signals) but have no wire-level model — no stuff bits, no CRC-15, no arbitration or bus time —
so there is nothing to reuse for this.

Frame layout counted here (bits, before stuffing)::

    standard: SOF 1 | ID 11 | RTR 1 | IDE 1 | r0 1 | DLC 4 | DATA 8n | CRC 15     = 34 + 8n
    extended: SOF 1 | ID 11 | SRR 1 | IDE 1 | ID 18 | RTR 1 | r1 1 | r0 1 | DLC 4
              | DATA 8n | CRC 15                                                  = 54 + 8n
    then (never stuffed): CRC delimiter 1 | ACK slot 1 | ACK delimiter 1 | EOF 7  = 10
    then the interframe space (intermission) 3, counted unless ``include_ifs=False``.

Stuffing covers SOF..CRC sequence: after five equal bits the transmitter inserts one bit of
the opposite level, and that stuff bit counts towards the next run. The classic worst-case
bound on stuff bits is ``(g + 8n - 1) // 4`` with ``g = 34`` (standard) or ``54`` (extended)
(Davis, Burns, Bril, Lukkien 2007). Remote frames have no data field (``n = 0`` whatever DLC).

How it fits on the send path: an impairment chain (:mod:`canbrake.bus.impair`) decides *when*
a frame may go to the bus (``TxFrame.t_release_s``); :meth:`BusTimingModel.submit` queues it
at that instant, and :meth:`BusTimingModel.advance` says when it actually went out.
"""
from __future__ import annotations

import math
from dataclasses import dataclass
from functools import lru_cache
from typing import Any, Literal, Sequence

import numpy as np

from canbrake.bus import _wire
from canbrake.bus._timing import Delivery, EventCore, Pending, Ticket

__all__ = [
    "Stuffing",
    "QueuePolicy",
    "IFS_BITS",
    "TIME_EPS_S",
    "STANDARD_BITRATES_BPS",
    "crc15",
    "stuff_bit_count",
    "frame_bitstream",
    "frame_bits",
    "frame_time_s",
    "Ticket",
    "Delivery",
    "LatencyStats",
    "LoadStats",
    "BusTimingModel",
]

Stuffing = Literal["worst", "actual", "none"]
QueuePolicy = Literal["priority", "fifo"]

#: bits of the interframe space (intermission) between two frames
IFS_BITS = 3
#: bits after the CRC sequence that are never stuffed: CRC delim, ACK slot, ACK delim, EOF
_TRAILER_BITS = 1 + 1 + 1 + 7
#: stuffable bits before the data field + CRC: SOF..DLC plus CRC-15
_STUFFED_OVERHEAD = {False: 34, True: 54}
#: common classic CAN bit rates (any positive rate up to 1 Mbit/s is accepted)
STANDARD_BITRATES_BPS = (10_000, 20_000, 50_000, 83_333, 100_000, 125_000, 250_000, 500_000,
                         800_000, 1_000_000)
_MAX_BITRATE_BPS = 1_000_000
_MAX_STD_ID = 0x7FF
_MAX_EXT_ID = 0x1FFF_FFFF
_CRC15_POLY = 0x4599
_STUFFINGS = ("worst", "actual", "none")
#: time tolerance (s) for causality checks, far below one bit time (1 µs at 1 Mbit/s), so that
#: ``k * period`` and a running sum of periods that differ by float rounding are the same instant
TIME_EPS_S = 1e-12


# --------------------------------------------------------------------------------------------
# validation


def _check_frame(arbitration_id: int, is_extended: bool, dlc: int) -> None:
    if isinstance(arbitration_id, bool) or not isinstance(arbitration_id, (int, np.integer)):
        raise TypeError(f"arbitration_id must be an int, got {arbitration_id!r}")
    limit = _MAX_EXT_ID if is_extended else _MAX_STD_ID
    if not 0 <= arbitration_id <= limit:
        kind = "extended (29-bit)" if is_extended else "standard (11-bit)"
        raise ValueError(f"arbitration_id 0x{int(arbitration_id):X} out of range for a {kind} "
                         f"frame: 0x0..0x{limit:X}")
    if isinstance(dlc, bool) or not isinstance(dlc, (int, np.integer)) or not 0 <= dlc <= 8:
        raise ValueError(f"dlc must be an int 0..8 for classic CAN, got {dlc!r}")


def _check_stuffing(stuffing: str) -> None:
    if stuffing not in _STUFFINGS:
        raise ValueError(f"stuffing must be one of {_STUFFINGS}, got {stuffing!r}")


def _check_bitrate(bitrate_bps: float) -> float:
    if isinstance(bitrate_bps, bool) or not isinstance(bitrate_bps, (int, float, np.number)):
        raise TypeError(f"bitrate_bps must be a number, got {bitrate_bps!r}")
    rate = float(bitrate_bps)
    if not math.isfinite(rate) or rate <= 0:
        raise ValueError(f"bitrate_bps must be a positive finite number, got {bitrate_bps!r}")
    if rate > _MAX_BITRATE_BPS:
        raise ValueError(f"bitrate_bps={bitrate_bps!r} exceeds 1 Mbit/s, the classic CAN maximum "
                         "(CAN FD data phases are not modelled)")
    return rate


def _check_time(name: str, value: float) -> float:
    t = float(value)
    if not math.isfinite(t):
        raise ValueError(f"{name} must be a finite time in seconds, got {value!r}")
    return t


# --------------------------------------------------------------------------------------------
# bit-level reference: CRC-15 and stuffing


def crc15(bits: Sequence[int], init: int = 0) -> int:
    """CAN CRC-15 (polynomial 0x4599, init 0, no reflection, no final XOR) of a bit sequence.

    ``bits`` are 0/1 in transmission order (SOF first). Returns the 15-bit remainder.
    """
    crc = init
    for b in bits:
        top = ((crc >> 14) & 1) ^ (b & 1)
        crc = (crc << 1) & 0x7FFF
        if top:
            crc ^= _CRC15_POLY
    return crc


def _stuff_run(bits: Sequence[int], state: tuple[int, int] = (1, 0)) -> tuple[int, tuple[int, int]]:
    """Count stuff bits inserted into ``bits`` starting from ``state = (last level, run length)``.

    Returns ``(n_stuff, new_state)``. A stuff bit is inserted after every fifth equal bit,
    including after the last bit of ``bits``; it starts a new run of length 1.
    """
    last, run = state
    n = 0
    for b in bits:
        if b == last:
            run += 1
        else:
            last, run = b, 1
        if run == 5:
            n += 1
            last, run = 1 - last, 1
    return n, (last, run)


def stuff_bit_count(bits: Sequence[int]) -> int:
    """Number of stuff bits CAN inserts into ``bits`` (0/1 levels, the SOF..CRC span)."""
    return _stuff_run(bits)[0]


def _int_bits(value: int, width: int) -> list[int]:
    return [(value >> (width - 1 - i)) & 1 for i in range(width)]


def _header_bits(arbitration_id: int, is_extended: bool, dlc: int, is_remote: bool) -> list[int]:
    """SOF..DLC in transmission order (dominant = 0)."""
    rtr = 1 if is_remote else 0
    if is_extended:
        return ([0] + _int_bits(arbitration_id >> 18, 11) + [1, 1]
                + _int_bits(arbitration_id & 0x3FFFF, 18) + [rtr, 0, 0] + _int_bits(dlc, 4))
    return [0] + _int_bits(arbitration_id, 11) + [rtr, 0, 0] + _int_bits(dlc, 4)


def frame_bitstream(arbitration_id: int, is_extended: bool, dlc: int, data: bytes = b"",
                    *, is_remote: bool = False) -> list[int]:
    """Unstuffed bit stream SOF..CRC sequence of a classic frame (reference implementation).

    The CRC-15 covers SOF through the data field. ``data`` must hold ``dlc`` bytes for a data
    frame and is ignored for a remote frame.
    """
    _check_frame(arbitration_id, is_extended, dlc)
    bits = _header_bits(arbitration_id, is_extended, dlc, is_remote)
    if not is_remote:
        payload = _payload(data, dlc)
        for byte in payload:
            bits += _int_bits(byte, 8)
    return bits + _int_bits(crc15(bits), 15)


def _payload(data: bytes | Sequence[int] | None, dlc: int) -> bytes:
    if data is None:
        raise ValueError("stuffing='actual' needs the payload: data is None")
    payload = bytes(data)
    if len(payload) != dlc:
        raise ValueError(f"data has {len(payload)} bytes but dlc is {dlc}")
    return payload


def _actual_stuff_bits(arbitration_id: int, is_extended: bool, dlc: int, data: bytes,
                       is_remote: bool) -> int:
    """Stuff bits of a checked frame, computed by the compiled core (:mod:`canbrake.bus._wire`:
    header bit by bit, payload and CRC-15 through byte tables); ``frame_bitstream`` and
    ``stuff_bit_count`` above are the reference it is tested against."""
    return _wire.stuff_bits(int(arbitration_id), bool(is_extended), int(dlc), data, bool(is_remote))


# --------------------------------------------------------------------------------------------
# public frame-length functions


def frame_bits(arbitration_id: int, is_extended: bool, dlc: int,
               data: bytes | Sequence[int] | None = None,
               stuffing: Stuffing = "worst", *, is_remote: bool = False,
               include_ifs: bool = True) -> int:
    """Bit times one classic CAN frame occupies on the wire.

    Counts SOF, arbitration, control, data, CRC-15, CRC/ACK delimiters, ACK slot, EOF and —
    unless ``include_ifs=False`` — the 3-bit interframe space, plus stuff bits:

    * ``"worst"``: the standard bound ``(34|54 + 8·n − 1) // 4`` (``data`` not needed);
    * ``"actual"``: the real stream with its CRC-15 is stuffed (``data`` of ``dlc`` bytes needed
      for a data frame);
    * ``"none"``: no stuff bits (the lower bound).

    Example: 8-byte standard frame, worst case, with IFS: 135 bits = 270 µs at 500 kbit/s.
    """
    _check_frame(arbitration_id, is_extended, dlc)
    _check_stuffing(stuffing)
    n_data = 0 if is_remote else int(dlc)
    stuffable = _STUFFED_OVERHEAD[bool(is_extended)] + 8 * n_data
    total = stuffable + _TRAILER_BITS + (IFS_BITS if include_ifs else 0)
    if stuffing == "worst":
        total += (stuffable - 1) // 4
    elif stuffing == "actual":
        payload = b"" if is_remote else _payload(data, int(dlc))
        total += _actual_stuff_bits(arbitration_id, is_extended, dlc, payload, is_remote)
    if data is not None and not is_remote and stuffing != "actual" and len(data) != dlc:
        raise ValueError(f"data has {len(data)} bytes but dlc is {dlc}")
    return total


@lru_cache(maxsize=4096)
def _unstuffed_bits(arbitration_id: int, is_extended: bool, dlc: int) -> int:
    return frame_bits(arbitration_id, is_extended, dlc, stuffing="none")


def actual_frame_bits(arbitration_id: int, is_extended: bool, dlc: int, data: bytes) -> int:
    """``frame_bits(arbitration_id, is_extended, dlc, data, stuffing="actual")`` of a data frame
    (bits, with IFS), the identifier checked once per (id, dlc): the recorder's per-frame path."""
    if len(data) != dlc:
        return frame_bits(arbitration_id, is_extended, dlc, data, stuffing="actual")
    return _unstuffed_bits(arbitration_id, is_extended, dlc) + _actual_stuff_bits(
        arbitration_id, is_extended, dlc, data, False)


def frame_time_s(bits: int, bitrate_bps: float) -> float:
    """Seconds ``bits`` bit times take at ``bitrate_bps`` bit/s."""
    return bits / _check_bitrate(bitrate_bps)


# --------------------------------------------------------------------------------------------
# discrete-event bus model


# Ticket and Delivery: the compiled core's classes (canbrake.bus._timing)


@dataclass(frozen=True)
class LatencyStats:
    """Latency (end of transmission − queued, s) over delivered frames of one selection.

    ``n_pending`` frames of the selection are not delivered yet (queued, or on the wire past
    ``now_s``); the oldest has waited
    ``max_pending_age_s`` (a lower bound on its eventual latency; 0 if none). Percentiles are
    NaN when nothing was delivered.
    """

    n_delivered: int
    n_pending: int
    mean_s: float
    p50_s: float
    p95_s: float
    p99_s: float
    max_s: float
    max_pending_age_s: float


@dataclass(frozen=True)
class LoadStats:
    """Bus load per control period.

    ``busy_fraction[k]`` is the share of period k the bus was transmitting (≤ 1, what a bus
    analyser shows); ``offered_load[k]`` is the transmission time of the frames *queued* in
    period k divided by the period — above 1 the traffic does not fit and queues grow.
    Arrays have shape ``(n_periods,)``; period k is ``[t_from_s + k·period_s, … + period_s)``.
    """

    period_s: float
    t_from_s: float
    busy_fraction: np.ndarray
    offered_load: np.ndarray

    @property
    def mean_busy(self) -> float:
        return float(np.mean(self.busy_fraction)) if self.busy_fraction.size else math.nan

    @property
    def peak_busy(self) -> float:
        return float(np.max(self.busy_fraction)) if self.busy_fraction.size else math.nan

    @property
    def mean_offered(self) -> float:
        return float(np.mean(self.offered_load)) if self.offered_load.size else math.nan

    @property
    def peak_offered(self) -> float:
        return float(np.max(self.offered_load)) if self.offered_load.size else math.nan


def _arbitration_key(arbitration_id: int, is_extended: bool, is_remote: bool) -> tuple[int, ...]:
    """Order in which frames win arbitration (smaller wins), bit by bit as on the wire.

    Base ID first; then standard RTR vs extended SRR (recessive); then IDE (standard wins);
    then the 18-bit ID extension; then RTR (data frame beats remote frame). The compiled core
    packs the same order into one integer (:func:`canbrake.bus._timing.arb_key`).
    """
    rtr = 1 if is_remote else 0
    if is_extended:
        return (arbitration_id >> 18, 1, 1, arbitration_id & 0x3FFFF, rtr)
    return (arbitration_id, rtr, 0, 0, 0)


class BusTimingModel(EventCore):
    """Deterministic discrete-event model of one classic CAN bus, in simulated seconds.

    Each node has a transmit queue; ``queue_policy="priority"`` sends a node's lowest
    identifier first (a controller with several mailboxes), ``"fifo"`` sends in queue order
    (a single mailbox / software FIFO). Whenever the bus goes idle, the heads of the queues
    of all nodes with a frame queued at that instant arbitrate; the lowest identifier wins
    (:func:`_arbitration_key`) and is transmitted without pre-emption. Two nodes sending the
    same arbitration field (an error on a real bus) are ordered by queue time, then submission.

    Times within ``TIME_EPS_S`` (1 ps) count as the same instant, so that ``k * period`` and a
    running sum of periods that differ by float rounding arbitrate alike. Causality:
    :meth:`advance` commits only arbitrations before ``until_s − 2·TIME_EPS_S``; afterwards
    frames may be submitted with ``t_queue_s >= now_s − TIME_EPS_S``.

    Args:
        bitrate_bps: bit rate, > 0 and ≤ 1 Mbit/s (125k, 250k, 500k and 1M are the usual).
        stuffing: stuff-bit model for frame lengths, see :func:`frame_bits`.
        queue_policy: ``"priority"`` (default) or ``"fifo"`` within a node.
        include_ifs: count the 3-bit interframe space in each frame's bus time.
        record_history: keep what load and latency statistics need (O(frames) memory).
        faults: error sources and fault confinement (:mod:`canbrake.bus.faults`): failed
            attempts become error frames on the bus and are retransmitted; a bus-off node's
            frames are dropped (see :meth:`pop_dropped`). None = an error-free bus.
        tx_buffers: per-node transmit buffers (:class:`canbrake.bus.txbuffer.TxBufferConfig`:
            priority / FIFO of a depth / mailboxes with or without abort); the first config that
            applies to a node is its buffer, other nodes follow ``queue_policy``. A frame
            submitted to a full buffer is dropped (see :meth:`pop_dropped`).
    """

    def __init__(self, bitrate_bps: float, *, stuffing: Stuffing = "worst",
                 queue_policy: QueuePolicy = "priority", include_ifs: bool = True,
                 record_history: bool = True, faults: Any = None,
                 tx_buffers: Sequence[Any] | None = None) -> None:
        rate = _check_bitrate(bitrate_bps)
        _check_stuffing(stuffing)
        if queue_policy not in ("priority", "fifo"):
            raise ValueError(f"queue_policy must be 'priority' or 'fifo', got {queue_policy!r}")
        # queues, arbitration, transmission and the history lists: the compiled core
        super().__init__(rate, stuffing, queue_policy, bool(include_ifs), bool(record_history), faults, tx_buffers)

    # -- properties ---------------------------------------------------------------------------
    @property
    def now_s(self) -> float:
        """Time up to which :meth:`advance` has run (−inf before the first call)."""
        return self._now

    @property
    def busy_until_s(self) -> float:
        """End of the last frame that has started (−inf if none)."""
        return self._bus_free_at

    def bit_time_s(self) -> float:
        """Duration of one bit (s)."""
        return 1.0 / self.bitrate_bps

    def frame_duration_s(self, arbitration_id: int, is_extended: bool, dlc: int,
                         data: bytes | None = None, *, is_remote: bool = False) -> float:
        """Bus time (s) of one frame under this model's stuffing and IFS settings."""
        return frame_bits(arbitration_id, is_extended, dlc, data, self.stuffing,
                          is_remote=is_remote, include_ifs=self.include_ifs) / self.bitrate_bps

    def _pending(self) -> list[Pending]:
        return (list(self._future) + [p for q in self._ready.values() for p in q]
                + [p for b in self._buffers.values() for p in b.pending()])

    def buffer_counters(self) -> dict[str, dict[str, int]]:
        """Per node with a configured buffer: frames dropped on overflow, mailbox aborts."""
        return {n: {"overflow": b.n_overflow, "aborted": b.n_aborted} for n, b in sorted(self._buffers.items())}

    def pending_count(self, node: str | None = None, msg_id: int | None = None) -> int:
        """Frames submitted but not yet started, optionally for one node and/or identifier."""
        if node is None and msg_id is None:
            return len(self._future) + self._n_ready
        return sum(1 for p in self._pending()
                   if (node is None or p.ticket.node == node)
                   and (msg_id is None or p.ticket.arbitration_id == msg_id))

    # -- input (submit: EventCore) ----------------------------------------------------------
    def submit_message(self, node: str, msg: Any, t_queue_s: float, *, tag: Any = None) -> Ticket:
        """Queue a ``can.Message`` (duck-typed: arbitration_id, is_extended_id, dlc, data,
        is_remote_frame). CAN FD frames are refused."""
        if getattr(msg, "is_fd", False):
            raise ValueError("CAN FD frames are not modelled by BusTimingModel (classic CAN only)")
        remote = bool(getattr(msg, "is_remote_frame", False))
        data = None if remote else bytes(msg.data)
        return self.submit(node, msg.arbitration_id, bool(msg.is_extended_id), int(msg.dlc),
                           data, t_queue_s, is_remote=remote, tag=msg if tag is None else tag)

    # -- simulation: EventCore.advance, next_event_s, pop_dropped (compiled) -----------------

    # -- statistics ---------------------------------------------------------------------------
    def _need_history(self) -> None:
        if not self.record_history:
            raise RuntimeError("statistics need BusTimingModel(record_history=True)")

    def _busy_cumulative(self, t: np.ndarray) -> np.ndarray:
        """Total busy time in (−inf, t] for each t."""
        starts = np.asarray(self._busy_start)
        ends = np.asarray(self._busy_end)
        if starts.size == 0:
            return np.zeros_like(t)
        prefix = np.concatenate(([0.0], np.cumsum(ends - starts)))
        k = np.searchsorted(starts, t, side="right")  # intervals with start <= t
        last = np.maximum(k - 1, 0)
        partial = np.where(k > 0, np.minimum(t, ends[last]) - starts[last], 0.0)
        return np.where(k > 0, prefix[last], 0.0) + partial

    def bus_load(self, t_from_s: float, t_to_s: float) -> float:
        """Busy time / window length over ``[t_from_s, t_to_s]`` (in [0, 1]).

        Only frames that have started count, so the window must end by :attr:`now_s`.
        """
        self._need_history()
        a, b = self._window(t_from_s, t_to_s)
        if b > self._now:
            raise ValueError(f"t_to_s={b!r} is after now_s={self._now!r}: advance() the model "
                             "first, the future of the bus is not known yet")
        busy = self._busy_cumulative(np.array([a, b]))
        return float((busy[1] - busy[0]) / (b - a))

    def offered_load(self, t_from_s: float, t_to_s: float) -> float:
        """Transmission time of frames queued in ``[t_from_s, t_to_s)`` / window length.

        Above 1 the traffic cannot fit, whatever the arbitration order.
        """
        self._need_history()
        a, b = self._window(t_from_s, t_to_s)
        tq = np.asarray(self._offered_t)
        dur = np.asarray(self._offered_dur)
        return float(dur[(tq >= a) & (tq < b)].sum() / (b - a))

    def load_stats(self, period_s: float, t_from_s: float = 0.0,
                   t_to_s: float | None = None) -> LoadStats:
        """Per-period busy fraction and offered load over ``[t_from_s, t_to_s)`` (whole periods).

        ``t_to_s`` defaults to :attr:`now_s`. Queue times within 1e-9 periods of a period
        boundary count in the later period (robust to float rounding of ``k·period``).
        """
        self._need_history()
        period = _check_time("period_s", period_s)
        if period <= 0:
            raise ValueError(f"period_s must be > 0, got {period_s!r}")
        t_to = self._now if t_to_s is None else t_to_s
        a, b = self._window(t_from_s, t_to)
        if b > self._now:
            raise ValueError(f"t_to_s={b!r} is after now_s={self._now!r}: advance() first")
        n = int(math.floor((b - a) / period + 1e-9))
        edges = a + period * np.arange(n + 1)
        busy_cum = self._busy_cumulative(edges)
        busy = np.diff(busy_cum) / period
        tq = np.asarray(self._offered_t)
        dur = np.asarray(self._offered_dur)
        idx = np.floor((tq - a) / period + 1e-9).astype(np.int64) if tq.size else tq.astype(int)
        keep = (idx >= 0) & (idx < n)
        offered = np.bincount(idx[keep], weights=dur[keep], minlength=n)[:n] / period
        return LoadStats(period, a, busy, offered)

    def latency_stats(self, msg_id: int | None = None, *, is_extended: bool | None = None,
                      node: str | None = None) -> LatencyStats:
        """Latency percentiles (s) of delivered frames, filtered by identifier / node."""
        self._need_history()
        values: list[float] = []
        for (mid, ext, name), lats in self._lat_node.items():
            if msg_id is not None and mid != msg_id:
                continue
            if is_extended is not None and ext != is_extended:
                continue
            if node is not None and name != node:
                continue
            values.extend(lats)
        oldest = math.inf
        n_pending = 0
        for p in self._pending():
            tk = p.ticket
            if ((node is None or tk.node == node)
                    and (msg_id is None or tk.arbitration_id == msg_id)
                    and (is_extended is None or tk.is_extended == is_extended)):
                n_pending += 1
                oldest = min(oldest, tk.t_queue_s)
        for d in self._committed:  # on the wire, not finished by now_s
            if ((msg_id is None or d.arbitration_id == msg_id)
                    and (is_extended is None or d.is_extended == is_extended)
                    and (node is None or d.node == node)):
                n_pending += 1
                oldest = min(oldest, d.t_queue_s)
        age = max(0.0, self._now - oldest) if n_pending and oldest <= self._now else 0.0
        return _latency_stats(values, n_pending, age)

    def latency_by_message(self) -> dict[tuple[int, bool], LatencyStats]:
        """:meth:`latency_stats` for every (arbitration_id, is_extended) seen, sorted by id."""
        self._need_history()
        keys = set(self._lat)
        keys.update((p.ticket.arbitration_id, p.ticket.is_extended) for p in self._pending())
        keys.update((d.arbitration_id, d.is_extended) for d in self._committed)
        return {k: self.latency_stats(k[0], is_extended=k[1])
                for k in sorted(keys, key=lambda k: (k[0], k[1]))}

    def _window(self, t_from_s: float, t_to_s: float) -> tuple[float, float]:
        a = _check_time("t_from_s", t_from_s)
        b = _check_time("t_to_s", t_to_s)
        if not b > a:
            raise ValueError(f"empty window: t_to_s={t_to_s!r} must be > t_from_s={t_from_s!r}")
        return a, b


def _latency_stats(values: list[float], n_pending: int, pending_age: float) -> LatencyStats:
    if not values:
        nan = math.nan
        return LatencyStats(0, n_pending, nan, nan, nan, nan, nan, pending_age)
    arr = np.asarray(values)
    p50, p95, p99 = np.percentile(arr, [50, 95, 99])
    return LatencyStats(int(arr.size), n_pending, float(arr.mean()), float(p50), float(p95),
                        float(p99), float(arr.max()), pending_age)
