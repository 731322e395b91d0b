"""An ECU fed the memory bus's slot images (EcuNode.handle_raw, PeerTable.feed_raw) does what it
does fed python-can messages (handle_batch, feed): the same frames out, the same peer table,
sensors and counters, also for a state page with a bad CRC (rejected) and a frame outside the
ECU's routes (ignored)."""
from __future__ import annotations

import os
import uuid

import can

from canbrake.bus import memory_shm as shm
from canbrake.bus._ring import messages_of


def _ecus(car: int, n: int = 6):
    from canbrake.build import build_node
    from canbrake.scenario import load_scenario

    path = "scenarios/chen2023_case1_fine_rail.yaml"
    scn = load_scenario(path)
    plant = build_node(scn, "plant", run_dir=None)
    twins = []
    for _ in range(2):
        e = build_node(scn, "ecu", car=car, run_dir=None)
        e.start(0.0)
        twins.append(e)
    others = []
    for c in range(1, n + 1):
        if c != car:
            e = build_node(scn, "ecu", car=c, run_dir=None)
            e.start(0.0)
            others.append(e)
    return plant, twins, others


def _key(msgs):
    return [(m.arbitration_id, m.is_extended_id, bytes(m.data)) for m in msgs]


def test_handle_raw_equals_handle_batch_with_a_rejected_page():
    ch = f"ecuraw-{os.getpid()}-{uuid.uuid4().hex[:6]}"
    plant, (a, b), others = _ecus(3)
    bus = can.Bus(interface="canbrake", channel=ch)  # its ring makes the slot images (encode)
    try:
        ring = bus._ring
        tick0 = plant.start(0.0)
        states = []
        for e in others:
            states += e.handle_batch(list(tick0), 0.0)
        # a peer's state page with a broken CRC, and a frame of an identifier nobody routes
        bad = next(m for m in states if m.arbitration_id in a._state_pages)
        broken = can.Message(arbitration_id=bad.arbitration_id, data=bytes([bad.data[0] ^ 0xFF]) + bytes(bad.data[1:]),
                             is_extended_id=bad.is_extended_id)
        stray = can.Message(arbitration_id=0x7EE, data=b"\x01", is_extended_id=False)
        for batch in (list(tick0), [stray, broken, *states]):
            out_a = a.handle_batch(list(batch), 0.0)
            images = ring.encode(batch, True, 0.0)
            assert len(images) == len(batch) * shm.SLOT_BYTES
            out_b = b.handle_raw(images, 0.0, bus.raw_message)
            assert _key(out_a) == _key(out_b)
            assert (a.k, a.phase, a.sensors, a.stats.ticks) == (b.k, b.phase, b.sensors, b.stats.ticks)
            for nm, arr in a.peer_signals.items():
                assert arr.tobytes() == b.peer_signals[nm].tobytes()
            assert a.guard.stats() == b.guard.stats()
        assert a.stats.ticks == 1 and a.guard.stats()  # it computed tick 0, and counted the rejection
        assert a.stats.peer_corrupted == b.stats.peer_corrupted == 1
        assert b._peers.feed_raw(b"", 0, b.k, b.phase) & 7 == 0  # nothing: the end at once
    finally:
        bus.shutdown()


def _plant_key(p):
    return (p.k, p.finished, p._done, p.stats.commands_received, p.stats.commands_corrupted,
            p.stats.commands_out_of_sequence, p.guard.stats(), p._fresh_pages.tobytes(), p._fresh.tobytes())


