"""Tests of the in-memory cross-process bus, through python-can's own API (``interface="canbrake"``)."""
from __future__ import annotations

import multiprocessing as mp
import os
import signal
import subprocess
import sys
import tempfile
import threading
import time
from pathlib import Path

import can
import pytest

from conftest import default_sigint

from canbrake.bus import memory_shm as shm
from canbrake.bus.memory import MemoryBus, channel_pids, list_channels, remove_channel

SPAWN = mp.get_context("spawn")
TIMEOUT = 90.0  # s, generous bound for child processes on a loaded 2-core machine


@pytest.fixture()
def shm_dir(monkeypatch: pytest.MonkeyPatch):
    """A private channel directory, inherited by spawned children and subprocesses."""
    d = tempfile.mkdtemp(prefix="cbtest-", dir="/dev/shm" if os.path.isdir("/dev/shm") else None)
    monkeypatch.setenv("CANBRAKE_SHM_DIR", d)
    yield Path(d)
    for f in os.listdir(d):
        os.unlink(os.path.join(d, f))
    os.rmdir(d)


def bus(channel: str, **kw) -> can.BusABC:
    return can.Bus(interface="canbrake", channel=channel, **kw)


def frame(aid: int, data: bytes = b"", ext: bool = False, **kw) -> can.Message:
    return can.Message(arbitration_id=aid, data=data, is_extended_id=ext, **kw)


def fields(m: can.Message) -> tuple:
    return (m.arbitration_id, m.is_extended_id, m.is_remote_frame, m.is_error_frame, m.dlc,
            bytes(m.data), m.is_fd, m.bitrate_switch, m.error_state_indicator)


def assert_sleepers_consistent(b: MemoryBus) -> None:
    """The shared sleeper count (writers skip the wake scan when it is 0) matches the flags."""
    q = b._q
    flags = sum(q[e + shm.E_SLEEPING] for e in shm.live_entries(q))
    assert q[shm.H_SLEEPERS] == flags


def wait_for_pids(channel: str, n: int) -> None:
    end = time.monotonic() + TIMEOUT
    while len(channel_pids(channel)) < n:
        assert time.monotonic() < end, f"{n} buses never opened {channel}"
        time.sleep(0.02)


# ---------------------------------------------------------------- child processes (spawn)
def child_receive(channel: str, n: int, ready, out) -> None:
    with bus(channel) as b:
        ready.put(os.getpid())
        out.put([b.recv(TIMEOUT) for _ in range(n)])


def child_order(channel: str, idx: int, n_frames: int, n_total: int, start, out) -> None:
    with bus(channel, receive_own_messages=True) as b:
        start.wait(TIMEOUT)
        got = []
        for k in range(n_frames):
            b.send(frame(0x100 + idx, k.to_bytes(2, "little")))
            if k % 10 == 9:
                time.sleep(0.001)  # let the other writers in
            while (m := b.recv(0)) is not None:
                got.append((m.arbitration_id, bytes(m.data)))
        while len(got) < n_total:
            m = b.recv(TIMEOUT)
            assert m is not None
            got.append((m.arbitration_id, bytes(m.data)))
        out.put((idx, got))


def child_wakeups(channel: str, ready, out) -> None:
    with bus(channel, can_filters=[{"can_id": 0x100, "can_mask": 0x7FF, "extended": False}]) as b:
        ready.put(os.getpid())
        m = b.recv(TIMEOUT)
        out.put((m.arbitration_id if m else None, b.stats()))
        b.set_filters(None)
        first = b.recv(TIMEOUT)
        rest = []
        while (m := b.recv(0)) is not None:
            rest.append(m)
        out.put((1 + len(rest) if first else 0, b.stats()))


def child_echo(channel: str, n: int, yield_: bool, ready, out) -> None:
    with bus(channel, can_filters=[{"can_id": 0x10, "can_mask": 0x7FF}], yield_before_sleep=yield_) as b:
        ready.put(os.getpid())
        for _ in range(n):
            m = b.recv(TIMEOUT)
            if m is None:
                break
            b.send(frame(0x11, m.data))
        out.put(b.stats())


