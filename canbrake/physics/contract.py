"""The plant contract: what every physics model implements so that the one plant node
(:mod:`canbrake.nodes.plant`) can drive it, whatever the train.

A plant model is a vectorised, SI-only object over the vehicles of a consist, indexed from the
front (0 = first vehicle). The plant node holds each ECU's newest command (zero-order hold) and
calls :meth:`PlantModel.step` once per integration step; between steps it reads
:meth:`PlantModel.measurements` for the sensor frames and the trace.

Commands (``step``'s mapping) are per-vehicle arrays of shape ``(n_vehicles,)``, by name; a
vehicle whose ECU does not command that input holds NaN there and the model applies its own
default (no force, brake released, ...). Names the models understand (a model ignores names it
does not know, and lists the ones it uses in ``command_names``):

=====================  ==========================================================================
``brake_force_n``      longitudinal force demand of the vehicle's brake/traction equipment (N;
                       + brakes, − is traction). Chen's and Li's controllers use it.
``axle<j>_torque_nm``  torque demand on driven axle j (1-based) of the vehicle (N·m, + drives
                       forward). Cai's traction control.
``airbrake_apply``     driver's brake valve of the automatic air brake, on the leading vehicle
                       (1 apply, 0 release). Li's locomotive.
``ecp_demand``         electronically controlled pneumatic brake demand of a wagon's brake unit
                       (fraction 0..1 of a full service application).
=====================  ==========================================================================

Measurements are arrays by name. Every model provides, per vehicle ``(n_vehicles,)``:
``position_m``, ``speed_mps``, ``accel_mps2``, ``applied_brake_n`` (the force its brake/traction
equipment applies at the rail, + brakes), and per coupler ``(n_vehicles - 1,)``: ``deflection_m``
and ``coupler_force_n`` (coupler j joins vehicles j and j+1; force > 0 in compression for Chen's
Table 2 numbering, see each model). A model may add further per-vehicle arrays (shape
``(n_vehicles,)``, NaN where a vehicle has no such quantity), e.g. ``passive_force_n``,
``axle<j>_speed_radps``, ``brake_cylinder_pressure_pa``; their names are what ECUs list as sensors
and what ``signals.csv`` carries (``<name>_c<i>``; coupler arrays as ``<name>_k<j>``).

Failure: a model raises :class:`PlantDiverged` when its state becomes non-finite or leaves its
physical range; the plant node then ends the run with status "diverged".
"""
from __future__ import annotations

from typing import Mapping, Protocol, runtime_checkable

import numpy as np


class PlantDiverged(FloatingPointError):
    """The plant state became non-finite or left its physical range."""


#: measurements every model provides: per vehicle
VEHICLE_MEASUREMENTS = ("position_m", "speed_mps", "accel_mps2", "applied_brake_n")
#: measurements every model provides: per coupler
COUPLER_MEASUREMENTS = ("deflection_m", "coupler_force_n")


@runtime_checkable
class PlantModel(Protocol):
    """Physics of a consist as the plant node drives it (SI units)."""

    #: number of vehicles n
    n_vehicles: int
    #: vehicle masses (kg), shape (n,)
    mass_kg: np.ndarray
    #: command names this model acts on (see the module docstring)
    command_names: tuple[str, ...]

    def step(self, dt_s: float, commands: Mapping[str, np.ndarray]) -> None:
        """Advance by ``dt_s`` holding ``commands`` (arrays of shape (n,), NaN = not commanded).
        The arrays are the plant node's own, updated in place as command frames arrive: a model
        reads them during the step and keeps no reference to them (nor to views of them)."""

    def measurements(self) -> dict[str, np.ndarray]:
        """Current state by name: (n,) per vehicle, (n-1,) per coupler (see the module docstring)."""
