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
