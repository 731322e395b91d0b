"""End-to-end runs: in process on python-can's virtual bus, and as real OS processes on the
in-memory bus; determinism; run directory contract; supervision of failures."""
from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import can
import numpy as np
import pytest

from canbrake.analysis.summary import read_signals
from canbrake.run import run_scenario
from canbrake.scenario import load_scenario

from conftest import CASE1, ROOT, default_sigint

RUN_FILES = ["frames.log", "signals.csv", "summary.json", "scenario.yaml", "canbrake.dbc",
             "plots/speeds.png", "plots/errors.png", "plots/deflections.png", "plots/overview.png",
             "plots/decel.png", "plots/forces.png", "plots/stopping.png"]


def _frames(path: Path) -> list[tuple[int, bytes]]:
    return [(m.arbitration_id, bytes(m.data)) for m in can.LogReader(str(path))]


def test_closed_loop_on_python_can_virtual_bus(tmp_path, case1_short):
    s = run_scenario(case1_short, tmp_path, backend="virtual")
    assert s["status"] == "ok", s["message"]
    for f in RUN_FILES:
        assert (tmp_path / f).exists(), f
    assert s["ticks"] == 300
    # every tick carries SYNC, REFERENCE, 6 sensor, 6 state, 6 command frames (+ barrier frames)
    kinds = s["frames"]["by_kind"]
    assert kinds["sync"] == 301 and kinds["state"] == 6 * 300 and kinds["brake_cmd"] == 6 * 300
    assert s["frames"]["commands_missed"] == 0 and s["frames"]["peer_values_missing"] == 0


def _frames_by_tick(run_dir: Path) -> list[dict[str, dict[str, float]]]:
    """frames.log decoded with the run's DBC: per tick (from SYNC), message name -> signals."""
    import cantools

    db = cantools.database.load_file(str(run_dir / "canbrake.dbc"))
    ticks: list[dict[str, dict[str, float]]] = []
    for m in can.LogReader(str(run_dir / "frames.log")):
        msg = db.get_message_by_frame_id(m.arbitration_id)
        d = msg.decode(bytes(m.data), decode_choices=False)
        if msg.name == "SYNC":
            ticks.append({})
        ticks[-1][msg.name] = d
    return ticks


def test_bus_run_matches_ideal_communication_loop(tmp_path, case1_short):
    """With a perfect bus the distributed run is the ideal-communication loop up to CAN quantisation:
    at every tick each ECU computes from the plant's state of that same tick (its own and every
    peer's, in frames of that tick), and the plant applies that command over the next period."""
    from canbrake.build import build_controller, build_plant_model
    from canbrake.bus.signals import signal_format
    from canbrake.control.base import Observation

    scn = case1_short
    run_scenario(scn, tmp_path, backend="inprocess", plots=False)
    cols = read_signals(tmp_path / "signals.csv")
    n, steps = scn.n_cars, scn.n_ticks
    car = range(1, n + 1)
    x = np.column_stack([cols[f"position_m_c{c}"] for c in car])
    v = np.column_stack([cols[f"speed_mps_c{c}"] for c in car])
    cmd = np.column_stack([cols[f"brake_cmd_n_c{c}"] for c in car])
    ecu_cmd = np.column_stack([cols[f"ecu_brake_cmd_n_c{c}"] for c in car])
    frames = _frames_by_tick(tmp_path)
    assert len(frames) == steps + 1  # + the end-of-run SYNC
    half_q = signal_format("speed_mps").scale / 2 + 1e-7  # + signals.csv's 9 significant digits
    assert signal_format("position_m").scale == signal_format("speed_mps").scale
    ctrls = [build_controller(scn, c) for c in car]
    zero_age = np.zeros(n)
    for k in range(steps):
        f = frames[k]
        sx = np.array([f[f"SENSOR_C{c}"]["Position"] for c in car])
        sv = np.array([f[f"SENSOR_C{c}"]["Speed"] for c in car])
        # the frames of tick k carry the plant's state at tick k, quantised ...
        assert np.all(np.abs(sx - x[k]) <= half_q) and np.all(np.abs(sv - v[k]) <= half_q), k
        # ... and every peer's STATE frame of tick k carries that same measurement (no age)
        assert [f[f"STATE_C{c}"]["Position"] for c in car] == sx.tolist(), k
        assert [f[f"STATE_C{c}"]["Speed"] for c in car] == sv.tolist(), k
        ref = f["REFERENCE"]
        for i, c in enumerate(car):  # each ECU's controller on exactly these values gives its command
            out = ctrls[i].step(Observation(
                tick=k, time_s=k * scn.control_period_s, speed_mps=sv[i], position_m=sx[i],
                ref_speed_mps=ref["RefSpeed"], ref_decel_mps2=ref["RefDecel"], peer_speed_mps=sv,
                peer_position_m=sx, peer_age_s=zero_age))
            assert out.brake_force_n == pytest.approx(ecu_cmd[k, i], rel=1e-8, abs=0.01), (k, c)
            assert f[f"BRAKE_CMD_C{c}"]["BrakeForce"] == cmd[k, i]
    # the plant applies the command, in 10 N steps, over the next period (zero-order hold)
    assert np.all(np.abs(cmd[:-1] - ecu_cmd[:-1]) <= signal_format("brake_force_n").scale / 2 + 0.01)
    plant = build_plant_model(scn)
    for k in range(steps):
        plant.step(scn.control_period_s, {"brake_force_n": cmd[k]})
    meas = plant.measurements()
    np.testing.assert_allclose(meas["speed_mps"], v[-1], rtol=0, atol=1e-6)
    np.testing.assert_allclose(meas["position_m"], x[-1], rtol=0, atol=1e-6)


