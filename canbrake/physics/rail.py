"""Time-varying rail conditions and external disturbance forces.

Rail events model Chen 2023's cases 2 and 3 ("the railway condition deteriorates at t = 3.5 s …
adhesion control restores the braking capacity after 1 s"). Two per-car quantities:

``adhesion_mu``
    Usable wheel-rail adhesion μ. The rail force is capped at μ·m·g when the actuator is
    ``adhesion_limited`` (realistic profile; optional in the ideal one). A skid is a *cap*: the
    controller cannot push more force through the rail however much it commands.
``brake_effectiveness``
    Factor in [0, 1] on brake forces (a proportional loss, e.g. partial wheel-slide-protection
    release). A disturbance observer sees it as a disturbance and compensates it.

Disturbances are forces in N, positive towards +x (the direction of travel).
"""
from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Sequence

import numpy as np

from canbrake.arrays import ArrayLike
from canbrake.arrays import per_car as _per_car


@dataclass(frozen=True)
class RailEvent:
    """Rail condition in force for ``start_s <= t < end_s`` (s).

    ``adhesion_mu`` (dimensionless, scalar or per car) replaces the base μ when given;
    ``brake_effectiveness`` (0..1, scalar or per car) multiplies brake forces when given.
    A later event in the list overrides an earlier one where both apply.
    """

    start_s: float
    end_s: float = math.inf
    adhesion_mu: ArrayLike | None = None
    brake_effectiveness: ArrayLike | None = None


@dataclass(frozen=True)
class RailConditions:
    """Base adhesion (per car or scalar) plus a list of :class:`RailEvent`."""

    base_adhesion_mu: ArrayLike = 0.3
    events: Sequence[RailEvent] = ()

    def at(self, time_s: float, n_cars: int) -> tuple[np.ndarray, np.ndarray]:
        """(adhesion μ, brake effectiveness) per car at ``time_s``."""
        mu = _per_car(self.base_adhesion_mu, n_cars, "base_adhesion_mu")
        eff = np.ones(n_cars)
        for ev in self.events:
            if ev.start_s <= time_s < ev.end_s:
                if ev.adhesion_mu is not None:
                    mu = _per_car(ev.adhesion_mu, n_cars, "adhesion_mu")
                if ev.brake_effectiveness is not None:
                    eff = _per_car(ev.brake_effectiveness, n_cars, "brake_effectiveness")
        return mu, eff

    def change_times(self) -> list[float]:
        """Instants (s) at which the conditions change."""
        ts = set()
        for ev in self.events:
            ts.add(ev.start_s)
            if math.isfinite(ev.end_s):
                ts.add(ev.end_s)
        return sorted(ts)


@dataclass(frozen=True)
class DisturbanceForce:
    """External force on each car (N, + towards +x) for ``start_s <= t < end_s``:

        F_i(t) = offset_n[i] + amplitude_n[i] · sin(2π · frequency_hz · (t − start_s) + phase_rad)

    ``amplitude_n``/``offset_n`` are scalars or per-car arrays. ``frequency_hz = 0`` with an
    offset gives a constant force (a step disturbance).
    """

    amplitude_n: ArrayLike = 0.0
    frequency_hz: float = 0.0
    start_s: float = 0.0
    end_s: float = math.inf
    offset_n: ArrayLike = 0.0
    phase_rad: float = 0.0

    def force_n(self, time_s: float, n_cars: int) -> np.ndarray:
        """Force per car (N) at ``time_s``."""
        if not (self.start_s <= time_s < self.end_s):
            return np.zeros(n_cars)
        amp = _per_car(self.amplitude_n, n_cars, "amplitude_n")
        off = _per_car(self.offset_n, n_cars, "offset_n")
        return off + amp * math.sin(2.0 * math.pi * self.frequency_hz * (time_s - self.start_s) + self.phase_rad)


def disturbance_n(mass_kg: np.ndarray, t_s: float, v_mps: np.ndarray, on: np.ndarray,
                  coef: tuple[float, float, float]) -> np.ndarray:
    """Li 2024 eq. (40), σ_i in N: m_i {c0 + c1 sin(t+1) + c2 ∛v [sin(2t+2) + cos(3t+1)]}, (c0, c1, c2) =
    ``coef`` (paper: 0.002, 0.001, 0.0003), on the vehicles where ``on`` is True (paper: the locomotive
    and wagons 10, 20, ..., 100), zero elsewhere; masses ``mass_kg`` (kg), v in m/s (SI reading)."""
    v = np.abs(np.asarray(v_mps, dtype=float))
    c0, c1, c2 = coef
    acc = c0 + c1 * np.sin(t_s + 1.0) + c2 * np.cbrt(v) * (np.sin(2 * t_s + 2.0) + np.cos(3 * t_s + 1.0))
    return np.where(on, mass_kg * acc, 0.0)