def child_block_forever(channel: str, ready, backpressure: bool) -> None:
    with bus(channel, backpressure=backpressure) as b:
        ready.put(os.getpid())
        if backpressure:
            time.sleep(3600)  # never reads
        b.recv(None)


def child_slow_backpressure_reader(channel: str, n: int, ready, out) -> None:
    with bus(channel, backpressure=True) as b:
        ready.put(os.getpid())
        got = []
        while len(got) < n:
            m = b.recv(TIMEOUT)
            assert m is not None
            got.append(int.from_bytes(m.data, "little"))
            if len(got) % 16 == 0:
                time.sleep(0.002)
        out.put(got)


def child_die_holding_lock(channel: str) -> None:
    b = MemoryBus(channel)
    b._lock()  # the writer lock, then crash
    os.kill(os.getpid(), signal.SIGKILL)


# ---------------------------------------------------------------- tests
def test_plugin_is_registered(shm_dir: Path) -> None:
    assert can.interfaces.BACKENDS["canbrake"] == ("canbrake.bus.memory", "MemoryBus")
    with bus("reg") as b:
        assert isinstance(b, MemoryBus)
        assert b.state is can.BusState.ACTIVE
        assert {"interface": "canbrake", "channel": "reg"} in can.detect_available_configs("canbrake")
        assert (shm_dir / "canbrake-reg.bus").exists()


def test_round_trip_every_field_across_processes(shm_dir: Path) -> None:
    sent = [
        frame(0x123, b"\x01\x02\x03"),
        frame(0x1ABCDEF0, bytes(range(8)), ext=True),
        frame(0x7FF, b""),
        can.Message(arbitration_id=0x55, is_extended_id=False, is_remote_frame=True, dlc=4),
        can.Message(arbitration_id=0x00000080, is_extended_id=True, is_error_frame=True, dlc=8, data=bytes(8)),
        can.Message(arbitration_id=0x321, is_extended_id=False, is_fd=True, bitrate_switch=True,
                    error_state_indicator=True, data=bytes(range(64))),
        can.Message(arbitration_id=0x18FF00AA, is_extended_id=True, is_fd=True, data=b"\xaa" * 12),
    ]
    ready, out = SPAWN.Queue(), SPAWN.Queue()
    p = SPAWN.Process(target=child_receive, args=("rt", len(sent), ready, out))
    p.start()
    try:
        ready.get(timeout=TIMEOUT)
        with bus("rt") as b:
            t0 = time.time()
            for m in sent:
                b.send(m)
            t1 = time.time()
        got = out.get(timeout=TIMEOUT)
    finally:
        p.join(TIMEOUT)
    assert [fields(m) for m in got] == [fields(m) for m in sent]
    for m in got:
        assert m.channel == "rt" and m.is_rx
        assert t0 <= m.timestamp <= t1


def test_one_global_order_for_every_reader(shm_dir: Path) -> None:
    n_procs, n_frames = 3, 150
    start, out = SPAWN.Event(), SPAWN.Queue()
    procs = [SPAWN.Process(target=child_order, args=("ord", i, n_frames, n_procs * n_frames, start, out))
             for i in range(n_procs)]
    with bus("ord") as observer:  # a fourth reader that only listens
        for p in procs:
            p.start()
        wait_for_pids("ord", n_procs + 1)
        start.set()
        seen = []
        while len(seen) < n_procs * n_frames:
            m = observer.recv(TIMEOUT)
            assert m is not None
            seen.append((m.arbitration_id, bytes(m.data)))
        results = dict(out.get(timeout=TIMEOUT) for _ in procs)
    for p in procs:
        p.join(TIMEOUT)
    for i in range(n_procs):
        assert results[i] == seen, f"reader {i} saw another order"
        mine = [int.from_bytes(d, "little") for a, d in seen if a == 0x100 + i]
        assert mine == list(range(n_frames)), "a sender's frames must keep their order"
    switches = sum(1 for x, y in zip(seen, seen[1:]) if x[0] != y[0])
    assert switches > n_procs, "the writers should have interleaved"


