"""`canbrake bench`: memory in PSS (issue 28 defect 3) and the floor row (issue 26): no timed
assertions, only that the figures are what they say and come from the same run."""
from __future__ import annotations

import multiprocessing as mp
import math
import os

import pytest

from canbrake import benchmark
from canbrake.benchmark import pss_bytes, tree_memory


def _pss_of_smaps(pid: int) -> int:
    """The sum of the "Pss:" lines of /proc/PID/smaps (every mapping): what smaps_rollup rolls up."""
    total = 0
    with open(f"/proc/{pid}/smaps") as f:
        for ln in f:
            if ln.startswith("Pss:"):
                total += int(ln.split()[1]) * 1024
    return total


def _sleep_until(conn) -> None:  # noqa: ANN001 - a forked child holding the parent's pages
    conn.recv()


@pytest.mark.skipif(not os.path.exists("/proc/self/smaps_rollup"), reason="needs /proc/PID/smaps_rollup")
def test_pss_of_this_process_is_its_smaps_pss_and_less_than_rss():
    block = bytearray(os.urandom(1 << 20)) * 32  # 32 MB of this process's own pages
    pss = pss_bytes(os.getpid())
    assert pss is not None and pss == pytest.approx(_pss_of_smaps(os.getpid()), rel=0.05)
    assert len(block) == 32 << 20
    assert pss_bytes(2 ** 22 + 12345) is None  # no such process


def test_the_process_tree_from_children_files_is_the_tree_from_every_stat_file():
    """`_tree_pids` (each process's /proc/PID/task/*/children) finds the same descendants as a
    scan of every /proc/PID/stat, grandchildren and a thread's children included."""
    import subprocess
    import threading

    kids = [subprocess.Popen(["sh", "-c", "sleep 5 & sleep 5 & wait"]) for _ in range(2)]
    from_thread: list[subprocess.Popen] = []
    t = threading.Thread(target=lambda: from_thread.append(subprocess.Popen(["sleep", "5"])))
    t.start()
    t.join()
    try:
        import time

        def ppid(pid: int) -> int:
            with open(f"/proc/{pid}/stat") as f:
                st = f.read()
            return int(st[st.rindex(")") + 2:].split()[1])

        shells = {k.pid for k in kids}
        deadline = time.monotonic() + 5
        while True:  # until each shell has forked its two sleeps (this process may have other children)
            scan = benchmark._tree_pids_scan(os.getpid())
            grand = [p for p in scan if p not in shells and p != os.getpid() and ppid(p) in shells]
            if len(grand) >= 4 or time.monotonic() > deadline:
                break
            time.sleep(0.02)
        tree = benchmark._tree_pids(os.getpid())
        assert sorted(tree) == sorted(scan)
        assert len(grand) == 4 and {k.pid for k in kids + from_thread} | set(grand) <= set(tree)
        assert tree[0] == os.getpid()
    finally:
        for k in kids + from_thread:
            k.kill()
            k.wait()


@pytest.mark.skipif(not os.path.exists("/proc/self/smaps_rollup"), reason="needs /proc/PID/smaps_rollup")
def test_tree_memory_counts_forked_pages_once_in_pss_and_per_process_in_rss():
    """Three forked children share the parent's 64 MB: RSS summed over the four processes counts
    them four times, PSS about once (the figure `canbrake bench` reports)."""
    block = bytearray(os.urandom(1 << 20)) * 64
    ctx = mp.get_context("fork")
    pipes = [ctx.Pipe() for _ in range(3)]
    kids = [ctx.Process(target=_sleep_until, args=(b,)) for _, b in pipes]
    for k in kids:
        k.start()
    try:
        m = tree_memory(os.getpid())
        assert {k.pid for k in kids} <= set(m["procs"])
        assert m["rss"] > 3.5 * len(block)  # the block, counted once per process
        assert m["pss"] < 0.5 * m["rss"] and m["pss"] > len(block)
        assert m["pss"] == sum(v[1] for v in m["procs"].values())
    finally:
        for a, _ in pipes:
            a.send(None)
        for k in kids:
            k.join(10)
    assert len(block) == 64 << 20


