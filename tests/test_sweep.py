"""Sweeps: grid parsing, the mapping of axes to scenario overrides, a tiny serial sweep (results.csv,
heatmaps, resume), equality with a plain run, the Dask path (and that it leaves no process behind),
and the delay-compensated controller."""
from __future__ import annotations

import csv
import os
import signal
import subprocess
import sys
import time

import numpy as np
import pytest

from canbrake import sweep as sw
from canbrake.bus import dbc
from canbrake.scenario import load_scenario

from conftest import CASE1, ROOT, default_sigint

STATE_IDS = [dbc.STATE_BASE + c for c in range(1, 7)]
CMD_IDS = [dbc.BRAKE_CMD_BASE + c for c in range(1, 7)]


# ----------------------------------------------------------------------------- grid parsing
@pytest.mark.parametrize("spec, name, values, unit", [
    ("delay=0:50ms:11", "delay", tuple(i * 0.005 for i in range(11)), "ms"),
    ("delay=0ms:50ms:3", "delay", (0.0, 0.025, 0.05), "ms"),
    ("delay=0:0.05:2", "delay", (0.0, 0.05), ""),
    ("jitter=100:300us:3", "jitter", (1e-4, 2e-4, 3e-4), "us"),
    ("loss=0:0.5:11", "loss", tuple(i * 0.05 for i in range(11)), ""),
    ("loss=0:50%:3", "loss", (0.0, 0.25, 0.5), "%"),
    ("loss=0,1,5%", "loss", (0.0, 0.01, 0.05), "%"),
    ("bitrate=125,500,1000kbps", "bitrate", (125000.0, 500000.0, 1000000.0), "kbps"),
    ("period=1:10ms:2", "period", (0.001, 0.01), "ms"),
    ("delay=2ms:2ms:1", "delay", (0.002,), "ms"),
    ("set:controller.params.k=10,20,36", "set:controller.params.k", (10, 20, 36), ""),
    ("set:controller.name=chen2023,chen2023_compensated", "set:controller.name",
     ("chen2023", "chen2023_compensated"), ""),
    ("set:controller.params.k=10:30:3", "set:controller.params.k", (10.0, 20.0, 30.0), ""),
])
def test_parse_grid(spec, name, values, unit):
    ax = sw.parse_grid(spec)
    assert ax.name == name and ax.unit == unit
    assert len(ax.values) == len(values)
    for got, want in zip(ax.values, values):
        assert got == pytest.approx(want, rel=1e-12, abs=1e-15) if isinstance(want, float) else got == want


@pytest.mark.parametrize("spec, words", [
    ("delay", "missing '='"),
    ("delay=", "no values"),
    ("speed=0:1:3", "unknown axis 'speed'"),
    ("delay=0:50ms", "three parts"),
    ("delay=0:50ms:x", "not a whole number"),
    ("delay=0:50ms:0", "at least 1"),
    ("delay=0:50kg:3", "unit 'kg'"),
    ("delay=0:50:3", "did you mean 50ms"),
    ("delay=10ms:0ms:3", "greater than START"),
    ("delay=1ms:2ms:1", "START == STOP"),
    ("delay=1s:50ms:3", "different units"),
    ("loss=0:1.5:3", "between 0 and 1"),
    ("loss=0:10ms:3", "unit 'ms'"),
    ("delay=-5:5ms:3", "between 0"),
    ("delay=a:5ms:3", "not a number"),
    ("delay=1,1ms", "repeated"),
    ("set:controller..k=1,2", "dotted scenario path"),
])
def test_bad_grid_specs_fail_clearly(spec, words):
    with pytest.raises(sw.GridError) as e:
        sw.parse_grid(spec)
    assert words in str(e.value)
    assert spec in str(e.value)


