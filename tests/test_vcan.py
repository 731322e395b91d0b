"""SocketCAN interoperability on a real vcan0: python-can, can-utils and canbrake's vcan helpers.

Marked ``vcan``: skipped by default, run where vcan0 exists (root), e.g. through the VM:
``../shared/tools/vcan-vm -- python -m pytest -m vcan -q tests/`` (what ``.ci/run-vcan`` does).
"""

from __future__ import annotations

import os
import shutil
import signal
import subprocess
import sys
import tempfile
import time
from collections.abc import Iterator
from pathlib import Path

import can
import pytest

from canbrake.bus.vcan import (
    VcanError,
    check_socketcan_channel,
    explain_socketcan_error,
    open_socketcan_bus,
    vcan_down,
    vcan_up,
)

pytestmark = pytest.mark.vcan

CHANNEL = "vcan0"
PROBE_ID = 0x7FF  # readiness probe frames; never part of the checked traffic


def _frames() -> list[can.Message]:
    """A mix of classic frames: standard and extended ids, DLC 0..8, one remote frame."""
    return [
        can.Message(arbitration_id=0x123, data=bytes.fromhex("DEADBEEF"), is_extended_id=False),
        can.Message(arbitration_id=0x010, data=b"", is_extended_id=False),
        can.Message(arbitration_id=0x18FF50E5, data=bytes(range(8)), is_extended_id=True),
        can.Message(arbitration_id=0x7A0, data=b"\x01\x02\x03", is_extended_id=False),
        can.Message(arbitration_id=0x0C0FFEE, data=b"\xff" * 8, is_extended_id=True),
        can.Message(arbitration_id=0x321, is_remote_frame=True, dlc=4, is_extended_id=False),
    ]


def _key(m: can.Message) -> tuple[int, bool, bool, bytes, int]:
    return (m.arbitration_id, m.is_extended_id, m.is_remote_frame, bytes(m.data), m.dlc)


@pytest.fixture(scope="module", autouse=True)
def _vcan0_ready() -> None:
    """Fail (not skip) with the helper's clear message if vcan0 is unusable: these must run."""
    try:
        check_socketcan_channel(CHANNEL)
    except VcanError as err:
        pytest.fail(f"vcan tests need {CHANNEL}: {err}")


@pytest.fixture
def bus() -> Iterator[can.BusABC]:
    b = can.Bus(interface="socketcan", channel=CHANNEL)
    yield b
    b.shutdown()


def _drain(bus: can.BusABC) -> None:
    while bus.recv(timeout=0.05) is not None:
        pass


def _recv_n(bus: can.BusABC, n: int, timeout: float) -> list[can.Message]:
    """Receive ``n`` frames (probe frames ignored) within ``timeout`` seconds."""
    got: list[can.Message] = []
    deadline = time.monotonic() + timeout
    while len(got) < n and time.monotonic() < deadline:
        m = bus.recv(timeout=0.5)
        if m is not None and m.arbitration_id != PROBE_ID:
            got.append(m)
    return got


def _tool(name: str) -> str:
    path = shutil.which(name)
    if path is None:
        pytest.fail(f"{name} not found: install can-utils (`sudo apt-get install can-utils`)")
    return path


def test_python_can_round_trip(bus: can.BusABC) -> None:
    with can.Bus(interface="socketcan", channel=CHANNEL) as rx:
        _drain(rx)
        sent = _frames()
        for m in sent:
            bus.send(m)
        got = _recv_n(rx, len(sent), timeout=10)
    assert [_key(m) for m in got] == [_key(m) for m in sent]
    assert all(m.channel == CHANNEL for m in got)


def test_open_socketcan_bus_round_trip() -> None:
    with open_socketcan_bus(CHANNEL) as tx, open_socketcan_bus(CHANNEL) as rx:
        _drain(rx)
        tx.send(can.Message(arbitration_id=0x55, data=b"\xaa\x55", is_extended_id=False))
        got = _recv_n(rx, 1, timeout=10)
    assert [_key(m) for m in got] == [(0x55, False, False, b"\xaa\x55", 2)]


