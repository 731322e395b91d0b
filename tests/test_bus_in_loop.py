"""Impairments and the CAN timing model inside lockstep runs (issue 5 items 1-3)."""
from __future__ import annotations

import csv

import pytest

from canbrake.bus import dbc
from canbrake.bus.schedule import LockstepBusTiming
from canbrake.bus.timing import frame_bits
from canbrake.run import run_scenario
from canbrake.scenario import load_scenario

from conftest import CASE1


def _scn(**over):
    base = {"duration_s": 0.05}
    base.update(over)
    return load_scenario(CASE1, overrides=base)


def _ecu_trace(run_dir, car):
    with open(run_dir / f"ecu_c{car}.csv") as f:
        return list(csv.DictReader(f))


def test_replicated_timing_matches_hand_calculation():
    """5 ms period, 500 kbit/s, worst-case stuffing: SYNC (95 bits), REFERENCE (105) and six
    8-byte STATE frames (135 each) queued at t_k go out in identifier order."""
    bits = [frame_bits(dbc.SYNC_ID, False, 4), frame_bits(dbc.REFERENCE_ID, False, 5)]
    assert bits == [95, 105] and frame_bits(0x141, False, 8) == 135
    t = LockstepBusTiming(6, 0.005, 500_000, decision_offset_s=0.0025, heartbeat_every=20)
    for c in range(1, 7):
        expect = (95 + 105 + 135 * c) / 500_000
        assert t.latency_s(0, f"ecu{c}", dbc.STATE_BASE + c, 0.0) == pytest.approx(expect, abs=1e-12)
    # tick 0 also carries six 1-byte heartbeats (65 bits) after the states; the command queued at
    # the decision instant (2.5 ms = bit 1250) waits for the heartbeat on the wire (bits 1205-1270):
    # no pre-emption; it ends at bit 1270 + 105 = 1375
    assert frame_bits(dbc.HEARTBEAT_BASE + 1, False, 1) == 65
    assert t.latency_s(0, "ecu1", dbc.BRAKE_CMD_BASE + 1, 0.0025) == pytest.approx((1375 - 1250) / 500_000, abs=1e-12)
    # tick 1 has no heartbeats: the bus is idle at the decision instant
    assert t.latency_s(1, "ecu1", dbc.BRAKE_CMD_BASE + 1, 0.0075) == pytest.approx(105 / 500_000, abs=1e-12)


def test_a_delay_makes_peer_data_exactly_that_many_ticks_old(tmp_path):
    scn = _scn(bus={"impairments": [{"type": "delay", "delay_s": 0.002, "senders": ["ecu3"],
                                      "ids": [dbc.STATE_BASE + 3]}]})
    run_scenario(scn, tmp_path, backend="inprocess", plots=False)
    rows = _ecu_trace(tmp_path, 1)
    ages = [float(r["max_peer_age_s"]) for r in rows[5:]]
    assert max(ages) == pytest.approx(0.002) and min(ages) == pytest.approx(0.002)
    # car 3 itself is never stale
    assert all(float(r["max_peer_age_s"]) <= 0.002 + 1e-12 for r in _ecu_trace(tmp_path, 3))


def test_lost_and_corrupted_frames_are_never_used(tmp_path):
    scn = _scn(bus={"impairments": [
        {"type": "loss", "probability": 1.0, "ids": [dbc.STATE_BASE + 2]},
        {"type": "corrupt", "probability": 1.0, "n_bits": 1, "ids": [dbc.STATE_BASE + 4]}]})
    s = run_scenario(scn, tmp_path, backend="inprocess", plots=False)
    assert s["status"] == "ok"
    f = s["frames"]
    assert f["by_kind"].get("state", 0) == 5 * s["ticks"]  # car 2's never reach the bus
    assert f["peer_frames_corrupted"] == 5 * s["ticks"]     # car 4's fail the CRC at 5 receivers
    # receivers never had a value from car 2 or car 4: 2 peers x 5 receivers x ticks (+ car 2/4 missing one each)
    assert f["peer_values_missing"] == 2 * 5 * s["ticks"]


def test_lost_commands_are_held_and_counted(tmp_path):
    scn = _scn(bus={"impairments": [{"type": "loss", "probability": 0.5, "ids": [dbc.BRAKE_CMD_BASE + 1]}]})
    s = run_scenario(scn, tmp_path, backend="inprocess", plots=False)
    missed = s["frames"]["commands_missed"]
    assert 0.3 * s["ticks"] < missed < 0.7 * s["ticks"]
    assert s["frames"]["commands_received"] == 6 * s["ticks"] - missed


