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
"""
from __future__ import annotations

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


def _ecu_main(i: int, n: int, channel: str, barrier: Any, out: Any, yield_: bool = True, phases: int = 1) -> None:
    """ECU ``i`` (0-based) of the floor: answers every tick with its word (``phases=2``: after
    its state word and its peers' of the tick); ``out[i]``: its bus's sleeps (blocking waits)
    over the run."""
    import can

    from canbrake.run import _set_title

    _set_title(f"canbrake ecu{i + 1} floor")  # as a node's, so that `canbrake bench` sees its role
    peers = [j for j in range(n) if j != i]
    base = STATE_ID if phases == 2 else WORD_ID
    bus = _open(channel, [TICK_ID] + [base + j for j in peers], yield_)
    try:
        words = [0] * n
        my_id = WORD_ID + i
        barrier.wait(timeout=60)
        recv = bus.recv_filtered
        while True:
            m = recv(30.0)
            if m is None:
                raise TimeoutError(f"floor ECU {i}: no frame for 30 s")
            if m.arbitration_id != TICK_ID:  # (one exchange: a peer's word of the last period)
                words[m.arbitration_id - base] = _II.unpack_from(m.data)[1]
                continue
            tick = _Q.unpack_from(m.data)[0]
            if tick == _END:
                break
            if phases == 2:  # the state exchange: every peer's word of this tick before ours goes out
                bus.send(can.Message(arbitration_id=STATE_ID + i, data=_II.pack(tick & 0xFFFFFFFF, words[i]),
                                     is_extended_id=False))
                got = 0
                while got < len(peers):
                    ms = bus.recv_batch(30.0, len(peers) - got)
                    if not ms:
                        raise TimeoutError(f"floor ECU {i}: tick {tick}: {got} of {len(peers)} states after 30 s")
                    for p in ms:
                        t_p, words[p.arbitration_id - base] = _II.unpack_from(p.data)
                        if t_p != tick & 0xFFFFFFFF:  # a peer's state of another tick: the protocol broken
                            raise RuntimeError(f"floor ECU {i}: tick {tick}: state word of tick {t_p}")
                    got += len(ms)
            words[i] = (sum(words) + tick) & 0xFFFFFFFF
            bus.send(can.Message(arbitration_id=my_id, data=_II.pack(tick & 0xFFFFFFFF, words[i]),
                                 is_extended_id=False))
        out[i] = bus.stats().sleeps
    finally:
        bus.shutdown()


def _plant_main(n: int, channel: str, duration_s: float, barrier: Any, out: Any, yield_: bool = True) -> None:
    """The floor's plant: ticks for ``duration_s`` of wall time; ``out[n:]``: periods, seconds,
    mean, p99 and max round trip (s: tick sent -> the last ECU's word in), the plant's sleeps,
    round trips longer than 1 ms and than 10 ms."""
    import can

    from canbrake.run import _set_title

    _set_title("canbrake plant floor")
    bus = _open(channel, [WORD_ID + j for j in range(n)], yield_)
    try:
        barrier.wait(timeout=60)
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


def run_floor(n: int = 6, duration_s: float = 2.0, timeout_s: float = 120.0, phases: int = 1) -> dict[str, Any]:
    """Run the floor with ``n`` ECU processes for ``duration_s`` of wall time (``phases``: 1, the
    one exchange; 2, the lockstep protocol's state exchange and commands, module docstring).

    Returns ``status`` ("ok" or "failed" with ``message``), ``periods_per_s``, ``periods``,
    ``round_trip_mean_s`` / ``_p99_s`` / ``_max_s`` (tick sent -> last word in), ``over_1ms_pct`` /
    ``over_10ms_pct`` (round trips longer than a 1 / 10 ms period, %), ``sleeps_per_period``
    (blocking waits of all the floor's buses per period) and ``start_method``. Every process
    started here is reaped before it returns."""
    from canbrake.bus.memory import remove_channel
    from canbrake.run import _mp_context, memory_yield
    from canbrake.startup import children_skip_main

    if phases not in (1, 2):
        raise ValueError(f"phases must be 1 or 2, not {phases!r}")
    yield_ = memory_yield()  # decided once, here (as a run's orchestrator does), for every process

    with children_skip_main():
        ctx = _mp_context()
    channel = f"floor-{os.getpid()}-{uuid.uuid4().hex[:8]}"
    barrier = ctx.Barrier(n + 1)
    out = ctx.Array("d", n + 8, lock=False)
    procs = [ctx.Process(target=_ecu_main, args=(i, n, channel, barrier, out, yield_, phases),
                         name=f"canbrake-floor-ecu{i + 1}") for i in range(n)]
    procs.append(ctx.Process(target=_plant_main, args=(n, channel, duration_s, barrier, out, yield_),
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
    return res


if __name__ == "__main__":  # python -m canbrake.floor [N] [SECONDS] [PHASES]
    import json
    import sys

    from canbrake.floor import run_floor as _run  # the nodes' target functions must come from the module

    print(json.dumps(_run(int(sys.argv[1]) if len(sys.argv) > 1 else 6,
                          float(sys.argv[2]) if len(sys.argv) > 2 else 2.0,
                          phases=int(sys.argv[3]) if len(sys.argv) > 3 else 1)))
