"""Transmit buffer policies: priority inversion by FIFOs and non-abortable mailboxes, in the
timing model and in the response-time analysis."""
from __future__ import annotations

import random

import pytest
from hypothesis import HealthCheck, assume, given, settings
from hypothesis import strategies as st

from canbrake.bus.faults import FaultConfinement, FaultyTransceiver
from canbrake.bus.rta import CanMessage, analyze
from canbrake.bus.timing import BusTimingModel
from canbrake.bus.txbuffer import TxBufferConfig, inverting_nodes

US = 1e-6
C8 = 270 * US  # 8-byte frame, worst-case stuffing, at 500 kbit/s


def _order(cfg: TxBufferConfig | None, extra: list[tuple[str, int, float]] = ()) -> list[int]:
    m = BusTimingModel(500_000, tx_buffers=[cfg] if cfg else None)
    m.submit("blocker", 0x001, False, 8, None, 0.0)  # keeps the bus busy while the rest is queued
    for node, ident, t in [("n", 0x300, 1 * US), ("n", 0x301, 2 * US), ("n", 0x010, 3 * US),
                           ("m", 0x200, 4 * US), *extra]:
        m.submit(node, ident, False, 8, None, t)
    return [d.arbitration_id for d in m.advance(1.0)][1:]


def test_fifo_causes_priority_inversion() -> None:
    # priority buffer: n offers its 0x010 first; with a FIFO its 0x300 and 0x301 are ahead of it,
    # so m's 0x200 (lower priority than 0x010) goes first and 0x010 comes last
    assert _order(TxBufferConfig(nodes=["n"], policy="priority")) == [0x010, 0x200, 0x300, 0x301]
    assert _order(TxBufferConfig(nodes=["n"], policy="fifo")) == [0x200, 0x300, 0x301, 0x010]
    assert _order(None) == [0x010, 0x200, 0x300, 0x301]  # default: priority


def test_mailboxes_with_and_without_abort() -> None:
    # two mailboxes hold 0x300 and 0x301; 0x010 waits in the software queue ...
    no_abort = TxBufferConfig(nodes=["n"], policy="mailboxes", mailboxes=2)
    assert _order(no_abort) == [0x200, 0x300, 0x010, 0x301]  # ... until 0x300 frees a mailbox
    # with abort, 0x301 is aborted for 0x010, which then wins at once
    abort = TxBufferConfig(nodes=["n"], policy="mailboxes", mailboxes=2, abort=True)
    assert _order(abort) == [0x010, 0x200, 0x300, 0x301]
    # three mailboxes hold all of n's frames: no inversion
    assert _order(TxBufferConfig(nodes=["n"], policy="mailboxes", mailboxes=3)) == [0x010, 0x200, 0x300, 0x301]


def test_fifo_depth_overflow_drops_the_new_frame() -> None:
    m = BusTimingModel(500_000, tx_buffers=[TxBufferConfig(nodes=["n"], policy="fifo", depth=2)])
    m.submit("blocker", 0x001, False, 8, None, 0.0)
    for i, ident in enumerate((0x300, 0x301, 0x302)):
        m.submit("n", ident, False, 8, None, (i + 1) * US)
    assert [d.arbitration_id for d in m.advance(1.0)] == [0x001, 0x300, 0x301]
    (lost,) = m.pop_dropped()
    assert lost.arbitration_id == 0x302 and lost.dropped
    assert m.buffer_counters() == {"n": {"overflow": 1, "aborted": 0}}


def test_retransmission_keeps_the_frame_in_its_mailbox() -> None:
    fc = FaultConfinement(faulty=[FaultyTransceiver("n", 1.0, stop_s=100 * US)], seed=1)
    m = BusTimingModel(500_000, faults=fc, tx_buffers=[TxBufferConfig(nodes=["n"], policy="mailboxes", mailboxes=1)])
    m.submit("n", 0x300, False, 8, None, 0.0)
    m.submit("n", 0x010, False, 8, None, 0.0)
    out = m.advance(1.0)
    assert fc.events and {e.arbitration_id for e in fc.events} == {0x300}
    assert [d.arbitration_id for d in out] == [0x300, 0x010]


