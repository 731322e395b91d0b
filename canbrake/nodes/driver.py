"""Drivers: run node state machines over a real python-can bus or in one process.

- :func:`drive` — the loop of one OS process: receive, handle, send; honours the node's
  realtime deadlines; never busy-spins (blocking ``recv`` with a timeout).
- :func:`run_inprocess` — every node in one process and one thread, frames delivered in one
  global order; either straight from node to node (``medium="direct"``, the fast engine used
  by sweeps) or through python-can ``virtual`` buses (``medium="virtual"``, one Bus object per
  node, exercising python-can's own bus, copying and queueing code). Lockstep only.
"""
from __future__ import annotations

import multiprocessing as mp
import os
import time
import uuid
from collections import deque
from typing import Callable, Sequence

import can

from canbrake.bus.memory import BusOverrunError
from canbrake.nodes.base import Node


class NodeFailure(RuntimeError):
    """A node's process failed; the message names the node."""


class NodeCrash(NodeFailure):
    """A node's own code raised in an in-process run: ``node`` names it; the exception is the
    ``__cause__`` (its traceback goes to the run's logs/<node>.log, as a node process's does)."""

    def __init__(self, node: str, exc: BaseException) -> None:
        super().__init__(f"{node}: {type(exc).__name__}: {exc}")
        self.node = node


def _call(node: Node, fn: Callable[..., list[can.Message]], *args: object) -> list[can.Message]:
    """``fn(*args)`` of ``node``; an exception of the node's code becomes a :class:`NodeCrash`."""
    try:
        return fn(*args)
    except NodeFailure:
        raise
    except Exception as e:  # noqa: BLE001 - any bug of a node (or a user's controller) ends the run, named
        raise NodeCrash(node.name, e) from e


def _matches(filters: list[dict] | None, msg: can.Message) -> bool:
    if not filters:
        return True
    aid = msg.arbitration_id
    for f in filters:
        if (aid & f["can_mask"]) == (f["can_id"] & f["can_mask"]) and (
                "extended" not in f or f["extended"] == msg.is_extended_id):
            return True
    return False


def _send_all(bus: can.BusABC, msgs: Sequence[can.Message], retries: int = 200) -> None:
    if not msgs:
        return
    send_many = getattr(bus, "send_many", None)
    if send_many is not None and len(msgs) > 1:
        # canbrake's in-memory bus puts a burst on the bus at once and wakes each reader once
        send_many(list(msgs))
        return
    for m in msgs:
        for attempt in range(retries):
            try:
                bus.send(m)
                break
            except can.CanOperationError:
                # SocketCAN returns ENOBUFS when the interface queue is full: back off briefly.
                if attempt == retries - 1:
                    raise
                time.sleep(0.0005)


def _parent_alive(parent_pid: int) -> bool:
    """Is the orchestrator (``parent_pid``) still running? A node started by multiprocessing asks
    its parent sentinel (under a forkserver, the node's OS parent is the server, not the
    orchestrator); otherwise, the OS parent must still be ``parent_pid``."""
    parent = mp.parent_process()
    if parent is not None and parent.pid == parent_pid:
        return parent.is_alive()
    return os.getppid() == parent_pid


def drive(node: Node, bus: can.BusABC, *, clock: Callable[[], float] = time.time,
          idle_check_s: float = 0.5, parent_pid: int | None = None, spin_s: float = 0.0) -> None:
    """Run ``node`` on ``bus`` until it finishes. Checks every ``idle_check_s`` (s, busy or idle)
    that the parent process is still alive, so an orphaned node exits instead of running on or
    waiting forever. ``spin_s`` (s, realtime): within that much of the node's deadline it polls
    the bus and yields the CPU instead of sleeping, so the deadline is not missed by an OS
    wake-up's latency (a busy-wait/yield hybrid; 0 = always sleep)."""
    _send_all(bus, node.start(clock()))
    next_check = time.monotonic() + idle_check_s
    # canbrake's memory bus filters in shared memory: take its frames without BusABC.recv's
    # per-frame debug-log call (a measurable share of a frame's cost, see docs/performance.md)
    recv = getattr(bus, "recv_filtered", None) or bus.recv
    while not node.finished:
        deadline = node.next_deadline()
        now = clock()
        if deadline is None:
            timeout = idle_check_s
        elif spin_s > 0.0 and deadline - now <= spin_s:
            timeout = 0.0  # near the deadline: poll, and yield below if nothing came
        else:
            timeout = max(0.0, min(idle_check_s, deadline - now - spin_s))
        try:
            msg = recv(timeout=timeout)
        except BusOverrunError as e:
            # a flood overran this node's receive ring: count what was lost and receive on
            node.on_rx_overrun(e.frames_lost)
            continue
        now = clock()
        if msg is not None:
            _send_all(bus, node.handle(msg, now))
        elif timeout == 0.0 and spin_s > 0.0:
            os.sched_yield()
        deadline = node.next_deadline()
        if deadline is not None and now >= deadline:
            _send_all(bus, node.on_timer(now))
        if parent_pid is not None and (msg is None or time.monotonic() >= next_check):
            next_check = time.monotonic() + idle_check_s
            if not _parent_alive(parent_pid):
                raise NodeFailure(f"{node.name}: parent process went away")


