"""canbrake monitor: the state it derives from frames (against the run's own traces), the view
rendered headless by rich, attached to a live run on the in-memory bus, and in tmux."""
from __future__ import annotations

import io
import shutil
import subprocess
import sys
import threading
import time
import uuid

import can
import pytest
from rich.console import Console

import canbrake
from canbrake.bus import dbc
from canbrake.bus.codec import FrameCodec
from canbrake.bus.timing import frame_bits
from canbrake.monitor import MonitorState, monitor, open_monitor_bus, render, spacing_from_scenario

from conftest import ROOT


@pytest.fixture(scope="module")
def finished(tmp_path_factory):
    out = tmp_path_factory.mktemp("mon")
    return canbrake.run("chen2023_case1_fine_rail", out=out, bus="inprocess", duration_s=0.05, plots=False)


def test_state_from_a_runs_frames_matches_its_traces(finished):
    scn = canbrake.load_scenario(finished.run_dir / "scenario.yaml")
    st = MonitorState(finished.database, bitrate_bps=scn.bus.bitrate_bps, spacing_m=spacing_from_scenario(scn))
    for m in finished.frames():
        st.feed(m)
    snap = st.snapshot()
    assert snap["tick"] == 49 and snap["periods"] == 49 and snap["missed_commands"] == 0
    for car in (1, 6):
        state = finished.decoded(f"STATE_C{car}").iloc[-1]
        cmd = finished.decoded(f"BRAKE_CMD_C{car}").iloc[-1]
        assert snap["cars"][car]["speed_mps"] == pytest.approx(state["Speed"])
        assert snap["cars"][car]["brake_force_n"] == pytest.approx(cmd["BrakeForce"])
        assert snap["cars"][car]["e2e_errors"] == 0
    # Δl from the STATE positions = the plant's deflection (0.1 mm position quantisation, one tick apart)
    sig = finished.signals
    for j, d in enumerate(snap["deflections_m"], start=1):
        assert d == pytest.approx(sig[f"deflection_m_k{j}"].iloc[-2], abs=5e-4)
    # the load is the last second's wire bits at the bit rate: here the whole run's frames
    frames = list(finished.frames())
    bits = sum(frame_bits(m.arbitration_id, m.is_extended_id, m.dlc, bytes(m.data), stuffing="actual") for m in frames)
    span = frames[-1].timestamp - frames[0].timestamp
    assert snap["bus_load"] == pytest.approx(bits / span / scn.bus.bitrate_bps)
    assert sum(snap["rates_hz"].values()) == pytest.approx(len(frames) / span)


def test_deflection_compares_cars_at_the_same_period(finished):
    """Viewed between two SYNCs (some cars have sent this period's STATE, some not), Δl still compares
    positions of one period: never the 2.5 cm that one period at 90 km/h and 1 ms would read as."""
    scn = canbrake.load_scenario(finished.run_dir / "scenario.yaml")
    truth = float(finished.signals.filter(like="deflection_m_k").abs().to_numpy().max())
    for spacing in (spacing_from_scenario(scn), None):  # None: the first gap seen is the nominal one
        st = MonitorState(finished.database, bitrate_bps=scn.bus.bitrate_bps, spacing_m=spacing)
        worst = 0.0
        for m in finished.frames():
            st.feed(m)
            worst = max([worst, *(abs(d) for d in st.deflections_m() if d == d)])
        assert worst <= 2 * truth + 5e-4, (spacing is None, worst, truth)


def test_counts_e2e_errors_and_missing_commands():
    db = dbc.build_database(2)
    codec = FrameCodec(db)
    st = MonitorState(db)

    def send(name: str, values: dict, t: float, **kw) -> None:
        m = db.get_message_by_name(name)
        st.feed(can.Message(timestamp=t, arbitration_id=m.frame_id, is_extended_id=False,
                            data=codec[name].encode(values, **kw)))

    send("SYNC", {"Tick": 0}, 0.0)
    send("BRAKE_CMD_C1", {"Status": 0, "BrakeForce": 1000.0}, 0.0005, counter=0)
    good = codec["BRAKE_CMD_C2"].encode({"Status": 0, "BrakeForce": 2000.0}, counter=0)
    bad = bytes([good[0] ^ 0xFF]) + good[1:]
    st.feed(can.Message(timestamp=0.0006, arbitration_id=db.get_message_by_name("BRAKE_CMD_C2").frame_id,
                        is_extended_id=False, data=bad))
    send("SYNC", {"Tick": 1}, 0.001)
    snap = st.snapshot()
    assert snap["cars"][2]["e2e_errors"] == 1 and snap["cars"][1]["e2e_errors"] == 0
    assert snap["cars"][1]["brake_force_n"] == pytest.approx(1000.0)
    assert snap["missed_commands"] == 1  # car 2's only command failed its CRC


def test_view_renders_headless(finished):
    st = MonitorState(finished.database, bitrate_bps=1_000_000)
    for m in finished.frames():
        st.feed(m)
    con = Console(record=True, width=140, file=io.StringIO())
    con.print(render(st.snapshot(), "canbrake monitor — test"))
    text = con.export_text()
    assert "canbrake monitor — test" in text and "train — tick 49" in text
    assert "bus load" in text and "ECU3" in text and "PLANT" in text
    speed_c3 = finished.decoded("STATE_C3").iloc[-1]["Speed"] * 3.6
    assert f"{speed_c3:.2f}" in text


