"""Benchmark: the lockstep tick pattern on the canbrake in-memory bus vs python-can ``virtual``.

A tick (ARCHITECTURE.md): the plant sends SYNC(k) and one sensor frame per car; ECU i, once it
has SYNC(k) and its sensor frame (its filters accept only those and the peers' state frames),
sends its state frame (heard by every ECU) and its brake command; the plant waits for all
commands of tick k. Printed: ticks per wall second and the ratio to the baseline measured in
this same run, so machine load cancels out as far as it can. No assertions: numbers only.

    python bench/bench_memory_bus.py [--seconds 3] [--ecus 6] [--repeat 1]

Rows:
  virtual, 1 process      python-can ``virtual``: plant + ECU buses in one process, driven in turn
  canbrake, 1 process     the same driver on canbrake MemoryBus objects (per-frame cost, no wake-ups)
  canbrake, send          1 plant + N ECU processes (spawn), ``send`` per frame
  canbrake, send_many     same, bursts sent with ``MemoryBus.send_many`` (one wake-up per reader)
  no yield                same, ``yield_before_sleep=False``: readers block at once
"""
from __future__ import annotations

import argparse
import multiprocessing as mp
import os
import shutil
import statistics
import struct
import sys
import tempfile
import time
from typing import Callable, Optional

import can

SYNC_ID, CMD_BASE, STATE_BASE, SENSOR_BASE = 0x010, 0x020, 0x100, 0x200
_TICK = struct.Struct("<IB")  # tick, stop flag


def _msg(aid: int, k: int, stop: int = 0) -> can.Message:
    return can.Message(arbitration_id=aid, data=_TICK.pack(k, stop) + b"\0\0\0", is_extended_id=False)


def ecu_filters(i: int) -> list[dict]:
    return [
        {"can_id": SYNC_ID, "can_mask": 0x7FF, "extended": False},
        {"can_id": SENSOR_BASE + i, "can_mask": 0x7FF, "extended": False},
        {"can_id": STATE_BASE, "can_mask": 0x7F0, "extended": False},
    ]


PLANT_FILTERS = [{"can_id": CMD_BASE, "can_mask": 0x7F0, "extended": False}]


class EcuLogic:
    """ECU i: on SYNC(k) and sensor(k), reply with state(k) then command(k)."""

    def __init__(self, i: int) -> None:
        self.i, self.sync_k, self.sensor_k, self.next_k = i, -1, -1, 0
        self.peer_states = 0
        self.stop = False

    def on_frame(self, msg: can.Message) -> list[can.Message]:
        k, stop = _TICK.unpack_from(msg.data)
        aid = msg.arbitration_id
        if aid == SYNC_ID:
            self.sync_k, self.stop = k, bool(stop)
        elif aid == SENSOR_BASE + self.i:
            self.sensor_k = k
        elif aid & 0x7F0 == STATE_BASE:
            self.peer_states += 1
        else:
            return []  # not for this ECU (only on buses without filters)
        if self.sync_k == self.sensor_k == self.next_k and not self.stop:
            self.next_k += 1
            return [_msg(STATE_BASE + self.i, k), _msg(CMD_BASE + self.i, k)]
        return []


def plant_frames(k: int, n: int, stop: int = 0) -> list[can.Message]:
    return [_msg(SYNC_ID, k, stop)] + [_msg(SENSOR_BASE + i, k) for i in range(n)]


# ---------------------------------------------------------------- one process, driven in turn
def run_one_process(factory: Callable[..., can.BusABC], n: int, seconds: float) -> float:
    """Plant and ECU buses in this process; each tick every node drains its bus in turn."""
    plant = factory(PLANT_FILTERS)
    ecus = [(EcuLogic(i), factory(ecu_filters(i))) for i in range(n)]
    try:
        k = 0
        t0 = time.perf_counter()
        end = t0 + seconds
        while time.perf_counter() < end:
            for m in plant_frames(k, n):
                plant.send(m)
            for logic, bus in ecus:
                while (m := bus.recv(0)) is not None:
                    for out in logic.on_frame(m):
                        bus.send(out)
            got = 0
            while (m := plant.recv(0)) is not None:
                got += m.arbitration_id & 0x7F0 == CMD_BASE and _TICK.unpack_from(m.data)[0] == k
            assert got == n, f"tick {k}: {got}/{n} commands"
            k += 1
        return k / (time.perf_counter() - t0)
    finally:
        plant.shutdown()
        for _, bus in ecus:
            bus.shutdown()


# ---------------------------------------------------------------- 1 plant + n ECU processes
def ecu_process(i: int, channel: str, shm_dir: str, batch: bool, yield_: bool, ready: "mp.Queue", done: "mp.Queue") -> None:
    from canbrake.bus.memory import MemoryBus

    logic = EcuLogic(i)
    with MemoryBus(channel, can_filters=ecu_filters(i), shm_dir=shm_dir, yield_before_sleep=yield_) as bus:
        ready.put(i)
        while not logic.stop:
            m = bus.recv(10.0)
            if m is None:
                break
            out = logic.on_frame(m)
            if out:
                if batch:
                    bus.send_many(out)
                else:
                    for o in out:
                        bus.send(o)
        done.put((i, logic.next_k, bus.stats()))