def test_memory_sampler_reports_pss_total_and_per_ecu_process(monkeypatch):
    """The sampler's figures: totals in PSS and RSS, the largest ECU process's PSS (roles from
    the nodes' process titles)."""
    procs = {10: ("other", 50 << 20, 60 << 20), 11: ("ecu", 20 << 20, 90 << 20), 12: ("ecu", 22 << 20, 91 << 20),
             13: ("plant", 25 << 20, 95 << 20)}
    monkeypatch.setattr(benchmark, "tree_memory", lambda pid: {"pss": sum(v[1] for v in procs.values()),
                                                              "rss": sum(v[2] for v in procs.values()),
                                                              "procs": procs})
    s = benchmark._MemorySampler()
    s.sample()
    f = s.figures()
    assert f["peak_pss_mb"] == 117 and f["peak_rss_mb"] == 336
    assert f["ecu_pss_mb"] == 22 and f["ecu_rss_mb"] == 91 and f["ecu_processes"] == 2 and f["plant_pss_mb"] == 25


def test_memory_sampler_takes_the_per_ecu_pss_while_every_ecu_process_runs(monkeypatch):
    """As ECU processes exit, the last ones carry the shared pages the others left (PSS counts a
    page shared by k processes 1/k in each): the per-ECU figure comes from the samples where the
    most ECU processes were alive (48 ECUs measured 20.5 MB each while all ran, 31.8 at the end)."""
    states = [{11: ("ecu", 30 << 20, 90 << 20)},  # starting: alone with its shared pages
              {11: ("ecu", 20 << 20, 90 << 20), 12: ("ecu", 21 << 20, 90 << 20), 13: ("ecu", 20 << 20, 90 << 20)},
              {11: ("ecu", 20 << 20, 91 << 20), 12: ("ecu", 22 << 20, 92 << 20), 13: ("ecu", 20 << 20, 90 << 20)},
              {12: ("ecu", 35 << 20, 92 << 20)}]  # the last one exiting
    cur: list[dict] = []
    monkeypatch.setattr(benchmark, "tree_memory", lambda pid: {"pss": sum(v[1] for v in cur[0].values()),
                                                              "rss": sum(v[2] for v in cur[0].values()),
                                                              "procs": cur[0]})
    s = benchmark._MemorySampler()
    for st in states:
        cur[:] = [st]
        s.sample()
    f = s.figures()
    assert f["ecu_pss_mb"] == 22 and f["ecu_rss_mb"] == 92 and f["ecu_processes"] == 3
    assert f["peak_pss_mb"] == 62  # the total is the peak of the sums, every sample


def _children() -> set[int]:
    try:
        with open(f"/proc/{os.getpid()}/task/{os.getpid()}/children") as f:
            return {int(x) for x in f.read().split()}
    except OSError:
        return set()


def test_floor_runs_plant_and_ecu_processes_over_the_memory_bus_and_reaps_them(monkeypatch):
    from canbrake.bus.memory_shm import list_channels
    from canbrake.floor import run_floor

    # no yield before a blocking wait: with it, four processes kept runnable by a busy machine can
    # find every frame there after their yield for all 0.2 s and never block (0 sleeps, seen once)
    monkeypatch.setenv("CANBRAKE_MEMORY_YIELD", "0")
    before = set(list_channels())
    res = run_floor(3, 0.2)
    assert res["status"] == "ok", res
    assert res["periods"] > 0 and res["periods_per_s"] > 0 and res["ecus"] == 3
    assert 0 < res["round_trip_mean_s"] <= res["round_trip_p99_s"] <= res["round_trip_max_s"]
    assert res["sleeps_per_period"] > 0  # the ECUs and the plant blocked on the bus and were woken
    assert not [c for c in set(list_channels()) - before if c.startswith("floor-")]  # its channel is gone
    from multiprocessing import active_children

    assert not [p for p in active_children() if p.name.startswith("canbrake-floor")]