@pytest.mark.slow
def test_attaches_to_a_live_run_on_the_memory_bus(tmp_path):
    """Opened before the run on the same channel, the monitor sees every frame the recorder logs."""
    channel = f"montest-{uuid.uuid4().hex[:6]}"
    bus = open_monitor_bus(channel, None)
    st = MonitorState(dbc.build_database(6), bitrate_bps=1_000_000)
    con = Console(file=io.StringIO(), width=120)
    result: dict = {}
    th = threading.Thread(target=lambda: result.update(monitor(bus, st, console=con, duration_s=120)), daemon=True)
    th.start()
    try:
        r = canbrake.run("chen2023_case1_fine_rail", out=tmp_path, channel=channel, duration_s=0.05, plots=False)
        th.join(60)
    finally:
        bus.shutdown()
    assert not th.is_alive(), "the monitor did not stop at the end-of-run SYNC"
    assert result["periods"] == 49 and result["frames"] == r.summary["frames"]["on_bus"]


@pytest.mark.slow
@pytest.mark.skipif(shutil.which("tmux") is None, reason="tmux not installed")
def test_monitor_can_viewer_and_cantools_monitor_in_tmux(tmp_path):
    """In real terminals (tmux), while one run goes on an in-memory channel: `canbrake monitor`
    shows the train, and python-can's `can.viewer` and `cantools monitor` show its frames."""
    channel = f"montmux-{uuid.uuid4().hex[:6]}"
    tag = uuid.uuid4().hex[:6]
    py = f"PYTHONPATH={ROOT} {sys.executable}"
    cantools_cli = f"{py} -c 'import sys, cantools; sys.argv[0] = \"cantools\"; cantools._main()'"
    views = {
        f"cbmon{tag}": (f"{py} -m canbrake monitor --channel {channel} --duration 120",
                        ["periods 49", "train — tick 49"]),
        f"cbview{tag}": (f"{py} -m can.viewer -i canbrake -c {channel}", ["0x010", "0x011", "0x0C1"]),
        f"cbcant{tag}": (f"{cantools_cli} monitor -i canbrake -c {channel} {ROOT / 'dbc' / 'canbrake.dbc'}",
                         ["BRAKE_CMD_C1(", "Received:"]),
    }
    for session, (cmd, _) in views.items():
        subprocess.run(["tmux", "new-session", "-d", "-s", session, "-x", "140", "-y", "50", cmd + "; sleep 60"],
                       check=True)
    try:
        time.sleep(4)
        canbrake.run("chen2023_case1_fine_rail", out=tmp_path, channel=channel, duration_s=0.05, plots=False)
        for session, (_cmd, wanted) in views.items():
            deadline = time.time() + 30
            pane = ""
            while time.time() < deadline:
                pane = subprocess.run(["tmux", "capture-pane", "-p", "-t", session], capture_output=True,
                                      text=True).stdout
                if all(w in pane for w in wanted):
                    break
                time.sleep(0.5)
            assert all(w in pane for w in wanted), f"{session}:\n{pane}"
    finally:
        for session in views:
            subprocess.run(["tmux", "kill-session", "-t", session], capture_output=True)
        from canbrake.bus import memory_shm as shm

        for _ in range(50):  # the viewers die of SIGHUP without closing their bus: remove the channel left
            info = {it["channel"]: it for it in shm.channel_info()}
            if channel not in info:
                break
            if info[channel]["stale"] is True:
                shm.remove_channel(channel)
                break
            time.sleep(0.1)


def test_monitor_says_when_no_run_is_on_its_channel_yet(tmp_path, capsys):
    """A mistyped in-memory channel shows at once (the monitor still waits: a run may start later);
    with another bus open on the channel, no such line."""
    from canbrake.cli import main

    name = f"mon-{uuid.uuid4().hex[:6]}"
    assert main(["monitor", "--channel", name, "--duration", "0.05"]) == 0
    err = capsys.readouterr().err
    assert f"no run on channel {name!r} yet" in err and f"listening on {name}" in err
    other = can.Bus(interface="canbrake", channel=name)
    try:
        assert main(["monitor", "--channel", name, "--duration", "0.05"]) == 0
    finally:
        other.shutdown()
    err = capsys.readouterr().err
    assert "no run on channel" not in err and f"listening on {name}" in err


def test_deflection_bound_is_the_scenarios(finished):
    """The view judges Δl against the scenario's verdict bound (analysis.verdict.deflection_bound_m),
    not a fixed 1 cm; without a scenario it marks no deflection as over a bound."""
    from canbrake.analysis.verdict import deflection_bound_m

    scn = canbrake.load_scenario(finished.run_dir / "scenario.yaml")
    bound = deflection_bound_m(scn)
    assert bound is not None          # Chen's theta bounds (1 cm)

    def shown(b):
        st = MonitorState(finished.database, bitrate_bps=scn.bus.bitrate_bps, spacing_m=spacing_from_scenario(scn),
                          bound_m=b)
        for m in finished.frames():
            st.feed(m)
        console = Console(file=io.StringIO(), width=200, color_system="truecolor", force_terminal=True)
        console.print(render(st.snapshot()))
        return console.file.getvalue()

    tiny = shown(1e-9)                # every deflection over the bound: drawn red
    assert "\x1b[1;31m" in tiny.split("nodes")[0] and "±1e-07 cm" in tiny
    ok = shown(bound)                 # the run stays inside its bound: none red, the bound printed
    assert "\x1b[1;31m" not in ok.split("nodes")[0] and f"±{bound * 100:g} cm" in ok
    assert "±5 cm" in shown(0.05)
    assert "Δl bound: none" in shown(None)
