"""The floor of canbrake's process layout (issue 26, `canbrake bench`): the minimal lockstep
exchange with no model, no codec and no recorder, measured with canbrake's own pieces.

A plant process and ``n`` ECU processes, started as :func:`canbrake.run.run_processes` starts
nodes (:func:`canbrake.run._mp_context`: the forkserver with the node modules preloaded), each
open canbrake's in-memory bus (:class:`canbrake.bus.memory.MemoryBus`: the shared ring, the
pushed-down filters and its FIFO wake-ups, with the options a lockstep node gets) on a private
channel. Per period:

- the plant sends the tick (one 8-byte frame), which wakes every ECU;
- each ECU has the peers' words of the previous period (their frames, filtered for), reads the
  tick, sends its own word (tick and the sum of its peers' words, 8 bytes) and so wakes the plant;
- the plant waits for all ``n`` words, then starts the next period.

That is every frame and wake-up of a lockstep period and nothing else: what canbrake's engine
does beyond it (codec, E2E, model, controllers, recorder, bookkeeping) is what the bench's ratios
to this floor measure. Nothing here is a second bus: the frames go through ``MemoryBus``.

``phases=2`` is the floor of the lockstep protocol itself (docs/architecture.md): an ECU answers
the tick with its state word (``STATE_ID + i``), waits until every peer's state word of the tick
has come (woken once, as an ECU node in phase 1), and only then sends its word to the plant: the
two exchanges a consensus controller's period needs, with no work in them. Issue 26's targets
are ratios to the one-exchange floor; the bench shows this one beside it.

``period_s > 0`` is the floor of a realtime run: the processes take the realtime scheduling of
nodes (:func:`canbrake.nodes.rt.setup_realtime`: SCHED_FIFO and the plant's CPU where permitted,
the garbage collector frozen), and the plant sends tick k at ``t0 + k * period_s`` (waiting as
a realtime node does: asleep on the bus until ``spin_s`` before the tick, then polling and
yielding; a tick more than a period late moves the grid on, as the plant node's timer does).
A period whose words are not all in by the next tick's time is a deadline miss, as the plant
node counts one; the round trip (tick sent -> the last word in) is what a realtime run reports
as its command latency, with no model, codec, recorder or controller in it.
"""
from __future__ import annotations

import math
import os
import struct
import time
import uuid
from typing import Any

#: identifiers of the floor's frames: the plant's tick, ECU i's word at WORD_ID + i
TICK_ID = 0x010
WORD_ID = 0x100
#: ECU i's state word (``phases=2``)
STATE_ID = 0x200
_END = (1 << 64) - 1
_Q = struct.Struct("<Q")
_II = struct.Struct("<II")


def _open(channel: str, ids: list[int], yield_before_sleep: bool) -> Any:
    """A lockstep node's memory bus on ``channel`` accepting the standard ``ids`` (as
    :func:`canbrake.run._open_bus` opens it: backpressure on accepted frames, the yield knob)."""
    import can

    return can.Bus(interface="canbrake", channel=channel, receive_own_messages=False,
                   can_filters=[{"can_id": i, "can_mask": 0x7FF, "extended": False} for i in ids],
                   backpressure="accepted", yield_before_sleep=yield_before_sleep)


def _realtime(role: str, sched: Any, slot: int) -> None:
    """A realtime node's scheduling for this process (``role``), what was obtained written to
    ``sched`` (characters ``slot * _SCHED_LEN`` on)."""
    from canbrake.nodes.driver import freeze_heap
    from canbrake.nodes.rt import setup_realtime

    frozen = freeze_heap()
    got = (setup_realtime(role) + (f", gc: {frozen:,} objects frozen" if frozen else "")).encode()[:_SCHED_LEN]
    sched[slot * _SCHED_LEN:slot * _SCHED_LEN + len(got)] = got


#: characters of a process's scheduling description in run_floor's shared array
_SCHED_LEN = 160