def test_lockstep_is_deterministic_and_backend_independent(tmp_path, case1_short):
    a, b, c = tmp_path / "a", tmp_path / "b", tmp_path / "c"
    run_scenario(case1_short, a, backend="inprocess", plots=False)
    run_scenario(case1_short, b, backend="inprocess", plots=False)
    run_scenario(case1_short, c, backend="virtual", plots=False)
    assert (a / "frames.log").read_bytes() == (b / "frames.log").read_bytes() == (c / "frames.log").read_bytes()
    assert (a / "signals.csv").read_bytes() == (b / "signals.csv").read_bytes() == (c / "signals.csv").read_bytes()


def test_processes_on_memory_bus_equal_in_process_run(tmp_path):
    scn = load_scenario(CASE1, overrides={"duration_s": 0.2})
    s = run_scenario(scn, tmp_path / "mem", backend="memory", plots=False)
    assert s["status"] == "ok", s["message"]
    run_scenario(scn, tmp_path / "inp", backend="inprocess", plots=False)
    assert (tmp_path / "mem" / "signals.csv").read_bytes() == (tmp_path / "inp" / "signals.csv").read_bytes()
    assert (tmp_path / "mem" / "frames.log").read_bytes() == (tmp_path / "inp" / "frames.log").read_bytes()
    # each node process's CPU time and wake-ups (summary compute.processes); the plant sleeps
    # until every ECU's command is in (MemoryBus.recv_batch(min_frames=...)), not once per command
    pr = s["compute"]["processes"]
    assert set(pr["nodes"]) == {"plant", "recorder", *(f"ecu{i}" for i in range(1, 7))}
    assert all(v["cpu_per_period_s"] > 0 for v in pr["nodes"].values())
    assert pr["cpu_per_period_s"] == pytest.approx(sum(v["cpu_per_period_s"] for v in pr["nodes"].values()))
    assert pr["nodes"]["plant"]["wakeups_per_period"] <= 1.05, pr["nodes"]["plant"]


def test_frames_log_is_decoded_by_cantools_cli(tmp_path, case1_short):
    run_scenario(case1_short, tmp_path, backend="inprocess", plots=False)
    log = (tmp_path / "frames.log").read_text()
    r = subprocess.run([sys.executable, "-m", "cantools", "decode", str(ROOT / "dbc" / "canbrake.dbc")],
                       input=log, capture_output=True, text=True, timeout=120)
    assert r.returncode == 0, r.stderr
    lines = [ln for ln in r.stdout.splitlines() if ln.strip()]
    decoded = [ln for ln in lines if "::" in ln]
    n_frames = len(log.splitlines())
    assert n_frames > 1000
    # cantools prints each frame with its decoded message; every frame's id is in the DBC
    assert sum(1 for ln in lines if ln.startswith("(")) == n_frames
    assert "STATE_C3(" in r.stdout and "BRAKE_CMD_C1(" in r.stdout and "SYNC(" in r.stdout
    assert not any("Unknown" in ln for ln in decoded)


@pytest.mark.parametrize("backend", ["inprocess", "virtual"])
def test_a_node_that_raises_in_process_ends_the_run_named_with_its_traceback_kept(tmp_path, backend):
    """In one process as in a node process: status failed, the message names the ECU and the
    error, the traceback is in logs/ecu3.log, the traces and summary are written."""
    scn = load_scenario(CASE1, overrides={"duration_s": 0.2, "ecu": {"crash": {"car": 3, "at_s": 0.05}}})
    s = run_scenario(scn, tmp_path, backend=backend, plots=False)
    assert s["status"] == "failed"
    assert s["message"].startswith("ecu3: RuntimeError: injected crash of ecu3")
    assert "Traceback" in (tmp_path / "logs" / "ecu3.log").read_text()
    assert (tmp_path / "summary.json").exists() and 40 <= s["ticks"] <= 51