def test_filtered_out_frames_do_not_wake_a_reader_and_a_burst_wakes_once(shm_dir: Path) -> None:
    ready, out = SPAWN.Queue(), SPAWN.Queue()
    p = SPAWN.Process(target=child_wakeups, args=("wk", ready, out))
    p.start()
    try:
        ready.get(timeout=TIMEOUT)
        with bus("wk") as b:
            time.sleep(0.3)  # the child is now blocked in recv
            for _ in range(10):
                for k in range(5):
                    b.send(frame(0x200 + k, b"x"))  # rejected by the child's filter
                time.sleep(0.01)
            b.send(frame(0x100, b"y"))
            aid, stats = out.get(timeout=TIMEOUT)
            assert aid == 0x100
            assert stats.wakeups == 1, stats
            assert stats.sleeps == 1 and stats.spurious_wakeups == 0, stats
            time.sleep(0.3)  # blocked again, now without filters
            b.send_many([frame(0x300, bytes([k])) for k in range(20)])
            n, stats = out.get(timeout=TIMEOUT)
    finally:
        p.join(TIMEOUT)
    assert n == 20
    assert stats.wakeups == 2, stats  # one for the burst


@pytest.mark.parametrize("yield_", [True, False])
def test_ping_pong_never_loses_a_wake_up(shm_dir: Path, yield_: bool) -> None:
    n = 400
    ready, out = SPAWN.Queue(), SPAWN.Queue()
    p = SPAWN.Process(target=child_echo, args=("pp", n, yield_, ready, out))
    p.start()
    try:
        ready.get(timeout=TIMEOUT)
        with bus("pp", can_filters=[{"can_id": 0x11, "can_mask": 0x7FF}], yield_before_sleep=yield_) as b:
            for k in range(n):
                b.send(frame(0x10, k.to_bytes(2, "little")))
                m = b.recv(2.0)  # a lost wake-up would show as a 2 s stall and None
                assert m is not None and int.from_bytes(m.data, "little") == k, f"round trip {k}"
            mine = b.stats()
            theirs = out.get(timeout=TIMEOUT)
            p.join(TIMEOUT)
            assert_sleepers_consistent(b)
    finally:
        p.join(TIMEOUT)
    # every blocking recv was ended by a wake-up, never by running out of time
    for st in (mine, theirs):
        assert st.wakeups >= st.sleeps - 1 and st.spurious_wakeups <= 1, st


def test_recv_timeout_semantics(shm_dir: Path) -> None:
    with bus("to") as rx, bus("to") as tx, bus("to", can_filters=[{"can_id": 1, "can_mask": 0x7FF}]) as picky:
        t = time.monotonic()
        assert rx.recv(0) is None
        assert time.monotonic() - t < 0.1
        t = time.monotonic()
        assert rx.recv(0.2) is None
        assert 0.2 <= time.monotonic() - t < 1.0
        tx.send(frame(5, b"a"))
        assert rx.recv(0).arbitration_id == 5  # already there: poll returns it

        # frames the filter rejects neither end the wait early nor extend it
        stop = threading.Event()

        def noise() -> None:
            while not stop.is_set():
                tx.send(frame(2, b"n"))
                time.sleep(0.005)

        th = threading.Thread(target=noise)
        th.start()
        try:
            t = time.monotonic()
            assert picky.recv(0.3) is None
            assert 0.3 <= time.monotonic() - t < 1.0
        finally:
            stop.set()
            th.join()

        # timeout=None blocks until a frame comes
        threading.Timer(0.2, lambda: tx.send(frame(1, b"late"))).start()
        t = time.monotonic()
        m = picky.recv(None)
        assert m.data == b"late" and time.monotonic() - t >= 0.15