def test_cansend_frames_reach_python_can(bus: can.BusABC) -> None:
    _drain(bus)
    cansend = _tool("cansend")
    for spec in ("123#DEADBEEF", "18FF50E5#0001020304050607", "321#R4", "010#"):
        subprocess.run([cansend, CHANNEL, spec], check=True, timeout=30)
    got = _recv_n(bus, 4, timeout=10)
    assert [_key(m) for m in got] == [
        (0x123, False, False, bytes.fromhex("DEADBEEF"), 4),
        (0x18FF50E5, True, False, bytes(range(8)), 8),
        (0x321, False, True, b"", 4),
        (0x010, False, False, b"", 0),
    ]


def _start_candump(out: Path, rcvbuf: int = 0) -> subprocess.Popen[bytes]:
    """Start ``candump -L vcan0 > out`` and return once it provably records frames."""
    candump = _tool("candump")
    fh = out.open("wb")
    opts = ["-r", str(rcvbuf)] if rcvbuf else []
    proc = subprocess.Popen([candump, "-L", *opts, CHANNEL], stdout=fh, stderr=subprocess.PIPE)
    fh.close()
    with can.Bus(interface="socketcan", channel=CHANNEL) as probe:
        deadline = time.monotonic() + 60
        while f"{PROBE_ID:03X}#".encode() not in out.read_bytes():
            if proc.poll() is not None or time.monotonic() > deadline:
                proc.kill()
                pytest.fail(f"candump did not start: {proc.stderr.read()!r}")  # type: ignore[union-attr]
            probe.send(can.Message(arbitration_id=PROBE_ID, data=b"\x00", is_extended_id=False))
            time.sleep(0.2)
    return proc


def _stop(proc: subprocess.Popen[bytes]) -> None:
    proc.send_signal(signal.SIGINT)
    try:
        proc.wait(timeout=10)
    except subprocess.TimeoutExpired:
        proc.kill()
        proc.wait()


def test_candump_log_is_read_by_python_can(bus: can.BusABC, tmp_path: Path) -> None:
    log = tmp_path / "candump.log"
    proc = _start_candump(log)
    try:
        sent = _frames()
        for m in sent:
            bus.send(m)
        end = can.Message(arbitration_id=0x7FE, data=b"END", is_extended_id=False)
        bus.send(end)
        deadline = time.monotonic() + 30
        while b"7FE#454E44" not in log.read_bytes() and time.monotonic() < deadline:
            time.sleep(0.1)
    finally:
        _stop(proc)
    text = log.read_text()
    first = next(line for line in text.splitlines() if "123#" in line)
    # candump -L format: "(seconds.micros) vcan0 123#DEADBEEF"
    assert first.startswith("(") and first.split()[1:] == [CHANNEL, "123#DEADBEEF"]
    read = [m for m in can.LogReader(log) if m.arbitration_id not in (PROBE_ID, 0x7FE)]
    assert [_key(m) for m in read] == [_key(m) for m in sent]
    assert all(m.channel == CHANNEL for m in read)
    stamps = [m.timestamp for m in read]
    assert stamps == sorted(stamps) and abs(stamps[0] - time.time()) < 600


def _after_python_can_log(m: can.Message) -> tuple[int, bool, bool, bytes, int]:
    """What survives a python-can .log: its writer (4.6) drops a remote frame's DLC ("321#R")."""
    key = _key(m)
    return key[:4] + (0,) if m.is_remote_frame else key


def _write_log(path: Path, frames: list[can.Message]) -> None:
    """Write frames with python-can's own writer (.log = candump -L format), 1 ms apart."""
    t0 = time.time()
    with can.Logger(path) as writer:
        for i, m in enumerate(frames):
            m.timestamp = t0 + i * 0.001
            m.channel = CHANNEL
            writer.on_message_received(m)


def test_canplayer_replays_python_can_log(bus: can.BusABC, tmp_path: Path) -> None:
    log = tmp_path / "written.log"
    sent = _frames()
    _write_log(log, sent)
    assert log.read_text().splitlines()[0].split()[1] == CHANNEL
    _drain(bus)
    subprocess.run([_tool("canplayer"), "-I", str(log)], check=True, timeout=60)
    got = _recv_n(bus, len(sent), timeout=10)
    assert [_key(m) for m in got] == [_after_python_can_log(m) for m in sent]


