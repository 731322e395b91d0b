"""Consists as data: the scenario's ``train`` section, one schema per physics model family.

Every family is a pydantic model with a ``model`` discriminator that knows its vehicles and
builds its plant (an object following :class:`canbrake.physics.contract.PlantModel`). Vehicle
types are defined once and repeated (``vehicles: [{type: c80, count: 105}]``); tables (route,
reference curves) come from data files next to the scenario.
"""
from __future__ import annotations

#: the train model families besides "coupled" (defined in canbrake/scenario.py): each a pydantic
#: class with ``model: Literal[...]``, ``vehicle_count()``, ``vehicle_masses_kg()`` and
#: ``build_plant(scn, base_dir)``; one line per family.
TRAIN_MODELS: tuple[type, ...] = ()