def _ecu_main(i: int, n: int, channel: str, barrier: Any, out: Any, yield_: bool = True, phases: int = 1,
              period_s: float = 0.0, sched: Any = None) -> None:
    """ECU ``i`` (0-based) of the floor: answers every tick with its word (``phases=2``: after
    its state word and its peers' of the tick); ``out[i]``: its bus's sleeps (blocking waits)
    over the run. ``period_s > 0``: with a realtime node's scheduling (module docstring)."""
    import can

    from canbrake.run import _set_title

    _set_title(f"canbrake ecu{i + 1} floor")  # as a node's, so that `canbrake bench` sees its role
    peers = [j for j in range(n) if j != i]
    base = STATE_ID if phases == 2 else WORD_ID
    bus = _open(channel, [TICK_ID] + [base + j for j in peers], yield_)
    if period_s > 0 and sched is not None:
        _realtime("ecu", sched, 1 if i == 0 else 2)
    try:
        words = [0] * n
        my_id = WORD_ID + i
        barrier.wait(timeout=60)
        recv, recv_batch = bus.recv_filtered, bus.recv_batch
        backlog: list[Any] = []  # (realtime) frames that came after a tick which ended a state wait
        tick: int | None = None  # a tick taken while waiting for the states of the one before
        while True:
            if tick is None:
                m = backlog.pop(0) if backlog else recv(30.0)
                if m is None:
                    raise TimeoutError(f"floor ECU {i}: no frame for 30 s")
                if m.arbitration_id != TICK_ID:  # one exchange: a peer's word of the last period
                    if phases == 1:  # (two, realtime: a peer's state of a tick gone)
                        words[m.arbitration_id - base] = _II.unpack_from(m.data)[1]
                    continue
                tick = _Q.unpack_from(m.data)[0]
            if tick == _END:
                break
            if phases == 2:  # the state exchange: every peer's word of this tick before ours goes out
                bus.send(can.Message(arbitration_id=STATE_ID + i, data=_II.pack(tick & 0xFFFFFFFF, words[i]),
                                     is_extended_id=False))
                got, nxt = 0, None
                while got < len(peers) and nxt is None:
                    ms = backlog if backlog else recv_batch(30.0, len(peers) - got)
                    backlog = []
                    if not ms:
                        raise TimeoutError(f"floor ECU {i}: tick {tick}: {got} of {len(peers)} states after 30 s")
                    for x, p in enumerate(ms):
                        if p.arbitration_id == TICK_ID:  # realtime: the next tick came first, this one is missed
                            nxt, backlog = _Q.unpack_from(p.data)[0], list(ms[x + 1:])
                            break
                        t_p, w = _II.unpack_from(p.data)
                        if t_p != tick & 0xFFFFFFFF:
                            if period_s > 0:  # a peer late for a tick gone: not a fault in realtime
                                continue
                            raise RuntimeError(f"floor ECU {i}: tick {tick}: state word of tick {t_p}")
                        words[p.arbitration_id - base] = w
                        got += 1
                if nxt is not None:
                    tick = nxt
                    continue
            words[i] = (sum(words) + tick) & 0xFFFFFFFF
            bus.send(can.Message(arbitration_id=my_id, data=_II.pack(tick & 0xFFFFFFFF, words[i]),
                                 is_extended_id=False))
            tick = None
        out[i] = bus.stats().sleeps
    finally:
        bus.shutdown()


def _plant_main(n: int, channel: str, duration_s: float, barrier: Any, out: Any, yield_: bool = True,
                period_s: float = 0.0, sched: Any = None) -> None:
    """The floor's plant: ticks for ``duration_s`` of wall time; ``out[n:]``: periods, seconds,
    mean, p99 and max round trip (s: tick sent -> the last ECU's word in), the plant's sleeps,
    round trips longer than 1 ms and than 10 ms, then (``period_s > 0``) the p50 round trip,
    deadline misses, late periods and the seconds the grid moved on."""
    import can

    from canbrake.run import _set_title

    _set_title("canbrake plant floor")
    bus = _open(channel, [WORD_ID + j for j in range(n)], yield_)
    if period_s > 0:
        _realtime("plant", sched, 0)
    try:
        barrier.wait(timeout=60)
        if period_s > 0:
            _paced(bus, n, duration_s, period_s, out)
            return
        send, recv, clock = bus.send, bus.recv_batch, time.perf_counter
        trips: list[float] = []
        k = 0
        t0 = clock()
        end = t0 + duration_s
        while True:
            ts = clock()
            if ts >= end:
                break
            send(can.Message(arbitration_id=TICK_ID, data=_Q.pack(k), is_extended_id=False))
            got = 0
            while got < n:  # woken once the words still missing are in, as the plant node is
                ms = recv(30.0, n - got)
                if not ms:
                    raise TimeoutError(f"floor plant: tick {k}: {got} of {n} words after 30 s")
                got += sum(_II.unpack_from(m.data)[0] == k & 0xFFFFFFFF for m in ms)
            trips.append(clock() - ts)
            k += 1
        el = clock() - t0
        send(can.Message(arbitration_id=TICK_ID, data=_Q.pack(_END), is_extended_id=False))
        trips.sort()
        out[n:n + 8] = [k, el, sum(trips) / len(trips) if trips else 0.0,
                        trips[min(len(trips) - 1, int(0.99 * len(trips)))] if trips else 0.0,
                        trips[-1] if trips else 0.0, bus.stats().sleeps,
                        sum(t > 0.001 for t in trips), sum(t > 0.01 for t in trips)]
    finally:
        bus.shutdown()