def test_python_can_player_replays_log(bus: can.BusABC, tmp_path: Path) -> None:
    log = tmp_path / "written.log"
    sent = _frames()
    _write_log(log, sent)
    _drain(bus)
    proc = subprocess.Popen(
        [sys.executable, "-m", "can.player", "-i", "socketcan", "-c", CHANNEL, str(log)],
        stdout=subprocess.PIPE,
        stderr=subprocess.STDOUT,
    )
    got: list[can.Message] = []
    deadline = time.monotonic() + 240  # the emulated guest takes ~20 s just to import can
    while len(got) < len(sent) and time.monotonic() < deadline:
        got += _recv_n(bus, len(sent) - len(got), timeout=1)
        if proc.poll() is not None:
            got += _recv_n(bus, len(sent) - len(got), timeout=2)
            break
    out, _ = proc.communicate(timeout=60)
    assert proc.returncode == 0, out.decode(errors="replace")
    assert [_key(m) for m in got] == [_after_python_can_log(m) for m in sent]


def test_vcan_up_creates_and_raises_vcan2() -> None:
    assert os.geteuid() == 0, "run as root (the vcan VM does)"
    vcan_down("vcan2")
    try:
        assert vcan_up("vcan2") == "vcan2 created and up"
        check_socketcan_channel("vcan2")
        assert vcan_up("vcan2") == "vcan2 is already up"
        with can.Bus(interface="socketcan", channel="vcan2") as a, open_socketcan_bus("vcan2") as b:
            a.send(can.Message(arbitration_id=0x42, data=b"\x42", is_extended_id=False))
            assert [_key(m) for m in _recv_n(b, 1, timeout=10)] == [(0x42, False, False, b"\x42", 1)]
        subprocess.run(["ip", "link", "set", "down", "vcan2"], check=True)
        with pytest.raises(VcanError) as down:
            check_socketcan_channel("vcan2")
        assert down.value.kind == "down" and "ip link set up vcan2" in str(down.value)
        assert vcan_up("vcan2") == "vcan2 raised"
        check_socketcan_channel("vcan2")
    finally:
        vcan_down("vcan2")
    assert not Path("/sys/class/net/vcan2").exists()


def test_missing_channel_gives_clear_message() -> None:
    with pytest.raises(VcanError) as missing:
        check_socketcan_channel("vcan9")
    assert missing.value.kind == "missing"
    assert "vcan9 does not exist" in str(missing.value)
    assert "canbrake vcan up vcan9" in str(missing.value)
    with pytest.raises(VcanError) as opened:
        open_socketcan_bus("vcan9")
    assert opened.value.kind == "missing"
    # python-can's own error for the same thing maps to the same message
    with pytest.raises(OSError) as raw:
        can.Bus(interface="socketcan", channel="vcan9")
    assert explain_socketcan_error(raw.value, "vcan9").kind == "missing"


def test_not_a_can_interface_gives_clear_message() -> None:
    with pytest.raises(VcanError) as err:
        check_socketcan_channel("lo")
    assert err.value.kind == "not-can" and "--channel vcan0" in str(err.value)
    with pytest.raises(VcanError) as up:
        vcan_up("lo")
    assert up.value.kind == "not-can"



# --------------------------------------------------------------------------- canbrake run on vcan0
#
# One `canbrake run --bus socketcan --channel vcan0` (the CLI's main() in this process: its node
# processes are real OS processes on vcan0 as a user's are) with candump recording beside it and
# frames injected with cansend while it runs, and one run of the same scenario and seed on the
# in-memory bus (through the API, whose forkserver the later runs reuse). The guest
# CPU is emulated (~45 s to import numpy/scipy/pydantic/cantools, a few ticks per second), so
# the runs are short: CANBRAKE_VCAN_RUN_DURATION seconds of simulated time (default 0.1 s, 100
# lockstep ticks, ~2,000 frames).

SCENARIO = Path(__file__).resolve().parents[1] / "scenarios" / "chen2023_case1_fine_rail.yaml"
SEED = "7"
DURATION = os.environ.get("CANBRAKE_VCAN_RUN_DURATION", "0.1")
INJECT_ID = 0x1ABCDEF  # extended id: not in canbrake's DBC
ROGUE_ID = 0x081  # BRAKE_CMD_C1, sent by "someone else" with a wrong E2E checksum
START_TIMEOUT_S = os.environ.get("CANBRAKE_START_TIMEOUT_S", "900")


