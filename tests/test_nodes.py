"""Node state machines and modes: realtime pacing, divergence, the plant's command handling."""
from __future__ import annotations

import re

import numpy as np
import pytest

from canbrake.bus import dbc
from canbrake.bus.codec import FrameCodec
from canbrake.nodes.base import frame
from canbrake.nodes.plant import PlantNode
from canbrake.run import run_scenario
from canbrake.scenario import load_scenario

from conftest import CASE1


class _Exploding:
    """A plant model that diverges on its third step."""

    n_vehicles = 2
    mass_kg = np.ones(2)
    command_names = ("brake_force_n",)

    def __init__(self) -> None:
        self.steps = 0

    def step(self, dt_s, brake_force_cmd_n):
        self.steps += 1
        if self.steps == 3:
            raise FloatingPointError("state not finite")

    def measurements(self):
        z = np.zeros(2)
        return {"position_m": z, "speed_mps": z, "accel_mps2": z, "applied_brake_n": z,
                "deflection_m": np.zeros(1), "coupler_force_n": np.zeros(1)}


def _plant(model, n_ticks=10):
    layout = dbc.BusLayout(dbc.default_ecus(2, coupler_sensors=True))
    codec = FrameCodec(layout.database())
    return codec, PlantNode(model, codec, layout=layout, dt_s=0.01, n_ticks=n_ticks,
                            reference=lambda t: (10.0, 1.0))


def _finish_tick(codec, plant, k):
    out = []
    for c in (1, 2):
        out += plant.handle(frame(dbc.CMD_DONE_BASE + c, codec[f"CMD_DONE_C{c}"].encode({"Tick": k})), 0.0)
    return out


def test_plant_waits_for_every_command_done_then_advances():
    codec, plant = _plant(_Exploding(), n_ticks=5)
    first = plant.start(0.0)
    assert first[0].arbitration_id == dbc.SYNC_ID
    assert plant.handle(frame(dbc.CMD_DONE_BASE + 1, codec["CMD_DONE_C1"].encode({"Tick": 0})), 0.0) == []
    # a barrier frame of another tick does not count
    assert plant.handle(frame(dbc.CMD_DONE_BASE + 2, codec["CMD_DONE_C2"].encode({"Tick": 7})), 0.0) == []
    nxt = plant.handle(frame(dbc.CMD_DONE_BASE + 2, codec["CMD_DONE_C2"].encode({"Tick": 0})), 0.0)
    assert codec["SYNC"].decode(nxt[0].data)["Tick"] == 1 and plant.k == 1


def test_plant_uses_newest_valid_command_and_rejects_bad_crc_and_old_frames():
    codec, plant = _plant(_Exploding(), n_ticks=50)
    plant.start(0.0)
    c1 = codec["BRAKE_CMD_C1"]
    plant.handle(frame(dbc.BRAKE_CMD_BASE + 1, c1.encode({"BrakeForce": 1000.0}, counter=0)), 0.0)
    assert plant.cmd_n[0] == 1000.0
    bad = bytearray(c1.encode({"BrakeForce": 5000.0}, counter=0))
    bad[3] ^= 0x10
    plant.handle(frame(dbc.BRAKE_CMD_BASE + 1, bytes(bad)), 0.0)
    assert plant.cmd_n[0] == 1000.0 and plant.stats.commands_corrupted == 1
    _finish_tick(codec, plant, 0)
    _finish_tick(codec, plant, 1)  # tick 1: car 1's command lost -> held (zero-order hold), counted
    assert plant.stats.commands_missed == 1 + 2  # tick 0: car 2 missing; tick 1: both
    # a delayed frame from tick 0 arriving in tick 2 is older than the one in hand: ignored
    plant.handle(frame(dbc.BRAKE_CMD_BASE + 1, c1.encode({"BrakeForce": 9.0}, counter=0)), 0.0)
    assert plant.cmd_n[0] == 1000.0


