"""Benchmark: per-frame cost of the CAN timing model and of an impairment send path.

Both sit on the send path of every frame, so their cost adds to every tick (a 6-car tick is
19 frames plus the *_DONE frames). Prints microseconds per frame (best of ``--repeat``);
no assertions, numbers only.

    python bench/bench_timing.py [--frames 20000] [--repeat 3]

Rows:
  frame_bits worst          closed-form worst-case stuffing
  frame_bits actual         real bit stream: CRC-15 + stuffing (table driven)
  BusTimingModel            submit + advance, 6-car traffic at 500 kbit/s, 5 ms period
  SendPath empty            TxFrame + submit + release with no impairment
  SendPath 4 impairments    loss, Gilbert-Elliott, jitter, duplicate
  MessageSendPath 4 imp.    the same, from and to can.Message
"""
from __future__ import annotations

import argparse
import time
from typing import Callable

from canbrake.bus.impair import MessageSendPath, TxFrame, build_impairments
from canbrake.bus.timing import BusTimingModel, frame_bits

CHAIN = [{"type": "loss", "probability": 0.01},
         {"type": "gilbert_elliott", "p_gb": 0.01, "p_bg": 0.3},
         {"type": "jitter", "distribution": "uniform", "low_s": 0.0, "high_s": 1e-4},
         {"type": "duplicate", "probability": 0.01}]


def bench(fn: Callable[[int], int], n: int, repeat: int) -> float:
    best = float("inf")
    for _ in range(repeat):
        t0 = time.perf_counter()
        frames = fn(n)
        best = min(best, (time.perf_counter() - t0) / frames)
    return best * 1e6


def worst(n: int) -> int:
    for k in range(n):
        frame_bits(0x100 + (k & 0xFF), False, 8)
    return n


def actual(n: int) -> int:
    for k in range(n):
        frame_bits(0x100 + (k & 0xFF), False, 8, k.to_bytes(8, "little"), "actual")
    return n


def model(n: int) -> int:
    m = BusTimingModel(500_000, record_history=True)
    periods = n // 19
    for k in range(periods):
        t = k * 5e-3
        m.submit("plant", 0x080, False, 4, None, t)
        for i in range(6):
            m.submit("plant", 0x180 + i, False, 8, None, t)
            m.submit(f"ecu{i}", 0x200 + i, False, 8, None, t)
            m.submit(f"ecu{i}", 0x100 + i, False, 5, None, t)
        m.advance(t + 5e-3)
    return periods * 19


def send_path(specs: list) -> Callable[[int], int]:
    def run(n: int) -> int:
        path = build_impairments(specs, 1, "ecu1")
        payload = bytes(8)
        for k in range(n):
            t = k * 1e-4
            path.submit(TxFrame(0x101, False, payload, 8, "ecu1", t, t))
            path.release(t)
        return n
    return run


def message_path(n: int) -> int:
    import can

    path = MessageSendPath(build_impairments(CHAIN, 1, "ecu1"))
    msg = can.Message(arbitration_id=0x101, is_extended_id=False, data=bytes(8))
    for k in range(n):
        path.submit(msg, k * 1e-4)
    return n


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--frames", type=int, default=20_000)
    ap.add_argument("--repeat", type=int, default=3)
    args = ap.parse_args()
    rows = [("frame_bits worst", worst), ("frame_bits actual", actual),
            ("BusTimingModel", model), ("SendPath empty", send_path([])),
            ("SendPath 4 impairments", send_path(CHAIN)),
            ("MessageSendPath 4 imp.", message_path)]
    for name, fn in rows:
        print(f"{name:26s} {bench(fn, args.frames, args.repeat):7.2f} us/frame")


if __name__ == "__main__":
    main()