def test_two_phase_floor_waits_for_every_peer_state_before_the_word_to_the_plant(monkeypatch):
    """phases=2: each ECU answers the tick with its state word and sends its word to the plant
    only once every peer's state word of that tick is in (an ECU that finds one of another tick
    fails the run); the processes are reaped as with one exchange."""
    from multiprocessing import active_children

    from canbrake.floor import run_floor

    monkeypatch.setenv("CANBRAKE_MEMORY_YIELD", "0")
    two = run_floor(3, 0.3, phases=2)
    assert two["status"] == "ok", two
    assert two["phases"] == 2 and two["periods"] > 0 and two["sleeps_per_period"] > 0
    assert not [p for p in active_children() if p.name.startswith("canbrake-floor")]
    with pytest.raises(ValueError, match="phases"):
        run_floor(3, 0.1, phases=3)


def test_realtime_floor_paces_the_ticks_and_counts_the_periods_whose_words_come_late(monkeypatch):
    """period_s > 0: ticks on the period's wall-clock grid (so the periods are duration / period),
    realtime scheduling where permitted (said either way), a round trip and a deadline miss as a
    realtime run counts them; a period no process layout can answer in (20 us) misses nearly
    always, and an ECU that gets the next tick before its peers' states drops the tick it was in
    (not a failure), as a realtime ECU does."""
    from multiprocessing import active_children

    from canbrake.floor import run_floor

    monkeypatch.setenv("CANBRAKE_MEMORY_YIELD", "0")
    ok = run_floor(3, 0.4, phases=2, period_s=0.004)
    assert ok["status"] == "ok", ok
    assert 90 <= ok["periods"] <= 101 and ok["period_s"] == 0.004
    assert "plant " in ok["scheduling"] and "ECUs " in ok["scheduling"]  # SCHED_FIFO or the fallback, said
    assert 0 < ok["round_trip_p50_s"] <= ok["round_trip_p99_s"] <= ok["round_trip_max_s"]
    assert ok["deadline_misses"] <= ok["periods"] and ok["deadline_miss_pct"] < 50  # 4 ms: most answered
    short = run_floor(3, 0.2, phases=2, period_s=2e-5)
    assert short["status"] == "ok", short
    assert short["deadline_miss_pct"] > 50 and short["round_trip_p50_s"] == math.inf
    assert not [p for p in active_children() if p.name.startswith("canbrake-floor")]
    with pytest.raises(ValueError, match="period_s"):
        run_floor(3, 0.1, phases=2, period_s=float("nan"))


def test_bench_puts_the_floor_of_the_same_run_beside_the_lockstep_and_realtime_figures(monkeypatch):
    """run_bench measures the floor and every lockstep / realtime row carries value / that floor
    (the lockstep figures are stand-ins here: what is checked is where the ratios come from)."""
    from canbrake.benchmark import _row, run_bench

    monkeypatch.setattr(benchmark, "lockstep_figures", lambda *a: [
        _row("lockstep one process per ECU (memory bus)", 500.0, "periods/s", target=">= 25 % of the floor",
             floor_share_target=0.25),
        _row("memory per ECU process (PSS), one process per ECU", 22.0, "MB")])
    monkeypatch.setattr(benchmark, "realtime_figures", lambda *a: [
        _row("realtime 1 ms p99 command latency", 0.4, "ms"), _row("realtime 10 ms deadline misses", 0.0, "%")])
    res = run_bench(only=("lockstep", "realtime"), duration_s=0.2, repeat=1)
    def key(fig: str) -> str:
        if not fig.startswith("floor"):
            return fig
        return "rt1" if "realtime 1 ms" in fig else "rt10" if "realtime 10 ms" in fig else \
            "floor2" if "two phases" in fig else "floor"

    rows = {key(r["figure"]): r for r in res["figures"]}
    floor, floor2 = rows["floor"], rows["floor2"]
    assert floor["status"] == "ok" and floor["value"] > 0 and floor["floor_ecus"] == 6
    assert floor2["status"] == "ok" and floor2["value"] > 0 and floor2["floor_ecus"] == 6
    lock = rows["lockstep one process per ECU (memory bus)"]
    assert lock["floor"] == floor["value"] and lock["floor_ratio"] == pytest.approx(500.0 / floor["value"])
    assert lock["met"] == (500.0 / floor["value"] >= 0.25)  # judged against the one-exchange floor
    assert lock["protocol_floor"] == floor2["value"] and "of the two-phase floor" in lock["note"]
    # each realtime row is compared with the realtime floor of its period (paced, realtime scheduling)
    rt1, rt10 = rows["rt1"], rows["rt10"]
    assert rt1["status"] == "ok" and rt10["status"] == "ok" and "scheduled as realtime nodes" in rt1["note"]
    lat = rows["realtime 1 ms p99 command latency"]
    if rt1["value"] is not None:  # (a floor whose p99 fell on a missed period has no latency to compare)
        assert lat["floor"] == pytest.approx(rt1["value"])
        assert lat["floor_ratio"] == pytest.approx(0.4 / lat["floor"])
    miss10 = rows["realtime 10 ms deadline misses"]
    assert miss10["floor"] == pytest.approx(rt10["deadline_miss_pct"])
    assert rows["memory per ECU process (PSS), one process per ECU"]["floor"] == pytest.approx(floor["ecu_pss_mb"])
    assert "vs floor" in benchmark.table(res).splitlines()[0]