def _paced(bus: Any, n: int, duration_s: float, period_s: float, out: Any) -> None:
    """The plant's ticks at ``period_s`` on a wall-clock grid for ``duration_s`` (module
    docstring); fills ``out[n:]`` as :func:`_plant_main` says."""
    import can

    from canbrake.nodes.rt import spin_s

    send, recv, clock, yield_cpu = bus.send, bus.recv_batch, time.perf_counter, os.sched_yield
    spin = spin_s(period_s)
    trips: list[float] = []
    misses = late = 0
    slipped = 0.0
    k = 0
    t0 = clock()
    grid = t0  # tick k's time
    end = t0 + duration_s
    while grid < end:
        lateness = clock() - grid
        if lateness > period_s:  # a late wake-up: the grid moves on (the plant node's timer does so)
            late += 1
            grid += lateness
            slipped += lateness
        ts = clock()
        send(can.Message(arbitration_id=TICK_ID, data=_Q.pack(k), is_extended_id=False))
        deadline, got, trip = grid + period_s, 0, math.inf
        while True:  # the words of tick k until the deadline, then on to tick k + 1
            now = clock()
            rem = deadline - now
            if rem <= 0.0:
                break
            if rem > spin:
                ms = recv(rem - spin, n - got if got < n else 1)
            else:  # near the deadline: poll, yield the CPU if nothing came
                ms = recv(0.0, 1)
                if not ms:
                    yield_cpu()
            for m in ms:
                if _II.unpack_from(m.data)[0] == k & 0xFFFFFFFF:
                    got += 1
                    if got == n:
                        trip = clock() - ts
        if got < n:
            misses += 1
        trips.append(trip)
        grid = deadline
        k += 1
    el = clock() - t0
    send(can.Message(arbitration_id=TICK_ID, data=_Q.pack(_END), is_extended_id=False))
    trips.sort()
    fin = [t for t in trips if t < math.inf]
    pick = (lambda q: trips[min(len(trips) - 1, int(q * len(trips)))] if trips else 0.0)
    out[n:n + 12] = [k, el, sum(fin) / len(fin) if fin else 0.0, pick(0.99), trips[-1] if trips else 0.0,
                     bus.stats().sleeps, sum(t > 0.001 for t in trips), sum(t > 0.01 for t in trips),
                     pick(0.5), misses, late, slipped]