def test_canbrake_decode_reads_the_log(tmp_path, case1_short, capsys):
    from canbrake.cli import main

    run_scenario(case1_short, tmp_path, backend="inprocess", plots=False)
    assert main(["decode", str(tmp_path / "frames.log"), "--only", "BRAKE_CMD_C2"]) == 0
    out = capsys.readouterr().out.splitlines()
    assert len(out) == 300 and all("BrakeForce:" in ln and " N" in ln for ln in out)


def test_crashed_ecu_ends_run_with_message_and_logs(tmp_path):
    scn = load_scenario(CASE1, overrides={"duration_s": 1.0, "ecu": {"crash": {"car": 3, "at_s": 0.05}}})
    s = run_scenario(scn, tmp_path, backend="memory", plots=False)
    assert s["status"] == "failed"
    assert "ecu3" in s["message"] and "injected crash" in s["message"]
    assert (tmp_path / "logs" / "ecu3.log").exists()
    assert (tmp_path / "summary.json").exists() and (tmp_path / "frames.log").stat().st_size > 0
    assert 40 <= s["ticks"] <= 51
    assert len((tmp_path / "signals.csv").read_text().splitlines()) >= 41


def _alive(pid: int) -> bool:
    try:
        return "zombie" not in open(f"/proc/{pid}/status").read().lower()
    except FileNotFoundError:
        return False


def _descendants(pid: int) -> list[int]:
    """Every process below ``pid`` (node processes are children of multiprocessing's forkserver)."""
    out = subprocess.run(["ps", "-o", "pid=", "--ppid", str(pid)], capture_output=True, text=True).stdout
    kids = [int(x) for x in out.split()]
    return kids + [d for k in kids for d in _descendants(k)]


def test_ctrl_c_ends_run_cleanly_and_reaps_every_process(tmp_path):
    p = subprocess.Popen([sys.executable, "-m", "canbrake.cli", "run", str(CASE1), "--out", str(tmp_path),
                          "--no-plots"], stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
                         preexec_fn=default_sigint)
    deadline = time.time() + 60
    while time.time() < deadline and not (tmp_path / "signals.csv").exists():
        time.sleep(0.2)
    time.sleep(1.0)
    kids = _descendants(p.pid)
    assert len(kids) >= 8  # recorder, 6 ECUs, plant (+ forkserver, resource tracker)
    p.send_signal(signal.SIGINT)
    out, err = p.communicate(timeout=180)
    assert p.returncode == 130, err

    # multiprocessing's forkserver and resource tracker exit by themselves once their last pipe
    # closes: allow them a moment
    deadline = time.time() + 10
    while time.time() < deadline and any(_alive(k) for k in kids):
        time.sleep(0.2)
    assert not [k for k in kids if _alive(k)]
    s = json.loads((tmp_path / "summary.json").read_text())
    assert s["status"] == "interrupted" and s["ticks"] > 0


