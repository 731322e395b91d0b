"""Worst-case response-time analysis of periodic CAN messages (pure; no bus, no processes).

Implements the revised analysis of Davis, Burns, Bril and Lukkien, "Controller Area Network
(CAN) schedulability analysis: refuted, revisited and revised", Real-Time Systems 35:239-272
(2007), section 5 ("exact" analysis for fixed-priority non-pre-emptive CAN arbitration):

* transmission time ``C_m``: worst-case bit stuffing, 3-bit interframe space included —
  ``(g + 8·s + 13 + ⌊(g + 8·s − 1)/4⌋)·τ_bit`` with ``g = 34`` (11-bit) or ``54`` (29-bit),
  exactly :func:`canbrake.bus.timing.frame_bits` with ``stuffing="worst"``;
* blocking ``B_m = max_{k ∈ lp(m)} C_k`` (the longest lower-priority frame already on the wire);
* priority level-m busy period ``t_m = B_m + Σ_{k ∈ hep(m)} ⌈(t_m + J_k)/T_k⌉·C_k`` and the
  number of instances of m in it ``Q_m = ⌈(t_m + J_m)/T_m⌉``;
* for every instance q = 0..Q_m−1 the queueing delay
  ``w_m(q) = B_m + q·C_m + Σ_{k ∈ hp(m)} ⌈(w_m(q) + J_k + τ_bit)/T_k⌉·C_k`` and the response
  time ``R_m(q) = J_m + w_m(q) − q·T_m + C_m``; ``R_m = max_q R_m(q)``.

The original analysis (Tindell, Burns and Wellings 1994/1995) looked at q = 0 only. It is
optimistic when the previous instance of m is "pushed through" into the next period by
higher-priority traffic; ``method="tindell1994"`` reproduces it for comparison.

Times are seconds; a response time of ``math.inf`` means the busy period does not end (the
utilisation of the message and everything above it is ≥ 1). Priority is the CAN arbitration
order (lower identifier wins; an 11-bit frame beats a 29-bit one with the same base id).

Transmit buffer policies: the analysis above assumes each node queues its
frames by priority (enough mailboxes, the lowest id always competes). For a node with a FIFO
queue the sufficient treatment of Davis, Kollmann, Pollex and Slomka (2011, "Controller Area
Network (CAN) schedulability analysis with FIFO queues", ECRTS) is used in a simplified, safe
form: every message of a FIFO node is analysed at the priority of that node's *lowest*-priority
message (it may wait behind any of its own node's frames), while it still interferes with other
nodes at its own identifier. Mailboxes with abort behave like a priority queue; without abort a message
may wait until a lower-priority frame of its own node leaves a mailbox, so — when the node has
more messages than mailboxes — it is analysed as if its node had a FIFO (safe, pessimistic;
:func:`canbrake.bus.txbuffer.inverting_nodes` picks these nodes).
"""
from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Iterable, Literal, Sequence

from canbrake.bus.timing import _arbitration_key, _check_bitrate, frame_bits

__all__ = ["CanMessage", "MessageResponse", "Analysis", "analyze", "Method"]

Method = Literal["davis2007", "tindell1994"]
_EPS = 1e-9  # relative tolerance of ceilings: k·T computed in floats still counts as k
_MAX_ITER = 100_000


