"""Worst-case response-time analysis (Davis, Burns, Bril, Lukkien 2007) against hand-worked
examples and against the discrete-event timing model."""
from __future__ import annotations

import json
import math
import subprocess
import sys

import pytest
from hypothesis import HealthCheck, assume, given, settings
from hypothesis import strategies as st

from canbrake.bus.rta import CanMessage, analyze
from canbrake.bus.timing import BusTimingModel, frame_bits

from conftest import ROOT, SCENARIOS

MS = 1e-3
US = 1e-6


# --------------------------------------------------------------------------------------------
# a three-message example of the kind Davis et al. 2007 use in section 3 to show that the
# original analysis is optimistic (parameters ours, worked by hand below)
#
# 125 kbit/s (tau_bit = 8 us); three 7-byte standard frames: worst case 34 + 56 = 90 stuffable
# bits + 13 + (90 - 1)//4 = 22 stuff bits = 125 bits = 1 ms each. Priority A > B > C.
#   A: T = 2.5 ms          B: T = 3.5 ms          C: T = 3.5 ms
#
# Original analysis for C (q = 0 only): B_C = 0 (nothing below C);
#   w = ceil((w + tau)/2.5)·1 + ceil((w + tau)/3.5)·1, from w = 0: 2 -> 2 (1 + 1): w = 2 ms,
#   R_C = w + C = 3 ms.
# Revised analysis: busy period t = sum over A, B, C of ceil(t/T)·C:
#   t = 1 -> 3 -> 2+1+1 = 4 -> 2+2+2 = 6 -> 3+2+2 = 7 -> 3+2+2 = 7 ms; Q = ceil(7/3.5) = 2.
#   q = 1: w = 1·C + ceil((w+tau)/2.5) + ceil((w+tau)/3.5): 1 -> 3 -> 1+2+1 = 4 -> 1+2+2 = 5
#          -> 1+3+2 = 6 -> 6 ms;  R_C(1) = w - q·T + C = 6 - 3.5 + 1 = 3.5 ms.
# With a deadline of 3.25 ms for B and C, the original analysis accepts C, the revised one
# rejects it — and the simulated bus (below) shows the second instance of C taking 3.5 ms.
# B: B_B = C_C = 1 ms; busy period 1 -> 1+1+1+1 = 4 -> 1+2+2 = 5 -> 1+2+2 = 5: Q = 2;
#   q = 0: w = 1 + ceil((w+tau)/2.5): 1 -> 2 -> 2; R = 3 ms.  q = 1: w = 1 + 1 + ceil(..): 2 -> 3
#   -> 4 -> 4; R = 4 - 3.5 + 1 = 1.5 ms. R_B = 3 ms.
# A: B_A = 1 ms, R_A = 1 + 1 = 2 ms.


def _paper_set() -> list[CanMessage]:
    return [CanMessage("A", 0x1, 7, 2.5 * MS, sender="a"),
            CanMessage("B", 0x2, 7, 3.5 * MS, deadline_s=3.25 * MS, sender="b"),
            CanMessage("C", 0x3, 7, 3.5 * MS, deadline_s=3.25 * MS, sender="c")]


def test_paper_example_frame_is_one_millisecond() -> None:
    assert frame_bits(0x3, False, 7) == 125  # 125 bits at 125 kbit/s = 1 ms


def test_paper_example_revised_analysis_by_hand() -> None:
    a = analyze(_paper_set(), 125_000)
    r = a.by_name()
    assert [x.message.name for x in a.results] == ["A", "B", "C"]
    assert r["A"].response_s == pytest.approx(2 * MS) and r["A"].blocking_s == pytest.approx(1 * MS)
    assert r["B"].response_s == pytest.approx(3 * MS) and r["B"].busy_period_s == pytest.approx(5 * MS)
    assert r["B"].instances == 2
    c = r["C"]
    assert c.blocking_s == 0.0
    assert c.busy_period_s == pytest.approx(7 * MS) and c.instances == 2
    assert c.worst_instance == 1 and c.response_s == pytest.approx(3.5 * MS)
    assert c.tindell_s == pytest.approx(3 * MS)
    assert not c.schedulable and not a.schedulable
    assert a.utilisation == pytest.approx(1 / 2.5 + 2 / 3.5)


def test_original_analysis_is_optimistic_on_the_paper_example() -> None:
    old = analyze(_paper_set(), 125_000, method="tindell1994")
    assert old.by_name()["C"].response_s == pytest.approx(3 * MS)
    assert old.schedulable  # ... which the bus contradicts:


