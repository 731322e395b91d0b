"""The ECU's compiled decision (canbrake.nodes._ecu.EcuPeriod.decide) against the Python it
replaced in EcuNode._phase2: the same Observation field by field (also with peer hold: lost peers
NaN in a copy), the same command frames byte for byte (Status from the diagnostics and the
fallback, further commands), the own values written into the peer table."""
from __future__ import annotations

import math

import numpy as np
import pytest

from canbrake.bus.e2e import COUNTER_MODULO
from canbrake.control.base import ControlOutput, Observation
from canbrake.nodes.base import frame
from canbrake.nodes.ecu import _STATUS


class _Stub:
    """Records what it is given, returns ``out``."""

    def __init__(self, out: ControlOutput) -> None:
        self.out = out
        self.seen: list[Observation] = []

    def step(self, obs: Observation) -> ControlOutput:
        self.seen.append(obs)
        return self.out


def _ecu_after_tick0(car: int = 3):
    """ECU ``car`` of Chen case 1 that has taken tick 0's sensor and peer frames (not decided)."""
    from canbrake.build import build_node
    from canbrake.scenario import load_scenario

    scn = load_scenario("scenarios/chen2023_case1_fine_rail.yaml")
    plant = build_node(scn, "plant", run_dir=None)
    ecu = build_node(scn, "ecu", car=car, run_dir=None)
    ecu.start(0.0)
    tick0 = list(plant.start(0.0))
    states = []
    for c in range(1, 7):
        if c != car:
            e = build_node(scn, "ecu", car=c, run_dir=None)
            e.start(0.0)
            states += e.handle_batch(list(tick0), 0.0)
    return ecu, tick0, states


def _oracle(ecu, k: int, hold: int | None):
    """EcuNode._phase2's Observation as it was built in Python (own entries written first)."""
    sensors, table, i = ecu.sensors, ecu.peer_signals, ecu.i
    for nm in ecu._own_signals:
        table[nm][i] = sensors[nm]
    if hold is not None:
        peers, dropped = ecu._peers.hold_copy(k, hold, i)
    else:
        peers, dropped = ecu._peer_views, False
    speed = peers["speed_mps"]
    pt = ecu._peers
    age, fresh, max_age = pt.ages(k, ecu.dt, i, None if peers is ecu._peer_views else speed)
    age.flags.writeable = False  # the controller gets the table's own ages, read-only (PeerTable.age_view)
    nan = math.nan
    obs = Observation(tick=k, time_s=k * ecu.dt, speed_mps=sensors.get("speed_mps", nan),
                      position_m=sensors.get("position_m", nan), ref_speed_mps=pt.v_ref,
                      ref_decel_mps2=pt.a_ref, peer_speed_mps=speed, peer_position_m=peers["position_m"],
                      peer_age_s=age,
                      deflection_front_m=sensors.get("deflection_front_m") if ecu._has_front else None,
                      deflection_rear_m=(sensors.get("deflection_rear_m")
                                         if ecu._has_rear and "deflection_rear_m" in sensors else None),
                      ref_position_m=pt.x_ref, sensors=dict(sensors), peer_signals=peers)
    return obs, fresh, max_age, dropped


def _oracle_frames(ecu, k: int, result: ControlOutput, in_fallback: bool):
    diag = result.diagnostics
    status = int(diag["status"]) if "status" in diag else 0
    if in_fallback and status == 0:
        status = 1
    values = {"brake_force_n": result.brake_force_n, **result.commands} if result.commands else \
        {"brake_force_n": result.brake_force_n}
    values[_STATUS] = status
    return [frame(fid, codec.encode_from(values, keys, k % COUNTER_MODULO, k, True))
            for fid, codec, keys in ecu._cmd_msgs]


def _same_obs(a: Observation, b: Observation) -> None:
    assert type(a) is type(b) is Observation
    assert list(a.__dict__) == list(b.__dict__)
    for name, x in a.__dict__.items():
        y = b.__dict__[name]
        if isinstance(x, np.ndarray):
            assert type(y) is np.ndarray and x.tobytes() == y.tobytes() and x.flags.writeable == y.flags.writeable
        elif name == "peer_signals":
            assert list(x) == list(y) and all(x[n].tobytes() == y[n].tobytes() for n in x)
        elif isinstance(x, float) and math.isnan(x):
            assert isinstance(y, float) and math.isnan(y)
        else:
            assert x == y and type(x) is type(y), name