def test_receive_own_messages(shm_dir: Path) -> None:
    with bus("own", receive_own_messages=True) as a, bus("own") as b:
        a.send(frame(0x10, b"a"))
        b.send(frame(0x11, b"b"))
        got_a = [a.recv(1), a.recv(1)]
        assert [(m.arbitration_id, m.is_rx) for m in got_a] == [(0x10, False), (0x11, True)]
        m = b.recv(1)
        assert (m.arbitration_id, m.is_rx) == (0x10, True)
        assert b.recv(0) is None  # b does not hear itself


def test_overrun_raises_then_resumes_with_newest_frames(shm_dir: Path) -> None:
    with bus("ovr", ring_size=64) as tx, bus("ovr") as rx:
        for k in range(200):
            tx.send(frame(0x1, k.to_bytes(2, "little")))
        with pytest.raises(can.CanOperationError, match="overrun"):
            rx.recv(0)
        rest = []
        while (m := rx.recv(0)) is not None:
            rest.append(int.from_bytes(m.data, "little"))
        assert rest == list(range(200 - len(rest), 200)) and len(rest) >= 60
        st = rx.stats()
        assert st.overruns == 1 and st.frames_lost + len(rest) == 200
        assert tx.recv(0) is None  # a sender is never overrun by its own frames


def test_backpressure_reader_gets_every_frame(shm_dir: Path) -> None:
    n = 400
    ready, out = SPAWN.Queue(), SPAWN.Queue()
    with bus("bp", ring_size=64) as tx:
        p = SPAWN.Process(target=child_slow_backpressure_reader, args=("bp", n, ready, out))
        p.start()
        try:
            ready.get(timeout=TIMEOUT)
            for k in range(n):
                tx.send(frame(0x7, k.to_bytes(2, "little")), timeout=TIMEOUT)
            got = out.get(timeout=TIMEOUT)
        finally:
            p.join(TIMEOUT)
        assert got == list(range(n))
        assert tx.stats().send_waits > 0


def test_backpressure_send_times_out_on_a_stuck_reader(shm_dir: Path) -> None:
    code = ("import can, time; b = can.Bus(interface='canbrake', channel='stuck', backpressure=True, ring_size=64); "
            "print('ready', flush=True); time.sleep(60)")
    child = subprocess.Popen([sys.executable, "-c", code], stdout=subprocess.PIPE, text=True)
    try:
        assert child.stdout.readline().strip() == "ready"
        with bus("stuck", ring_size=64) as tx:
            for k in range(64):
                tx.send(frame(1, b"f"))
            t = time.monotonic()
            with pytest.raises(can.CanTimeoutError, match=str(child.pid)):
                tx.send(frame(1, b"f"), timeout=0.3)
            assert 0.3 <= time.monotonic() - t < 2.0
            # the reader crashes: the blocked writer notices and goes on
            threading.Timer(0.3, child.kill).start()
            t = time.monotonic()
            tx.send(frame(1, b"g"), timeout=TIMEOUT)
            assert time.monotonic() - t < 3.0
            assert channel_pids("stuck") == [os.getpid()]
    finally:
        child.kill()
        child.wait()


