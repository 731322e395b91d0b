"""canbrake.report.pool.map_tasks: results in order; an interrupt stops the runs that have not
started and ends the busy ones (tests/ issue: Ctrl-C went on starting a report's runs)."""
from __future__ import annotations

import multiprocessing as mp
import os
import time
from pathlib import Path

import pytest

from canbrake.report.pool import map_tasks


def _state(pid: int) -> str | None:
    """The process's state letter in /proc (Z: a zombie, not reaped), or None if there is no such process."""
    try:
        return Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()[0]
    except (OSError, IndexError):
        return None


def _square(x: int) -> int:
    return x * x


def _marked(task: tuple[str, int, float]) -> int:
    """Write ``<dir>/<i>.started``; sleep; on SIGTERM (run.Terminated) write ``<i>.terminated``."""
    from canbrake.run import Terminated

    d, i, sleep_s = task
    try:  # (the interrupt comes once .started exists: inside the try, whenever it lands)
        Path(d, f"{i}.started").write_text(str(os.getpid()))
        time.sleep(sleep_s)
    except Terminated:
        Path(d, f"{i}.terminated").write_text("")
        raise
    return i


@pytest.mark.parametrize("jobs", [1, 2])
def test_results_in_task_order(jobs: int) -> None:
    seen: list[int] = []
    assert map_tasks(_square, range(7), jobs, each=seen.append) == [x * x for x in range(7)]
    assert seen == [x * x for x in range(7)]


def test_interrupt_cancels_pending_and_ends_busy_workers(tmp_path: Path) -> None:
    # task 0 returns at once; 1 and 2 are busy for a minute when the main process is interrupted
    # (after task 0's result); 3..7 must never start
    tasks = [(str(tmp_path), 0, 0.0)] + [(str(tmp_path), i, 60.0) for i in range(1, 8)]

    def interrupt(result: int) -> None:
        deadline = time.monotonic() + 30
        while time.monotonic() < deadline and len(list(tmp_path.glob("*.started"))) < 3:
            time.sleep(0.05)  # both workers have taken their minute-long task
        raise KeyboardInterrupt

    with pytest.raises(KeyboardInterrupt):
        map_tasks(_marked, tasks, 2, each=interrupt)
    started = sorted(int(p.stem) for p in tmp_path.glob("*.started"))
    terminated = sorted(int(p.stem) for p in tmp_path.glob("*.terminated"))
    assert started == [0, 1, 2]
    assert terminated == [1, 2]           # the busy runs were told to end (SIGTERM -> Terminated)
    # every worker ended and reaped: no process of ours left (by the OS, not the Popen objects'
    # bookkeeping, which can miss a worker that the executor's thread and the cleanup both waited for)
    left = {p.pid: _state(p.pid) for p in mp.active_children()}
    assert all(st is None for st in left.values()), left
