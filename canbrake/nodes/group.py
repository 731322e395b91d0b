"""Several nodes hosted in one process: :class:`NodeGroup` is itself a node.

One OS process per ECU is the default; a long train (1 + 105 ECUs) on 2 cores can instead host
``ecu.per_process`` ECUs per process. The group listens with the union of its members' filters,
hands each received frame to every member that accepts it, and delivers the frames a member
sends to the other members at once (a bus does not echo a node's own frames back to its
process), in the order they were sent, before returning them for the bus. Every member sees the
same frames as it would in its own process, so a lockstep run's frames and signals are the same
(tested).
"""
from __future__ import annotations

from collections import deque
from typing import Any, Sequence

import can

from canbrake.nodes.base import Node


def _matches(filters: list[dict[str, Any]] | None, msg: can.Message) -> bool:
    if not filters:
        return True
    aid = msg.arbitration_id
    return any((aid & f["can_mask"]) == (f["can_id"] & f["can_mask"])
               and ("extended" not in f or f["extended"] == msg.is_extended_id) for f in filters)


class NodeGroup(Node):
    """``members`` run as one node (same process, one bus)."""

    def __init__(self, members: Sequence[Node]) -> None:
        self.members = list(members)
        self.name = "+".join(m.name for m in self.members) if len(self.members) <= 3 else \
            f"{self.members[0].name}..{self.members[-1].name}"
        self._filters = [m.filters() for m in self.members]

    @property  # type: ignore[override]
    def finished(self) -> bool:
        return all(m.finished for m in self.members)

    def filters(self) -> list[dict[str, Any]] | None:
        if any(not f for f in self._filters):
            return None
        seen: dict[tuple[int, int, bool], dict[str, Any]] = {}
        for f in self._filters:
            for x in f:  # type: ignore[union-attr]
                seen.setdefault((x["can_id"], x["can_mask"], bool(x.get("extended"))), x)
        return list(seen.values())

    def _loop(self, first: list[tuple[int, can.Message]]) -> list[can.Message]:
        """Deliver each sent frame to the other members (recursively); return all frames sent."""
        out: list[can.Message] = []
        queue = deque(first)
        while queue:
            sender, msg = queue.popleft()
            out.append(msg)
            for i, m in enumerate(self.members):
                if i != sender and not m.finished and _matches(self._filters[i], msg):
                    queue.extend((i, x) for x in m.handle(msg, 0.0))
        return out

    def start(self, now: float) -> list[can.Message]:
        return self._loop([(i, x) for i, m in enumerate(self.members) for x in m.start(now)])

    def handle(self, msg: can.Message, now: float) -> list[can.Message]:
        sent: list[tuple[int, can.Message]] = []
        for i, m in enumerate(self.members):
            if not m.finished and _matches(self._filters[i], msg):
                sent.extend((i, x) for x in m.handle(msg, now))
        return self._loop(sent) if sent else []

    def next_deadline(self) -> float | None:
        ds = [d for d in (m.next_deadline() for m in self.members) if d is not None]
        return min(ds) if ds else None

    def on_timer(self, now: float) -> list[can.Message]:
        sent: list[tuple[int, can.Message]] = []
        for i, m in enumerate(self.members):
            d = m.next_deadline()
            if d is not None and now >= d:
                sent.extend((i, x) for x in m.on_timer(now))
        return self._loop(sent) if sent else []

    def close(self, status: str = "ok") -> None:
        first: BaseException | None = None
        for m in self.members:
            try:
                m.close(status)
            except Exception as e:  # noqa: BLE001 - close every member, report the first failure
                first = first or e
        if first is not None:
            raise first