def test_plant_handle_raw_equals_handle_batch_with_a_rejected_command():
    """The plant fed slot images (PlantNode.handle_raw, CommandTable.take_batch_raw) does what it
    does fed messages: the same frames out (the next tick's, as slot images), commands and counters, also for a
    command with a bad CRC (rejected), a frame of an identifier the table does not route and a
    batch that completes the tick."""
    from canbrake.build import build_node
    from canbrake.scenario import load_scenario

    scn = load_scenario("scenarios/chen2023_case1_fine_rail.yaml")
    ch = f"plantraw-{os.getpid()}-{uuid.uuid4().hex[:6]}"
    a, b = (build_node(scn, "plant", run_dir=None) for _ in range(2))
    ecus = []
    for c in range(1, 7):
        e = build_node(scn, "ecu", car=c, run_dir=None)
        e.start(0.0)
        ecus.append(e)
    bus = can.Bus(interface="canbrake", channel=ch)
    try:
        ring = bus._ring
        tick0 = a.start(0.0)
        assert _key(b.start(0.0)) == _key(tick0)
        assert a._commands_close_slots() and b._commands_close_slots()
        # the ECUs' phases until their commands come (their state pages to each other)
        frames, cmds = list(tick0), []
        for _ in range(4):
            nxt = []
            for e in ecus:
                nxt += e.handle_batch(list(frames), 0.0)
            cmds += [m for m in nxt if m.arbitration_id in a._cmd_pages]
            frames = nxt
        assert len(cmds) == a._n_pages
        bad = cmds[0]
        broken = can.Message(arbitration_id=bad.arbitration_id, is_extended_id=bad.is_extended_id,
                             data=bytes([bad.data[0] ^ 0xFF]) + bytes(bad.data[1:]))
        stray = can.Message(arbitration_id=0x7EE, data=b"\x01", is_extended_id=False)
        for batch in ([stray, broken, *cmds[1:3]], cmds[3:] + cmds[:1]):
            out_a = a.handle_batch(list(batch), 0.0)
            out_b = b.handle_raw(ring.encode(batch, True, 0.0), 0.0, bus.raw_message)
            # the next tick's frames as slot images (TickFrames.images), the messages' frames
            assert type(out_b) is (bytes if out_a else list)
            assert _key(out_a) == _key(messages_of(out_b) if type(out_b) is bytes else out_b)
            assert _plant_key(a) == _plant_key(b)
        assert a.k == 1 and a.stats.commands_corrupted == 1  # the tick went on, the bad CRC counted
        assert b.handle_raw(b"", 0.0, bus.raw_message) == []
    finally:
        for p in (a, b):
            p.close()
        bus.shutdown()


def _recorder_rig(tmp_path, mode: str):
    """Chen case 1's lockstep plant and six ECUs (they make a period's frames) and two recorders in
    ``mode``, logging to tmp_path/a and tmp_path/b: one to be fed messages, one slot images."""
    from canbrake.build import build_node
    from canbrake.scenario import load_scenario

    scn = load_scenario("scenarios/chen2023_case1_fine_rail.yaml")
    rec_scn = scn if mode == "lockstep" else load_scenario("scenarios/chen2023_case1_fine_rail.yaml",
                                                          overrides={"mode": mode})
    plant = build_node(scn, "plant", run_dir=None)
    ecus = []
    for c in range(1, 7):
        e = build_node(scn, "ecu", car=c, run_dir=None)
        e.start(0.0)
        ecus.append(e)
    recs = []
    for name in ("a", "b", "c"):
        r = build_node(rec_scn, "recorder", run_dir=None)
        r.log_path = tmp_path / name / "frames.log"
        r.log_path.parent.mkdir()
        r.start(0.0)
        recs.append(r)
    return plant, ecus, recs


def _answers(ecus, frames) -> list:
    """Every frame the lockstep ``ecus`` send, phase after phase, in answer to a period's opening ``frames``."""
    out = []
    for _phase in range(4):
        nxt = []
        for e in ecus:
            nxt += e.handle_batch(list(frames), 0.0)
        out += nxt
        frames = nxt
    return out