def _rogue_brake_cmd(n: int) -> str:
    """cansend spec of a full-force BRAKE_CMD_C1 whose CRC byte is deliberately wrong."""
    from canbrake.bus.e2e import e2e_crc

    payload = bytearray([0, n % 15, 0xFF, 0xFF, 0x7F])
    payload[0] = e2e_crc(ROGUE_ID, payload) ^ 0x5A
    return f"{ROGUE_ID:03X}#{payload.hex().upper()}"


def _run_args(bus: str, out: Path) -> list[str]:
    args = ["run", str(SCENARIO), "--bus", bus, "--seed", SEED, "--duration", DURATION,
            "--out", str(out), "--no-plots"]
    return args + (["--channel", CHANNEL] if bus == "socketcan" else [])


def _check(proc: subprocess.CompletedProcess[str]) -> None:
    assert proc.returncode == 0, f"{proc.args}\n{proc.stdout}\n{proc.stderr}"


def _log_rows(path: Path, drop: set[str] = frozenset()) -> list[tuple[str, ...]]:  # type: ignore[assignment]
    """frames.log lines without the channel column: (timestamp, id#data, flags...); frames whose
    ``id#data`` is in ``drop`` left out."""
    rows = []
    for line in path.read_text().splitlines():
        parts = line.split()
        if parts and parts[2] not in drop:
            rows.append((parts[0], *parts[2:]))
    return rows


def _id_data(msgs: list[can.Message]) -> list[tuple[int, bool, bytes]]:
    return sorted((m.arbitration_id, m.is_extended_id, bytes(m.data)) for m in msgs)


@pytest.fixture(scope="module")
def socketcan_run(tmp_path_factory: pytest.TempPathFactory) -> dict[str, object]:
    """``canbrake run --bus socketcan --channel vcan0`` (the CLI's main(), in this process: a
    second Python process would pay the guest's ~45 s of imports again, and so would its
    forkserver) with ``candump -L vcan0`` recording beside it; once the plant's first SYNC is on
    the wire, a thread injects a foreign extended frame and a rogue brake command (wrong CRC) with
    ``cansend`` in turn until the run ends."""
    import threading

    from canbrake.cli import main

    root = tmp_path_factory.mktemp("socketcan_run")
    out, dump = root / "run", root / "candump.log"
    candump = _start_candump(dump, rcvbuf=16 << 20)
    os.environ.setdefault("CANBRAKE_START_TIMEOUT_S", START_TIMEOUT_S)
    sent: list[str] = []
    done = threading.Event()
    # canbrake monitor, can.viewer, cantools monitor on vcan0: opt-in, their start (~45 s of imports in
    # the VM) comes before the run and does not fit CI's VM budget; CANBRAKE_VCAN_MONITOR=1 turns it on
    viewers = _start_viewers(root) if os.environ.get("CANBRAKE_VCAN_MONITOR") == "1" else None

    def inject() -> None:
        with can.Bus(interface="socketcan", channel=CHANNEL,
                     can_filters=[{"can_id": 0x010, "can_mask": 0x7FF, "extended": False}]) as watch:
            started = False
            while not done.is_set():
                if not started:
                    started = watch.recv(timeout=0.5) is not None
                    continue
                n = len(sent)
                spec = _rogue_brake_cmd(n) if n % 2 else f"{INJECT_ID:08X}#C0FFEE{n:02X}"
                subprocess.run([_tool("cansend"), CHANNEL, spec], check=True, timeout=30)
                sent.append(spec)
                done.wait(0.3)

    injector = threading.Thread(target=inject, daemon=True)
    try:
        t0 = time.monotonic()
        injector.start()
        try:
            rc = main(_run_args("socketcan", out))
        finally:
            done.set()
            injector.join(60)
        wall = time.monotonic() - t0
        time.sleep(1.0)  # let candump write the last frames
    finally:
        _stop(candump)
        shown = _stop_viewers(viewers) if viewers is not None else None
    assert not injector.is_alive()
    proc = subprocess.CompletedProcess(["canbrake", *_run_args("socketcan", out)], rc, "", "")
    return {"proc": proc, "out": out, "candump": dump, "wall": wall, "sent": sent, "viewers": shown}