def run_floor(n: int = 6, duration_s: float = 2.0, timeout_s: float = 120.0, phases: int = 1,
              period_s: float = 0.0) -> dict[str, Any]:
    """Run the floor with ``n`` ECU processes for ``duration_s`` of wall time (``phases``: 1, the
    one exchange; 2, the lockstep protocol's state exchange and commands, module docstring).

    Returns ``status`` ("ok" or "failed" with ``message``), ``periods_per_s``, ``periods``,
    ``round_trip_mean_s`` / ``_p99_s`` / ``_max_s`` (tick sent -> last word in), ``over_1ms_pct`` /
    ``over_10ms_pct`` (round trips longer than a 1 / 10 ms period, %), ``sleeps_per_period``
    (blocking waits of all the floor's buses per period) and ``start_method``. ``period_s > 0``
    (realtime, module docstring) adds ``period_s``, ``deadline_misses`` and
    ``deadline_miss_pct`` (periods whose words were not all in by the next tick), ``late_periods``,
    ``slipped_s``, ``round_trip_p50_s`` (a missed period's round trip counts as infinite: a
    percentile that falls on one is ``inf``) and ``scheduling`` (the plant's, the first ECU's,
    the others' as the first's unless they differ). Every process started here is reaped before
    it returns."""
    from canbrake.bus.memory import remove_channel
    from canbrake.run import _mp_context, memory_yield
    from canbrake.startup import children_skip_main

    if phases not in (1, 2):
        raise ValueError(f"phases must be 1 or 2, not {phases!r}")
    if not period_s >= 0.0:
        raise ValueError(f"period_s must be >= 0, not {period_s!r}")
    yield_ = memory_yield()  # decided once, here (as a run's orchestrator does), for every process

    with children_skip_main():
        ctx = _mp_context()
    channel = f"floor-{os.getpid()}-{uuid.uuid4().hex[:8]}"
    barrier = ctx.Barrier(n + 1)
    out = ctx.Array("d", n + 12, lock=False)
    sched = ctx.Array("c", 3 * _SCHED_LEN, lock=False)  # plant, ECU 1, one of the others (realtime)
    procs = [ctx.Process(target=_ecu_main, args=(i, n, channel, barrier, out, yield_, phases, period_s, sched),
                         name=f"canbrake-floor-ecu{i + 1}") for i in range(n)]
    procs.append(ctx.Process(target=_plant_main, args=(n, channel, duration_s, barrier, out, yield_, period_s,
                                                        sched),
                             name="canbrake-floor-plant"))
    res: dict[str, Any] = {"status": "ok", "message": "", "ecus": n, "phases": phases,
                           "start_method": ctx.get_start_method()}
    try:
        for p in procs:
            with children_skip_main():
                p.start()
        from multiprocessing.connection import wait

        deadline = time.monotonic() + timeout_s + duration_s
        while time.monotonic() < deadline:  # until all are done or one failed
            alive = [p for p in procs if p.exitcode is None]
            if not alive or any(p.exitcode for p in procs):
                break
            wait([p.sentinel for p in alive], timeout=max(0.0, deadline - time.monotonic()))
        bad = [p for p in procs if p.exitcode != 0]
        if bad:
            p = bad[0]
            res.update(status="failed", message=f"{p.name} " + ("did not finish" if p.exitcode is None
                                                                 else f"exited with status {p.exitcode}"))
    finally:
        for p in procs:
            if p.pid is None:
                continue  # never started
            if p.exitcode is None:
                p.terminate()
                p.join(5.0)
            if p.exitcode is None:
                p.kill()
                p.join()
        try:
            remove_channel(channel, force=True)
        except Exception:  # noqa: BLE001 - nothing left, or already removed by the last bus
            pass
    if res["status"] == "ok":
        periods, el, mean, p99, mx, plant_sleeps, over1, over10 = out[n:n + 8]
        res.update(periods=int(periods), wall_s=el, periods_per_s=periods / el if el else None,
                   round_trip_mean_s=mean, round_trip_p99_s=p99, round_trip_max_s=mx,
                   sleeps_per_period=(plant_sleeps + sum(out[:n])) / periods if periods else None,
                   over_1ms_pct=100.0 * over1 / periods if periods else None,
                   over_10ms_pct=100.0 * over10 / periods if periods else None)
        if period_s > 0:
            p50, misses, late, slipped = out[n + 8:n + 12]
            said = [bytes(sched[i * _SCHED_LEN:(i + 1) * _SCHED_LEN]).rstrip(b"\0").decode() for i in range(3)]
            res.update(period_s=period_s, round_trip_p50_s=p50, deadline_misses=int(misses),
                       deadline_miss_pct=100.0 * misses / periods if periods else None, late_periods=int(late),
                       slipped_s=slipped,
                       scheduling=f"plant {said[0]}; ECUs {said[1]}" + (f" / {said[2]}" if said[2] != said[1] else ""))
    return res


if __name__ == "__main__":  # python -m canbrake.floor [N] [SECONDS] [PHASES] [PERIOD_S]
    import json
    import sys

    from canbrake.floor import run_floor as _run  # the nodes' target functions must come from the module

    print(json.dumps(_run(int(sys.argv[1]) if len(sys.argv) > 1 else 6,
                          float(sys.argv[2]) if len(sys.argv) > 2 else 2.0,
                          phases=int(sys.argv[3]) if len(sys.argv) > 3 else 1,
                          period_s=float(sys.argv[4]) if len(sys.argv) > 4 else 0.0)))
