"""Observation.of (the ECU's once-per-period construction without the frozen dataclass's
per-field setattr) gives the very Observation the constructor gives, with every field set."""
from __future__ import annotations

import dataclasses
from pathlib import Path

from canbrake.control.base import Observation
from canbrake.run import run_scenario
from canbrake.scenario import load_scenario

ROOT = Path(__file__).resolve().parents[1]


def test_the_ecus_observations_have_every_field_and_equal_the_constructors(tmp_path, monkeypatch):
    made = []
    of = Observation.of.__func__

    def spy(cls, **fields):
        obs = of(cls, **fields)
        made.append(obs)
        return obs

    monkeypatch.setattr(Observation, "of", classmethod(spy))
    scn = load_scenario(ROOT / "scenarios" / "emu8_example.yaml", overrides={"duration_s": 0.03})
    run_scenario(scn, tmp_path, backend="inprocess", plots=False)
    names = {f.name for f in dataclasses.fields(Observation)}
    assert made and all(set(vars(o)) == names for o in made)
    for o in made[:20]:
        again = Observation(**vars(o))
        assert again == o and repr(again) == repr(o)