def test_apply_floor_compares_rates_latency_misses_and_memory_with_the_floor_of_the_same_size():
    from canbrake.benchmark import _row, apply_floor, table

    floors = {6: {"periods_per_s": 2000.0, "round_trip_p99_s": 0.0005, "over_1ms_pct": 2.0, "over_10ms_pct": 0.0,
                  "ecu_pss_mb": 20.0},
              "realtime 1 ms": {"round_trip_p99_s": math.inf, "deadline_miss_pct": 2.0},
              "realtime 10 ms": {"round_trip_p99_s": 0.0006, "deadline_miss_pct": 0.0},
              12: {"periods_per_s": 400.0, "round_trip_p99_s": 0.002, "over_1ms_pct": 50.0, "over_10ms_pct": 1.0}}
    rows = [_row("floor: plant + 6 ECU processes, memory bus, no model", 2000.0, "periods/s", floor_ecus=6),
            _row("lockstep in-process engine", 500.0, "periods/s"),
            _row("scale 12 cars (Chen), one process per ECU", 100.0, "periods/s", cars=12),
            _row("scale 48 cars (Chen), in process", 10.0, "periods/s", cars=48),  # no floor of 48 measured
            _row("realtime 1 ms deadline misses", 5.0, "% of periods", status="diverged"),
            _row("realtime 10 ms deadline misses", 0.0, "% of periods"),
            _row("realtime 1 ms p99 command latency", None, "ms", status="ok"),
            _row("memory per ECU process (PSS), one process per ECU", 22.0, "MB")]
    apply_floor(rows, floors)
    by = {r["figure"]: r for r in rows}
    assert "floor_ratio" not in rows[0]
    assert by["lockstep in-process engine"]["floor_ratio"] == 0.25
    assert by["scale 12 cars (Chen), one process per ECU"]["floor_ratio"] == 0.25  # the 12-ECU floor
    assert "floor_ratio" not in by["scale 48 cars (Chen), in process"]
    assert by["realtime 1 ms deadline misses"]["floor_ratio"] == 2.5  # a diverged run's figure still compares
    rt10 = by["realtime 10 ms deadline misses"]
    assert rt10["floor"] == 0.0 and rt10["floor_ratio"] is None
    assert "floor_ratio" not in by["realtime 1 ms p99 command latency"]
    assert by["memory per ECU process (PSS), one process per ECU"]["floor_ratio"] == pytest.approx(1.1)
    lines = table({"figures": rows}).splitlines()
    assert "0.25x (2,000)" in lines[2] and "- (0.00)" in lines[6]