def test_the_bus_reaches_the_revised_bound_and_exceeds_the_original_one() -> None:
    """All three queued at t = 0 (the critical instant), periodically afterwards."""
    m = BusTimingModel(125_000)
    msgs = _paper_set()
    for msg in msgs:
        k = 0
        while k * msg.period_s < 20 * MS:
            m.submit(msg.sender, msg.arbitration_id, False, 7, None, k * msg.period_s, tag=(msg.name, k))
            k += 1
    done = m.advance(1.0)
    lat = {d.tag: d.latency_s for d in done}
    # A 0-1, B 1-2, C 2-3; A 3-4 (released 2.5); B 4-5; A 5-6 (released 5.0); C#1 6-7:
    assert lat[("C", 1)] == pytest.approx(3.5 * MS)
    worst_c = max(v for (name, _k), v in lat.items() if name == "C")
    bound = analyze(msgs, 125_000).by_name()
    assert worst_c == pytest.approx(bound["C"].response_s)
    assert worst_c > bound["C"].tindell_s
    for name in "AB":
        assert max(v for (n, _k), v in lat.items() if n == name) <= bound[name].response_s + 1e-12


# --------------------------------------------------------------------------------------------
# more hand checks


def test_overloaded_priority_level_has_no_bound() -> None:
    # two 8-byte frames (135 bits = 270 us at 500k) every 500 us: U = 1.08
    a = analyze([CanMessage("x", 1, 8, 500 * US), CanMessage("y", 2, 8, 500 * US)], 500_000)
    x, y = a.results
    assert x.response_s == pytest.approx(540 * US)  # blocked by y, then itself
    assert math.isinf(y.response_s) and not y.schedulable and y.instances == 0
    assert a.utilisation == pytest.approx(1.08)
    assert a.as_dict()["messages"][1]["response_s"] is None


def test_duplicate_identifiers_and_bad_messages_are_refused() -> None:
    with pytest.raises(ValueError, match="share identifier 0x10"):
        analyze([CanMessage("a", 0x10, 1, 1e-3), CanMessage("b", 0x10, 2, 1e-3)], 500_000)
    with pytest.raises(ValueError, match="period_s"):
        CanMessage("a", 0x10, 1, 0.0)
    with pytest.raises(ValueError, match="out of range"):
        CanMessage("a", 0x800, 1, 1e-3)


def test_fifo_node_bound_covers_head_of_line_blocking() -> None:
    """Node n has a FIFO: its high-priority 0x010 may wait behind its own 0x300."""
    msgs = [CanMessage("hi", 0x010, 8, 10 * MS, sender="n"), CanMessage("mid", 0x200, 8, 10 * MS, sender="m"),
            CanMessage("lo", 0x300, 8, 10 * MS, sender="n")]
    prio = analyze(msgs, 500_000).by_name()
    fifo = analyze(msgs, 500_000, fifo_nodes=["n"]).by_name()
    c = 270 * US
    assert prio["hi"].response_s == pytest.approx(2 * c)  # blocked by one frame, then itself
    assert fifo["hi"].response_s == pytest.approx(3 * c)  # behind lo in the FIFO, and mid wins against lo
    sim = BusTimingModel(500_000, queue_policy="fifo")
    sim.submit("n", 0x300, False, 8, None, 0.0)
    sim.submit("n", 0x010, False, 8, None, 1 * US)
    sim.submit("m", 0x200, False, 8, None, 0.0)
    lat = {d.arbitration_id: d.t_end_s for d in sim.advance(1.0)}
    assert lat[0x010] - 1 * US <= fifo["hi"].response_s
    assert lat[0x010] - 1 * US > prio["hi"].response_s  # the priority bound would be wrong here


def test_scenario_message_set_by_hand() -> None:
    """Chen case 1, realistic profile: 10 ms period at 1 Mbit/s; worst-case frame lengths
    SYNC 95, REFERENCE and commands 105, STATE 135, heartbeats 65 bits (1 us each)."""
    from canbrake.bus.schedule import message_set
    from canbrake.scenario import load_scenario

    scn = load_scenario(SCENARIOS / "chen2023_case1_fine_rail.yaml", profile="realistic")
    assert scn.bus.bitrate_bps == 1_000_000 and scn.control_period_s == pytest.approx(0.01)
    from canbrake.build import bus_layout

    a = analyze(message_set(scn, bus_layout(scn)), scn.bus.bitrate_bps)
    r = a.by_name()
    assert len(a.results) == 2 + 1 + 6 * 3
    # everything fits in one period, so R = blocking by the longest lower frame + all above + itself
    assert r["SYNC"].response_s == pytest.approx((135 + 95) * US)
    assert r["STATE_C6"].response_s == pytest.approx((65 + 95 + 105 + 6 * 105 + 6 * 135) * US)
    total = 95 + 105 + 6 * 105 + 6 * 135 + 7 * 65
    assert r["HEARTBEAT_C6"].response_s == pytest.approx(total * US)  # lowest: no blocking
    assert r["HEARTBEAT_C6"].message.period_s == pytest.approx(scn.ecu.heartbeat_period_s)
    assert a.utilisation == pytest.approx((95 + 105 + 6 * 105 + 6 * 135) / 10_000 + 7 * 65 / 100_000)
    assert a.schedulable


