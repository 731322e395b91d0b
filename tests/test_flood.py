"""Floods are survived: a node whose receive ring is overrun drops, counts and receives on, and a
run under a babbling flood ends normally with the flooding identifier in its counters."""
from __future__ import annotations

import os
import tempfile
from pathlib import Path

import can
import pytest

from canbrake.bus.guard import FrameGuard
from canbrake.bus.memory import BusOverrunError
from canbrake.nodes.base import Node, frame
from canbrake.nodes.driver import drive
from canbrake.run import run_scenario
from canbrake.scenario import load_scenario
from conftest import CASE1


@pytest.fixture()
def shm_dir(monkeypatch: pytest.MonkeyPatch):
    d = tempfile.mkdtemp(prefix="cbflood-", dir="/dev/shm" if os.path.isdir("/dev/shm") else None)
    monkeypatch.setenv("CANBRAKE_SHM_DIR", d)
    yield Path(d)
    for f in os.listdir(d):
        os.unlink(os.path.join(d, f))
    os.rmdir(d)


class _UntilEnd(Node):
    """Takes every frame and finishes on id 0x123."""

    name = "listener"

    def __init__(self) -> None:
        self.guard = FrameGuard()
        self.seen: list[int] = []

    def handle(self, msg: can.Message, now: float) -> list[can.Message]:
        self.seen.append(msg.arbitration_id)
        self.finished = msg.arbitration_id == 0x123
        return []


def test_an_overrun_reader_drops_counts_and_receives_on(shm_dir):
    ring = 64
    with can.Bus(interface="canbrake", channel="flood", ring_size=ring) as tx, \
            can.Bus(interface="canbrake", channel="flood") as rx:
        for k in range(10 * ring):  # the flood: ten rings' worth before the listener reads
            tx.send(frame(0x001, k.to_bytes(2, "little")))
        tx.send(frame(0x123, b"\x01"))
        with pytest.raises(BusOverrunError) as e:  # what the bus itself reports, typed
            rx.recv(0)
        assert e.value.frames_lost > 0 and isinstance(e.value, can.CanOperationError)
    with can.Bus(interface="canbrake", channel="flood2", ring_size=ring) as tx, \
            can.Bus(interface="canbrake", channel="flood2") as rx:
        for k in range(10 * ring):
            tx.send(frame(0x001, k.to_bytes(2, "little")))
        tx.send(frame(0x123, b"\x01"))
        node = _UntilEnd()
        drive(node, rx, idle_check_s=0.05)  # does not raise
        assert node.finished and node.seen[-1] == 0x123
        st = node.guard.stats()
        assert st["rx_overruns"] == 1
        assert st["rx_frames_lost"] + len(node.seen) == 10 * ring + 1


def test_a_babbling_flood_does_not_fail_the_run_and_the_flooder_is_named(tmp_path):
    over = {"duration_s": 0.05, "bus": {"impairments": [
        {"type": "babble", "sender": "rogue", "arbitration_id": 1, "rate_hz": 200_000.0, "dlc": 8}]}}
    s = run_scenario(load_scenario(CASE1, overrides=over), tmp_path / "flood", backend="inprocess", plots=False)
    clean = run_scenario(load_scenario(CASE1, overrides={"duration_s": 0.05, "bus": {"impairments": [
        {"type": "loss", "probability": 0.0}]}}), tmp_path / "clean", backend="inprocess", plots=False)
    assert s["status"] == "ok" and s["ticks"] == 50
    # the plant releases the flood at each tick start: emissions at 0, 5 us, ... up to t_49 = 49 ms
    assert s["safety"]["flood"]["frames_on_unknown_ids"] == {"0x001": 49 * 200 + 1}
    assert s["safety"]["verdict"] == "attack or fault detected"
    assert (tmp_path / "flood" / "signals.csv").read_bytes() == (tmp_path / "clean" / "signals.csv").read_bytes()
    assert clean["safety"]["verdict"] == "clean"


