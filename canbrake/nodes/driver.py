"""Drivers: run node state machines over a real python-can bus or in one process.

- :func:`drive` — the loop of one OS process: receive, handle, send; honours the node's
  realtime deadlines; never busy-spins (blocking ``recv`` with a timeout).
- :func:`run_inprocess` — every node in one process and one thread, frames delivered in one
  global order; either straight from node to node (``medium="direct"``, the fast engine used
  by sweeps) or through python-can ``virtual`` buses (``medium="virtual"``, one Bus object per
  node, exercising python-can's own bus, copying and queueing code). Lockstep only.
"""
from __future__ import annotations

import contextlib
import gc
import multiprocessing as mp
import os
import time
import uuid
from typing import Any, Callable, Sequence

import can

from canbrake.bus.memory import BusOverrunError
from canbrake.nodes.base import Node
from canbrake.nodes._route import hand, split
from canbrake.nodes.group import Router, _matches


def freeze_heap() -> int:
    """Freeze what this process's garbage collector holds (``gc.freeze``), so that the run's full
    collections skip the objects set up before it: a full (generation 2) collection walks every
    object (~100,000 after numpy, python-can, cantools and the scenario are loaded; 37 ms
    measured on this machine, a missed 10 ms deadline in realtime and ~4 % of a 106-ECU lockstep
    run's time). Objects made during the run are collected as usual. No collection first: in a
    node process forked from the forkserver, a collection writes every object's header and so
    un-shares the pages it inherited (measured: ~20 MB more PSS per ECU process); freezing only
    moves the collector's lists. ``CANBRAKE_GC=off`` leaves the collector alone. Returns the
    number of objects frozen."""
    if os.environ.get("CANBRAKE_GC", "freeze") == "off":
        return 0
    gc.freeze()
    return gc.get_freeze_count()


#: the in-process engine's first-generation threshold (:func:`frozen_heap`; Python's default 700)
INPROCESS_GC_THRESHOLD = 50_000


@contextlib.contextmanager
def frozen_heap():
    """:func:`freeze_heap` for the duration of an in-process run, unfrozen after it (the calling
    process goes on: its later garbage is collected again). During the run the collector's
    first generation is collected every :data:`INPROCESS_GC_THRESHOLD` net allocations instead of
    every 700: a lockstep run has no deadline a longer collection could miss, and the collections
    cost ~2 % of a period (Chen case 1, alternated: the same as no collection at all). Node
    processes keep the default (a realtime node's collections stay short)."""
    if os.environ.get("CANBRAKE_GC", "freeze") == "off":
        yield
        return
    gc.freeze()  # (not freeze_heap: its count walks the frozen objects, ~9 ms, and nothing reads it here)
    old = gc.get_threshold()
    gc.set_threshold(max(old[0], INPROCESS_GC_THRESHOLD), *old[1:])
    try:
        yield
    finally:
        gc.set_threshold(*old)
        gc.unfreeze()


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
    # canbrake's memory bus filters in shared memory and hands over every pending frame at once
    # (MemoryBus.recv_batch); any other python-can bus gives one frame per recv
    recv_batch = getattr(bus, "recv_batch", None)
    # ... and, to a node that takes them so (an ECU, the plant, the recorder), as slot images read and filtered in one
    # compiled call (MemoryBus.recv_raw): no can.Message per frame received
    recv_raw = getattr(bus, "recv_raw", None)
    handle_raw = getattr(node, "handle_raw", None)
    recv: Callable[[float, int], Sequence[Any]]
    handle: Callable[[Sequence[Any], float], list[can.Message]]
    send: Callable[[list[can.Message]], None]
    if recv_raw is not None and handle_raw is not None:
        message = bus.raw_message  # type: ignore[attr-defined]
        recv = recv_raw
        def handle(frames: Sequence[Any], now: float) -> list[can.Message]:  # noqa: E306
            return handle_raw(frames, now, message)
        send_burst = getattr(bus, "send_burst", None)
        send = send_burst or (lambda msgs: _send_all(bus, msgs))
        node.sends_images = send_burst is not None
    else:
        if recv_batch is None:
            def recv_batch(timeout: float | None, min_frames: int = 1,
                           _recv: Callable[..., can.Message | None] = bus.recv) -> list[can.Message]:
                m = _recv(timeout=timeout)
                return [] if m is None else [m]
        def recv(timeout: float, n: int) -> Sequence[Any]:  # noqa: E306
            return recv_batch(timeout=timeout, min_frames=n)
        handle = node.handle_batch
        send = lambda msgs: _send_all(bus, msgs)  # noqa: E731
    # realtime (``spin_s``), a node that asks for it (an ECU): once its frames are sent, let the
    # other runnable processes of its priority (the other ECUs, SCHED_FIFO) go first: what it does
    # after sending (its trace row) is on no one's path, theirs is on the period's
    rt_yield = spin_s > 0.0 and getattr(node, "yield_after_send", False)
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
            frames = recv(timeout, node.frames_wanted())
        except BusOverrunError as e:
            # a flood overran this node's receive ring: count what was lost and receive on
            node.on_rx_overrun(e.frames_lost)
            continue
        now = clock()
        if frames:
            out = handle(frames, now)
            send(out)
            if out and rt_yield:
                os.sched_yield()  # (see rt_yield above)
            node.after_send()
        elif timeout == 0.0 and spin_s > 0.0:
            os.sched_yield()
        deadline = node.next_deadline()
        if deadline is not None and now >= deadline:
            send(node.on_timer(now))
            node.after_send()
        if parent_pid is not None and (not frames or time.monotonic() >= next_check):
            next_check = time.monotonic() + idle_check_s
            if not _parent_alive(parent_pid):
                raise NodeFailure(f"{node.name}: parent process went away")


