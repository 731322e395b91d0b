"""Testing your own controller with canbrake's pytest plugin: plain `pytest`, nothing to import
but your controller. The fixtures (canbrake_scenario, canbrake_run, canbrake_memory_run,
canbrake_rogue, railway) come with canbrake; see docs/testing-your-controller.md.

    pytest examples/tests
"""
import sys
from pathlib import Path

import pytest

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))  # examples/: where my_controller.py lives
import my_controller  # noqa: E402,F401  (registers the controller "my_pd")


@pytest.fixture
def scenario(canbrake_scenario):
    """Chen's six-car train braking from ~90 km/h, driven by my controller, 0.3 s."""
    return canbrake_scenario("chen2023_case1_fine_rail", duration_s=0.3, controller__name="my_pd",
                             controller__params={"kp": 20.0, "kc": 5.0})


def test_tracks_the_reference_speed(canbrake_run, scenario, railway):
    r = canbrake_run(scenario)                      # in this process: fast and deterministic
    railway.speed_band(r, band_kmh=5.0, after_s=0.2)


def test_stops_in_time(canbrake_run, scenario, railway):
    r = canbrake_run(scenario)
    railway.stopping_distance(r, tolerance_m=5.0)   # against v0*²/2a*


def test_keeps_couplers_within_a_bound(canbrake_run, scenario, railway):
    r = canbrake_run(scenario, bus="virtual")      # python-can's virtual bus
    railway.deflection_within(r, bound_m=0.10)


def test_brake_units_reject_a_forged_command(canbrake_run, canbrake_rogue, scenario, railway):
    """A rogue node sends "full brake, car 1" with a wrong E2E checksum every 10 ms: every one is
    rejected, and the train still behaves."""
    attacked = canbrake_rogue(scenario, 0x081, bytes.fromhex("0000FFFF7F"), rate_hz=100, start_s=0.1)
    r = canbrake_run(attacked)
    railway.e2e_rejections(r, at_least=15)
    railway.speed_band(r, band_kmh=5.0, after_s=0.2)


def test_on_the_cross_process_bus(canbrake_memory_run, scenario, railway):
    r = canbrake_memory_run(scenario, duration_s=0.1)  # one OS process per ECU, as `canbrake run`
    railway.no_deadline_misses(r)
    railway.e2e_rejections(r)                         # none