def run_processes(n: int, seconds: float, batch: bool, shm_dir: str, yield_: bool = True) -> tuple[float, float, float]:
    """Returns (ticks/s, wake-ups per tick per ECU, wake-ups per tick of the plant)."""
    from canbrake.bus.memory import MemoryBus

    ctx = mp.get_context("spawn")
    channel = f"bench{os.getpid()}{'b' if batch else 's'}{'y' if yield_ else ''}"
    ready, done = ctx.Queue(), ctx.Queue()
    with MemoryBus(channel, can_filters=PLANT_FILTERS, shm_dir=shm_dir, yield_before_sleep=yield_) as plant:
        procs = [ctx.Process(target=ecu_process, args=(i, channel, shm_dir, batch, yield_, ready, done))
                 for i in range(n)]
        for p in procs:
            p.start()
        for _ in range(n):
            ready.get(timeout=60)
        send: Callable[[list[can.Message]], None] = (
            plant.send_many if batch else (lambda ms: [plant.send(m) for m in ms])  # type: ignore[func-returns-value]
        )
        k = 0
        t0 = time.perf_counter()
        end = t0 + seconds
        while time.perf_counter() < end:
            send(plant_frames(k, n))
            got = 0
            while got < n:
                m = plant.recv(10.0)
                if m is None:
                    raise RuntimeError(f"tick {k}: ECUs stopped answering")
                got += _TICK.unpack_from(m.data)[0] == k
            k += 1
        rate = k / (time.perf_counter() - t0)
        plant_wakeups = plant.stats().wakeups / max(k, 1)
        send(plant_frames(k, n, stop=1))
        results = [done.get(timeout=30) for _ in range(n)]
        for p in procs:
            p.join(timeout=30)
    wakeups = statistics.mean(s.wakeups for _, _, s in results) / max(k, 1)
    return rate, wakeups, plant_wakeups


def main(argv: Optional[list[str]] = None) -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--seconds", type=float, default=3.0, help="duration of each measurement (s)")
    ap.add_argument("--ecus", type=int, default=6)
    ap.add_argument("--repeat", type=int, default=1, help="runs per row; the median is printed")
    args = ap.parse_args(argv)

    from canbrake.bus.memory import MemoryBus

    shm_dir = tempfile.mkdtemp(prefix="canbrake-bench-", dir="/dev/shm" if os.path.isdir("/dev/shm") else None)
    n, secs = args.ecus, args.seconds

    def virtual_factory(filters: list[dict]) -> can.BusABC:
        # no filters: python-can filters in software and recv(0) gives up at the first rejected
        # frame; the node logic ignores frames that are not for it instead
        return can.Bus(interface="virtual", channel=f"bench-{os.getpid()}")

    def memory_factory(filters: list[dict]) -> can.BusABC:
        return MemoryBus(f"inproc{os.getpid()}", can_filters=filters, shm_dir=shm_dir)

    def one_process(factory: Callable[..., can.BusABC]) -> Callable[[], tuple[float, str]]:
        return lambda: (run_one_process(factory, n, secs), "")

    def processes(batch: bool, yield_: bool) -> Callable[[], tuple[float, str]]:
        def run() -> tuple[float, str]:
            rate, wk, wp = run_processes(n, secs, batch, shm_dir, yield_)
            return rate, f"wake-ups/tick: {wk:.2f} per ECU, {wp:.2f} plant"
        return run

    rows: list[tuple[str, Callable[[], tuple[float, str]]]] = [
        ("python-can virtual, 1 process (baseline)", one_process(virtual_factory)),
        ("canbrake MemoryBus, 1 process", one_process(memory_factory)),
        (f"canbrake, 1 plant + {n} ECU procs, send", processes(False, True)),
        (f"canbrake, 1 plant + {n} ECU procs, send_many", processes(True, True)),
        (f"canbrake, 1 plant + {n} ECU procs, send_many, no yield", processes(True, False)),
    ]
    # rows run in turn, `repeat` rounds: each ratio is against the baseline of its own round,
    # so a change of machine load between rounds cancels out
    results: dict[str, list[tuple[float, float, str]]] = {label: [] for label, _ in rows}
    load0 = os.getloadavg()[0]
    try:
        for _ in range(args.repeat):
            base = 0.0
            for label, run in rows:
                rate, extra = run()
                base = base or rate
                results[label].append((rate, rate / base, extra))
    finally:
        shutil.rmtree(shm_dir, ignore_errors=True)

    print(f"lockstep tick = SYNC + {n} sensor frames, {n} state frames, {n} commands; {secs:g} s per "
          f"row, median of {args.repeat} rounds; {os.cpu_count()} CPUs, load average "
          f"{load0:.1f} -> {os.getloadavg()[0]:.1f}")
    for label, runs in results.items():
        rate = statistics.median(r[0] for r in runs)
        ratio = statistics.median(r[1] for r in runs)
        extra = sorted(runs)[len(runs) // 2][2]
        print(f"  {label:<50} {rate:7.0f} ticks/s  x{ratio:5.2f}  {extra}")


if __name__ == "__main__":
    sys.exit(main())
