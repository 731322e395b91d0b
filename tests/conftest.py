"""Shared fixtures: paths and a short Chen case-1 scenario; test distribution over pytest-xdist
workers (a private channel directory per worker)."""
from __future__ import annotations

import os
import shutil
import tempfile
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
SCENARIOS = ROOT / "scenarios"
CASE1 = SCENARIOS / "chen2023_case1_fine_rail.yaml"


@pytest.fixture
def case1_short():
    """Chen case 1 (paper profile) cut to 0.3 s of simulated time."""
    from canbrake.scenario import load_scenario

    return load_scenario(CASE1, overrides={"duration_s": 0.3})


def default_sigint() -> None:
    """preexec_fn for children the tests interrupt: a shell that starts jobs in the background
    hands them SIGINT ignored, and Python then never raises KeyboardInterrupt; restore it."""
    import signal

    signal.signal(signal.SIGINT, signal.SIG_DFL)


def pytest_configure(config: pytest.Config) -> None:
    """Under pytest-xdist each worker gets its own in-memory-bus channel directory
    ($CANBRAKE_SHM_DIR, inherited by every run and node it starts), so that one worker's start-of-run
    clean-up of stale channels never meets another worker's channels being created. Tests that
    need a directory of their own still set one."""
    worker = os.environ.get("PYTEST_XDIST_WORKER")
    if worker and "CANBRAKE_SHM_DIR" not in os.environ:
        base = "/dev/shm" if os.path.isdir("/dev/shm") else None
        d = tempfile.mkdtemp(prefix=f"cbtest-{worker}-", dir=base)
        os.environ["CANBRAKE_SHM_DIR"] = d
        config.stash[_SHM_DIR] = d


def pytest_sessionfinish(session: pytest.Session) -> None:
    """Stop the node processes' forkserver if a test left it running (canbrake.run's API keeps it
    for the next run; `canbrake run` stops it itself): every child of the session is reaped."""
    import sys

    run = sys.modules.get("canbrake.run")
    if run is not None:
        run.stop_node_server()


def pytest_unconfigure(config: pytest.Config) -> None:
    d = config.stash.get(_SHM_DIR, None)
    if d is not None:
        shutil.rmtree(d, ignore_errors=True)


_SHM_DIR = pytest.StashKey[str]()