def test_timing_model_runs_are_deterministic_across_backends(tmp_path):
    scn = _scn(control_period_s=0.005, duration_s=0.2,
               bus={"timing": "model", "bitrate_bps": 500_000,
                    "impairments": [{"type": "jitter", "distribution": "uniform", "low_s": 0.0, "high_s": 0.004},
                                    {"type": "loss", "probability": 0.1}]})
    a = run_scenario(scn, tmp_path / "a", backend="inprocess", plots=False)
    run_scenario(scn, tmp_path / "b", backend="virtual", plots=False)
    assert a["status"] == "ok"
    assert (tmp_path / "a" / "frames.log").read_bytes() == (tmp_path / "b" / "frames.log").read_bytes()
    assert (tmp_path / "a" / "signals.csv").read_bytes() == (tmp_path / "b" / "signals.csv").read_bytes()
    other = run_scenario(scn.model_copy(update={"seed": 2}), tmp_path / "c", backend="inprocess", plots=False)
    assert (tmp_path / "c" / "frames.log").read_bytes() != (tmp_path / "a" / "frames.log").read_bytes()
    assert other["status"] == "ok"


def test_a_frame_still_queued_when_the_run_ends_is_starved_without_looking_past_the_end():
    """13x overloaded (6 cars at 1 ms on 125 kbit/s): the lowest-priority frame (a heartbeat)
    never gets on the bus. With the run's length as horizon the model answers 'starved' after
    simulating the run's ticks only; without, it looks max_wait_ticks periods ahead. Frames that
    do get through have the same latency either way."""
    import math

    def model(horizon):
        t = LockstepBusTiming(6, 0.001, 125_000, decision_offset_s=0.0005, heartbeat_every=1, max_wait_ticks=300)
        t.horizon_ticks = horizon
        return t

    bounded, free = model(30), model(None)
    hb6 = dbc.HEARTBEAT_BASE + 6
    assert bounded.latency_s(0, "ecu6", hb6, 0.0) == math.inf
    assert bounded._next_tick == 30             # simulated up to the run's end, not beyond
    assert free.latency_s(0, "ecu6", hb6, 0.0) == math.inf
    assert free._next_tick == 301               # max_wait_ticks periods of look-ahead
    for k, node, fid in ((0, "plant", dbc.SYNC_ID), (2, "plant", dbc.SYNC_ID), (0, "plant", dbc.REFERENCE_ID)):
        t_q = k * 0.001 + (0.0005 if node == "ecu1" else 0.0)
        assert model(30).latency_s(k, node, fid, t_q) == model(None).latency_s(k, node, fid, t_q) < 0.03


def test_overloaded_bus_delays_and_starves_frames(tmp_path):
    """Chen's 6 cars every 1 ms do not fit even 1 Mbit/s: the model must show it."""
    scn = _scn(duration_s=0.1, bus={"timing": "model", "bitrate_bps": 1_000_000})
    s = run_scenario(scn, tmp_path, backend="inprocess", plots=False)
    lat = s["bus_latency_in_loop"]
    assert lat["state"]["late_frames"] + lat["state"]["starved"] > 0
    assert s["frames"]["peer_values_missing"] > 0
    fits = _scn(duration_s=0.1, control_period_s=0.005, bus={"timing": "model", "bitrate_bps": 500_000})
    s2 = run_scenario(fits, tmp_path / "fits", backend="inprocess", plots=False)
    l2 = s2["bus_latency_in_loop"]
    assert l2["state"]["late_frames"] == 0 and l2["state"]["starved"] == 0
    assert s2["frames"]["peer_values_missing"] == 0
    assert l2["state"]["max_s"] == pytest.approx((95 + 105 + 6 * 135) / 500_000)


def test_per_link_impairment_hits_only_that_receiver(tmp_path):
    """A link ecu3 -> ecu1 that loses everything: ecu1 never has car 3's state, ecu2 always does."""
    scn = _scn(bus={"impairments": [{"type": "loss", "probability": 1.0, "senders": ["ecu3"],
                                      "receivers": ["ecu1"]}]})
    s = run_scenario(scn, tmp_path, backend="inprocess", plots=False)
    assert s["status"] == "ok"
    assert s["frames"]["by_kind"]["state"] == 6 * s["ticks"]  # on the bus: nothing lost at the sender
    e1 = _ecu_trace(tmp_path, 1)
    e2 = _ecu_trace(tmp_path, 2)
    assert all(int(r["peers_fresh"]) == 5 for r in e1)
    assert all(int(r["peers_fresh"]) == 6 for r in e2)


def test_per_link_delay_is_taken_ticks_later(tmp_path):
    scn = _scn(bus={"impairments": [{"type": "delay", "delay_s": 0.003, "senders": ["ecu2"],
                                      "receivers": ["ecu5"]}]})
    run_scenario(scn, tmp_path, backend="inprocess", plots=False)
    ages = [float(r["max_peer_age_s"]) for r in _ecu_trace(tmp_path, 5)[5:]]
    assert min(ages) == pytest.approx(0.003) and max(ages) == pytest.approx(0.003)
    assert all(float(r["max_peer_age_s"]) == 0 for r in _ecu_trace(tmp_path, 4))