#: the viewers' text once they are up (can.viewer's column header, cantools monitor's status line)
_VIEWER_READY = {"viewer": "Count", "cantools": "Received:"}


def _start_viewers(root: Path) -> dict[str, object]:
    """``canbrake monitor`` (plain output, the way a script or CI runs it) and, when tmux is there,
    python-can's ``can.viewer`` and ``cantools monitor`` in tmux panes, all on vcan0; returns once
    each listens (a Python process needs ~45 s to start in the VM: they start side by side)."""
    mon_out, mon_err = (root / "monitor.out").open("w"), (root / "monitor.err").open("w")
    mon = subprocess.Popen([sys.executable, "-m", "canbrake", "monitor", "--channel", CHANNEL, "--scenario",
                            str(SCENARIO), "--duration", "1500"], stdout=mon_out, stderr=mon_err, text=True,
                           # plain output to a file is 80 columns wide by default (rich): the table's
                           # headers would wrap; a terminal this wide shows them on one line
                           env={**os.environ, "COLUMNS": "200"})
    mon_out.close()
    mon_err.close()
    panes: dict[str, str] = {}
    # tmux's socket must be on a file system that holds sockets (the VM's /tmp is 9p: it cannot)
    os.environ.setdefault("TMUX_TMPDIR", tempfile.gettempdir())
    if shutil.which("tmux"):
        tag = f"{os.getpid()}"
        py = f"PYTHONPATH={Path(__file__).resolve().parents[1]} {sys.executable}"
        cmds = {"viewer": f"{py} -m can.viewer -i socketcan -c {CHANNEL}",
                "cantools": f"{py} -c 'import sys, cantools; sys.argv[0] = \"cantools\"; cantools._main()' "
                            f"monitor -i socketcan -c {CHANNEL} {SCENARIO.parents[1] / 'dbc' / 'canbrake.dbc'}"}
        for name, cmd in cmds.items():
            panes[name] = f"cb{name}{tag}"
            subprocess.run(["tmux", "new-session", "-d", "-s", panes[name], "-x", "150", "-y", "60",
                            cmd + "; sleep 3600"], check=True)
    deadline = time.monotonic() + 600
    while time.monotonic() < deadline and mon.poll() is None:
        up = "listening on" in (root / "monitor.err").read_text()
        up = up and all(_VIEWER_READY[n] in _pane(s) for n, s in panes.items())
        if up:
            break
        time.sleep(1)
    return {"monitor": mon, "root": root, "panes": panes}


def _pane(session: str) -> str:
    return subprocess.run(["tmux", "capture-pane", "-p", "-t", session], capture_output=True, text=True).stdout


def _stop_viewers(v: dict[str, object]) -> dict[str, object]:
    """Wait for ``canbrake monitor`` to stop by itself at the end-of-run SYNC (killed after 300 s),
    capture the panes and close them; returns what each showed."""
    mon: subprocess.Popen[str] = v["monitor"]  # type: ignore[assignment]
    try:
        rc = mon.wait(timeout=300)
    except subprocess.TimeoutExpired:
        mon.kill()
        rc = mon.wait()
    root: Path = v["root"]  # type: ignore[assignment]
    shown: dict[str, object] = {"monitor_rc": rc, "monitor": (root / "monitor.out").read_text(),
                                "monitor_err": (root / "monitor.err").read_text()}
    panes: dict[str, str] = v["panes"]  # type: ignore[assignment]
    for name, session in panes.items():
        shown[name] = _pane(session)
        subprocess.run(["tmux", "kill-session", "-t", session], capture_output=True)
    return shown


@pytest.fixture(scope="module")
def memory_run(tmp_path_factory: pytest.TempPathFactory) -> dict[str, object]:
    """The same scenario and seed on the in-memory bus, through the API (the CLI's run path is the
    socketcan run's): run_scenario leaves multiprocessing's forkserver running, so the runs after
    it (every scenario, the C ECU) fork their nodes from it instead of paying the guest's imports
    again (tests/conftest.py stops it at the end of the session)."""
    from canbrake.run import run_scenario
    from canbrake.scenario import load_scenario

    out = tmp_path_factory.mktemp("memory_run") / "run"
    os.environ.setdefault("CANBRAKE_START_TIMEOUT_S", START_TIMEOUT_S)
    scn = load_scenario(SCENARIO, overrides={"seed": int(SEED), "duration_s": float(DURATION)})
    s = run_scenario(scn, out, backend="memory", plots=False)
    rc = 0 if s["status"] == "ok" and s.get("verdict") != "diverged" else 1
    return {"proc": subprocess.CompletedProcess(["canbrake", *_run_args("memory", out)], rc, "", s.get("message", "")),
            "out": out}