def test_crashed_reader_and_crashed_lock_holder_do_not_block_writers(shm_dir: Path) -> None:
    ready = SPAWN.Queue()
    sleeper = SPAWN.Process(target=child_block_forever, args=("crash", ready, False))
    sleeper.start()
    ready.get(timeout=TIMEOUT)
    with bus("crash") as tx:
        time.sleep(0.2)
        os.kill(sleeper.pid, signal.SIGKILL)
        sleeper.join(TIMEOUT)
        tx.send(frame(1, b"z"))  # wakes the dead reader: must not raise nor block
        assert channel_pids("crash") == [os.getpid()]
        assert_sleepers_consistent(tx)

    ready = SPAWN.Queue()
    sleeper = SPAWN.Process(target=child_block_forever, args=("crash", ready, False))
    sleeper.start()
    ready.get(timeout=TIMEOUT)
    with bus("crash") as tx:
        time.sleep(0.2)
        os.kill(sleeper.pid, signal.SIGKILL)
        sleeper.join(TIMEOUT)
        assert channel_pids("crash") == [os.getpid()]  # reaped while marked asleep
        assert_sleepers_consistent(tx)
        for k in range(100):
            tx.send(frame(1, b"z"))

        locker = SPAWN.Process(target=child_die_holding_lock, args=("crash",))
        locker.start()
        locker.join(TIMEOUT)
        assert locker.exitcode == -signal.SIGKILL
        t = time.monotonic()
        tx.send(frame(2, b"after"))
        assert time.monotonic() - t < 1.0
    assert list_channels() == []


def test_cleanup_leaves_no_files(shm_dir: Path) -> None:
    a, b = bus("clean"), bus("clean", backpressure=True)
    assert len(os.listdir(shm_dir)) == 5  # channel file + 2 FIFOs per bus
    a.shutdown()
    b.shutdown()
    b.shutdown()  # twice is fine
    assert os.listdir(shm_dir) == []
    with pytest.raises(can.CanOperationError):
        a.send(frame(1))

    # a crashed last user leaves files behind; remove_channel clears them
    code = "import can, os; b = can.Bus(interface='canbrake', channel='left'); os._exit(0)"
    subprocess.run([sys.executable, "-c", code], check=True)
    assert list_channels() == ["left"]
    assert remove_channel("left") is True
    assert os.listdir(shm_dir) == []
    assert remove_channel("left") is False

    # reopening after a crash works: the dead entry is reaped
    subprocess.run([sys.executable, "-c", code], check=True)
    with bus("left") as c:
        assert channel_pids("left") == [os.getpid()]
        with pytest.raises(can.CanOperationError, match="still open"):
            remove_channel("left")
        assert remove_channel("left", force=True)
        with pytest.raises(can.CanOperationError, match="removed"):
            c.send(frame(1))
    assert os.listdir(shm_dir) == []


@pytest.mark.parametrize("name", ["a/b", "..", "", ".hidden", "-x", "a b", "x" * 65, "tab\t"])
def test_unsafe_channel_names_are_rejected(shm_dir: Path, name: str) -> None:
    with pytest.raises(can.CanInitializationError, match="channel name"):
        bus(name)
    with pytest.raises(can.CanInitializationError):
        remove_channel(name)
    assert os.listdir(shm_dir) == []


def test_use_after_fork_is_refused(shm_dir: Path) -> None:
    with bus("fork") as b:
        pid = os.fork()
        if pid == 0:  # child
            try:
                b.send(frame(1))
                code = 1
            except can.CanOperationError:
                code = 0
            os._exit(code)
        _, status = os.waitpid(pid, 0)
        assert os.waitstatus_to_exitcode(status) == 0
        assert channel_pids("fork") == [os.getpid()]  # the child did not free our entry


def test_periodic_send_from_a_thread(shm_dir: Path) -> None:
    with bus("per") as tx, bus("per") as rx:
        task = tx.send_periodic(frame(0x42, b"p"), period=0.02, duration=0.2)
        got = [rx.recv(1.0) for _ in range(5)]
        task.stop()
        assert all(m is not None and m.arbitration_id == 0x42 for m in got)


def test_notifier_thread_and_own_frames_from_another_thread(shm_dir: Path) -> None:
    with bus("ntf", receive_own_messages=True) as b:
        reader = can.BufferedReader()
        notifier = can.Notifier(b, [reader], timeout=0.1)
        try:
            time.sleep(0.1)  # the notifier thread blocks in recv on this same bus
            b.send(frame(0x77, b"self"))
            m = reader.get_message(2.0)
            assert m is not None and m.arbitration_id == 0x77 and not m.is_rx
        finally:
            notifier.stop()