def test_diverging_plant_ends_the_run_for_everyone():
    codec, plant = _plant(_Exploding(), n_ticks=50)
    plant.start(0.0)
    _finish_tick(codec, plant, 0)
    _finish_tick(codec, plant, 1)
    out = _finish_tick(codec, plant, 2)
    assert plant.finished and plant.stats.status == "diverged"
    assert codec["SYNC"].decode(out[-1].data)["Tick"] == dbc.SYNC_END_TICK


def test_realtime_mode_is_paced_by_the_wall_clock(tmp_path):
    scn = load_scenario(CASE1, profile="realistic", overrides={"mode": "realtime", "duration_s": 0.5})
    s = run_scenario(scn, tmp_path, backend="memory", plots=False)
    assert s["status"] == "ok", s["message"]
    assert s["ticks"] == 50
    # never faster than real time (a lower bound is robust on a loaded machine)
    assert s["real_time_factor"] <= 1.05
    dm = s["deadline_misses"]
    assert isinstance(dm["plant"], int) and isinstance(dm["ecus"], int) and dm["max_lateness_s"] >= 0


def test_realtime_run_reports_scheduling_latency_and_miss_share_in_summary(tmp_path):
    """summary.json's realtime section: misses over the periods that ended, p99 latency (or null
    when over 1 % of periods were late), and what scheduling every process obtained."""
    scn = load_scenario(CASE1, profile="realistic", overrides={"mode": "realtime", "duration_s": 0.2})
    s = run_scenario(scn, tmp_path, backend="memory", plots=False)
    rt = s["realtime"]
    assert rt["periods"] == s["ticks"] == 20
    assert rt["plant_deadline_misses"] == s["deadline_misses"]["plant"]
    assert rt["plant_deadline_miss_pct"] == pytest.approx(100 * rt["plant_deadline_misses"] / 20)
    assert (rt["cmd_latency_p99_s"] is None) == (rt["cmd_latency_missing"] > 0.01 * 20)
    assert set(rt["scheduling"]) == {"plant", "recorder", *(f"ecu_c{c}" for c in range(1, 7))}
    assert all(v.startswith(("SCHED_FIFO", "SCHED_OTHER")) for v in rt["scheduling"].values())
    # every node froze what its garbage collector held after setting up (canbrake.nodes.rt)
    assert all(re.search(r"gc: [\d,]+ objects frozen$", v) for v in rt["scheduling"].values())


def test_node_setup_freezes_the_garbage_collector_unless_told_not_to(monkeypatch):
    """A full collection walks every object of a node (tens of ms, a missed 10 ms deadline);
    every node process (and an in-process run, for its duration) collects once after setting
    up and freezes what it holds, so later full collections skip it."""
    import gc

    from canbrake.nodes.driver import INPROCESS_GC_THRESHOLD, freeze_heap, frozen_heap

    try:
        n = freeze_heap()
        assert n > 1000 and n == gc.get_freeze_count()
        gc.unfreeze()
        before = gc.get_threshold()
        with frozen_heap():  # an in-process run: frozen, its first generation collected less often
            assert gc.get_freeze_count() > 1000
            assert gc.get_threshold()[0] == max(before[0], INPROCESS_GC_THRESHOLD)
            assert gc.get_threshold()[1:] == before[1:]
        assert gc.get_freeze_count() == 0 and gc.get_threshold() == before
        monkeypatch.setenv("CANBRAKE_GC", "off")
        assert freeze_heap() == 0 and gc.get_freeze_count() == 0
        with frozen_heap():
            assert gc.get_freeze_count() == 0 and gc.get_threshold() == before
    finally:
        gc.unfreeze()


def test_realtime_setup_reports_scheduling_without_touching_the_collector(monkeypatch):
    import gc

    from canbrake.nodes.rt import setup_realtime

    monkeypatch.setenv("CANBRAKE_RT_AFFINITY", "none")
    got = setup_realtime("not-a-role")
    assert got.startswith("SCHED_OTHER (not a realtime role)") and gc.get_freeze_count() == 0