def test_a_node_that_accepts_only_some_ids_never_loses_them_to_a_flood(shm_dir):
    """backpressure="accepted" (lockstep nodes): a flood on identifiers the reader filters out
    overwrites freely and raises no overrun; a frame it accepts is never overwritten unread —
    the flooder is held back (and times out) instead."""
    ring = 64
    want = [{"can_id": 0x123, "can_mask": 0x7FF, "extended": False}]
    with can.Bus(interface="canbrake", channel="fl3", ring_size=ring) as tx, \
            can.Bus(interface="canbrake", channel="fl3", can_filters=want, backpressure="accepted") as rx:
        for k in range(10 * ring):  # ten rings of frames it does not accept, nothing to wait for
            tx.send(frame(0x001, k.to_bytes(2, "little")))
        tx.send(frame(0x123, b"\x01"))
        sent = 0
        with pytest.raises(can.CanTimeoutError):
            for k in range(2 * ring):  # the flood reaches the unread 0x123: the flooder waits
                tx.send(frame(0x001, b"\x00"), timeout=0.05)
                sent += 1
        assert sent == ring - 1  # every slot but the one holding 0x123
        got = rx.recv(0)  # no BusOverrunError: nothing it accepts was lost
        assert got.arbitration_id == 0x123 and bytes(got.data) == b"\x01"
        assert rx.recv(0) is None
        tx.send(frame(0x001, b"\x00"), timeout=0.05)  # read: the flood goes on
        assert rx.stats().frames_lost == 0 and rx.stats().overruns == 0


@pytest.mark.slow
def test_a_rogue_flooding_the_bus_in_lockstep_neither_stalls_nor_changes_the_run(tmp_path, shm_dir):
    """A foreign process floods identifier 0x001 as fast as it can on the run's cross-process bus
    (a 256-frame ring, so it goes round many times while a node is busy): the lockstep run ends normally, its
    signals.csv equals the in-process run's, and the recorder names the flooding identifier."""
    import threading
    import uuid

    over = {"duration_s": 0.05}
    run_scenario(load_scenario(CASE1, overrides=over), tmp_path / "inprocess", backend="inprocess", plots=False)
    channel = f"cbflood-{uuid.uuid4().hex[:6]}"
    stop = threading.Event()
    sent = [0]
    nothing = [{"can_id": 0x7FF, "can_mask": 0x7FF, "extended": False}]
    rogue_bus = can.Bus(interface="canbrake", channel=channel, ring_size=256, can_filters=nothing)

    def flood() -> None:
        from canbrake.bus.memory import channel_pids

        burst = [frame(0x001, bytes(8)) for _ in range(32)]
        while not stop.is_set() and len(channel_pids(channel)) < 1 + 8:  # the plant, 6 ECUs, the recorder
            stop.wait(0.01)
        while not stop.is_set() and sent[0] < 160 * 256:
            try:
                rogue_bus.send_many(burst, timeout=0.2)
                sent[0] += len(burst)
            except can.CanTimeoutError:
                pass  # held back by a node that has not read yet

    t = threading.Thread(target=flood, daemon=True)
    t.start()
    try:
        s = run_scenario(load_scenario(CASE1, overrides=over), tmp_path / "memory", backend="memory",
                         channel=channel, plots=False, stall_timeout_s=20)
    finally:
        stop.set()
        t.join()
        rogue_bus.shutdown()
    assert s["status"] == "ok" and s["ticks"] == 50, s.get("message")
    assert sent[0] > 8 * 256  # the ring went round many times during the run
    assert s["safety"]["flood"]["frames_on_unknown_ids"]["0x001"] > 0
    assert s["safety"]["verdict"] == "attack or fault detected"
    assert (tmp_path / "memory" / "signals.csv").read_bytes() == (tmp_path / "inprocess" / "signals.csv").read_bytes()
