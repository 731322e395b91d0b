"""Combinations of vehicles, equipment and controllers that cannot work are refused before a run
with one line naming the field (issue 27): a brake pipe without a locomotive to feed it, adhesion
on a vehicle without driven axles, a driver's valve away from the head of the train, a controller
for more axles than its vehicle has. Each is what the plant would otherwise silently ignore."""
from __future__ import annotations

import subprocess
import sys

import pytest

from canbrake.scenario import ScenarioError, load_scenario

NO_DIST = {"train.disturbance.enabled": False, "train.disturbance.vehicles": []}


def refused(name: str, overrides: dict, match: str) -> None:
    with pytest.raises(ScenarioError, match=match) as e:
        load_scenario(name, overrides=overrides)
    assert "\n" not in str(e.value)


def test_a_brake_pipe_without_a_locomotive_to_feed_it():
    refused("li2024_pid", {"train.vehicles": [{"type": "c80", "count": 10}], **NO_DIST},
            r"--set train.vehicles: train.vehicles.0.type: vehicle type c80 has an air brake, but nothing feeds the "
            r"brake pipe: the leading vehicle \(c80\) is not a locomotive")
    # with ECP too: the head-end unit and the pipe's air come from the locomotive
    refused("li2024_ecp_over_can", {"train.vehicles": [{"type": "c80", "count": 5}, {"type": "hxd1"}], **NO_DIST},
            r"leading vehicle \(c80\) is not a locomotive .*with ECP: the head-end unit")


def test_adhesion_on_a_wagon_without_driven_axles():
    refused("li2024_pid", {"train.vehicle_types.c80.wheels": {"model": "adhesion_limit", "mu": 0.3}},
            r"train.vehicle_types.c80.wheels: adhesion on vehicle type c80, which has no driven axles")


def test_the_drivers_valve_away_from_the_head_of_the_train():
    refused("li2024_pid", {"ecus.0.vehicle": 3}, r"ECU loco on vehicle 3 runs li2024_pid, which works the driver's "
                                                 r"brake valve \(airbrake_apply\): the valve is on the leading vehicle")


def test_a_locomotive_controller_on_an_ecp_wagon():
    refused("hh106_ecp_consensus", {"ecus.1.controller.name": "li2024_pid", "ecus.1.vehicles": "2-2",
                                    "ecus.1.name": "wagon2"},
            r"ECU wagon2 on vehicle 2 runs li2024_pid, which works the driver's brake valve")
    # a force-only controller is what the wagon's ECP unit takes: still fine
    assert load_scenario("hh106_ecp_consensus").n_ecus == 106


def test_a_traction_controller_on_a_vehicle_without_axles():
    refused("cai2014_case1", {"ecus.0.vehicle": 2},
            r"ECU traction on vehicle 2 \(carriage\) runs cai2014 for 4 driven axles, but vehicle 2 has no driven "
            r"axles \(train.vehicle_types.carriage.wheels\)")
    refused("cai2014_case1", {"ecus.0.controller.params.axles": 6},
            r"runs cai2014 for 6 driven axles, but vehicle 1 has 4 driven axles")


def test_the_cli_says_it_in_one_line_and_exits_2(tmp_path):
    r = subprocess.run([sys.executable, "-m", "canbrake", "run", "cai2014_case1", "--set", "ecus.0.vehicle=2",
                        "--bus", "inprocess", "--out", str(tmp_path / "r")], capture_output=True, text=True)
    assert r.returncode == 2 and "Traceback" not in r.stderr and len(r.stderr.strip().splitlines()) == 1, r.stderr
    assert not (tmp_path / "r").exists()


def test_a_misspelt_listens_is_one_line():
    refused("chen2023_case1_fine_rail", {"ecus": [{"vehicles": "1-6", "listens": "neighbors"}]},
            r"ecus.0.listens: expected all, none, neighbours or a list of ECU names, got 'neighbors'")