def test_cli_bad_grid_exits_2_with_one_line(capsys):
    from canbrake.cli import main

    assert main(["sweep", str(CASE1), "--grid", "delay=0:50:11"]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "did you mean 50ms" in err[0] and "Traceback" not in err[0]
    assert main(["sweep", str(CASE1), "--grid", "loss=0:0.5:3", "--grid", "loss=0:0.1:2"]) == 2
    assert "given twice" in capsys.readouterr().err


@pytest.mark.parametrize("args, expect", [
    (["--set", "controller.params.k=nan"], "--set controller.params.k: must be a finite number, got nan"),
    (["--set", "controller.params.bogus=1"], "--set controller.params.bogus: unknown parameter"),
    (["--grid", "set:controller.params.k=1,nan"], "(set:controller.params.k=nan): controller.params.k: must be a finite"),
    (["--grid", "set:controller.params.bogus=1,2"], "controller.params.bogus: unknown parameter"),
])
def test_cli_bad_controller_parameters_exit_2_before_any_run(args, expect, tmp_path, capsys):
    """Controller parameters of the base scenario and of grid points are checked against the
    controller's schema while planning: one line, exit 2, no sweep directory."""
    from canbrake.cli import main

    out = tmp_path / "sw"
    assert main(["sweep", str(CASE1), *args, "--duration", "0.01", "--workers", "0", "--out", str(out), "-q"]) == 2
    err = [ln for ln in capsys.readouterr().err.splitlines() if ln.startswith("canbrake: error:")]
    assert len(err) == 1 and expect in err[0], err
    assert not out.exists()


# ----------------------------------------------------------------------------- overrides
def test_delay_and_loss_map_onto_state_and_command_frames_of_every_ecu():
    base = load_scenario(CASE1).model_dump(mode="json")
    ov = sw.point_overrides(base, {"delay": 0.005, "loss": 0.1}, 6)
    imps = ov["bus.impairments"]
    assert [i["type"] for i in imps] == ["loss", "delay"]
    for i in imps:
        assert sorted(i["ids"]) == sorted(STATE_IDS + CMD_IDS)
        assert "senders" not in i  # every ECU
    assert imps[0]["probability"] == 0.1 and imps[1]["delay_s"] == 0.005
    scn = load_scenario(CASE1, overrides=ov)  # validates against the schema
    assert [s.type for s in scn.bus.impairments] == ["loss", "delay"]
    # zero values add nothing: the point is the plain scenario
    assert sw.point_overrides(base, {"delay": 0.0, "loss": 0.0}, 6) == {}
    # one-sided axes, jitter, bit rate, period, generic set
    ov = sw.point_overrides(base, {"state_delay": 0.002, "cmd_loss": 0.3, "jitter": 0.001, "bitrate": 250000.0,
                                   "period": 0.002, "set:controller.params.k": 20}, 6)
    by = {i["type"]: i for i in ov["bus.impairments"]}
    assert sorted(by["delay"]["ids"]) == STATE_IDS and sorted(by["loss"]["ids"]) == CMD_IDS
    assert by["jitter"]["distribution"] == "uniform" and by["jitter"]["high_s"] == 0.001
    assert ov["bus.bitrate_bps"] == 250000 and ov["control_period_s"] == 0.002
    assert ov["controller.params.k"] == 20


def test_scenario_impairments_are_kept_and_random_points_get_seeds(tmp_path):
    base = load_scenario(CASE1).model_dump(mode="json")
    base["bus"]["impairments"] = [{"type": "delay", "delay_s": 0.001, "senders": ["ecu3"]}]
    ov = sw.point_overrides(base, {"loss": 0.2}, 6)
    assert ov["bus.impairments"][0] == base["bus"]["impairments"][0] and ov["bus.impairments"][1]["type"] == "loss"
    assert sw.is_random({"loss": 0.2}) and sw.is_random({"jitter": 1e-3}) and not sw.is_random({"delay": 0.01})
    assert sw.is_random({"delay": 0.0}, [{"type": "gilbert_elliott"}])
    plan = sw.plan_sweep(CASE1, [sw.parse_grid("delay=0,1ms"), sw.parse_grid("loss=0,0.1")], tmp_path, seeds=3)
    seeds = {(t.params["delay"], t.params["loss"]): [] for t in plan.tasks}
    for t in plan.tasks:
        seeds[(t.params["delay"], t.params["loss"])].append(t.seed)
    assert seeds[(0.0, 0.0)] == [1] and seeds[(0.001, 0.0)] == [1]
    assert seeds[(0.0, 0.1)] == [1, 2, 3] and seeds[(0.001, 0.1)] == [1, 2, 3]
    assert len({t.point_id for t in plan.tasks}) == len(plan.tasks) == 8
    assert plan.duration_s == pytest.approx(1.0)  # 1000 periods of 1 ms, below the scenario's 10 s


# ----------------------------------------------------------------------------- tiny sweeps
DUR = 0.02  # simulated seconds per run in these tests
AXES = ("delay=0,2ms", "loss=0,0.2")


@pytest.fixture(scope="module")
def tiny(tmp_path_factory):
    out = tmp_path_factory.mktemp("sweep")
    res = sw.run_sweep(CASE1, [sw.parse_grid(g) for g in AXES], out, duration_s=DUR, seeds=2, workers=0,
                       progress=False)
    return out, res


def test_serial_sweep_writes_one_row_per_point_and_seed_and_heatmaps(tiny):
    out, res = tiny
    with open(out / "results.csv", newline="") as f:
        rows = list(csv.DictReader(f))
    # (0,0) and (2 ms, 0) once; the two lossy points with 2 seeds each
    assert len(rows) == 6 == res.ran
    key = sorted((float(r["delay_s"]), float(r["loss"]), int(r["seed"])) for r in rows)
    assert key == [(0.0, 0.0, 1), (0.0, 0.2, 1), (0.0, 0.2, 2), (0.002, 0.0, 1), (0.002, 0.2, 1), (0.002, 0.2, 2)]
    for col in ("point_id", "status", "safety", "max_abs_deflection_m", "speed_rmse_kmh_max",
                "convergence_time_s", "frames_commands_missed", "bus_load_bus_load_mean", "unstable"):
        assert col in rows[0], col
    assert all(r["status"] in ("ok", "diverged") for r in rows)
    lossy = [r for r in rows if float(r["loss"]) > 0]
    assert all(int(r["frames_peer_values_missing"]) > 0 for r in lossy)  # the loss reached the ECUs
    delayed = [r for r in rows if float(r["delay_s"]) > 0 and float(r["loss"]) == 0]
    assert int(delayed[0]["frames_commands_missed"]) > 0  # ... and the delay the plant
    for name in ("heatmap_deflection.png", "heatmap_speed_rmse.png", "heatmap_convergence.png",
                 "heatmap_safety.png"):
        p = out / name
        assert p.exists() and p.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n" and p.stat().st_size < 150_000
    th = (out / "thresholds.md").read_text()
    assert "| delay | loss=0 |" in th and "| loss | delay=0ms |" in th
    # traces are trimmed by default, summaries kept
    pdir = out / "points" / rows[0]["point_id"]
    assert (pdir / "summary.json").exists() and not (pdir / "frames.log").exists()


def test_resume_skips_done_points(tiny, monkeypatch):
    out, _ = tiny
    calls = []
    real = sw.run_point

    def counting(task):
        calls.append(task.point_id)
        return real(task)

    real_batch = sw.run_batch_points

    def counting_batch(tasks):  # the batch engine runs these points (canbrake.batch)
        calls.extend(t.point_id for t in tasks)
        return real_batch(tasks)

    monkeypatch.setattr(sw, "run_point", counting)
    monkeypatch.setattr(sw, "run_batch_points", counting_batch)
    axes = [sw.parse_grid(g) for g in AXES]
    res = sw.run_sweep(CASE1, axes, out, duration_s=DUR, seeds=2, workers=0, progress=False, plots=False)
    assert calls == [] and res.skipped == 6 and len(res.rows) == 6
    # a row missing from results.csv but with an ok summary.json is not rerun either
    rows = sw.read_results(out / "results.csv")
    sw.write_results(out / "results.csv", rows[1:])
    res = sw.run_sweep(CASE1, axes, out, duration_s=DUR, seeds=2, workers=0, progress=False, plots=False)
    assert calls == [] and len(res.rows) == 6
    # a point with neither is run again, only that one
    victim = rows[-1]["point_id"]
    (out / "points" / victim / "summary.json").unlink()
    sw.write_results(out / "results.csv", [r for r in rows if r["point_id"] != victim])
    res = sw.run_sweep(CASE1, axes, out, duration_s=DUR, seeds=2, workers=0, progress=False, plots=False)
    assert calls == [victim] and res.ran == 1
    assert len(sw.read_results(out / "results.csv")) == 6
    # a different configuration is a different point
    res = sw.run_sweep(CASE1, [sw.parse_grid("delay=0ms")], out, duration_s=DUR, seeds=2, workers=0,
                       progress=False, plots=False, sets={"controller.params.k": 30})
    assert res.ran == 1


def test_zero_point_equals_a_plain_run(tiny, tmp_path):
    from canbrake.run import run_scenario

    _, res = tiny
    row = next(r for r in res.rows if r["delay_s"] == 0 and r["loss"] == 0)
    scn = load_scenario(CASE1, overrides={"duration_s": DUR})
    m = run_scenario(scn, tmp_path, backend="inprocess", plots=False)["metrics"]
    assert row["max_abs_deflection_m"] == m["max_abs_deflection_m"]
    assert row["speed_rmse_kmh_max"] == max(m["speed_rmse_kmh"])
    assert row["convergence_time_s"] == m["convergence_time_s"]
    assert row["final_speed_error_kmh_c6"] == m["final_speed_error_kmh"][5]


def test_classification():
    ok = {"status": "ok", "max_abs_deflection_m": 0.005, "convergence_time_s": 0.02,
          "speed_rmse_after_convergence_kmh_max": 0.1, "final_speed_error_kmh_max": 0.01}
    assert sw.classify(ok)["safety"] == "ok"
    assert sw.classify({**ok, "convergence_time_s": None})["safety"] == "degraded"
    assert sw.classify({**ok, "max_abs_deflection_m": 0.02})["safety"] == "violation"
    assert sw.classify({**ok, "max_abs_deflection_m": 0.9})["safety"] == "unstable"
    assert sw.classify({**ok, "final_speed_error_kmh_max": 3.0})["safety"] == "unstable"
    assert sw.classify({**ok, "status": "diverged"})["safety"] == "unstable"
    assert sw.classify({"status": "error"})["safety"] is None


# ----------------------------------------------------------------------------- Dask
def _session_procs(sid: int) -> list[int]:
    import psutil

    out = []
    for p in psutil.process_iter(["pid"]):
        try:
            if os.getsid(p.pid) == sid:
                out.append(p.pid)
        except (ProcessLookupError, PermissionError):
            pass
    return out


def test_dask_local_cluster_with_two_workers(tmp_path):
    pytest.importorskip("distributed")
    import psutil

    before = {c.pid for c in psutil.Process().children(recursive=True)}
    res = sw.run_sweep(CASE1, [sw.parse_grid("delay=0,1ms")], tmp_path, duration_s=0.02, workers=2,
                       progress=False, plots=False)
    assert len(res.rows) == 2 and all(r["status"] == "ok" for r in res.rows)
    assert len(sw.read_results(tmp_path / "results.csv")) == 2
    time.sleep(0.5)
    # (multiprocessing's resource tracker is this process's own helper and lives as long as it does)
    left = [c for c in psutil.Process().children(recursive=True) if c.pid not in before and c.is_running()
            and c.status() != psutil.STATUS_ZOMBIE and "resource_tracker" not in " ".join(c.cmdline())]
    assert left == [], [c.cmdline() for c in left]


def test_existing_dask_scheduler_is_used_and_left_running(tmp_path):
    distributed = pytest.importorskip("distributed")
    with distributed.LocalCluster(n_workers=1, threads_per_worker=1, processes=False, protocol="tcp://",
                                  host="127.0.0.1", dashboard_address=None) as cluster:
        res = sw.run_sweep(CASE1, [sw.parse_grid("loss=0.1")], tmp_path, duration_s=0.02, seeds=2,
                           scheduler=cluster.scheduler_address, progress=False, plots=False)
        assert sorted(r["seed"] for r in res.rows) == [1, 2] and all(r["status"] == "ok" for r in res.rows)
        assert cluster.status.name == "running" and len(cluster.workers) == 1  # not ours to close
    with pytest.raises(sw.GridError, match="cannot connect"):
        sw.run_sweep(CASE1, [sw.parse_grid("loss=0.2")], tmp_path, duration_s=0.02, progress=False,
                     scheduler="tcp://127.0.0.1:9")


def test_ctrl_c_stops_a_dask_sweep_and_leaves_no_process(tmp_path):
    pytest.importorskip("distributed")
    out = tmp_path / "sw"
    # the per-point engine, points of 2 s: they end one by one, the first well before the last (the
    # batch engine ends a batch's points together, and 0.2 s points all ended before the Ctrl-C)
    p = subprocess.Popen([sys.executable, "-m", "canbrake.cli", "sweep", str(CASE1), "--grid", "delay=0:10ms:11",
                          "--workers", "2", "--duration", "2", "--engine", "points", "--out", str(out), "-q",
                          "--no-plots"],
                         cwd=ROOT, start_new_session=True, stdout=subprocess.PIPE, stderr=subprocess.PIPE,
                         preexec_fn=default_sigint)
    deadline = time.time() + 60
    while time.time() < deadline and not list((out / "points").glob("*/summary.json")):
        time.sleep(0.1)  # workers up and through their first points
    os.killpg(p.pid, signal.SIGINT)  # as a terminal's Ctrl-C: to the whole process group
    _, err = p.communicate(timeout=60)
    assert p.returncode == 130, err.decode()
    assert "resume" in err.decode() and "Traceback" not in err.decode()
    deadline = time.time() + 10
    while _session_procs(p.pid) and time.time() < deadline:
        time.sleep(0.2)
    assert _session_procs(p.pid) == []
    assert len(sw.read_results(out / "results.csv")) < 11  # stopped early; what finished is kept


# ----------------------------------------------------------------------------- compensated controller
def _obs(tick, dt, x, v, px, pv, age):
    from canbrake.control.base import Observation

    return Observation(tick=tick, time_s=tick * dt, speed_mps=v, position_m=x, ref_speed_mps=25.0,
                       ref_decel_mps2=0.97, peer_speed_mps=np.asarray(pv, float),
                       peer_position_m=np.asarray(px, float), peer_age_s=np.asarray(age, float))


def test_compensated_equals_chen_with_fresh_data_and_aligns_old_peer_samples():
    from canbrake.control.base import make_controller
    from canbrake.control.chen import ChenConsensusController
    import canbrake.control.chen_compensated as cc

    dt, n, i = 0.001, 3, 1
    kw = dict(car_index=i, n_cars=n, mass_kg=20000.0, dt_s=dt)
    chen = make_controller("chen2023", {"nominal_spacing_m": 10.0}, **kw)
    comp = cc.ChenCompensatedController(nominal_spacing_m=10.0, **kw)
    assert isinstance(comp, ChenConsensusController)
    # fresh data: identical commands
    x = lambda k, car: 100.0 - 10.0 * car + 25.0 * k * dt + 0.002 * car * k * dt  # noqa: E731
    v = lambda k, car: 25.0 + 0.002 * car  # noqa: E731
    for k in range(5):
        o = _obs(k, dt, x(k, i), v(k, i), [x(k, j) for j in range(n)], [v(k, j) for j in range(n)], [0.0] * n)
        assert comp.step(o).brake_force_n == pytest.approx(chen.step(o).brake_force_n, rel=1e-12)
    # peers 3 ticks old: the compensated deflection is that of one instant (exact here); Chen's is off by v·age
    k = 8
    for kk in range(5, k):
        comp.step(_obs(kk, dt, x(kk, i), v(kk, i), [x(kk, j) for j in range(n)], [v(kk, j) for j in range(n)],
                       [0.0] * n))
    o = _obs(k, dt, x(k, i), v(k, i), [x(k - 3, j) for j in range(n)], [v(k - 3, j) for j in range(n)],
             [0.003, 0.0, 0.003])
    true_front = x(k, 0) - x(k, 1) - 10.0
    d = comp.step(o).diagnostics
    assert d["deflection_front_m"] == pytest.approx(true_front, abs=1e-9)
    assert chen.step(o).diagnostics["deflection_front_m"] == pytest.approx(true_front - 25.0 * 0.003, abs=1e-4)
    assert d["latency_estimate_s"] == pytest.approx(0.003) and d["gain_scale"] < 1.0
    with pytest.raises(ValueError, match="stale_policy"):
        cc.ChenCompensatedController(stale_policy="drop", **kw)


@pytest.mark.parametrize("ctrl, holds_bound", [("chen2023", False), ("chen2023_compensated", True)])
def test_lost_state_frames_break_chen_but_not_the_compensated_loop(tmp_path, ctrl, holds_bound):
    row = sw.run_point(sw.PointTask(
        "p", {"state_loss": 0.1}, 1,
        load_scenario(CASE1, overrides={"duration_s": 0.1, "controller.name": ctrl,
                                        "bus.impairments": sw.impairments_for({"state_loss": 0.1}, 6)}
                      ).model_dump(mode="json"), str(tmp_path / ctrl)))
    assert row["status"] in ("ok", "diverged")
    assert (row["max_abs_deflection_m"] <= sw.DEFLECTION_BOUND_M) is holds_bound, row["max_abs_deflection_m"]
