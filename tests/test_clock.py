"""ECU clock drift and timer jitter in the lockstep timing replica."""
from __future__ import annotations

import pytest

from canbrake.bus import dbc
from canbrake.bus.clock import ClockConfig, EcuClock
from canbrake.bus.schedule import LockstepBusTiming

US = 1e-6


def test_drift_offset_slides_and_wraps() -> None:
    # -2000 ppm: the timer runs slow, each 5 ms period the send instant slides 10 us later;
    # after 5 ms / 10 us = 500 periods it has slid a whole period and wraps to 0
    c = EcuClock(ClockConfig(car=1, ppm=-2000), 0.005)
    offs = [c.offset_s(k) for k in range(502)]
    assert offs[1] == pytest.approx(10 * US) and offs[60] == pytest.approx(600 * US)
    assert offs[499] == pytest.approx(4990 * US) and offs[500] == pytest.approx(0.0, abs=1e-12)
    fast = EcuClock(ClockConfig(car=1, ppm=+2000, phase_s=0.001), 0.005)
    assert [fast.offset_s(k) for k in (0, 1, 100)] == pytest.approx([1000 * US, 990 * US, 0.0], abs=1e-12)


def test_timer_jitter_is_bounded_and_seeded() -> None:
    ca, cb = (EcuClock(ClockConfig(car=1, jitter_s=50e-6), 0.001, seed=3) for _ in range(2))
    a = [ca.offset_s(k) for k in range(200)]
    b = [cb.offset_s(k) for k in range(200)]
    assert a == b and 0 <= min(a) and max(a) < 50e-6 and len(set(a)) == 200


def test_a_drifting_ecu_state_frame_slides_out_of_the_arbitration_window() -> None:
    """2 cars, 5 ms, 500 kbit/s: SYNC (95 bits, 0-190 us), REFERENCE (105 bits, 190-400 us) and
    STATE_C2 (135 bits = 270 us) at t_k; ecu1's STATE_C1 (0x141, beats 0x142) queued at
    t_k + 10 us x k. While its offset is at most 400 us it goes first after REFERENCE and ends at
    670 us; from 410 us on STATE_C2 has taken the bus at 400 us (no pre-emption) and STATE_C1
    ends at 670 + 270 = 940 us, until its offset passes 670 us and it starts at its offset."""
    t = LockstepBusTiming(2, 0.005, 500_000, decision_offset_s=0.0025, heartbeat_every=1000,
                          clocks={"ecu1": EcuClock(ClockConfig(car=1, ppm=-2000), 0.005)})
    lat = {k: t.latency_s(k, "ecu1", dbc.STATE_BASE + 1, k * 0.005) for k in (1, 10, 39, 40, 41, 60, 70, 499, 500)}
    assert [lat[k] for k in (1, 10, 39, 40)] == pytest.approx([670 * US] * 4)
    assert lat[41] == pytest.approx(940 * US) and lat[60] == pytest.approx(940 * US)
    assert lat[70] == pytest.approx(700 * US + 270 * US)
    assert lat[499] == pytest.approx(4990 * US + 270 * US)
    # wrapped: tick 499's state ends 260 us into tick 500 (no pre-emption), then SYNC 260-450,
    # REFERENCE 450-660 and tick 500's STATE_C1 660-930 us
    assert lat[500] == pytest.approx(930 * US)


