"""`canbrake bench` machinery (no timing assertions: figures are numbers, not pass/fail)."""
from __future__ import annotations

import os

from canbrake.benchmark import _failed, _row, run_case_subprocess, table
from canbrake.nodes.rt import setup_realtime


def test_a_failing_case_is_a_row_not_a_traceback():
    res = run_case_subprocess({"scenario": "no_such_scenario.yaml", "backend": "inprocess"})
    assert res["status"] == "failed" and "no_such_scenario" in res["message"]
    out = table({"figures": [_failed("lockstep in-process engine", res, ">= 10000 periods/s"),
                             _row("codec decode", 0.5, "us/frame", "cantools", 1.5, 3.0, ">= 3x", True),
                             _row("x", 2.0, "ms", target="< 0.5 ms", met=False, status="diverged")]})
    lines = out.splitlines()
    assert "FAILED" in lines[1] and "yes" in lines[2] and "3.00x" in lines[2]
    assert "DIVERGED (NO)" in lines[3]


def test_realtime_scheduling_can_be_turned_off_and_says_so(monkeypatch):
    monkeypatch.setenv("CANBRAKE_RT_SCHED", "off")
    assert setup_realtime("plant") == "SCHED_OTHER (CANBRAKE_RT_SCHED=off)"
    assert os.sched_getscheduler(0) == os.SCHED_OTHER
