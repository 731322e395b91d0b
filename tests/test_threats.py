"""The EN 50159 threat matrix (canbrake.threats): each threat, without and with authentication,
must be detected (counted by reason) and met with the safe reaction: frames dropped and braking
unchanged, or car 3's brake unit in fail-safe exactly one time-out after its last valid command.
Threats the defences of a setting cannot see are asserted as such (they are in docs/safety.md)."""
from __future__ import annotations

from pathlib import Path

import pytest

from canbrake.bus.secoc import write_key
from canbrake.threats import ATTACK_S, DURATION_S, THREATS, TIMEOUT_S, expected_failsafe_s, run_threat
from conftest import CASE1

DT = 0.001
N_TICKS = round(DURATION_S / DT)


@pytest.fixture(scope="module")
def work(tmp_path_factory) -> tuple[Path, Path]:
    d = tmp_path_factory.mktemp("threats")
    return d, write_key(d / "key.hex")


@pytest.mark.slow
@pytest.mark.parametrize("secured", [False, True], ids=["e2e", "secoc"])
@pytest.mark.parametrize("threat", THREATS, ids=[t.key for t in THREATS])
def test_threat_is_detected_and_met_safely(threat, secured, work):
    d, key = work
    o = run_threat(threat, CASE1, d, key if secured else None)
    exp = threat.expect[secured]
    assert o.status == "ok" and o.ticks == N_TICKS  # nothing stops or stalls the run
    for reason in exp.reasons:
        assert o.rejected.get(reason, 0) > 0, (reason, o.rejected)
    if exp.failsafe:
        assert o.failsafe_first_s == expected_failsafe_s(DT)
        assert o.reaction_s <= TIMEOUT_S + DT
        assert o.verdict == "detected, fail-safe engaged"
    else:
        assert o.failsafe_first_s is None
    assert o.unchanged == exp.unchanged
    if exp.unchanged:  # dropped, counted, and braking as if clean
        assert o.ticks_changed == 0 and o.verdict == "attack or fault detected"
    if exp.undetected:
        assert o.ticks_changed > 0 and o.failsafe_first_s is None


def test_replay_counts_follow_from_the_15_period_alias(work):
    """Each command repeated 14.9 periods later lands in the period 15 after its own, where its
    counter equals the genuine one: without SecOC it wins (the genuine command is then rejected as
    a repetition) from tick ATTACK + 15 to the end; with SecOC each copy fails as stale."""
    d, key = work
    replay = next(t for t in THREATS if t.key == "replay_15")
    n = N_TICKS - round(ATTACK_S / DT) - 15
    plain = run_threat(replay, CASE1, d, None)
    assert plain.rejected == {"counter": n}
    secured = run_threat(replay, CASE1, d, key)
    assert secured.rejected == {"freshness": n} and secured.unchanged


def test_replayed_state_frames_are_counted_by_what_caught_them(work):
    """Secured: every replayed authenticator (tick 10) is stale; each replayed STATE_C3 is dropped
    by its counter, or, in the periods where its counter aliases to the current tick (k = 10 mod
    15), for want of an authenticator that verifies it — at each of car 3's five listeners."""
    d, key = work
    o = run_threat(next(t for t in THREATS if t.key == "state_replay"), CASE1, d, key)
    aliased = sum(1 for k in range(round(ATTACK_S / DT), N_TICKS) if k % 15 == 10)
    assert o.rejected["authentication"] == 5 * aliased
    assert o.rejected["freshness"] == o.rejected["counter"] + o.rejected["authentication"]
    assert o.unchanged