def test_a_late_realtime_wakeup_moves_the_grid_on_instead_of_bursting(tmp_path):
    """The plant's timer fires 3.5 periods late: one late period, the grid moves on by the
    lateness (slipped_s), and the next deadline is a whole period away (no catch-up burst)."""
    from canbrake.build import build_node

    scn = load_scenario(CASE1, overrides={"mode": "realtime", "duration_s": 0.1})
    plant = build_node(scn, "plant", run_dir=None)
    plant.start(100.0)
    dt = scn.control_period_s
    late = 100.0 + dt + 3.5 * dt  # the first deadline is 100 + dt
    plant.on_timer(late)
    assert plant.k == 1 and plant.stats.late_periods == 1 and plant.stats.deadline_misses == 1
    assert plant.stats.slipped_s == pytest.approx(3.5 * dt)
    assert plant.next_deadline() == pytest.approx(late + dt)
    plant.on_timer(late + dt + 0.1 * dt)  # on time again (within a period): the grid stays
    assert plant.stats.late_periods == 1 and plant.next_deadline() == pytest.approx(late + 2 * dt)


def test_a_realtime_plant_writes_its_row_once_the_periods_commands_are_in(tmp_path):
    """Realtime: the plant's trace row of a period is not written when its SYNC goes out (the
    ECUs need the CPUs then) but once every ECU's command of the period is in, or else when the
    next period's row is taken; the rows stay in order, one per period."""
    from canbrake.build import build_node

    scn = load_scenario(CASE1, overrides={"mode": "realtime", "duration_s": 0.1})
    plant = build_node(scn, "plant", run_dir=None)
    ecus = [build_node(scn, "ecu", car=c, run_dir=None) for c in range(1, 7)]
    for e in ecus:
        e.start(0.0)
    plant.out_dir = tmp_path
    plant.start(100.0)
    dt = scn.control_period_s
    rows = lambda: (tmp_path / "signals.csv").read_text().count("\n") - 1  # noqa: E731
    frames = plant.on_timer(100.0 + dt)  # tick 1: tick 0's row taken
    plant.after_send()
    assert plant.k == 1 and rows() == 0  # SYNC sent: the row waits
    # the ECUs answer tick 1: their states to each other, their commands to the plant
    phase = list(frames)
    cmds = []
    for _ in range(3):
        nxt = []
        for e in ecus:
            nxt += e.handle_batch(list(phase), 100.0 + dt)
        cmds += [m for m in nxt if m.arbitration_id in plant._cmd_pages]
        phase = nxt
    assert len(cmds) == 6
    plant.handle_batch(cmds[:5], 100.0 + 1.5 * dt)
    assert rows() == 0  # one command still to come
    plant.handle_batch(cmds[5:], 100.0 + 1.6 * dt)
    assert rows() == 1  # all in: tick 0's row written
    plant.on_timer(100.0 + 2 * dt)  # tick 2, no command comes: tick 1's row when tick 2's is taken
    plant.after_send()
    assert rows() == 1
    plant.on_timer(100.0 + 3 * dt)
    assert rows() == 2
    plant.close()
    ticks = [int(ln.split(",")[0]) for ln in (tmp_path / "signals.csv").read_text().splitlines()[1:]]
    assert ticks == [0, 1, 2]


def test_virtual_and_inprocess_refuse_realtime(tmp_path):
    from canbrake.scenario import ScenarioError

    scn = load_scenario(CASE1, overrides={"mode": "realtime", "duration_s": 0.1})
    with pytest.raises(ScenarioError, match="lockstep only"):
        run_scenario(scn, tmp_path, backend="virtual")