def _key(msgs):
    return [(m.arbitration_id, m.is_extended_id, m.dlc, bytes(m.data)) for m in msgs]


@pytest.mark.parametrize("car", [1, 3, 6])
@pytest.mark.parametrize("hold", [None, 0, 5])
def test_decide_equals_the_python_phase2(car, hold):
    ecu, tick0, states = _ecu_after_tick0(car)
    ecu.handle_batch(tick0, 0.0)  # sensors, reference; phase 1 (its state sent); not yet decided
    ecu._peers.feed(states[:3], 0, ecu.k, ecu.phase)  # some peers' state pages only (others lost)
    k = ecu.k + 3  # three periods later: peers of tick 0 are 3 periods old
    out = ControlOutput(12_345.678, {"status": 0.0, "x": 1.5}, {"brake_force_n": 99.0, "extra": 2.0}, {"b": 1.0})
    stub = _Stub(out)
    want, fresh_w, max_age_w, dropped_w = _oracle(ecu, k, hold)
    result, cmds, max_age, fresh, dropped = ecu._period.decide(stub, k, -1 if hold is None else hold, False)
    assert result is out and len(stub.seen) == 1
    _same_obs(stub.seen[0], want)
    # the ages are the table's buffer, written once per period: valid for the call, as the peer views
    assert stub.seen[0].peer_age_s is ecu._peers.age_view
    with pytest.raises(ValueError):
        stub.seen[0].peer_age_s[0] = 1.0
    assert (fresh, max_age, dropped) == (fresh_w, max_age_w, dropped_w)
    assert dropped == (hold is not None)  # peers never heard of (the lost pages' senders) are dropped
    assert _key(cmds) == _key(_oracle_frames(ecu, k, out, dropped_w))
    assert len(ecu._control_pending) == 1 and ecu._control_pending[0] >= 0.0


def test_ages_into_the_table_equal_a_new_array_and_check_the_speed_length():
    ecu, tick0, states = _ecu_after_tick0(3)
    ecu.handle_batch(tick0, 0.0)
    pt = ecu._peers
    pt.feed(states[:3], 0, ecu.k, ecu.phase)
    for k in (0, 2, 9):
        a, fa, ma = pt.ages(k, ecu.dt, ecu.i)
        b, fb, mb = pt.ages(k, ecu.dt, ecu.i, None, True)
        assert b is pt.age_view and not b.flags.writeable and a.flags.writeable
        assert a.tobytes() == b.tobytes() and (fa, ma) == (fb, mb)
    with pytest.raises(ValueError, match="values for 6 ECUs"):
        pt.ages(1, ecu.dt, ecu.i, np.zeros(3))


def test_decide_status_fallback_and_the_step_times():
    ecu, tick0, _states = _ecu_after_tick0(2)
    ecu.handle_batch(tick0, 0.0)
    for diag, fallback in (({}, True), ({"status": 3.7}, True), ({"status": 0}, False), ({}, False)):
        out = ControlOutput(-500.0, diag)
        cmds = ecu._period.decide(_Stub(out), 7, -1, fallback)[1]
        assert _key(cmds) == _key(_oracle_frames(ecu, 7, out, fallback))
    # the step times go to the histogram 1,024 at a time (the pending list is the node's)
    ecu._control_pending[:] = [1e-6] * 1023
    ecu._period.decide(_Stub(ControlOutput(0.0)), 8, -1, False)
    assert ecu._control_pending == [] and ecu._control_time.n == 1024


def test_decide_writes_the_own_values_into_the_table():
    ecu, tick0, _states = _ecu_after_tick0(4)
    ecu.handle_batch(tick0, 0.0)
    ecu.sensors["speed_mps"] = 21.25
    ecu._period.decide(_Stub(ControlOutput(0.0)), 1, -1, False)
    assert ecu.peer_signals["speed_mps"][ecu.i] == 21.25
    assert ecu._own_signals and all(ecu.peer_signals[n][ecu.i] == ecu.sensors[n] for n in ecu._own_signals)