def test_logger_and_log_reader_over_the_bus(shm_dir: Path, tmp_path: Path) -> None:
    sent = [frame(0x100 + k, bytes([k] * (k % 9))) for k in range(20)]
    sent.append(frame(0x1FFFFFFF, b"ext", ext=True))
    log = tmp_path / "frames.log"
    with bus("log") as tx, bus("log", backpressure=True) as recorder:
        with can.Logger(log) as writer:
            for m in sent:
                tx.send(m)
            while (m := recorder.recv(0)) is not None:
                writer(m)
    # replay the file onto the bus, like can.player does
    with bus("log", preserve_timestamps=True) as player, bus("log") as rx:
        with can.LogReader(log) as reader:
            replayed = list(reader)
        for m in replayed:
            player.send(m)
        got = [rx.recv(1) for _ in replayed]
    assert [fields(m) for m in got] == [fields(m) for m in sent]
    assert [m.timestamp for m in got] == [m.timestamp for m in replayed]


def test_can_logger_and_can_player_command_lines(shm_dir: Path, tmp_path: Path) -> None:
    sent = [frame(0x200 + k, bytes([k, 0xAA])) for k in range(10)]
    out_log = tmp_path / "out.log"
    logger = subprocess.Popen([sys.executable, "-m", "can.logger", "-i", "canbrake", "-c", "cli",
                               "-f", str(out_log)], stdout=subprocess.DEVNULL, stderr=subprocess.PIPE,
                              preexec_fn=default_sigint)
    try:
        wait_for_pids("cli", 1)
        with bus("cli") as tx:
            for m in sent:
                tx.send(m)
            time.sleep(0.3)
        logger.send_signal(signal.SIGINT)
        assert logger.wait(TIMEOUT) == 0, logger.stderr.read()
    finally:
        logger.kill()
    with can.LogReader(out_log) as reader:
        logged = list(reader)
    assert [fields(m) for m in logged] == [fields(m) for m in sent]

    with bus("cli") as rx:
        subprocess.run([sys.executable, "-m", "can.player", "-i", "canbrake", "-c", "cli", "--ignore-timestamps",
                        str(out_log)], check=True, stdout=subprocess.DEVNULL, timeout=TIMEOUT)
        got = [rx.recv(1) for _ in sent]
    assert [fields(m) for m in got] == [fields(m) for m in sent]
    assert os.listdir(shm_dir) == []


def _wait_for_sleeper(b: MemoryBus, n: int = 1) -> None:
    end = time.monotonic() + TIMEOUT
    while b._q[shm.H_SLEEPERS] < n:
        assert time.monotonic() < end, "the reader never went to sleep"
        time.sleep(0.01)


def test_a_reader_waiting_for_n_frames_is_woken_once_and_loses_none_at_a_timeout(shm_dir: Path) -> None:
    """recv_batch(min_frames=n): the writers count the frames the sleeping reader accepts and
    wake it when the n-th comes (one wake-up for n frames sent one by one, filtered-out frames not
    counted); a timeout with fewer returns those that came, none skipped."""
    with bus("mf", yield_before_sleep=False, can_filters=[{"can_id": 0x100, "can_mask": 0x700}]) as r, \
            bus("mf") as w:
        got: list[list[can.Message]] = []
        t = threading.Thread(target=lambda: got.append(r.recv_batch(TIMEOUT, min_frames=3)))
        t.start()
        _wait_for_sleeper(w)
        for k in range(3):
            w.send(frame(0x101 + k, bytes([k])))
            w.send(frame(0x200, b"x"))  # not accepted: not counted
            time.sleep(0.05)
            assert_sleepers_consistent(w)
        t.join(TIMEOUT)
        assert [m.arbitration_id for m in got[0]] == [0x101, 0x102, 0x103]
        assert r.stats().wakeups == 1 and r.stats().sleeps == 1, r.stats()
        # a timeout with 2 of 3: both returned, in order, nothing skipped
        got.clear()
        t = threading.Thread(target=lambda: got.append(r.recv_batch(0.5, min_frames=3)))
        t.start()
        _wait_for_sleeper(w)
        w.send(frame(0x110, b"a"))
        w.send(frame(0x111, b"b"))
        t.join(TIMEOUT)
        assert r.stats().wakeups == 1, r.stats()  # not woken: it timed out
        rest = got[0] + r.recv_batch(0)
        assert [m.arbitration_id for m in rest] == [0x110, 0x111]
        assert_sleepers_consistent(w)