def test_analysis_of_a_fifo_node_bounds_the_inversion() -> None:
    msgs = [CanMessage("n_lo", 0x300, 8, 5e-3, sender="n"), CanMessage("n_lo2", 0x301, 8, 5e-3, sender="n"),
            CanMessage("n_hi", 0x010, 8, 5e-3, sender="n"), CanMessage("m", 0x200, 8, 5e-3, sender="m"),
            CanMessage("blocker", 0x001, 8, 5e-3, sender="blocker")]
    cfg = [TxBufferConfig(nodes=["n"], policy="fifo")]
    fifo = inverting_nodes(cfg, {"n": 3, "m": 1, "blocker": 1})
    assert fifo == ["n"]
    r = analyze(msgs, 500_000, fifo_nodes=fifo).by_name()
    # n_hi at n's lowest level (0x301): everything else on the bus can go before it: 4 frames + itself
    assert r["n_hi"].response_s == pytest.approx(5 * C8)
    assert analyze(msgs, 500_000).by_name()["n_hi"].response_s == pytest.approx(3 * C8)  # blocker, itself + 1 blocking
    # the simulated inversion (test_fifo_causes_priority_inversion): 0x010 queued at 3 us ends last
    m = BusTimingModel(500_000, tx_buffers=cfg)
    m.submit("blocker", 0x001, False, 8, None, 0.0)
    for node, ident, t in [("n", 0x300, 1 * US), ("n", 0x301, 2 * US), ("n", 0x010, 3 * US), ("m", 0x200, 4 * US)]:
        m.submit(node, ident, False, 8, None, t)
    lat = {d.arbitration_id: d.latency_s for d in m.advance(1.0)}
    assert 3 * C8 < lat[0x010] <= r["n_hi"].response_s


_POLICIES = [TxBufferConfig(policy="priority"), TxBufferConfig(policy="fifo"),
             TxBufferConfig(policy="mailboxes", mailboxes=1), TxBufferConfig(policy="mailboxes", mailboxes=2),
             TxBufferConfig(policy="mailboxes", mailboxes=2, abort=True)]


@settings(max_examples=60, deadline=None, suppress_health_check=[HealthCheck.filter_too_much])
@given(n=st.integers(2, 6), data=st.data())
def test_no_simulated_latency_exceeds_the_bound_whatever_the_buffers(n: int, data) -> None:
    ids = data.draw(st.lists(st.integers(0, 0x7FF), min_size=n, max_size=n, unique=True))
    msgs = [CanMessage(f"m{i}", ident, data.draw(st.integers(0, 8)), data.draw(st.integers(2, 30)) * 0.5e-3,
                       sender=f"n{data.draw(st.integers(0, 2))}") for i, ident in enumerate(ids)]
    cfgs = [TxBufferConfig(nodes=[f"n{j}"], **data.draw(st.sampled_from(_POLICIES)).model_dump(exclude={"nodes"}))
            for j in range(3)]
    per_node: dict[str, int] = {}
    for m in msgs:
        per_node[m.sender] = per_node.get(m.sender, 0) + 1
    a = analyze(msgs, 500_000, fifo_nodes=inverting_nodes(cfgs, per_node))
    assume(a.schedulable)
    bound = {r.message.name: r.response_s for r in a.results}
    phases = [data.draw(st.sampled_from([0.0, 0.3, 0.77])) * m.period_s for m in msgs]
    model = BusTimingModel(500_000, tx_buffers=cfgs)
    horizon = 30 * max(m.period_s for m in msgs)
    events = sorted((ph + k * m.period_s, i) for i, (m, ph) in enumerate(zip(msgs, phases))
                    for k in range(int((horizon - ph) / m.period_s) + 1))
    for t, i in events:  # submission in time order, as nodes do
        m = msgs[i]
        model.submit(m.sender, m.arbitration_id, False, m.dlc, None, t, tag=(m.name, t))
    for d in model.advance(horizon + 1.0):
        assert d.latency_s <= bound[d.tag[0]] + 1e-9, (d.tag, d.latency_s, bound[d.tag[0]])
    assert not model.pop_dropped()


def test_fifo_ecus_delay_their_commands_behind_their_own_state_frames_in_the_loop_model() -> None:
    """The replicated lockstep model of 6 ECUs, 5 ms period, 500 kbit/s, command queued 1 us after
    the state frame. Tick 1 (no heartbeats): SYNC 95 bits (0-190 us), REFERENCE 105 (190-400 us);
    priority buffers: the six commands (0x081..) come next, CMD_C1 ends at 400 + 210 = 610 us;
    FIFO buffers: ecu1's STATE_C1 is ahead of its command and goes first (400-670 us), then
    CMD_C1 (670-880 us)."""
    from canbrake.bus import dbc
    from canbrake.bus.schedule import LockstepBusTiming

    def cmd_latency(cfgs):
        t = LockstepBusTiming(6, 0.005, 500_000, decision_offset_s=1e-6, heartbeat_every=20, tx_buffers=cfgs)
        return t.latency_s(1, "ecu1", dbc.BRAKE_CMD_BASE + 1, 0.005 + 1e-6)

    assert cmd_latency(None) == pytest.approx(609 * US, abs=1e-12)
    assert cmd_latency([TxBufferConfig(policy="fifo")]) == pytest.approx(879 * US, abs=1e-12)
    assert cmd_latency([TxBufferConfig(policy="mailboxes", mailboxes=2)]) == pytest.approx(609 * US, abs=1e-12)