def test_stall_watch_tells_a_stall_from_nodes_that_compute():
    """No new tick for the limit: a stall, unless the nodes used CPU meanwhile (then at most
    ``grace`` limits in all); a new tick resets it; a stopped node uses no CPU."""
    from canbrake.run import StallWatch

    w = StallWatch(start_s=30.0, stall_s=10.0, busy_share=0.2, grace=3)
    cpu = [0.0]
    assert w.update(-1, 0.0, lambda: cpu[0]) is None
    assert w.update(-1, 29.0, lambda: cpu[0]) is None          # before the first tick: start_s applies
    assert w.update(5, 31.0, lambda: cpu[0]) is None           # a tick: progress
    assert w.update(5, 40.0, lambda: cpu[0]) is None
    msg = w.update(5, 41.5, lambda: cpu[0])                    # 10.5 s, no CPU used: stalled
    assert msg is not None and "at tick 5" in msg and "waiting for frames" in msg
    w = StallWatch(start_s=30.0, stall_s=10.0, busy_share=0.2, grace=3)
    w.update(7, 0.0, lambda: 0.0)
    assert w.update(7, 11.0, lambda: 8.0) is None              # 8 CPU s in 11 s: computing
    msg = w.update(7, 22.5, lambda: 9.0)                       # then 1 CPU s in 11.5 s: stalled
    assert msg is not None and "no progress for 22 s" in msg
    w = StallWatch(start_s=30.0, stall_s=10.0, busy_share=0.2, grace=3)
    w.update(7, 0.0, lambda: 0.0)
    assert w.update(7, 11.0, lambda: 8.0) is None
    assert w.update(7, 22.0, lambda: 16.0) is None
    msg = w.update(7, 33.0, lambda: 24.0)                      # computing, but for 3 limits: a loop
    assert msg is not None and "kept computing" in msg
    assert w.update(8, 34.0, lambda: 25.0) is None             # (a new tick would have reset it)


def test_processes_cpu_s_counts_a_busy_child_not_a_sleeping_one():
    import subprocess
    import sys
    import time

    from canbrake.run import _processes_cpu_s

    busy = subprocess.Popen([sys.executable, "-c", "import time\nt = time.process_time()\n"
                             "while time.process_time() - t < 0.6: pass\ntime.sleep(30)"])
    idle = subprocess.Popen([sys.executable, "-c", "import time; time.sleep(30)"])
    try:
        deadline = time.time() + 30
        while (_processes_cpu_s([busy.pid]) or 0.0) < 0.5 and time.time() < deadline:
            time.sleep(0.1)
        assert _processes_cpu_s([busy.pid]) >= 0.5
        assert _processes_cpu_s([idle.pid]) < 0.5
        assert _processes_cpu_s([2 ** 22 + 7]) == 0.0  # no such process: nothing counted
    finally:
        busy.kill()
        idle.kill()
        busy.wait()
        idle.wait()


def _csv_reference(rows: list[list]) -> bytes:
    """What the traces wrote before their per-row format: csv.writer, floats as f"{v:.9g}"."""
    import csv
    import io

    buf = io.StringIO(newline="")
    w = csv.writer(buf)
    for row in rows:
        w.writerow([f"{v:.9g}" if isinstance(v, float) else v for v in row])
    return buf.getvalue().encode()


def test_trace_rows_are_written_as_the_csv_module_writes_them(tmp_path):
    """CsvTrace's compiled per-row %-format writes the bytes csv.writer would, for every value
    type the nodes append (floats incl. NaN/inf/-0/huge, numpy scalars, ints, bools) and falls
    back to csv.writer for the rest (a str needing quotes, None)."""
    from hypothesis import given, settings, strategies as st

    from canbrake.nodes.base import CsvTrace

    value = st.one_of(st.floats(allow_nan=True, allow_infinity=True), st.integers(-2 ** 62, 2 ** 62),
                      st.booleans(), st.floats(allow_nan=True).map(np.float64),
                      st.integers(-2 ** 31, 2 ** 31 - 1).map(np.int64), st.booleans().map(np.bool_),
                      st.sampled_from(["a,b", 'q"t', "plain", None]))
    n = [0]

    @settings(max_examples=150, deadline=None)
    @given(st.lists(st.lists(value, max_size=6), min_size=1, max_size=4))
    def check(rows):
        n[0] += 1
        path = tmp_path / f"t{n[0]}.csv"
        t = CsvTrace(path, ["h1", "h2"])
        for row in rows:
            t.append(list(row))
        t.close()
        assert path.read_bytes() == _csv_reference([["h1", "h2"], *rows])

    check()