def test_drift_makes_peer_data_late_in_a_run(tmp_path) -> None:
    """ecu3's state frames are used in the same tick only while their offset (sliding 10 us per
    1 ms tick at -10000 ppm) plus queueing stays under the deadline c·T = 0.5 ms; afterwards they
    are one tick old."""
    import csv

    from canbrake.run import run_scenario
    from canbrake.scenario import load_scenario

    from conftest import CASE1

    scn = load_scenario(CASE1, overrides={
        "duration_s": 0.1, "control_period_s": 0.005, "bus": {"timing": "model", "bitrate_bps": 500_000},
        "ecu": {"clocks": [{"car": 3, "ppm": -100_000}]}})
    s = run_scenario(scn, tmp_path, backend="inprocess", plots=False)
    assert s["status"] == "ok"
    with open(tmp_path / "ecu_c1.csv") as f:
        ages = [float(r["max_peer_age_s"]) for r in csv.DictReader(f)]
    # -100000 ppm at 5 ms: ecu3's offset grows 0.5 ms per tick and wraps every 10 ticks; its state
    # is late (offset + queueing > 2.5 ms) in about half of the ticks
    late = sum(1 for a in ages[1:] if a > 0)
    assert 0.3 * len(ages) < late < 0.7 * len(ages)
    assert max(ages) == pytest.approx(0.005)


def _realtime_ecu_and_tick0(clocks: list[dict]):
    """A realtime ECU of car 3 with ``ecu.clocks`` and the plant's frames of tick 0."""
    from canbrake.build import build_node
    from canbrake.scenario import load_scenario

    path = "scenarios/chen2023_case1_fine_rail.yaml"
    rt = load_scenario(path, profile="realistic", overrides={"mode": "realtime", "ecu.clocks": clocks})
    plant = build_node(load_scenario(path, profile="realistic"), "plant", run_dir=None)
    ecu = build_node(rt, "ecu", car=3, run_dir=None)
    ecu.start(0.0)
    return ecu, plant.start(0.0)


def test_realtime_ecu_timer_drifts_and_jitters() -> None:
    """Realtime: car 3's timer is 4 ms (phase) + 2000 ppm slow: its state frame of tick k leaves
    at sensor time + (phase + k·T·2e-3) mod T + jitter, on the ECU's timer (next_deadline), not
    when the sensor frame arrives; jitter stays within jitter_s."""
    ecu, frames = _realtime_ecu_and_tick0([{"car": 3, "ppm": -2000, "phase_s": 0.004}])
    t0 = 100.0
    assert [m for f in frames for m in ecu.handle(f, t0)] == []  # the sensors are in, the timer has not fired
    assert ecu.next_deadline() == pytest.approx(t0 + 0.004)
    assert ecu.on_timer(t0 + 0.0039) == []
    sent = ecu.on_timer(t0 + 0.004)
    assert {m.arbitration_id for m in sent} >= {dbc.STATE_BASE + 3}
    jit, _ = _realtime_ecu_and_tick0([{"car": 3, "jitter_s": 0.001}])
    for f in _:
        jit.handle(f, t0)
    assert t0 <= jit.next_deadline() < t0 + 0.001


def test_realtime_timer_past_the_next_sync_is_a_sample_slip() -> None:
    ecu, frames = _realtime_ecu_and_tick0([{"car": 3, "phase_s": 0.0099}])
    for f in frames:
        ecu.handle(f, 0.0)
    nxt = frames[0].__class__(arbitration_id=frames[0].arbitration_id, is_extended_id=False,
                              data=(1).to_bytes(4, "little"))
    ecu.handle(nxt, 0.0098)  # tick 1's SYNC before the timer of tick 0 fired
    assert ecu.stats.timer_slips == 1 and ecu.next_deadline() is None and ecu.k == 1


def test_realtime_accepts_clocks_lockstep_still_needs_the_timing_model() -> None:
    from canbrake.bus.schedule import check_faults
    from canbrake.scenario import ScenarioError, load_scenario

    path = "scenarios/chen2023_case1_fine_rail.yaml"
    from canbrake.build import bus_layout

    scn = load_scenario(path, overrides={"mode": "realtime", "ecu.clocks": [{"car": 2, "ppm": 50}]})
    check_faults(scn, bus_layout(scn))
    scn = load_scenario(path, overrides={"ecu.clocks": [{"car": 2, "ppm": 50}]})
    with pytest.raises(ScenarioError, match="bus.timing: model"):
        check_faults(scn, bus_layout(scn))