def test_a_reader_waiting_for_n_frames_keeps_what_came_under_a_flood(shm_dir: Path) -> None:
    """A protected reader (backpressure="accepted") asleep for 3 frames with 1 come: a writer
    going round a small ring with frames it does not accept may not overwrite that one; it
    wakes the reader to read it instead of waiting for it, and nothing is lost."""
    with bus("mff", ring_size=64, backpressure="accepted", yield_before_sleep=False,
             can_filters=[{"can_id": 0x100, "can_mask": 0x700, "extended": False}]) as r, \
            bus("mff", can_filters=[{"can_id": 0x7FF, "can_mask": 0x7FF, "extended": False}]) as w:
        got: list[can.Message] = []
        t = threading.Thread(target=lambda: got.extend(r.recv_batch(3.0, min_frames=3)))  # 2 never come
        t.start()
        _wait_for_sleeper(w)
        w.send(frame(0x101, b"1"))
        for _ in range(20):  # 20 rings of frames the reader does not accept
            w.send_many([frame(0x200, b"x")] * 64, timeout=5.0)
        t.join(TIMEOUT)
        more = r.recv_batch(0)
        assert [m.arbitration_id for m in got + more] == [0x101]
        assert r.stats().frames_lost == 0


def test_a_reader_woken_only_by_one_identifier_keeps_every_frame_before_it(shm_dir: Path) -> None:
    """wake_on (the lockstep recorder: SYNC): asleep, the frames it accepts do not wake it, the
    named one does, and it then has every frame in order; writers going round a small ring wait
    for it (backpressure) and wake it to read instead of overwriting what it has not read."""
    with bus("wko", ring_size=64, backpressure=True, yield_before_sleep=False, wake_on=0x010) as r, \
            bus("wko", can_filters=[{"can_id": 0x7FF, "can_mask": 0x7FF, "extended": False}]) as w:
        got: list[can.Message] = []
        t = threading.Thread(target=lambda: got.extend(r.recv_batch(TIMEOUT)))
        t.start()
        _wait_for_sleeper(w)
        for k in range(5):
            w.send(frame(0x100 + k, bytes([k])))
            time.sleep(0.02)
        assert not got and r.stats().wakeups == 0
        w.send(frame(0x010, b"\x01\x00\x00\x00"))
        t.join(TIMEOUT)
        assert [m.arbitration_id for m in got] == [0x100, 0x101, 0x102, 0x103, 0x104, 0x010]
        assert r.stats().wakeups == 1
        # a flood of 10 rings while it sleeps: held back and woken, nothing lost
        got.clear()
        t = threading.Thread(target=lambda: [got.extend(r.recv_batch(TIMEOUT)) for _ in iter(
            lambda: not got or got[-1].arbitration_id != 0x010, False)])
        t.start()
        _wait_for_sleeper(w)
        for i in range(640):
            w.send(frame(0x200, i.to_bytes(2, "little")), timeout=5.0)
        w.send(frame(0x010, b"\x02\x00\x00\x00"))
        t.join(TIMEOUT)
        assert [int.from_bytes(m.data, "little") for m in got[:-1]] == list(range(640))
        assert r.stats().frames_lost == 0
