"""Train physics: carriages, couplers, resistance, brake actuators, rail conditions.

Knows nothing of CAN or controllers. SI units inside; see :mod:`canbrake.physics.train`.
"""
from canbrake.physics.actuator import BrakeActuator
from canbrake.physics.rail import DisturbanceForce, RailConditions, RailEvent
from canbrake.physics.resistance import DavisResistance, davis_1926
from canbrake.physics.train import GRAVITY_MPS2, PlantDiverged, PlantState, TrainPlant

__all__ = [
    "BrakeActuator",
    "DavisResistance",
    "DisturbanceForce",
    "GRAVITY_MPS2",
    "PlantDiverged",
    "PlantState",
    "RailConditions",
    "RailEvent",
    "TrainPlant",
    "davis_1926",
]