def _python_take_batch(node, feed, batch, message_at, now):
    """EcuNode._take_batch as it was in Python (the oracle of the compiled take_batch)."""
    from canbrake.bus._codec import (FEED_END, FEED_FRAME, FEED_HELD, FEED_PHASE1, FEED_PHASE2, FEED_REJECT,
                                      FEED_SYNC, REJECT_CRC)
    out = []
    i = 0
    while True:
        r = feed(batch, i, node.k, node.phase)
        ev, i = r & 7, r >> 3
        if ev == FEED_END:
            break
        if ev == FEED_SYNC:
            node._start_period(node._peers.sync_tick)
        elif ev == FEED_FRAME:
            out += node._handle_frame(message_at(i), now)
            if node.finished:
                break
        elif ev == FEED_PHASE1:
            if node.clock is not None and node.phase == 0 and node.k >= 0:
                node._p1_at = now + node.clock.offset_s(node.k)
            else:
                out += node._phase1(now)
        elif ev == FEED_PHASE2:
            out += node._phase2(now)
        elif ev == FEED_REJECT:
            node.guard.reject("crc" if node._peers.last_code == REJECT_CRC else "counter")
            node._count_peer_rejection()
        elif ev == FEED_HELD:
            node._late_rx.append(message_at(i))
        else:
            node._arm_external(now)
        i += 1
    return out


def _node_key(e):
    return (e.k, e.phase, e.finished, dict(e.sensors), e.stats.ticks, e.stats.peer_corrupted,
            e.stats.peer_stale_or_duplicate, e.stats.peer_missing, e.guard.stats(), len(e._late_rx),
            {n: a.tobytes() for n, a in e.peer_signals.items()})


def test_take_batch_equals_the_python_loop_over_periods_with_a_rejected_page():
    """Two twins of ECU 3 through 4 periods of Chen case 1 with every peer: one by the compiled
    loop (handle_batch), one by the Python loop it replaced; a corrupted state page and a stray
    frame in every period."""
    import can

    from canbrake.build import build_node
    from canbrake.scenario import load_scenario

    scn = load_scenario("scenarios/chen2023_case1_fine_rail.yaml")
    plant = build_node(scn, "plant", run_dir=None)
    a, b = (build_node(scn, "ecu", car=3, run_dir=None) for _ in range(2))
    others = [build_node(scn, "ecu", car=c, run_dir=None) for c in (1, 2, 4, 5, 6)]
    for e in (a, b, *others):
        e.start(0.0)
    gen = list(plant.start(0.0))
    for _tick in range(4):
        states = []
        for e in others:
            states += e.handle_batch(list(gen), 0.0)
        bad = next(m for m in states if m.arbitration_id in a._state_pages)
        broken = can.Message(arbitration_id=bad.arbitration_id, is_extended_id=bad.is_extended_id,
                             data=bytes([bad.data[0] ^ 0x5A]) + bytes(bad.data[1:]))
        stray = can.Message(arbitration_id=0x7EE, data=b"\x01", is_extended_id=False)
        sent = []
        for batch in (list(gen), [stray, broken, *states]):
            out_a = a.handle_batch(list(batch), 0.0)
            out_b = _python_take_batch(b, b._peers.feed, list(batch), batch.__getitem__, 0.0)
            assert _key(out_a) == _key(out_b)
            assert _node_key(a) == _node_key(b)
            sent.append(out_a)
        cmds = list(sent[1])  # ECU 3's commands (its phase 1's state frames go to its peers)
        for e in others:
            cmds += e.handle_batch(states + sent[0], 0.0)
        gen = list(plant.handle_batch(cmds, 0.0))
    assert a.stats.ticks == 4 and a.stats.peer_corrupted == 4


