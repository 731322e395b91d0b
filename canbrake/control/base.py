"""Controller interface shared by ECU processes and the in-process engines.

A controller is one object per carriage with explicit state and no I/O. Every control
period the caller builds an :class:`Observation` from whatever it knows (in an ECU:
the sensor frame and the latest peer frames received over CAN; in the ideal engine:
the plant state directly) and calls :meth:`Controller.step`.

Units are SI throughout: m, s, m/s, m/s^2, N, kg.
"""
from __future__ import annotations

from abc import ABC, abstractmethod
from dataclasses import dataclass, field
from typing import Any, Callable, Mapping

import numpy as np


@dataclass(frozen=True)
class Observation:
    """What carriage ``car_index``'s ECU knows when it computes tick ``tick``.

    Peer arrays have shape ``(n_cars,)`` and are indexed by car (0-based); the entry of
    the car itself holds its own measurement with age 0. A value never received is NaN
    with age ``inf``.
    """

    tick: int
    time_s: float
    speed_mps: float
    position_m: float
    ref_speed_mps: float
    ref_decel_mps2: float  # a* > 0 means the reference decelerates
    peer_speed_mps: np.ndarray
    peer_position_m: np.ndarray
    peer_age_s: np.ndarray
    # Locally measured coupler deflections (m); None where there is no coupler or no sensor.
    # front: coupler to car i-1 (Δl_{i-1} = x_{i-1} - x_i - spacing), rear: to car i+1 (Δl_i).
    deflection_front_m: float | None = None
    deflection_rear_m: float | None = None
    #: reference position x*(t_k) (m); NaN when the scenario's reference has none
    ref_position_m: float = float("nan")
    #: every local sensor signal of the ECU by name (SI, names as in
    #: :mod:`canbrake.physics.contract`, e.g. ``speed_mps``, ``passive_force_n``, ``axle1_speed_radps``)
    sensors: Mapping[str, float] = field(default_factory=dict)
    #: broadcast signals received from peers by name, each shape ``(n_ecus,)`` indexed by ECU
    #: (NaN where never received); ages in ``peer_age_s``
    peer_signals: Mapping[str, np.ndarray] = field(default_factory=dict)


@dataclass
class ControlOutput:
    """Result of one control step.

    ``brake_force_n`` > 0 decelerates the car, < 0 is traction. ``diagnostics`` holds named
    scalars for the trace (e.g. ``observer_accel_mps2``), all SI.
    """

    brake_force_n: float
    diagnostics: dict[str, float] = field(default_factory=dict)
    #: further actuator commands by name (see :mod:`canbrake.physics.contract`), e.g.
    #: ``{"axle1_torque_nm": ...}``, ``{"airbrake_apply": 1.0}``
    commands: dict[str, float] = field(default_factory=dict)
    #: values this ECU broadcasts to its peers in its next STATE frame, by name
    broadcast: dict[str, float] = field(default_factory=dict)


class Controller(ABC):
    """One carriage's controller: explicit state, no I/O."""

    #: names of the diagnostics this controller reports, in a stable order
    diagnostic_names: tuple[str, ...] = ()
    #: local sensor signals this controller reads (its ECU's SENSOR frames carry them)
    sensor_names: tuple[str, ...] = ("speed_mps", "position_m")
    #: actuator commands it sends (its ECU's command frames carry them); ``brake_force_n`` is
    #: ``ControlOutput.brake_force_n``, the others come from ``ControlOutput.commands``
    command_names: tuple[str, ...] = ("brake_force_n",)
    #: signals it broadcasts to peers in its STATE frame: sensor names (sent as measured) or
    #: names of ``ControlOutput.broadcast`` (sent one period later)
    broadcast_names: tuple[str, ...] = ("speed_mps", "position_m")
    #: whether it needs the reference position x* (a REFERENCE_POS frame)
    needs_ref_position: bool = False

    def __init__(self, car_index: int, n_cars: int, mass_kg: float, dt_s: float) -> None:
        self.car_index = car_index
        self.n_cars = n_cars
        self.mass_kg = float(mass_kg)
        self.dt_s = float(dt_s)

    @abstractmethod
    def step(self, obs: Observation) -> ControlOutput:
        """Compute this period's command from ``obs``."""

    def reset(self) -> None:  # pragma: no cover - default: stateless
        """Return to the initial state."""


ControllerFactory = Callable[..., Controller]
_REGISTRY: dict[str, ControllerFactory] = {}


def register(name: str) -> Callable[[ControllerFactory], ControllerFactory]:
    """Class decorator: make a controller available under ``name`` in scenarios."""

    def deco(cls: ControllerFactory) -> ControllerFactory:
        _REGISTRY[name] = cls
        return cls

    return deco


def available() -> list[str]:
    """Names of the registered controllers."""
    _load_builtin()
    return sorted(_REGISTRY)


def make_controller(
    name: str,
    params: Mapping[str, Any],
    *,
    car_index: int,
    n_cars: int,
    mass_kg: float,
    dt_s: float,
) -> Controller:
    """Build the controller registered as ``name`` for one car."""
    _load_builtin()
    try:
        cls = _REGISTRY[name]
    except KeyError:
        raise KeyError(f"unknown controller {name!r}; available: {', '.join(sorted(_REGISTRY))}") from None
    return cls(car_index=car_index, n_cars=n_cars, mass_kg=mass_kg, dt_s=dt_s, **dict(params))


def _load_builtin() -> None:
    # Importing the modules runs their @register decorators.
    from canbrake.control import chen, chen_compensated, ecp, li2024, pi  # noqa: F401
