"""Transmit buffer policies of a CAN node (pure): what frame a node offers to arbitration.

* ``priority`` — the ideal: the node always offers its highest-priority pending frame (enough
  mailboxes, or a driver that keeps them sorted). Optional ``depth``: frames held at most.
* ``fifo`` — one queue in submission order (a single mailbox fed by a software FIFO, e.g. a
  Linux qdisc): the head blocks everything behind it, whatever their identifiers — priority
  inversion. A frame submitted to a full FIFO of ``depth`` is dropped (overflow).
* ``mailboxes`` — ``mailboxes`` hardware transmit buffers; the controller offers the
  highest-priority frame among them; further frames wait in a FIFO software queue (``depth``
  bounds it). Without ``abort`` a high-priority frame waits until a mailbox frees, i.e. until a
  lower-priority frame of the same node wins arbitration (priority inversion). With ``abort``
  the lowest-priority pending mailbox frame is aborted and put back at the head of the
  software queue to make room.

References: Davis, Kollmann, Pollex, Slomka 2011 (FIFO queues); Khan, Davis, Navet
("Schedulability analysis of CAN with non-abortable transmission requests", ETFA).
"""
from __future__ import annotations

import heapq
from collections import deque
from typing import Any, Literal

from pydantic import BaseModel, ConfigDict, Field, model_validator

__all__ = ["TxBufferPolicy", "TxBufferConfig", "TxBuffer", "make_tx_buffer", "inverting_nodes"]

TxBufferPolicy = Literal["priority", "fifo", "mailboxes"]


class TxBufferConfig(BaseModel):
    """Scenario entry ``bus.tx_buffers[i]``: the transmit buffer of some nodes."""

    model_config = ConfigDict(extra="forbid", frozen=True)

    nodes: list[str] | None = Field(None, description="nodes it applies to (ecu1, plant, ...); None = every ECU")
    policy: TxBufferPolicy = Field("priority", description="priority (ideal), fifo, or mailboxes")
    depth: int | None = Field(None, ge=1, description="frames the (software) queue holds; a frame "
                                                       "submitted to a full queue is dropped. None = unbounded")
    mailboxes: int = Field(1, ge=1, le=64, description="hardware transmit buffers (policy mailboxes)")
    abort: bool = Field(False, description="mailboxes: abort a lower-priority pending frame for a higher one")

    @model_validator(mode="after")
    def _check(self) -> "TxBufferConfig":
        if self.nodes == []:
            raise ValueError("nodes is an empty list; omit it to mean every ECU")
        if self.policy != "mailboxes" and (self.mailboxes != 1 or self.abort):
            raise ValueError(f"mailboxes/abort only apply to policy: mailboxes (got policy: {self.policy})")
        return self

    def applies_to(self, node: str) -> bool:
        return node.startswith("ecu") if self.nodes is None else node in self.nodes


class TxBuffer:
    """One node's transmit buffer holding ``_Pending`` frames of the timing model (which carry
    ``bus_key``, the arbitration order, and ``ticket.t_queue_s`` / ``ticket.seq``)."""

    def __init__(self, policy: TxBufferPolicy = "priority", depth: int | None = None, mailboxes: int = 1,
                 abort: bool = False) -> None:
        if policy not in ("priority", "fifo", "mailboxes"):
            raise ValueError(f"policy must be priority, fifo or mailboxes, got {policy!r}")
        self.policy = policy
        self.depth = depth
        self.k = mailboxes
        self.abort = abort
        self._heap: list[tuple[Any, int, Any]] = []   # priority
        self._fifo: deque[Any] = deque()              # fifo; software queue of mailboxes
        self._mb: list[Any] = []                      # mailboxes (unsorted, <= k)
        self._refilled: Any = None
        self.n_overflow = 0
        self.n_aborted = 0

    def __len__(self) -> int:
        return len(self._heap) + len(self._fifo) + len(self._mb)

    def push(self, p: Any) -> Any:
        """Add a frame; returns the frame dropped because the queue is full (``p``) or None."""
        if self.policy == "mailboxes":
            if len(self._mb) < self.k:
                self._mb.append(p)
                return None
            if self.abort:
                victim = max(self._mb, key=lambda x: x.bus_key)
                if p.bus_key < victim.bus_key:
                    self._mb.remove(victim)
                    self._mb.append(p)
                    self._fifo.appendleft(victim)
                    self.n_aborted += 1
                    if self.depth is not None and len(self._fifo) > self.depth:
                        self.n_overflow += 1
                        return self._fifo.pop()
                    return None
            if self.depth is not None and len(self._fifo) >= self.depth:
                self.n_overflow += 1
                return p
            self._fifo.append(p)
            return None
        if self.depth is not None and len(self) >= self.depth:
            self.n_overflow += 1
            return p
        if self.policy == "priority":
            heapq.heappush(self._heap, (p.bus_key, p.ticket.seq, p))
        else:
            self._fifo.append(p)
        return None

    def head(self) -> Any:
        """The frame the node offers to arbitration now (None if empty)."""
        if self.policy == "priority":
            return self._heap[0][2] if self._heap else None
        if self.policy == "fifo":
            return self._fifo[0] if self._fifo else None
        return min(self._mb, key=lambda x: x.bus_key) if self._mb else None

    def pop_head(self) -> Any:
        """Remove and return :meth:`head` (it won arbitration)."""
        if self.policy == "priority":
            return heapq.heappop(self._heap)[2]
        if self.policy == "fifo":
            return self._fifo.popleft()
        p = self.head()
        self._mb.remove(p)
        self._refilled = None
        if self._fifo:
            self._refilled = self._fifo.popleft()
            self._mb.append(self._refilled)
        return p

    def requeue(self, p: Any) -> None:
        """Put back the frame just popped (its attempt failed): it is retransmitted from where it was."""
        if self.policy == "priority":
            heapq.heappush(self._heap, (p.bus_key, p.ticket.seq, p))
        elif self.policy == "fifo":
            self._fifo.appendleft(p)
        else:
            if self._refilled is not None:
                self._mb.remove(self._refilled)
                self._fifo.appendleft(self._refilled)
                self._refilled = None
            self._mb.append(p)

    def drain(self) -> list[Any]:
        """Remove and return everything (bus-off)."""
        out = [e[2] for e in self._heap] + list(self._mb) + list(self._fifo)
        self._heap, self._mb, self._fifo = [], [], deque()
        return out

    def pending(self) -> list[Any]:
        return [e[2] for e in self._heap] + list(self._mb) + list(self._fifo)


def make_tx_buffer(cfg: TxBufferConfig) -> TxBuffer:
    return TxBuffer(cfg.policy, cfg.depth, cfg.mailboxes, cfg.abort)


def inverting_nodes(configs: list[TxBufferConfig], messages_per_node: dict[str, int]) -> list[str]:
    """Nodes whose buffer can delay a frame behind a lower-priority frame of the same node (FIFO,
    or fewer non-abortable mailboxes than the node has messages): the response-time analysis
    treats their messages at the node's lowest priority."""
    out = []
    for node, n_msgs in messages_per_node.items():
        cfg = next((c for c in configs if c.applies_to(node)), None)
        if cfg is None:
            continue
        if cfg.policy == "fifo" and n_msgs > 1:
            out.append(node)
        elif cfg.policy == "mailboxes" and not cfg.abort and cfg.mailboxes < n_msgs:
            out.append(node)
    return sorted(out)
