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


def component_scenario(types: dict, vehicles: list, speed_kmh: float = 60.0, **train: object) -> dict:
    """A scenario mapping of a train built from ``train.vehicle_types`` and ``vehicles`` (issue
    27's component schema), 2 s at 10 ms from ``speed_kmh``; ``train``: further train-level keys."""
    return {"name": "t", "duration_s": 2.0, "control_period_s": 0.01,
            "train": {"vehicle_types": types, "vehicles": vehicles, **train},
            "initial": {"speed_kmh": speed_kmh}, "reference": {"speed_kmh": speed_kmh, "decel_kmh_per_s": 1.0}}


def component_plant(data: dict):
    """The coupled kernel's TrainPlant that scenario mapping ``data`` builds."""
    import copy

    from canbrake.build import build_plant_model
    from canbrake.scenario import resolve

    return build_plant_model(resolve(copy.deepcopy(data), "t.yaml")).plant


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