# --------------------------------------------------------------------------------------------
# property: a schedulable set's bound holds for every frame the timing model simulates


@st.composite
def _message_sets(draw):
    n = draw(st.integers(2, 6))
    ids = draw(st.lists(st.integers(0, 0x7FF), min_size=n, max_size=n, unique=True))
    msgs, phases = [], []
    for i, ident in enumerate(ids):
        period = draw(st.integers(2, 40)) * 0.5 * MS
        jitter = draw(st.sampled_from([0.0, 0.0, 0.1, 0.25])) * period
        msgs.append(CanMessage(f"m{i}", ident, draw(st.integers(0, 8)), period, jitter_s=jitter,
                               sender=f"n{draw(st.integers(0, 2))}"))
        phases.append(draw(st.sampled_from([0.0, draw(st.floats(0, 1, exclude_max=True))])) * period)
    seed = draw(st.integers(0, 2**31))
    return msgs, phases, seed


@settings(max_examples=80, deadline=None, suppress_health_check=[HealthCheck.filter_too_much])
@given(_message_sets())
def test_no_simulated_latency_exceeds_the_bound(case) -> None:
    import random

    msgs, phases, seed = case
    a = analyze(msgs, 500_000)
    assume(a.schedulable)
    bound = {r.message.name: r.response_s for r in a.results}
    rng = random.Random(seed)
    model = BusTimingModel(500_000)
    horizon = 30 * max(m.period_s for m in msgs)
    for m, phase in zip(msgs, phases):
        k = 0
        while phase + k * m.period_s < horizon:
            arrival = phase + k * m.period_s
            release = arrival + (m.jitter_s * rng.choice([0.0, 1.0, rng.random()]))
            model.submit(m.sender, m.arbitration_id, False, m.dlc, None, release, tag=(m.name, arrival))
            k += 1
    for d in model.advance(horizon + 1.0):
        name, arrival = d.tag
        assert d.t_end_s - arrival <= bound[name] + 1e-9, (name, d.t_end_s - arrival, bound[name])


# --------------------------------------------------------------------------------------------
# command line


@pytest.mark.parametrize("scenario", sorted(p.name for p in SCENARIOS.glob("*.yaml")))
def test_cli_analyze_every_scenario(scenario: str, tmp_path, capsys) -> None:
    from canbrake.cli import main

    out = tmp_path / "a.json"
    capsys.readouterr()
    assert main(["analyze", str(SCENARIOS / scenario), "--json", str(out), "--ticks", "200"]) == 0
    data = json.loads(out.read_text())
    printed = capsys.readouterr().out  # the table: a header and one row per message (per segment)
    assert " R1994 " in printed and all(f" {m['id_hex']:>6s} " in printed for m in data["messages"])
    assert "schedulable" in printed.lower()
    assert data["messages"] and {"response_s", "schedulable", "simulated"} <= set(data["messages"][0])
    for m in data["messages"]:  # the simulated latencies never exceed a finite bound
        s = m.get("simulated")
        if m["response_s"] is not None and s and s["max_s"] is not None:
            assert s["max_s"] <= m["response_s"] + 1e-9


def test_cli_analyze_prints_table_and_refuses_bad_input(tmp_path) -> None:
    ok = subprocess.run([sys.executable, "-m", "canbrake", "analyze", str(SCENARIOS / "chen2023_case1_fine_rail.yaml"),
                         "--profile", "realistic", "--ticks", "100"], capture_output=True, text=True, cwd=ROOT)
    assert ok.returncode == 0, ok.stderr
    assert "STATE_C6" in ok.stdout and "schedulable" in ok.stdout and "sim p99" in ok.stdout
    bad = subprocess.run([sys.executable, "-m", "canbrake", "analyze", str(tmp_path / "missing.yaml")],
                         capture_output=True, text=True, cwd=ROOT)
    assert bad.returncode == 2 and "Traceback" not in bad.stderr and "missing.yaml" in bad.stderr