def test_paused_ecus_count_the_realtime_periods_they_never_commanded(tmp_path):
    """SIGSTOP every ECU process at once for 0.25 s of a 10 ms realtime run (what a pause of the
    machine does to them while the plant, pinned and at a higher priority, runs on): on SIGCONT
    each takes the SYNCs it missed in a row, and the periods whose next SYNC came before their
    peers' states are counted (skipped_periods, the summary's realtime.ecu_skipped_periods).
    Before, those periods left no trace on the ECUs' side: no ECU timer had fired for them."""
    import json
    import os
    import signal
    import subprocess
    import sys
    import time

    import psutil

    out = tmp_path / "run"
    proc = subprocess.Popen([sys.executable, "-m", "canbrake", "run", str(CASE1), "--profile", "realistic",
                             "--mode", "realtime", "--duration", "2.5", "--no-plots", "--out", str(out)],
                            stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    try:
        ecus: list = []
        until = time.monotonic() + 60
        while len(ecus) < 6 and time.monotonic() < until and proc.poll() is None:
            ecus = []
            for c in psutil.Process(proc.pid).children(recursive=True):
                try:
                    if " ".join(c.cmdline()).startswith("canbrake ecu"):
                        ecus.append(c)
                except psutil.Error:
                    pass
            time.sleep(0.02)
        assert len(ecus) == 6, "the six ECU processes never appeared"
        until = time.monotonic() + 60
        while not (out / "bus_load.csv").exists() and time.monotonic() < until:  # the recorder saw a period
            time.sleep(0.02)
        time.sleep(0.3)
        for e in ecus:
            os.kill(e.pid, signal.SIGSTOP)
        time.sleep(0.25)
        for e in ecus:
            os.kill(e.pid, signal.SIGCONT)
        assert proc.wait(timeout=120) == 0
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait()
    s = json.loads((out / "summary.json").read_text())
    skipped = [json.loads((out / f"ecu_c{c}_stats.json").read_text())["skipped_periods"] for c in range(1, 7)]
    assert min(skipped) >= 10, skipped  # ~25 periods of 10 ms stopped
    assert s["realtime"]["ecu_skipped_periods"] == sum(skipped)
    assert min(s["deadline_misses"]["missed_commands_per_car"]) >= 10


def test_summary_reports_the_time_of_the_model_and_controller_steps(tmp_path, monkeypatch):
    """summary.json's compute: the plant model's and every controller's step wall time, measured
    by the nodes; a controller made 2 ms slower shows as such, the physics does not move."""
    import time as _time

    from canbrake.control.chen import ChenConsensusController

    scn = load_scenario(CASE1, overrides={"duration_s": 0.02})
    s = run_scenario(scn, tmp_path / "a", backend="inprocess", plots=False)
    c = s["compute"]
    assert c["model_step_s"]["n"] == s["ticks"] == 20
    assert c["control_step_s"]["n"] == 6 * 20 and c["control_step_s"]["ecus"] == 6
    assert 0 < c["control_step_s"]["mean_s"] <= c["control_step_s"]["max_s"]
    assert c["control_step_s"]["p99_s"] <= c["control_step_s"]["max_s"] * 1.001
    assert c["per_period_s"] == pytest.approx(c["model_step_s"]["mean_s"] + 6 * c["control_step_s"]["mean_s"])
    assert 0 < c["per_period_s"] < c["loop_per_period_s"]  # the engine does more than the formulas

    step = ChenConsensusController.step

    def slow(self, obs):
        t_end = _time.perf_counter() + 2e-3
        while _time.perf_counter() < t_end:
            pass
        return step(self, obs)

    monkeypatch.setattr(ChenConsensusController, "step", slow)
    s2 = run_scenario(scn, tmp_path / "b", backend="inprocess", plots=False)
    c2 = s2["compute"]["control_step_s"]
    assert c2["mean_s"] >= 2e-3 and c2["p99_s"] >= 2e-3 * 0.999
    assert s2["compute"]["model_step_s"]["mean_s"] < 2e-3  # the plant's figure is its own


def test_frame_is_the_message_python_can_would_make():
    """nodes.base.frame (compiled, canbrake.bus._ring.data_frame) builds the can.Message that
    can.Message(arbitration_id=..., data=..., is_extended_id=id > 0x7FF) builds, slot for slot,
    with the slot path and with python-can's constructor."""
    import can

    from canbrake.bus import _ring
    from canbrake.nodes.base import frame

    slots = [s for s in can.Message.__slots__ if s != "__weakref__"]
    before = _ring.fast_messages()
    try:
        for fast in (True, False):
            _ring.fast_messages(fast)
            for aid, data in ((0x123, b"\x01\x02"), (0x7FF, b""), (0x800, bytearray(8)), (0x18FF0001, b"\xff" * 8),
                              (0x1, bytes(range(64))), (0x2, bytes(70))):
                got = frame(aid, data)
                want = can.Message(arbitration_id=aid, data=data, is_extended_id=aid > 0x7FF)
                assert type(got) is can.Message
                assert [getattr(got, s) for s in slots] == [getattr(want, s) for s in slots], (aid, fast)
                assert type(got.data) is bytearray and (got.data is data) == (want.data is data)
    finally:
        _ring.fast_messages(before)


@pytest.mark.parametrize("mode", ["lockstep", "realtime"])
def test_nodes_ask_the_bus_to_wake_them_once_a_phase_in_both_modes(mode):
    """The plant sleeps until every ECU's command pages have come, an ECU in phase 1 until each
    listened peer's state has come (in realtime too, where the period's timer or the compute
    deadline ends a wait for frames that do not come), instead of being woken at each frame."""
    from canbrake.build import build_node

    scn = load_scenario(CASE1, overrides={"mode": mode, "duration_s": 0.1})
    plant = build_node(scn, "plant", run_dir=None)
    first = plant.start(0.0)
    assert plant.frames_wanted() == scn.n_ecus  # one command page per ECU in Chen case 1
    ecu = build_node(scn, "ecu", car=1, run_dir=None)
    ecu.start(0.0)
    assert ecu.frames_wanted() == 1  # waiting for SYNC
    ecu.handle_batch(first, 0.0)
    assert ecu.phase == 1 and len(ecu._listened) >= 1
    assert ecu.frames_wanted() == len(ecu._listened)


def test_realtime_plant_sends_its_period_as_slot_images_where_the_driver_takes_them():
    """On the memory bus (``sends_images``, set by the node driver) the realtime plant's timer returns
    the next period's frames as slot images, no ``can.Message`` each: the same frames, in the same
    order, as the list it returns elsewhere."""
    from canbrake.build import build_node
    from canbrake.bus._ring import messages_of
    from canbrake.bus.memory_shm import SLOT_BYTES

    scn = load_scenario(CASE1, overrides={"mode": "realtime", "duration_s": 0.1})
    got = {}
    for images in (False, True):
        plant = build_node(scn, "plant", run_dir=None)
        plant.sends_images = images
        plant.start(100.0)
        got[images] = plant.on_timer(plant.next_deadline())
        assert plant.k == 1
    assert type(got[False]) is list and type(got[True]) is bytes
    assert len(got[True]) == len(got[False]) * SLOT_BYTES
    assert [(m.arbitration_id, bytes(m.data)) for m in messages_of(got[True])] == \
           [(m.arbitration_id, bytes(m.data)) for m in got[False]]


def test_realtime_command_latency_counts_from_the_sync_on_the_bus_not_from_the_timer():
    """The realtime plant's command latency is what it says (SYNC sent -> last command in): it
    counts from the moment its driver has put the period's SYNC on the bus (after_send), and the
    plant's own time before that (its timer -> SYNC sent: step, measurements, send) is reported
    apart (sync_delay_*), not hidden in it nor in the ECUs' share."""
    import time

    from canbrake.build import build_node

    rt = load_scenario(CASE1, overrides={"mode": "realtime", "duration_s": 0.1})
    ls = load_scenario(CASE1, overrides={"duration_s": 0.1})
    plant = build_node(rt, "plant", run_dir=None)
    t0 = time.time()
    first = plant.start(t0)  # the period's timer fired at t0
    time.sleep(0.003)  # the plant's own work before its SYNC is on the bus
    plant.after_send()
    sent = plant._sync_wall
    assert sent >= t0 + 0.003 and plant._sync_delay.n == 1 and plant._sync_delay.max >= 0.003
    plant.after_send()  # once a period: a later call does not move it
    assert plant._sync_wall == sent and plant._sync_delay.n == 1
    ecus = [build_node(ls, "ecu", car=c, run_dir=None) for c in range(1, 7)]
    for e in ecus:
        e.start(0.0)
    frames, period = list(first), []
    for _phase in range(4):  # the ECUs' answer to tick 0 (the lockstep nodes make the same frames)
        nxt = []
        for e in ecus:
            nxt += e.handle_batch(list(frames), 0.0)
        period += nxt
        frames = nxt
    cmds = [m for m in period if m.arbitration_id in plant._cmd_pages]
    assert len(cmds) == 6
    plant.handle_batch(cmds, sent + 0.0004)
    assert plant._cmd_latency.n == 1 and plant._cmd_latency.max == pytest.approx(0.0004, abs=1e-6)  # (ulp of 1.8e9 s: 2.4e-7)


@pytest.mark.parametrize("late", [0, 1, 2])
def test_realtime_command_latency_quantiles_in_bounded_memory_with_late_periods_ranked_last(late):
    """The plant keeps each period's command latency in a histogram (bounded memory, however long
    the run): p50/p99 are the nearest-rank values of every period within the bins' 0.1 %, a period
    whose commands came too late ranks last as infinitely late, and a quantile or maximum that
    falls on one is null."""
    from canbrake.build import build_node

    rt = load_scenario(CASE1, overrides={"mode": "realtime", "duration_s": 0.1})
    plant = build_node(rt, "plant", run_dir=None)
    rng = np.random.default_rng(3)
    lat = rng.uniform(2e-4, 9e-4, 98)
    for x in lat:
        plant._cmd_latency.add(float(x))
    plant._cmd_late = late
    plant.close()
    ex = plant.stats.extra
    ranked = np.sort(np.concatenate([lat, np.full(late, np.inf)]))
    n = ranked.size
    assert ex["cmd_latency_periods"] == n and ex["cmd_latency_missing"] == late
    for key, q in (("p50", 0.5), ("p99", 0.99)):
        want = ranked[int(np.ceil(q * n)) - 1]
        if np.isinf(want):
            assert ex[f"cmd_latency_{key}_s"] is None
        else:
            assert ex[f"cmd_latency_{key}_s"] == pytest.approx(want, rel=1e-3)
    assert (ex["cmd_latency_max_s"] is None) == (late > 0)
    assert (ex["cmd_latency_p99_s"] is None) == (late >= 1)  # 1 of 99: the 99th percentile's rank is 99
