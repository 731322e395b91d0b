"""CAN error handling and fault confinement for the timing model (ISO 11898-1, classic CAN). Pure.

What happens on the wire when a frame is hit by a bit error (global error: every node sees it):

* the transmission stops at the error; an **error frame** follows — error flag (6 dominant
  bits; the other nodes' flags superpose) and error delimiter (8 recessive) — then the 3-bit
  intermission. Bus time of the failed attempt: ``error_bit + 1 + 6 + 8 + 3`` bit times;
* the frame is **retransmitted automatically**: it re-enters arbitration at once;
* **fault confinement** per node: transmit and receive error counters (TEC, REC). Rules
  modelled (rule numbers as in the fault-confinement rules of ISO 11898-1 / Bosch CAN 2.0):
  transmitter error TEC += 8 (rule 3),
  receiver error REC += 1 (rule 1), successful transmission TEC −= 1 (rule 7), successful
  reception REC −= 1, or back to 119 from above 127 (rule 8). A node is *error-active* with
  both counters ≤ 127, *error-passive* from 128, *bus-off* when TEC > 255; a bus-off node
  takes no part in bus traffic (its queued and new frames are dropped) until it has seen
  128 occurrences of 11 consecutive recessive bits — each frame or error frame on the bus
  ends with one (ACK delimiter + EOF + intermission, or error delimiter + intermission), an
  idle bus gives one every 11 bit times — then it restarts error-active with TEC = REC = 0
  (``auto_recovery``; otherwise it stays bus-off, as a controller waiting for its host).
  ``recovery_delay_s`` models the host's restart delay (e.g. AUTOSAR CanSM's bus-off recovery
  time): the node only starts counting the 128 sequences that long after going bus-off.

Error sources: a bit error rate on the bus (each bit of each frame flipped independently with
probability ``ber`` → a frame of n bits is hit with 1 − (1 − ber)^n), and a faulty transceiver
(the node corrupts each of its own frames with a probability). The error bit is uniform over
the frame (SOF to EOF).

Limits (documented, not modelled): local errors seen by some receivers only, the rule-2 REC += 8
after a dominant bit following an error flag, error-passive "suspend transmission" (8 bits),
the ACK-error exception for error-passive transmitters, overload frames, and that a bus-off
controller also stops receiving.
"""
from __future__ import annotations

import math
import random
from dataclasses import dataclass, field
from typing import Iterable, Literal

__all__ = ["ErrorState", "BitErrorSource", "FaultyTransceiver", "ErrorEvent", "StateChange",
           "NodeCounters", "FaultConfinement", "ERROR_FRAME_BITS", "RECOVERY_SEQUENCES",
           "RECESSIVE_SEQUENCE_BITS", "STATE_CODE"]

ErrorState = Literal["active", "passive", "bus_off"]
#: numeric code of each state, for CSV columns and plots
STATE_CODE = {"active": 0, "passive": 1, "bus_off": 2}
ERROR_FLAG_BITS = 6
ERROR_DELIMITER_BITS = 8
#: error flag + error delimiter (the intermission is counted by the timing model)
ERROR_FRAME_BITS = ERROR_FLAG_BITS + ERROR_DELIMITER_BITS
RECOVERY_SEQUENCES = 128
RECESSIVE_SEQUENCE_BITS = 11
PASSIVE_LIMIT = 128
BUS_OFF_LIMIT = 255


@dataclass(frozen=True)
class BitErrorSource:
    """Bit error rate ``ber`` (per bit) on every frame sent in ``[start_s, stop_s)``."""

    ber: float
    start_s: float = 0.0
    stop_s: float = math.inf

    def __post_init__(self) -> None:
        if not 0.0 <= self.ber < 1.0:
            raise ValueError(f"ber must be in [0, 1), got {self.ber!r}")


@dataclass(frozen=True)
class FaultyTransceiver:
    """``node`` corrupts each frame it sends in ``[start_s, stop_s)`` with ``probability``."""

    node: str
    probability: float
    start_s: float = 0.0
    stop_s: float = math.inf

    def __post_init__(self) -> None:
        if not 0.0 <= self.probability <= 1.0:
            raise ValueError(f"probability must be in [0, 1], got {self.probability!r}")