def run_inprocess(nodes: Sequence[Node], *, medium: str = "direct", max_frames: int | None = None) -> int:
    """Run all ``nodes`` in this process until every node has finished; returns frames moved.

    Nodes start in the given order (put the plant, the time master, last).
    """
    if medium == "direct":
        return _run_direct(nodes, max_frames)
    if medium == "virtual":
        return _run_virtual(nodes, max_frames)
    raise ValueError(f"unknown in-process medium {medium!r}")


def _end_with_time_master(nodes: Sequence[Node]) -> None:
    """Once the time master has finished and every frame is delivered, the run is over: nodes
    still waiting (an unauthenticated END before the scheduled last tick is not trusted, see
    :func:`canbrake.bus.guard.sync_verdict`) are finished too."""
    if any(n.time_master and n.finished for n in nodes):
        for n in nodes:
            for m in getattr(n, "members", [n]):  # a NodeGroup finishes with its members
                m.finished = True


def _run_direct(nodes: Sequence[Node], max_frames: int | None) -> int:
    filters = [n.filters() or None for n in nodes]
    # Routing: nodes whose filters are all exact standard ids are looked up by id; the others
    # (the recorder: no filter) are matched frame by frame. Order of delivery = order of `nodes`.
    # Each identifier's route (node index, node, filters to match or None) is computed once.
    exact: list[set[int] | None] = []
    for f in filters:
        exact.append({x["can_id"] for x in f} if f and all(x["can_mask"] == 0x7FF for x in f) else None)
    routes: dict[int, list[tuple[int, Node, list[dict] | None]]] = {}
    routes_ext: dict[int, list[tuple[int, Node, list[dict] | None]]] = {}

    def route(aid: int, extended: bool) -> list[tuple[int, Node, list[dict] | None]]:
        if extended:  # exact-id nodes take standard frames only
            r = routes_ext[aid] = [(i, nodes[i], filters[i]) for i, ex in enumerate(exact) if ex is None]
        else:
            r = routes[aid] = [(i, nodes[i], filters[i] if ex is None else None)
                               for i, ex in enumerate(exact) if ex is None or aid in ex]
        return r

    queue: deque[tuple[int, can.Message]] = deque()
    for idx, node in enumerate(nodes):
        queue.extend((idx, m) for m in _call(node, node.start, 0.0))
    moved = 0
    popleft, extend = queue.popleft, queue.extend
    node = nodes[0]
    try:  # what _call does, around the loop instead of per delivery (a call less per frame and node)
        while queue:
            sender, msg = popleft()
            moved += 1
            if max_frames is not None and moved > max_frames:
                raise NodeFailure(f"in-process run exceeded {max_frames} frames")
            aid = msg.arbitration_id
            targets = (routes_ext if msg.is_extended_id else routes).get(aid) or route(aid, msg.is_extended_id)
            for idx, node, flt in targets:
                if idx == sender or node.finished:
                    continue
                if flt is not None and not _matches(flt, msg):
                    continue
                out = node.handle(msg, 0.0)
                if out:
                    extend([(idx, m) for m in out])
    except NodeFailure:
        raise
    except Exception as e:  # noqa: BLE001 - as in _call: the node whose handle raised, named
        raise NodeCrash(node.name, e) from e
    _end_with_time_master(nodes)
    unfinished = [n.name for n in nodes if not n.finished]
    if unfinished:
        raise NodeFailure(f"in-process run stalled; unfinished nodes: {', '.join(unfinished)}")
    return moved


def _run_virtual(nodes: Sequence[Node], max_frames: int | None) -> int:
    channel = f"canbrake-{uuid.uuid4().hex[:8]}"
    # Filters are applied here rather than in the Bus: BusABC.recv(timeout=0) returns None as soon
    # as the frame at the head of the queue is filtered out, which would hide the frames behind it.
    buses = [can.Bus(interface="virtual", channel=channel, receive_own_messages=False) for n in nodes]
    filters = [n.filters() for n in nodes]
    moved = 0
    try:
        for node, bus in zip(nodes, buses):
            _send_all(bus, _call(node, node.start, 0.0))
        progress = True
        while progress:
            progress = False
            for node, bus, flt in zip(nodes, buses, filters):
                while (msg := bus.recv(timeout=0)) is not None:
                    progress = True
                    moved += 1
                    if max_frames is not None and moved > max_frames:
                        raise NodeFailure(f"in-process run exceeded {max_frames} frames")
                    if not node.finished and _matches(flt, msg):
                        _send_all(bus, _call(node, node.handle, msg, 0.0))
    finally:
        for bus in buses:
            bus.shutdown()
    _end_with_time_master(nodes)
    unfinished = [n.name for n in nodes if not n.finished]
    if unfinished:
        raise NodeFailure(f"virtual-bus run stalled; unfinished nodes: {', '.join(unfinished)}")
    return moved