def test_recorder_handle_raw_equals_handle_batch(tmp_path):
    """The recorder fed slot images (RecorderNode.handle_raw) logs and counts what it does fed
    messages: the same frames.log bytes and counts, a frame outside the database and a remote
    frame included; and so does the recorder fed messages through its compiled batch handler (the
    in-process Router's, RecorderTaker), the period in two batches."""
    from canbrake.nodes._trace import RecorderTaker

    plant, ecus, (a, b, c) = _recorder_rig(tmp_path, "lockstep")
    recs = [a, b, c]
    take_c = c.batch_handler()
    assert type(take_c) is RecorderTaker
    bus = can.Bus(interface="canbrake", channel=f"recraw-{os.getpid()}-{uuid.uuid4().hex[:6]}")
    try:
        frames = plant.start(0.0)
        stray = can.Message(arbitration_id=0x7EE, data=b"\x01", is_extended_id=False)
        # a remote frame asks for 2 bytes and carries none: its bits without a data field
        remote = can.Message(arbitration_id=0x1ABCDE, is_extended_id=True, is_remote_frame=True, dlc=2)
        for _ in range(3):  # tick 0 and 1: the plant's frames, the ECUs' phases, its next tick
            period = list(frames) + _answers(ecus, frames)
            period += [stray, remote]
            frames = plant.handle_batch([m for m in period if m.arbitration_id in plant._cmd_pages], 0.0)
            a.handle_batch(list(period), 0.0)
            b.handle_raw(bus._ring.encode(period, True, 0.0), 0.0, bus.raw_message)
            assert take_c(period[:5], 0.0) == [] and take_c(period[5:], 0.0) == []
            assert a._counts == b._counts == c._counts and a._phase_of == b._phase_of == c._phase_of
            assert a._closing_seen == c._closing_seen
        for r in recs:
            r.close()
        assert (tmp_path / "a" / "frames.log").read_bytes() == (tmp_path / "b" / "frames.log").read_bytes()
        assert (tmp_path / "a" / "frames.log").read_bytes() == (tmp_path / "c" / "frames.log").read_bytes()
        assert (tmp_path / "a" / "frames.log").read_bytes().count(b"\n") > 30
        assert b.handle_raw(b"", 0.0, bus.raw_message) == []
    finally:
        plant.close()
        bus.shutdown()


def _take_all(take, batch, n, key_at):
    """take_frames' caller (the recorder's loop): a new key (``key_at(i)``, its frame_key) gets
    phase 1, a SYNC is passed; stops (fails) if a loop takes no step."""
    counts, phase_of, kept, events = {}, {}, [], []
    i, resume = 0, False
    while i < n:
        i, ev, closed = take(batch, i, resume, counts, {0x300}, 0x010, phase_of, kept)
        events.append((i, ev, closed))
        assert len(events) <= 4 * n, events[-4:]  # a phase set under another key than the loop's
        if ev == 0:
            break
        if ev == 2:
            phase_of[key_at(i)] = 1
        resume = True
    return counts, phase_of, [(p, aid, data, _key([m])) for p, aid, data, m in kept], events


def test_take_frames_raw_equals_take_frames():
    """The recorder's compiled loop over slot images counts, phases and keeps what it does over
    messages: standard and extended identifiers, a SYNC, a closing frame, an error frame, a
    remote frame and a frame of no database."""
    from canbrake.nodes._trace import frame_key, take_frames, take_frames_raw

    msgs = [can.Message(arbitration_id=0x010, data=b"\x00\x00\x00\x00", is_extended_id=False),
            can.Message(arbitration_id=0x300, data=b"\x01\x02", is_extended_id=False),
            can.Message(arbitration_id=0x010, data=b"\x01\x00\x00\x00", is_extended_id=True),
            can.Message(arbitration_id=0x1ABCDEF0, data=bytes(range(8)), is_extended_id=True),
            can.Message(arbitration_id=0x2A0, is_remote_frame=True, dlc=4, is_extended_id=False),
            can.Message(arbitration_id=0x080, is_error_frame=True, data=bytes(8), is_extended_id=False),
            can.Message(arbitration_id=0x7EE, data=b"", is_extended_id=False),
            can.Message(arbitration_id=0x300, data=b"\x03", is_extended_id=False),
            can.Message(arbitration_id=0x010, data=b"\x02\x00\x00\x00", is_extended_id=False)]
    bus = can.Bus(interface="canbrake", channel=f"takeraw-{os.getpid()}-{uuid.uuid4().hex[:6]}")
    try:
        images = bus._ring.encode(msgs, True, 0.0)
        got = _take_all(lambda b, *a: take_frames_raw(bus.raw_message, b, *a), images, len(msgs),
                        lambda i: frame_key(msgs[i].arbitration_id, msgs[i].is_extended_id, msgs[i].is_error_frame))
        ref = _take_all(take_frames, msgs, len(msgs),
                        lambda i: frame_key(msgs[i].arbitration_id, msgs[i].is_extended_id, msgs[i].is_error_frame))
        assert got == ref
        # message None: each frame kept as its slot image (the recorder's candump path), the same frames
        kept = []
        imgs = _take_all(lambda b, *a: take_frames_raw(None, b, *a[:-1], kept), images, len(msgs),
                         lambda i: frame_key(msgs[i].arbitration_id, msgs[i].is_extended_id, msgs[i].is_error_frame))
        assert imgs[:2] == ref[:2] and imgs[3] == ref[3]
        assert all(type(m) is bytes and len(m) == shm.SLOT_BYTES for *_x, m in kept)
        assert [(p, aid, data, _key([bus.raw_message(m, 0)])) for p, aid, data, m in kept] == ref[2]
        assert sum(e[1] == 1 for e in ref[3]) == 2 and ref[3][-1][1] == 0  # two SYNCs, then the end
        assert take_frames_raw(bus.raw_message, b"", 0, False, {}, set(), 0x010, {}, []) == (0, 0, 0)
    finally:
        bus.shutdown()