def run_inprocess(nodes: Sequence[Node], *, medium: str = "direct", max_frames: int | None = None) -> int:
    """Run all ``nodes`` in this process until every node has finished; returns frames moved.

    Nodes start in the given order (put the plant, the time master, last).
    """
    with frozen_heap():
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
    """Frames move in generations (:class:`~canbrake.nodes.group.Router`): a lockstep phase is
    one generation, each node handles its share of it in one call."""
    router = Router(nodes)
    gen: list[tuple[int, can.Message]] = []
    for idx, node in enumerate(nodes):
        gen.extend((idx, m) for m in _call(node, node.start, 0.0))
    moved = 0
    # Router.step(Router.inboxes(gen), 0.0) without its two Python frames per generation
    n, routes, route, handlers = len(router.nodes), router._routes, router.route, router._handlers
    try:  # what _call does, around the loop instead of per call
        while gen:
            moved += len(gen)
            if max_frames is not None and moved > max_frames:
                raise NodeFailure(f"in-process run exceeded {max_frames} frames")
            gen = hand(router, router.nodes, handlers, split(gen, routes, route, n), 0.0)
    except NodeFailure:
        raise
    except Exception as e:  # noqa: BLE001 - as in _call: the node whose handle raised, named
        raise NodeCrash((router.current or nodes[0]).name, e) from e
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
                batch: list[can.Message] = []
                while (msg := bus.recv(timeout=0)) is not None:
                    moved += 1
                    if max_frames is not None and moved > max_frames:
                        raise NodeFailure(f"in-process run exceeded {max_frames} frames")
                    if _matches(flt, msg):
                        batch.append(msg)
                if batch:
                    progress = True
                    if not node.finished:
                        _send_all(bus, _call(node, node.handle_batch, batch, 0.0))
    finally:
        for bus in buses:
            bus.shutdown()
    _end_with_time_master(nodes)
    unfinished = [n.name for n in nodes if not n.finished]
    if unfinished:
        raise NodeFailure(f"virtual-bus run stalled; unfinished nodes: {', '.join(unfinished)}")
    return moved