def test_state_frames_equal_the_python_encoding_with_broadcast_and_authenticators():
    ecu, tick0, _states = _ecu_after_tick0(2)
    ecu.handle_batch(tick0, 0.0)
    k = 17
    for broadcast in ({}, {"speed_mps": 1.0, "position_m": -3.0, "other": 2.0}):
        values = {**broadcast, **ecu.sensors} if broadcast else ecu.sensors
        want = [frame(fid, codec.encode_from(values, keys, k % COUNTER_MODULO, k))
                for fid, codec, keys, _auth in ecu._state_msgs]
        assert want and _key(ecu._period.state_frames(k, broadcast)) == _key(want)
    # with an authenticator (SecOC): each state frame followed by its own
    from canbrake.nodes._ecu import EcuPeriod

    calls = []

    def auth(auth_id, fid, payload, tick):
        calls.append((auth_id, fid, bytes(payload), tick))
        return bytes(8)

    msgs = [(fid, codec, keys, 0x555) for fid, codec, keys, _a in ecu._state_msgs]
    p = EcuPeriod(ecu._peers, ecu.sensors, ecu._own_signals, ecu.i, ecu.dt, ecu._peer_views, Observation,
                  False, False, [], _STATUS, [], ecu._control_time, None, msgs, auth)
    got = p.state_frames(k, {})
    assert [m.arbitration_id for m in got] == [x for fid, *_ in msgs for x in (fid, 0x555)]
    assert calls == [(0x555, m.arbitration_id, bytes(m.data), k) for m in got[0::2]]


@pytest.mark.parametrize("buffered", [True, False])
def test_trace_rows_equal_the_csv_module(tmp_path, buffered):
    """decide's trace rows (left pending, written by the next decide or write_row: straight into
    the file inside buffered_traces, else by CsvTrace.append_dict; values the compiled row does
    not write, by the csv writer) are csv.writer's rows (floats "%.9g") of tick, brake force, the
    diagnostics by name (NaN where missing), max peer age (inf: none) and peers fresh."""
    import contextlib
    import csv
    import io

    from canbrake.nodes.base import CsvTrace, buffered_traces

    ecu, tick0, states = _ecu_after_tick0(3)
    ecu.handle_batch(tick0, 0.0)
    ecu._peers.feed(states[:3], 0, ecu.k, ecu.phase)
    names = ("x", "missing", "status")
    header = ["tick", "brake_cmd_n", *names, "max_peer_age_s", "peers_fresh"]
    with buffered_traces() if buffered else contextlib.nullcontext():
        trace = CsvTrace(tmp_path / "t.csv", header)
    assert (trace.row_write() is not None) == buffered
    ecu._period.set_trace(trace, names)
    outs = [ControlOutput(12_345.678, {"status": 0.0, "x": 1.5}), ControlOutput(np.float64(-0.1), {"x": np.float64(2.5)}),
            ControlOutput(7, {"x": None, "status": 1}), ControlOutput(0.3, {"x": 2 ** 70}),
            ControlOutput(1e-300, {"x": True, "status": np.int64(2)})]
    want = [header]
    for j, out in enumerate(outs):
        k = ecu.k + j
        result, _cmds, max_age, fresh, _dropped = ecu._period.decide(_Stub(out), k, -1, False)
        want.append([k, out.brake_force_n, *[out.diagnostics.get(n, math.nan) for n in names],
                     max_age if max_age > -math.inf else math.inf, fresh])
    ecu._period.write_row()
    ecu._period.write_row()  # nothing pending: nothing written
    trace.close()
    buf = io.StringIO()
    w = csv.writer(buf)
    for row in want:
        w.writerow([f"{v:.9g}" if isinstance(v, float) else v for v in row])
    assert (tmp_path / "t.csv").read_bytes() == buf.getvalue().encode()


def test_batch_handler_equals_handle_batch():
    """EcuNode.batch_handler (the Router's compiled handle_batch) against handle_batch: the same
    frames out and the same state after the plant's tick frames and the peers' states."""
    from canbrake.nodes._ecu import BatchTaker

    a, tick0, states = _ecu_after_tick0(3)
    b, _tick0, _states = _ecu_after_tick0(3)
    handler = b.batch_handler()
    assert type(handler) is BatchTaker and type(a.batch_handler()) is BatchTaker
    for batch in (tick0, states):
        want = a.handle_batch(list(batch), 0.0)
        got = handler(list(batch), 0.0)
        assert _key(got) == _key(want) and got
        assert (b.k, b.phase, b.stats.ticks) == (a.k, a.phase, a.stats.ticks)
        assert b.sensors == a.sensors or all(
            x == y or (math.isnan(x) and math.isnan(y)) for x, y in zip(b.sensors.values(), a.sensors.values()))
        assert all(b.peer_signals[n].tobytes() == a.peer_signals[n].tobytes() for n in a.peer_signals)
    assert a.stats.ticks == 1