def test_realtime_recorder_handle_raw_equals_handle_batch(tmp_path):
    """The realtime recorder fed slot images (RecorderNode.handle_raw: the frames between SYNCs in
    compiled loops) logs, counts and loads the bus as it does fed messages: the same frames.log
    bytes (the senders' time stamps, ``now`` for a frame without one), counts, error frames and
    per-period bits, with a frame outside the database, a remote frame and error frames among them."""
    plant, ecus, (a, b, c) = _recorder_rig(tmp_path, "realtime")
    c.close()
    recs = [a, b]
    assert a.mode == b.mode == "realtime"
    assert c.batch_handler() == c.handle_batch  # realtime: no compiled handler
    bus = can.Bus(interface="canbrake", channel=f"recrt-{os.getpid()}-{uuid.uuid4().hex[:6]}")
    loads = []
    try:
        frames = plant.start(0.0)
        t = 1000.0
        for tick in range(4):
            period = list(frames) + _answers(ecus, frames)
            period += [can.Message(arbitration_id=0x7EE, data=b"\x01", is_extended_id=False),
                       can.Message(arbitration_id=0x1ABCDE, is_extended_id=True, is_remote_frame=True, dlc=2),
                       can.Message(arbitration_id=0x0, is_error_frame=True, data=bytes(8))]
            for i, m in enumerate(period):
                m.timestamp = 0.0 if i % 7 == 3 else t + i * 1e-5  # some without a time stamp
            t += 0.001
            frames = plant.handle_batch([m for m in period if m.arbitration_id in plant._cmd_pages], 0.0)
            half = len(period) // 2  # two receives a period, a SYNC in the first
            now = 2000.0 + tick
            for part in (period[:half], period[half:]):
                a.handle_batch([can.Message(**{s: getattr(m, s) for s in (
                    "timestamp", "arbitration_id", "is_extended_id", "is_remote_frame", "is_error_frame", "dlc",
                    "data")}) for m in part], now)
                b.handle_raw(bus._ring.encode(part, True, 0.0), now, bus.raw_message)
            assert a._counts == b._counts and a.error_frames == b.error_frames and a._rt_bits == b._rt_bits
            loads.append(b._series.n)
        assert loads[-1] >= 3 and a._series.sum == b._series.sum and a._series.peak == b._series.peak
        for r in recs:
            r.close()
        log_a = (tmp_path / "a" / "frames.log").read_bytes()
        assert log_a == (tmp_path / "b" / "frames.log").read_bytes()
        assert log_a.count(b"\n") > 40 and b"(2001.000000)" in log_a and b"R\n" in log_a
    finally:
        plant.close()
        bus.shutdown()