@dataclass(frozen=True)
class CanMessage:
    """One periodic (or sporadic, minimum inter-arrival ``period_s``) CAN message.

    ``deadline_s`` defaults to the period; ``jitter_s`` is the queuing jitter (s) between the
    periodic release and the moment the frame is in the controller's transmit buffer.
    ``sender`` names the node (used for FIFO / mailbox buffer policies).
    """

    name: str
    arbitration_id: int
    dlc: int
    period_s: float
    is_extended: bool = False
    deadline_s: float | None = None
    jitter_s: float = 0.0
    sender: str = ""

    def __post_init__(self) -> None:
        frame_bits(self.arbitration_id, self.is_extended, self.dlc)  # validates id and dlc
        if not (math.isfinite(self.period_s) and self.period_s > 0):
            raise ValueError(f"message {self.name}: period_s must be > 0, got {self.period_s!r}")
        if not (math.isfinite(self.jitter_s) and self.jitter_s >= 0):
            raise ValueError(f"message {self.name}: jitter_s must be >= 0, got {self.jitter_s!r}")
        if self.deadline_s is not None and not self.deadline_s > 0:
            raise ValueError(f"message {self.name}: deadline_s must be > 0, got {self.deadline_s!r}")

    @property
    def deadline(self) -> float:
        """Deadline (s), the period unless given."""
        return self.period_s if self.deadline_s is None else float(self.deadline_s)


@dataclass(frozen=True)
class MessageResponse:
    """Result for one message (times in seconds; ``response_s`` may be ``math.inf``)."""

    message: CanMessage
    priority: int            # 0 = highest
    c_s: float               # worst-case transmission time
    blocking_s: float        # B_m
    busy_period_s: float     # t_m (inf if unbounded)
    instances: int           # Q_m (0 if unbounded)
    worst_instance: int      # q with the largest R_m(q)
    response_s: float        # R_m
    tindell_s: float         # R_m(0), what the 1994 analysis reports
    schedulable: bool        # R_m <= deadline

    @property
    def slack_s(self) -> float:
        return self.message.deadline - self.response_s


@dataclass(frozen=True)
class Analysis:
    """Response times of a message set on one bus, by priority (highest first)."""

    bitrate_bps: float
    method: str
    results: list[MessageResponse]
    utilisation: float
    notes: list[str] = field(default_factory=list)

    @property
    def schedulable(self) -> bool:
        return all(r.schedulable for r in self.results)

    def by_name(self) -> dict[str, MessageResponse]:
        return {r.message.name: r for r in self.results}

    def as_dict(self) -> dict:
        """JSON-ready form (inf written as null)."""

        def f(x: float) -> float | None:
            return x if math.isfinite(x) else None

        return {
            "bitrate_bps": self.bitrate_bps, "method": self.method,
            "utilisation": self.utilisation, "schedulable": self.schedulable, "notes": self.notes,
            "messages": [{
                "name": r.message.name, "id": r.message.arbitration_id,
                "id_hex": f"0x{r.message.arbitration_id:X}", "extended": r.message.is_extended,
                "sender": r.message.sender, "dlc": r.message.dlc, "priority": r.priority,
                "period_s": r.message.period_s, "deadline_s": r.message.deadline,
                "jitter_s": r.message.jitter_s, "c_s": r.c_s, "blocking_s": r.blocking_s,
                "busy_period_s": f(r.busy_period_s), "instances": r.instances,
                "worst_instance": r.worst_instance, "response_s": f(r.response_s),
                "tindell1994_s": f(r.tindell_s), "schedulable": r.schedulable,
            } for r in self.results],
        }


def _ceil(x: float) -> int:
    return math.ceil(x - _EPS * max(1.0, abs(x)))


def _fixed_point(start: float, fn, limit: float) -> float:
    """Iterate ``x = fn(x)`` from ``start`` until it repeats; inf once it exceeds ``limit``."""
    x = start
    for _ in range(_MAX_ITER):
        nxt = fn(x)
        if nxt > limit:
            return math.inf
        if nxt <= x * (1 + 1e-12) + 1e-15:
            return max(x, nxt)
        x = nxt
    return math.inf