def _injected_specs(run: dict[str, object]) -> set[str]:
    return set(run["sent"])  # type: ignore[arg-type]


def test_canbrake_run_on_vcan0_exits_0(socketcan_run: dict[str, object]) -> None:
    _check(socketcan_run["proc"])  # type: ignore[arg-type]
    out = socketcan_run["out"]
    assert isinstance(out, Path)
    for name in ("frames.log", "signals.csv", "summary.json", "scenario.yaml", "canbrake.dbc"):
        assert (out / name).is_file(), name
    first = (out / "frames.log").read_text().splitlines()[0]
    assert first.split()[1] == CHANNEL


def test_monitor_and_viewers_follow_the_run_on_vcan0(socketcan_run: dict[str, object]) -> None:
    """Attached to vcan0 before the run: ``canbrake monitor`` stops by itself at the end-of-run SYNC
    and shows the train at the run's last period; ``can.viewer`` and ``cantools monitor`` (tmux)
    show the run's frames decoded or raw."""
    import json

    if socketcan_run["viewers"] is None:
        pytest.skip("CANBRAKE_VCAN_MONITOR=1 attaches the viewers to the vcan0 run (not in CI's VM budget)")
    _check(socketcan_run["proc"])  # type: ignore[arg-type]
    out = socketcan_run["out"]
    assert isinstance(out, Path)
    ticks = json.loads((out / "summary.json").read_text())["ticks"]
    shown: dict[str, object] = socketcan_run["viewers"]  # type: ignore[assignment]
    text = str(shown["monitor"])
    assert shown["monitor_rc"] == 0, shown["monitor_err"]
    # a live viewer in the slow emulated guest may lose frames from its socket's receive queue: it
    # must show the train at the run's last tick, not necessarily have counted every period
    assert f"train — tick {ticks - 1}" in text and "periods " in text, text
    assert "speed (km/h)" in text and "Δl to next (cm)" in text
    if "viewer" in shown:
        # the emulated guest's viewers drop frames from their sockets (counts of 50-90 of 100): each must
        # show SYNC and REFERENCE and brake commands of some car, not necessarily of car 1
        viewer = str(shown["viewer"])
        assert all(f"0x{i:03X}" in viewer for i in (0x010, 0x011)), viewer
        assert any(f"0x{0x081 + c:03X}" in viewer for c in range(6)), viewer
        assert "BRAKE_CMD_C" in str(shown["cantools"]) and "Received:" in str(shown["cantools"]), shown["cantools"]


def test_socketcan_run_signals_equal_memory_run(
    socketcan_run: dict[str, object], memory_run: dict[str, object]
) -> None:
    """Same seed, same signals.csv to the byte, rogue brake commands and all (they are rejected)."""
    _check(socketcan_run["proc"])  # type: ignore[arg-type]
    _check(memory_run["proc"])  # type: ignore[arg-type]
    sc, mem = socketcan_run["out"], memory_run["out"]
    assert isinstance(sc, Path) and isinstance(mem, Path)
    assert (sc / "signals.csv").read_bytes() == (mem / "signals.csv").read_bytes()


def test_socketcan_run_frames_equal_memory_run(
    socketcan_run: dict[str, object], memory_run: dict[str, object]
) -> None:
    """Same payloads in the same order (frames injected with cansend aside); the timestamps are
    equal up to the control period of the first injected frame (its wire time shifts the later
    stamps, and an overloaded period's stamps are scaled to fit the period, so the frames before
    it in the same period move too)."""
    _check(socketcan_run["proc"])  # type: ignore[arg-type]
    _check(memory_run["proc"])  # type: ignore[arg-type]
    sc, mem = socketcan_run["out"], memory_run["out"]
    assert isinstance(sc, Path) and isinstance(mem, Path)
    injected = _injected_specs(socketcan_run)
    sc_all = _log_rows(sc / "frames.log")
    sc_rows, mem_rows = _log_rows(sc / "frames.log", injected), _log_rows(mem / "frames.log")
    assert len(mem_rows) > 1000
    first_injected = next((i for i, r in enumerate(sc_all) if r[1] in injected), len(sc_all))
    assert first_injected < len(sc_all), "no injected frame in the socketcan run's frames.log"
    period_start = max((i for i, r in enumerate(sc_all[:first_injected]) if r[1].startswith("010#")), default=0)
    assert sc_all[:period_start] == mem_rows[:period_start]
    assert [r[1:] for r in sc_rows] == [r[1:] for r in mem_rows], (
        f"frames.log payloads differ: socketcan {len(sc_rows)} frames, memory {len(mem_rows)}"
    )


