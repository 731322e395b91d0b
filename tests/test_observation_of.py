"""The ECU's once-per-period Observation (canbrake.nodes._ecu.EcuPeriod.decide, and
Observation.of: without the frozen dataclass's per-field setattr) is the very Observation the
constructor gives, with every field set."""
from __future__ import annotations

import dataclasses
from pathlib import Path

import canbrake.nodes.ecu as ecu_mod
from canbrake.control.base import Observation
from canbrake.nodes._ecu import EcuPeriod
from canbrake.run import run_scenario
from canbrake.scenario import load_scenario

ROOT = Path(__file__).resolve().parents[1]


def test_the_ecus_observations_have_every_field_and_equal_the_constructors(tmp_path, monkeypatch):
    made = []

    class Spy:
        def __init__(self, controller):
            self.controller = controller

        def step(self, obs):
            made.append(obs)
            return self.controller.step(obs)

    class SpyPeriod(EcuPeriod):
        def decide(self, controller, *args):
            return super().decide(Spy(controller), *args)

    monkeypatch.setattr(ecu_mod, "EcuPeriod", SpyPeriod)
    scn = load_scenario(ROOT / "scenarios" / "emu8_example.yaml", overrides={"duration_s": 0.03})
    run_scenario(scn, tmp_path, backend="inprocess", plots=False)
    names = {f.name for f in dataclasses.fields(Observation)}
    assert made and all(set(vars(o)) == names for o in made)
    for o in made[:20]:
        again = Observation(**vars(o))
        assert again == o and repr(again) == repr(o)


def test_observation_of_equals_the_constructor():
    fields = {f.name: i for i, f in enumerate(dataclasses.fields(Observation))}
    o = Observation.of(**fields)
    assert type(o) is Observation and o == Observation(**fields) and repr(o) == repr(Observation(**fields))