def analyze(messages: Iterable[CanMessage], bitrate_bps: float, *,
            method: Method = "davis2007", fifo_nodes: Sequence[str] = (),
            horizon_s: float | None = None) -> Analysis:
    """Worst-case response time of every message (see the module docstring for the equations).

    Args:
        messages: the message set; identifiers must be distinct on the bus.
        bitrate_bps: bit rate (bit/s).
        method: ``"davis2007"`` (revised, default) or ``"tindell1994"`` (original, optimistic).
        fifo_nodes: senders whose messages may wait behind any frame of their own node (a FIFO
            transmit queue, or mailboxes without abort): analysed at the node's lowest priority.
        horizon_s: give up (R = inf) once a busy period exceeds this; default 1000 × the
            longest period.
    """
    rate = _check_bitrate(bitrate_bps)
    if method not in ("davis2007", "tindell1994"):
        raise ValueError(f"method must be 'davis2007' or 'tindell1994', got {method!r}")
    msgs = sorted(messages, key=lambda m: _arbitration_key(m.arbitration_id, m.is_extended, False))
    seen: dict[tuple, str] = {}
    for m in msgs:
        key = (m.arbitration_id, m.is_extended)
        if key in seen:
            raise ValueError(f"messages {seen[key]} and {m.name} share identifier "
                             f"0x{m.arbitration_id:X}: two senders cannot arbitrate the same id")
        seen[key] = m.name
    tau = 1.0 / rate
    cs = [frame_bits(m.arbitration_id, m.is_extended, m.dlc, stuffing="worst") / rate for m in msgs]
    n = len(msgs)
    util = sum(c / m.period_s for c, m in zip(cs, msgs))
    limit = horizon_s if horizon_s is not None else 1000.0 * max((m.period_s for m in msgs), default=1.0)
    fifo = set(fifo_nodes) & {m.sender for m in msgs}
    notes: list[str] = []
    if fifo:
        notes.append("FIFO/no-abort nodes " + ", ".join(sorted(fifo))
                     + ": their messages analysed at their node's lowest priority")
    # priority level each message waits at: its own, or (FIFO node) its node's lowest
    level = [max(j for j in range(n) if msgs[j].sender == m.sender) if m.sender in fifo else i
             for i, m in enumerate(msgs)]
    results: list[MessageResponse] = []
    for i, m in enumerate(msgs):
        lv = level[i]
        c_m = cs[i]
        own_fifo = m.sender in fifo
        hp = [j for j in range(n) if j != i and (j < lv or (own_fifo and msgs[j].sender == m.sender))]
        hp_set = set(hp)
        blocking = max((cs[j] for j in range(n) if j != i and j not in hp_set), default=0.0)
        hep = hp + [i]
        u_hp = sum(cs[k] / msgs[k].period_s for k in hp)
        u_hep = u_hp + c_m / m.period_s

        def busy(t: float) -> float:
            return blocking + sum(_ceil((t + msgs[k].jitter_s) / msgs[k].period_s) * cs[k] for k in hep)

        def w_of(q: int) -> float:
            def fn(w: float) -> float:
                return blocking + q * c_m + sum(
                    _ceil((w + msgs[k].jitter_s + tau) / msgs[k].period_s) * cs[k] for k in hp)
            return math.inf if u_hp >= 1.0 else _fixed_point(blocking + q * c_m, fn, limit)

        t_busy = math.inf if u_hep >= 1.0 else _fixed_point(c_m, busy, limit)
        q_count = 0 if not math.isfinite(t_busy) else max(1, _ceil((t_busy + m.jitter_s) / m.period_s))
        r_tindell = m.jitter_s + w_of(0) + c_m
        r, q_worst = r_tindell, 0
        if method == "davis2007":
            if not math.isfinite(t_busy):
                r = math.inf
            for q in range(1, q_count):
                rq = m.jitter_s + w_of(q) - q * m.period_s + c_m
                if rq > r:
                    r, q_worst = rq, q
        ok = r <= m.deadline * (1 + 1e-12)
        results.append(MessageResponse(m, i, c_m, blocking, t_busy, q_count, q_worst, r, r_tindell, ok))
    return Analysis(rate, method, results, util, notes)