def test_candump_beside_run_sees_the_same_frames(socketcan_run: dict[str, object]) -> None:
    from canbrake.nodes.recorder import is_sim_control

    _check(socketcan_run["proc"])  # type: ignore[arg-type]
    out, dump = socketcan_run["out"], socketcan_run["candump"]
    assert isinstance(out, Path) and isinstance(dump, Path)
    injected = _injected_specs(socketcan_run)

    def ours(m: can.Message) -> bool:
        spec = f"{m.arbitration_id:08X}#" if m.is_extended_id else f"{m.arbitration_id:03X}#"
        return (m.arbitration_id != PROBE_ID and spec + bytes(m.data).hex().upper() not in injected
                and (m.is_extended_id or not is_sim_control(m.arbitration_id)))  # never in frames.log

    wire = [m for m in can.LogReader(dump) if ours(m)]
    logged = [m for m in can.LogReader(out / "frames.log") if ours(m)]
    assert len(logged) > 1000
    assert len(wire) == len(logged), f"candump saw {len(wire)} frames, frames.log has {len(logged)}"
    assert _id_data(wire) == _id_data(logged)


def test_canbrake_decode_reads_candump_log(socketcan_run: dict[str, object],
                                          capsys: pytest.CaptureFixture[str]) -> None:
    from canbrake.cli import main

    _check(socketcan_run["proc"])  # type: ignore[arg-type]
    out, dump = socketcan_run["out"], socketcan_run["candump"]
    assert isinstance(out, Path) and isinstance(dump, Path)
    assert main(["decode", str(dump), "--dbc", str(out / "canbrake.dbc")]) == 0
    lines = [ln for ln in capsys.readouterr().out.splitlines() if f" {CHANNEL} " in ln]
    assert any("SYNC(" in ln for ln in lines), lines[:20]
    assert any("BRAKE_CMD_C1(" in ln for ln in lines)
    assert any("STATE_C6(" in ln for ln in lines)


def test_cansend_during_run_is_recorded(socketcan_run: dict[str, object]) -> None:
    """Every frame sent with cansend is on the wire (candump); those sent while the recorder ran
    are in frames.log with their exact payload."""
    _check(socketcan_run["proc"])  # type: ignore[arg-type]
    out, dump = socketcan_run["out"], socketcan_run["candump"]
    assert isinstance(out, Path) and isinstance(dump, Path)
    sent: list[str] = socketcan_run["sent"]  # type: ignore[assignment]
    assert len(sent) >= 2, f"only {len(sent)} frames injected before the run ended"
    wire = [ln.split()[2] for ln in dump.read_text().splitlines() if ln.split()[2] in sent]
    logged = [r[1] for r in _log_rows(out / "frames.log") if r[1] in sent]
    assert sorted(wire) == sorted(sent)
    assert logged and set(logged) <= set(sent)
    assert any(s.startswith(f"{INJECT_ID:08X}#") for s in logged)
    assert any(s.startswith(f"{ROGUE_ID:03X}#") for s in logged)


def test_rogue_brake_command_is_rejected_by_the_plant(socketcan_run: dict[str, object]) -> None:
    """A BRAKE_CMD_C1 from outside with a wrong E2E checksum reaches the plant, which counts it
    as corrupted and does not apply it (signals.csv equals the memory run's: test above)."""
    import json

    _check(socketcan_run["proc"])  # type: ignore[arg-type]
    out = socketcan_run["out"]
    assert isinstance(out, Path)
    rogue = {s for s in socketcan_run["sent"] if s.startswith(f"{ROGUE_ID:03X}#")}  # type: ignore[attr-defined]
    logged = [r[1] for r in _log_rows(out / "frames.log") if r[1] in rogue]
    summary = json.loads((out / "summary.json").read_text())
    corrupted = summary["frames"]["commands_corrupted"]
    assert 1 <= corrupted <= len(logged), (corrupted, len(logged))
    assert summary["frames"]["commands_received"] == 6 * summary["ticks"]