@dataclass(frozen=True)
class ErrorEvent:
    """One failed transmission attempt and its error frame (simulated seconds)."""

    t_start_s: float      # SOF of the failed attempt
    t_end_s: float        # end of the error frame's intermission
    node: str             # transmitter
    arbitration_id: int
    is_extended: bool
    error_bit: int        # bit index (from SOF) at which the error was detected
    cause: str            # "bit_error" or "faulty_transceiver"
    tec: int              # transmitter's TEC after the error
    state: ErrorState     # transmitter's state after the error


@dataclass(frozen=True)
class StateChange:
    """A node entered ``state`` at ``t_s`` (TEC/REC after the change)."""

    t_s: float
    node: str
    state: ErrorState
    tec: int
    rec: int


@dataclass
class NodeCounters:
    """Fault-confinement state of one node."""

    tec: int = 0
    rec: int = 0
    state: ErrorState = "active"
    recovery_sequences: int = 0
    n_bus_off: int = 0
    n_tx_errors: int = 0
    bus_off_s: float = 0.0          # total time spent bus-off (closed episodes)
    bus_off_since: float = math.nan
    idle_anchor: float = math.nan   # start of the idle stretch being counted for recovery
    idle_counted: int = 0


@dataclass
class FaultConfinement:
    """Error sources + per-node counters; driven by :class:`canbrake.bus.timing.BusTimingModel`."""

    bit_errors: list[BitErrorSource] = field(default_factory=list)
    faulty: list[FaultyTransceiver] = field(default_factory=list)
    seed: int = 0
    auto_recovery: bool = True
    bitrate_bps: float = 500_000.0
    recovery_delay_s: float = 0.0

    def __post_init__(self) -> None:
        self._rng = random.Random(self.seed)
        self.nodes: dict[str, NodeCounters] = {}
        self.events: list[ErrorEvent] = []
        self.changes: list[StateChange] = []

    # -- nodes ------------------------------------------------------------------------------
    def register(self, node: str) -> NodeCounters:
        c = self.nodes.get(node)
        if c is None:
            c = self.nodes[node] = NodeCounters()
        return c

    def is_bus_off(self, node: str) -> bool:
        c = self.nodes.get(node)
        return c is not None and c.state == "bus_off"

    def state(self, node: str) -> ErrorState:
        c = self.nodes.get(node)
        return "active" if c is None else c.state

    def _update(self, node: str, c: NodeCounters, t: float) -> None:
        if c.tec > BUS_OFF_LIMIT:
            new: ErrorState = "bus_off"
        elif c.tec >= PASSIVE_LIMIT or c.rec >= PASSIVE_LIMIT:
            new = "passive"
        else:
            new = "active"
        if new != c.state:
            if new == "bus_off":
                c.n_bus_off += 1
                c.bus_off_since = t
                c.recovery_sequences = 0
            c.state = new
            self.changes.append(StateChange(t, node, new, c.tec, c.rec))

    # -- error draw -------------------------------------------------------------------------
    def draw(self, node: str, bits: int, t: float) -> tuple[int, str] | None:
        """Whether the frame of ``bits`` (SOF..EOF) that ``node`` starts at ``t`` is hit:
        ``(error bit, cause)`` or None."""
        p_ok_bus = 1.0
        for s in self.bit_errors:
            if s.start_s <= t < s.stop_s and s.ber > 0:
                p_ok_bus *= (1.0 - s.ber) ** bits
        p_ok_node = 1.0
        for f in self.faulty:
            if f.node == node and f.start_s <= t < f.stop_s:
                p_ok_node *= 1.0 - f.probability
        if p_ok_bus == 1.0 and p_ok_node == 1.0:
            return None
        u = self._rng.random()
        p_bus = 1.0 - p_ok_bus
        if u < p_bus:
            cause = "bit_error"
        elif u < 1.0 - p_ok_bus * p_ok_node:
            cause = "faulty_transceiver"
        else:
            return None
        return self._rng.randrange(bits), cause

    # -- outcomes ---------------------------------------------------------------------------
    def tx_error(self, node: str, t_end: float) -> NodeCounters:
        """A transmission of ``node`` failed (error frame ends at ``t_end``)."""
        c = self.register(node)
        c.tec += 8              # rule 3
        c.n_tx_errors += 1
        self._update(node, c, t_end)
        for name, r in self.nodes.items():
            if name != node and r.state != "bus_off":
                r.rec = min(r.rec + 1, 255)  # rule 1
                self._update(name, r, t_end)
        return c

    def tx_ok(self, node: str, t_end: float) -> None:
        """A frame of ``node`` went through; every other node received it."""
        c = self.register(node)
        if c.tec:
            c.tec -= 1          # rule 7
            self._update(node, c, t_end)
        for name, r in self.nodes.items():
            if name != node and r.rec and r.state != "bus_off":
                r.rec = 119 if r.rec > 127 else r.rec - 1  # rule 8
                self._update(name, r, t_end)

    # -- bus-off recovery -------------------------------------------------------------------
    def _recover(self, name: str, c: NodeCounters, t: float) -> None:
        c.tec = c.rec = 0
        c.recovery_sequences = 0
        c.bus_off_s += t - c.bus_off_since
        c.bus_off_since = math.nan
        c.state = "active"
        self.changes.append(StateChange(t, name, "active", 0, 0))

    def _monitoring(self, c: NodeCounters, t: float) -> bool:
        """Is this bus-off node counting recessive sequences at ``t`` (after its restart delay)?"""
        return (c.state == "bus_off" and self.auto_recovery
                and t >= c.bus_off_since + self.recovery_delay_s - 1e-12)

    def frame_end(self, t_end: float) -> None:
        """A frame or error frame ended at ``t_end``: one sequence of 11 recessive bits."""
        for name, c in self.nodes.items():
            if self._monitoring(c, t_end):
                c.recovery_sequences += 1
                if c.recovery_sequences >= RECOVERY_SEQUENCES:
                    self._recover(name, c, t_end)

    def idle(self, stretch_start: float, t: float) -> None:
        """The bus has been idle since ``stretch_start`` (end of the last frame) up to ``t``:
        one sequence per 11 bit times, counted from the later of the stretch start and the end
        of a node's restart delay."""
        if not t > stretch_start or not math.isfinite(stretch_start):
            return
        seq_s = RECESSIVE_SEQUENCE_BITS / self.bitrate_bps
        for name, c in self.nodes.items():
            if c.state != "bus_off" or not self.auto_recovery:
                continue
            a = max(stretch_start, c.bus_off_since + self.recovery_delay_s)
            if not t > a:
                continue
            if c.idle_anchor != a:
                c.idle_anchor, c.idle_counted = a, 0
            total = int(math.floor((t - a) / seq_s + 1e-9))
            n = total - c.idle_counted
            if n <= 0:
                continue
            need = RECOVERY_SEQUENCES - c.recovery_sequences
            if n >= need:
                self._recover(name, c, a + (c.idle_counted + need) * seq_s)
                c.idle_anchor, c.idle_counted = math.nan, 0
            else:
                c.recovery_sequences += n
                c.idle_counted = total

    # -- summaries --------------------------------------------------------------------------
    def summary(self, t_now: float) -> dict:
        """Per node: counters, state, bus-off episodes and time (s); error frames by cause."""
        nodes = {}
        for name, c in sorted(self.nodes.items()):
            off = c.bus_off_s + (t_now - c.bus_off_since if c.state == "bus_off" else 0.0)
            nodes[name] = {"state": c.state, "tec": c.tec, "rec": c.rec, "tx_errors": c.n_tx_errors,
                           "bus_off_episodes": c.n_bus_off, "bus_off_s": off,
                           "max_tec": max((e.tec for e in self.events if e.node == name), default=c.tec)}
        causes: dict[str, int] = {}
        for e in self.events:
            causes[e.cause] = causes.get(e.cause, 0) + 1
        return {"error_frames": len(self.events), "by_cause": causes, "auto_recovery": self.auto_recovery,
                "nodes": nodes,
                "state_changes": [{"t_s": s.t_s, "node": s.node, "state": s.state, "tec": s.tec, "rec": s.rec}
                                  for s in self.changes]}


def states_at(changes: Iterable[StateChange], nodes: Iterable[str], t: float) -> dict[str, ErrorState]:
    """State of every node at time ``t`` from a list of changes (in time order)."""
    out: dict[str, ErrorState] = {n: "active" for n in nodes}
    for ch in changes:
        if ch.t_s > t:
            break
        out[ch.node] = ch.state
    return out
