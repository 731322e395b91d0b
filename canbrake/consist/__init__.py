"""Consists as data: the scenario's ``train`` section, one schema per physics model family.

Every family is a pydantic model with a ``model`` discriminator that knows its vehicles and
builds its plant (an object following :class:`canbrake.physics.contract.PlantModel`). Vehicle
types are defined once and repeated (``vehicles: [{type: c80, count: 105}]``); tables (route,
reference curves) come from data files next to the scenario.
"""
