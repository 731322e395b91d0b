"""Fail-safe reaction of each car's brake unit when its brake commands stop arriving intact.

Set-up throughout: Chen case 1 (paper profile, ideal actuator, 1 ms period); from 0.05 s on, car 3's
brake commands (BRAKE_CMD_C3, 0x083) are lost or corrupted on the bus. With
``safety.command_timeout_s = 0.02`` the plant's brake unit for car 3 must switch to its own
fail-safe force, ``mass x failsafe_decel_mps2``, once 20 periods have passed without a valid
command — and not a tick earlier.
"""
from __future__ import annotations

import json

import numpy as np
import pytest

from canbrake.analysis.summary import read_signals
from canbrake.run import run_scenario
from canbrake.scenario import ScenarioError, load_scenario
from conftest import CASE1

CMD3 = 0x083
M3 = float(load_scenario(CASE1).vehicle_masses_kg()[2])  # car 3's mass in case 1 (kg), Table 2
DECEL = 1.2   # m/s^2


def _scenario(impairment: dict, *, timeout: float | None = 0.02, latch: bool = True, duration: float = 0.3):
    over = {"duration_s": duration, "bus": {"impairments": [impairment]},
            "safety": {"command_timeout_s": timeout, "failsafe_decel_mps2": DECEL, "latch": latch}}
    return load_scenario(CASE1, overrides=over)


def _run(scn, out, backend="inprocess"):
    s = run_scenario(scn, out, backend=backend, plots=False)
    assert s["status"] == "ok", s["message"]
    return s, read_signals(out / "signals.csv")


LOSS = {"type": "loss", "probability": 1.0, "ids": [CMD3], "start_s": 0.05}


def test_lost_commands_engage_the_failsafe_brake_after_the_timeout(tmp_path):
    s, sig = _run(_scenario(LOSS), tmp_path)
    fs = sig["failsafe_c3"]
    # the last command car 3's unit receives is tick 49's; tick 49 + 20 is still within the timeout
    first = int(np.flatnonzero(fs)[0])
    assert first == 49 + 20 + 1
    assert fs[first:].all() and not fs[:first].any()
    for c in (1, 2, 4, 5, 6):
        assert not sig[f"failsafe_c{c}"].any()
    # ideal actuator: the applied force is the fail-safe force from the next tick on ...
    applied = sig["brake_applied_n_c3"]
    np.testing.assert_allclose(applied[first + 1:-1], M3 * DECEL)
    # ... while the held command is still what the unit last received
    assert (sig["brake_cmd_n_c3"][50:-1] == sig["brake_cmd_n_c3"][49]).all()
    assert s["failsafe"] == {"command_timeout_s": 0.02, "activations": 1,
                             "car_ticks": len(fs) - 1 - first, "first_activation_s": {"c3": 0.07}}
    assert s["frames"]["commands_missed"] == 300 - 50


def test_without_a_timeout_the_last_command_is_held(tmp_path):
    s, sig = _run(_scenario(LOSS, timeout=None), tmp_path)
    assert "failsafe_c3" not in sig and "failsafe" not in s
    held = sig["brake_cmd_n_c3"][49]
    assert held > M3 * DECEL  # so the test above can tell the two forces apart
    np.testing.assert_allclose(sig["brake_applied_n_c3"][51:-1], held)


def test_corrupted_commands_fail_the_e2e_check_and_engage_the_failsafe(tmp_path):
    corrupt = {"type": "corrupt", "probability": 1.0, "n_bits": 1, "ids": [CMD3], "start_s": 0.05}
    s, sig = _run(_scenario(corrupt), tmp_path)
    assert s["frames"]["commands_corrupted"] == 300 - 50
    assert int(np.flatnonzero(sig["failsafe_c3"])[0]) == 70


def test_unlatched_failsafe_releases_on_the_next_valid_command(tmp_path):
    window = {**LOSS, "stop_s": 0.15}
    s, sig = _run(_scenario(window, latch=False), tmp_path)
    fs = sig["failsafe_c3"]
    on = np.flatnonzero(fs)
    assert on[0] == 70 and on[-1] == 149 and len(on) == 80  # until tick 150's command arrives
    assert s["failsafe"]["activations"] == 1
    np.testing.assert_allclose(sig["brake_applied_n_c3"][71:150], M3 * DECEL)
    latched, sig2 = _run(_scenario(window, latch=True), tmp_path / "latched")
    assert sig2["failsafe_c3"][70:-1].all()


def test_failsafe_is_the_same_on_the_cross_process_bus(tmp_path):
    scn = _scenario(LOSS, duration=0.1)
    _run(scn, tmp_path / "inprocess")
    s, _ = _run(scn, tmp_path / "memory", backend="memory")
    assert s["failsafe"]["first_activation_s"] == {"c3": 0.07}
    assert (tmp_path / "memory" / "signals.csv").read_bytes() == (tmp_path / "inprocess" / "signals.csv").read_bytes()
    assert json.loads((tmp_path / "memory" / "plant_stats.json").read_text())["failsafe_activations"] == 1


def test_timeout_shorter_than_a_period_is_refused():
    with pytest.raises(ScenarioError, match="safety.command_timeout_s"):
        load_scenario(CASE1, overrides={"safety": {"command_timeout_s": 0.0005}})
    with pytest.raises(ScenarioError, match="failsafe_decel_mps2"):
        load_scenario(CASE1, overrides={"safety": {"command_timeout_s": 0.01, "failsafe_decel_mps2": -1}})