def test_killed_orchestrator_leaves_no_process_behind(tmp_path):
    """`kill -9` of `canbrake run` (no chance to clean up): the node processes notice that their
    orchestrator is gone and exit, and so does multiprocessing's forkserver."""
    p = subprocess.Popen([sys.executable, "-m", "canbrake.cli", "run", str(CASE1), "--out", str(tmp_path),
                          "--no-plots"], stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    deadline = time.time() + 60
    while time.time() < deadline and not (tmp_path / "signals.csv").exists():
        time.sleep(0.2)
    kids = _descendants(p.pid)
    assert len(kids) >= 8
    p.kill()
    p.communicate(timeout=30)

    deadline = time.time() + 30
    while time.time() < deadline and any(_alive(k) for k in kids):
        time.sleep(0.2)
    assert not [k for k in kids if _alive(k)]


def test_run_works_when_tmpdir_cannot_hold_a_socket(tmp_path):
    """The forkserver listens on a unix socket under TMPDIR; a TMPDIR too long for a socket path
    (or on 9p, as in the vcan VM) must not break a run: it falls back to ``spawn``."""
    tmpdir = tmp_path / ("x" * 60) / ("y" * 50)
    tmpdir.mkdir(parents=True)
    r = subprocess.run([sys.executable, "-m", "canbrake", "run", str(CASE1), "--duration", "0.01",
                        "--out", str(tmp_path / "out"), "--no-plots"], capture_output=True, text=True,
                       timeout=300, env={**os.environ, "TMPDIR": str(tmpdir)})
    assert r.returncode == 0, r.stderr
    assert json.loads((tmp_path / "out" / "summary.json").read_text())["ticks"] == 10


@pytest.mark.slow  # the whole case (the bar holds over the full run): ~20 s
def test_case1_acceptance_over_the_bus(tmp_path):
    """Issue 3's bar, through the same node code and frames as `canbrake run`: every coupler
    deflection within ±1 cm throughout, every car within 0.5 km/h of v* after convergence."""
    scn = load_scenario(CASE1)
    s = run_scenario(scn, tmp_path, backend="inprocess", plots=False)
    assert s["status"] == "ok" and s["ticks"] == scn.n_ticks
    m = s["metrics"]
    assert m["max_abs_deflection_m"] <= 0.01
    assert m["convergence_time_s"] is not None and m["convergence_time_s"] < 1.0
    assert m["speed_max_abs_error_after_convergence_kmh"] <= 0.5
    assert max(abs(e) for e in m["final_speed_error_kmh"]) < 0.5


def _fake_run(d, damaged: bool = False):
    """signals.csv (ticks 0..49) and two ECU traces: one missing tick 7 and writing tick 9 twice."""
    import csv as _csv

    d.mkdir()
    with open(d / "signals.csv", "w", newline="") as f:
        w = _csv.writer(f)
        w.writerow(["tick", "t_s", "speed_mps_c1", "brake_cmd_n_c1"])
        for k in range(50):
            w.writerow([k, f"{k * 0.001:.9g}", f"{25 - k / 3:.9g}", "nan" if k % 11 == 0 else f"{k * 1e5 / 7:.9g}"])
    for c in (1, 2):
        with open(d / f"ecu_c{c}.csv", "w", newline="") as f:
            w = _csv.writer(f)
            w.writerow(["tick", "brake_cmd_n", "observer_accel_mps2"])
            for k in range(50):
                if c == 2 and k == 7:
                    continue
                w.writerow([k, f"{k * 3.0:.9g}", f"{-k / 9:.9g}"])
                if c == 2 and k == 9:
                    w.writerow([k, "1", "2"])
    if damaged:  # a writer killed mid-row
        with open(d / "ecu_c1.csv", "a") as f:
            f.write("50,1.5")
        with open(d / "signals.csv", "a") as f:
            f.write("50,0.05,2")


@pytest.mark.parametrize("damaged", [False, True])
def test_the_fast_readers_give_the_bytes_and_floats_of_the_row_by_row_ones(tmp_path, damaged, monkeypatch):
    """summary.read_signals / merge_ecu_columns read complete files with pandas / on the lines'
    text: the same floats and the same merged bytes as the careful row-by-row code."""
    from canbrake.analysis import summary as S

    _fake_run(tmp_path / "fast", damaged)
    _fake_run(tmp_path / "slow", damaged)
    a = S.read_signals(tmp_path / "fast" / "signals.csv")
    b = S._read_signals_rows(tmp_path / "slow" / "signals.csv")
    assert list(a) == list(b) and all(np.array_equal(a[k], b[k], equal_nan=True) for k in a)
    assert len(a["tick"]) == 50 and np.isnan(a["brake_cmd_n_c1"][11])
    content = S.merge_ecu_columns(tmp_path / "fast", 2)
    monkeypatch.setattr(S, "_merge_ecu_columns_fast", lambda *x: False)
    assert S.merge_ecu_columns(tmp_path / "slow", 2) is None
    merged = (tmp_path / "fast" / "signals.csv").read_bytes()
    assert merged == (tmp_path / "slow" / "signals.csv").read_bytes()
    # the merged content handed on (a partial last row is dropped, as the merge drops it) and a
    # column filter: the file's floats
    assert content is not None and merged.endswith(content[1]) and content[0] == merged.decode().splitlines()[0].split(",")
    whole = S._read_signals_rows(tmp_path / "slow" / "signals.csv")
    keep = {"tick", "speed_mps_c1", "observer_accel_mps2_c2"}
    some = S.read_signals(tmp_path / "fast" / "signals.csv", keep=keep.__contains__, content=content)
    assert list(some) == [k for k in whole if k in keep]
    assert all(np.array_equal(some[k], whole[k], equal_nan=True) for k in some)
    lines = merged.decode().splitlines()
    assert lines[0].endswith(",ecu_brake_cmd_n_c1,observer_accel_mps2_c1,brake_cmd_n_c2,observer_accel_mps2_c2")
    assert lines[1 + 7].endswith(",,")                   # ECU 2 has no tick 7
    assert lines[1 + 9].endswith(",1,2")                 # its tick 9 written twice: the last one
