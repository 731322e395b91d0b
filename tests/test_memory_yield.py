"""The memory bus's yield-before-sleep decision (canbrake.run.memory_yield): explicit with
CANBRAKE_MEMORY_YIELD, otherwise from what is runnable now and the load average."""
from __future__ import annotations

import pytest

import canbrake.run as R


@pytest.mark.parametrize("others, load, cpus, yields", [
    (0, 0.1, 2, True),    # idle
    (0, 3.0, 2, True),    # the load average still counts a finished run: nothing runs now
    (2, 0.5, 2, False),   # other work has just started (the load average has not risen yet)
    (1, 3.0, 2, False),   # busy for a while and something else runnable now
    (1, 0.8, 2, True),    # one other task on two CPUs
    (None, 3.0, 2, False),  # no /proc/loadavg: the load average alone
    (None, 0.5, 2, True),
])
def test_auto_yields_unless_the_machine_is_busy_now(monkeypatch, others, load, cpus, yields):
    monkeypatch.delenv("CANBRAKE_MEMORY_YIELD", raising=False)
    monkeypatch.setattr(R, "_runnable_others", lambda *a, **k: others)
    monkeypatch.setattr(R.os, "getloadavg", lambda: (load, load, load))
    monkeypatch.setattr(R.os, "cpu_count", lambda: cpus)
    assert R.memory_yield() is yields


def test_the_variable_decides_when_given(monkeypatch):
    monkeypatch.setattr(R, "_runnable_others", lambda *a, **k: 5)
    for v, want in (("1", True), ("0", False)):
        monkeypatch.setenv("CANBRAKE_MEMORY_YIELD", v)
        assert R.memory_yield() is want


def test_runnable_others_reads_the_running_count():
    n = R._runnable_others(samples=2, gap_s=0.0)
    assert n is None or n >= 0


def test_a_run_decides_before_it_starts_the_forkserver(monkeypatch, tmp_path):
    """The forkserver, just started, imports the node code: asked after it, the rule counted that
    import as other work (a bench between cases: load average at the CPUs, so "no yield")."""
    calls: list[str] = []

    class Started(Exception):
        pass

    def ctx() -> None:
        calls.append("forkserver")
        raise Started

    monkeypatch.setattr(R, "memory_yield", lambda: calls.append("decide") or True)
    monkeypatch.setattr(R, "_mp_context", ctx)
    monkeypatch.setattr(R, "clean_killed_runs", lambda *a, **k: [])
    with pytest.raises(Started):
        R.run_processes(None, tmp_path, None)  # type: ignore[arg-type]
    assert calls == ["decide", "forkserver"]