#: one or two scenarios of each train model on vcan0: the emulated guest needs ~25 s per scenario
#: and CI's VM budget is 14 min. Every scenario is run byte-identically on the in-process,
#: python-can virtual and in-memory buses in the default suite (test_engine, test_li2024_engine,
#: test_cai2014); the 106-ECU ECP train takes minutes in the guest and is left to those.
# one per train model (coupled metro, a user's EMU, adhesion high-speed, heavy haul): CI's VM budget
VCAN_SCENARIOS = ["chen2023_case2_poor_rail.yaml", "emu8_example.yaml", "cai2014_case4.yaml", "li2024_rbfnn_smc_ndo.yaml"]


@pytest.mark.parametrize("scenario", VCAN_SCENARIOS)
def test_every_scenario_runs_on_vcan0(scenario: str, tmp_path: Path, memory_run: dict[str, object]) -> None:
    """The other scenarios, briefly (0.02 s or two control periods), through the API on vcan0: the
    run ends ok (what makes `canbrake run` exit 0), and the same signals.csv and frames as the
    in-process engine for the same seed. (``memory_run`` first: its forkserver is reused, so these
    runs do not pay the guest's import time again.)"""
    from canbrake.run import run_scenario
    from canbrake.scenario import load_scenario

    path = SCENARIO.parent / scenario
    period = load_scenario(path).control_period_s  # at least two control periods
    overrides = {"seed": int(SEED), "duration_s": max(0.02, 2 * period)}
    summaries = {}
    for name, backend, kw in (("sc", "socketcan", {"channel": CHANNEL}), ("ip", "inprocess", {})):
        summaries[name] = s = run_scenario(load_scenario(path, overrides=overrides), tmp_path / name,
                                           backend=backend, plots=False, **kw)
        assert s["status"] == "ok" and s.get("verdict") != "diverged", (backend, s.get("message"), s.get("verdict"))
    assert summaries["sc"]["ticks"] == summaries["ip"]["ticks"] >= 2
    assert (tmp_path / "sc" / "signals.csv").read_bytes() == (tmp_path / "ip" / "signals.csv").read_bytes()
    assert _log_rows(tmp_path / "sc" / "frames.log") == _log_rows(tmp_path / "ip" / "frames.log")


def test_readme_canplayer_line_replays_a_memory_run(memory_run: dict[str, object]) -> None:
    """The README's ``canplayer -I runs/c1/frames.log vcan0=canbrake0``, as written there, replays a
    run of the in-memory bus started by the CLI (random channel) onto vcan0: ``candump -L vcan0``
    records every frame of its frames.log, in order (issue 28: the log named the random channel and
    canplayer, mapping ``canbrake0``, replayed nothing)."""
    import shlex

    _check(memory_run["proc"])  # type: ignore[arg-type]
    log = memory_run["out"] / "frames.log"  # type: ignore[operator]
    readme = Path(__file__).resolve().parents[1] / "README.md"
    line = next(ln for ln in readme.read_text().splitlines() if ln.startswith("canplayer -I runs/c1/frames.log"))
    argv = [str(log) if a == "runs/c1/frames.log" else a for a in shlex.split(line.split("#")[0])]
    assert argv[-1] == f"{CHANNEL}=canbrake0", argv
    dump = log.parent / "replayed.log"
    proc = _start_candump(dump, rcvbuf=16 << 20)
    try:
        subprocess.run([_tool("canplayer"), *argv[1:]], check=True, timeout=120)
        time.sleep(1.0)  # let candump write the last frames
    finally:
        _stop(proc)
    logged = [(m.arbitration_id, bytes(m.data)) for m in can.LogReader(log)]
    replayed = [(m.arbitration_id, bytes(m.data)) for m in can.LogReader(dump) if m.arbitration_id != PROBE_ID]
    assert len(logged) > 1000
    assert replayed == logged
