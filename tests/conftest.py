"""Shared fixtures: paths and a short Chen case-1 scenario."""
from __future__ import annotations

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
