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

from typing import Any, Sequence

import can

from canbrake.nodes._route import hand, split
from canbrake.nodes.base import Node


def _matches(filters: list[dict[str, Any]] | None, msg: can.Message) -> bool:
    if not filters:
        return True
    aid = msg.arbitration_id
    return any((aid & f["can_mask"]) == (f["can_id"] & f["can_mask"])
               and ("extended" not in f or f["extended"] == msg.is_extended_id) for f in filters)


class Router:
    """Delivery among ``nodes`` in one process, in generations: every node gets, in one
    :meth:`Node.handle_batch` call, the frames of the current generation it accepts (in order,
    its own left out); what the nodes send makes the next generation (node order, each node's
    frames in the order sent). A lockstep phase is one generation, so each node's Python side
    runs once per phase, not once per frame. Each identifier's route is computed once."""

    def __init__(self, nodes: Sequence[Node]) -> None:
        self.nodes = list(nodes)
        self.filters = [n.filters() or None for n in self.nodes]
        # nodes whose filters are all exact identifiers: a set lookup instead of matching
        self._exact: list[set[tuple[int, bool]] | None] = []
        for f in self.filters:
            full = f and all(x["can_mask"] == (0x1FFFFFFF if x.get("extended") else 0x7FF) and "extended" in x
                             for x in f)
            self._exact.append({(x["can_id"], bool(x["extended"])) for x in f} if full else None)  # type: ignore[union-attr]
        #: identifier << 1 | extended -> indices of the nodes that accept it (empty routes too)
        self._routes: dict[int, tuple[int, ...]] = {}
        self.current: Node | None = None  # the node being called (names a crash)
        #: each node's handle_batch, bound once (Node.batch_handler; hand calls these)
        self._handlers = [n.batch_handler() for n in self.nodes]

    def route(self, aid: int, extended: bool) -> tuple[int, ...]:
        """Indices of the nodes that accept identifier ``aid``."""
        key = aid << 1 | bool(extended)
        r = self._routes.get(key)
        if r is None:
            probe = can.Message(arbitration_id=aid, is_extended_id=extended)
            pair = (aid, bool(extended))
            r = self._routes[key] = tuple(i for i, (f, ex) in enumerate(zip(self.filters, self._exact))
                                          if (pair in ex if ex is not None else _matches(f, probe)))
        return r

    def inboxes(self, gen: list[tuple[int, can.Message]]) -> list[list[can.Message]]:
        """Each node's share of a generation of (sender index or -1, frame) (compiled)."""
        return split(gen, self._routes, self.route, len(self.nodes))

    def step(self, inbox: list[list[can.Message]], now: float) -> list[tuple[int, can.Message]]:
        """Hand each node its batch; returns the next generation (compiled)."""
        return hand(self, self.nodes, self._handlers, inbox, now)


class NodeGroup(Node):
    """``members`` run as one node (same process, one bus)."""

    def __init__(self, members: Sequence[Node]) -> None:
        self.members = list(members)
        self.name = "+".join(m.name for m in self.members) if len(self.members) <= 3 else \
            f"{self.members[0].name}..{self.members[-1].name}"
        self._router = Router(self.members)
        self._filters = self._router.filters

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

    def _loop(self, gen: list[tuple[int, can.Message]], now: float) -> list[can.Message]:
        """Deliver the members' frames to the other members, generation by generation; return
        every frame sent, in order."""
        out: list[can.Message] = []
        while gen:
            out.extend([m for _i, m in gen])
            gen = self._router.step(self._router.inboxes(gen), now)
        return out

    def start(self, now: float) -> list[can.Message]:
        return self._loop([(i, x) for i, m in enumerate(self.members) for x in m.start(now)], now)

    def handle(self, msg: can.Message, now: float) -> list[can.Message]:
        return self.handle_batch([msg], now)

    def handle_batch(self, msgs: list[can.Message], now: float) -> list[can.Message]:
        sent = self._router.step(self._router.inboxes([(-1, m) for m in msgs]), now)
        return self._loop(sent, now) if sent else []

    def after_send(self) -> None:
        for m in self.members:
            m.after_send()

    def next_deadline(self) -> float | None:
        ds = [d for d in (m.next_deadline() for m in self.members) if d is not None]
        return min(ds) if ds else None

    def on_timer(self, now: float) -> list[can.Message]:
        sent: list[tuple[int, can.Message]] = []
        for i, m in enumerate(self.members):
            d = m.next_deadline()
            if d is not None and now >= d:
                sent.extend((i, x) for x in m.on_timer(now))
        return self._loop(sent, now) if sent else []
    def close(self, status: str = "ok") -> None:
        first: BaseException | None = None
        for m in self.members:
            try:
                m.close(status)
            except Exception as e:  # noqa: BLE001 - close every member, report the first failure
                first = first or e
        if first is not None:
            raise first
