"""Brake/traction actuator of each carriage: command (N) -> force on the rail (N).

Sign convention everywhere in canbrake: a positive force is a *brake* force (it opposes motion);
a negative one is traction (it pushes the car towards +x).

Two profiles:

``ideal`` (Chen 2023's assumption)
    The effort equals the command at once, any sign, no rating.
``realistic``
    First-order lag (``time_constant_s``, ~0.3 s for a blended electro-pneumatic brake), a jerk limit
    expressed as a force rate per unit mass (``jerk_limit_mps3``, ~1 m/s³ for passenger comfort),
    saturation at the brake rating (``brake_rating_mps2`` · m) and traction rating
    (``traction_rating_mps2`` · m), and at adhesion μ·m·g.

In both profiles the rail force is then multiplied by the per-car brake *effectiveness* set by rail
events (brake forces only), and capped at μ·m·g when ``adhesion_limited`` (default: realistic only).
Whether a brake force can move a car is decided by the plant, not here: at standstill a brake is
static friction (see :mod:`canbrake.physics.train`).
"""
from __future__ import annotations

import math
from dataclasses import dataclass, replace
from typing import Literal

import numpy as np

ActuatorKind = Literal["ideal", "realistic"]


@dataclass(frozen=True)
class BrakeActuator:
    """Actuator parameters (the lag, the ratings and the jerk limit per unit mass: one value for
    every car, or a tuple with one per car; the kind is the train's).

    Attributes
    ----------
    kind: ``"ideal"`` or ``"realistic"``.
    time_constant_s: first-order lag (s), realistic only; per car, 0 = that car's brake applies the
        command at once (an ideal brake among lagged ones; give it an ``inf`` jerk limit).
    jerk_limit_mps3: max |dF/dt| / m (m/s³), realistic only; ``inf`` disables it.
    brake_rating_mps2: max brake force / m (m/s²); ``inf`` = no rating.
    traction_rating_mps2: max traction force / m (m/s²); ``inf`` = no rating.
    adhesion_limited: cap the rail force at μ·m·g (μ from the rail conditions).
    """

    kind: ActuatorKind = "ideal"
    time_constant_s: float | tuple[float, ...] = 0.3
    jerk_limit_mps3: float | tuple[float, ...] = 1.0
    brake_rating_mps2: float | tuple[float, ...] = math.inf
    traction_rating_mps2: float | tuple[float, ...] = math.inf
    adhesion_limited: bool = False

    @property
    def jerk_limited(self) -> bool:
        """Whether any car's effort rate is limited (a finite jerk limit)."""
        return bool(np.any(np.isfinite(np.asarray(self.jerk_limit_mps3, dtype=float))))

    def __post_init__(self) -> None:
        if self.kind not in ("ideal", "realistic"):
            raise ValueError(f"actuator kind must be 'ideal' or 'realistic', not {self.kind!r}")
        if self.kind == "realistic" and not (self.time_constant_s > 0 if isinstance(self.time_constant_s, (int, float))
                                             else all(t >= 0 for t in self.time_constant_s)):
            raise ValueError("realistic actuator needs time_constant_s > 0 (per car: >= 0, 0 = at once)")

    @classmethod
    def ideal(cls, *, adhesion_limited: bool = False) -> "BrakeActuator":
        """Applied = commanded, any sign (Chen 2023). ``adhesion_limited`` adds the μ·m·g cap."""
        return cls(kind="ideal", adhesion_limited=adhesion_limited)

    @classmethod
    def realistic(
        cls,
        *,
        time_constant_s: float = 0.3,
        jerk_limit_mps3: float = 1.0,
        brake_rating_mps2: float = 1.5,
        traction_rating_mps2: float = 1.0,
        adhesion_limited: bool = True,
    ) -> "BrakeActuator":
        """Metro-like brake: 0.3 s lag, 1 m/s³ jerk, 1.5 m/s² emergency rating, 1.0 m/s² traction."""
        return cls(
            kind="realistic",
            time_constant_s=time_constant_s,
            jerk_limit_mps3=jerk_limit_mps3,
            brake_rating_mps2=brake_rating_mps2,
            traction_rating_mps2=traction_rating_mps2,
            adhesion_limited=adhesion_limited,
        )

    def with_(self, **changes: object) -> "BrakeActuator":
        """Copy with some fields changed."""
        return replace(self, **changes)  # type: ignore[arg-type]


class ActuatorState:
    """Vectorised actuator state over cars: the brake *effort* (N) before rail limits."""

    def __init__(self, params: BrakeActuator, mass_kg: np.ndarray) -> None:
        self.params = params
        self.mass_kg = mass_kg
        self.effort_n = np.zeros_like(mass_kg)
        f = lambda x: x if isinstance(x, float) else np.asarray(x, dtype=float)  # noqa: E731 - per car
        self._brake_max = f(params.brake_rating_mps2) * mass_kg
        self._trac_max = f(params.traction_rating_mps2) * mass_kg
        self._rate_max = f(params.jerk_limit_mps3) * mass_kg
        self._unrated = bool(np.all(np.isinf(params.brake_rating_mps2)) and np.all(np.isinf(params.traction_rating_mps2)))
        self._jerk_limited = params.jerk_limited
        tau = params.time_constant_s
        #: per car: 1 where the brake applies the command at once (time constant 0), else None
        self._instant = None
        if params.kind == "ideal":
            self._instant = np.ones(np.shape(mass_kg)[-1:], dtype=bool)
        elif not isinstance(tau, (int, float)) and any(t == 0 for t in tau):
            self._instant = np.asarray(tau, dtype=float) == 0.0
        self._lag: float | np.ndarray = 0.0
        self._lag_h = -1.0

    def demand_n(self, command_n: np.ndarray) -> np.ndarray:
        """The command clipped to the ratings (N)."""
        if self._unrated:
            return command_n
        return np.minimum(np.maximum(command_n, -self._trac_max), self._brake_max)

    def advance(self, command_n: np.ndarray, h_s: float) -> np.ndarray:
        """Advance the effort over ``h_s`` seconds under a held command; return the effort (N)."""
        p = self.params
        demand = self.demand_n(command_n)
        if p.kind == "ideal":
            self.effort_n = demand
            return self.effort_n
        # exact first-order lag over h, then the jerk (force-rate) limit
        step = (demand - self.effort_n) * self.lag_factor(h_s)
        if self._jerk_limited:
            lim = self._rate_max * h_s
            step = np.minimum(np.maximum(step, -lim), lim)
        self.effort_n = self.effort_n + step
        if self._instant is not None:
            self.effort_n = np.where(self._instant, demand, self.effort_n)
        return self.effort_n

    def lag_factor(self, h_s: float) -> float | np.ndarray:
        """The first-order lag's share of the gap closed over ``h_s`` seconds, 1 − e^(−h/τ) (realistic;
        per car where the cars' time constants differ, 1 for a car whose brake applies at once)."""
        if h_s != self._lag_h:
            self._lag_h = h_s
            tau = self.params.time_constant_s
            if isinstance(tau, (int, float)):
                self._lag = 1.0 - math.exp(-h_s / tau)
            else:
                t = np.asarray(tau, dtype=float)
                self._lag = np.where(t > 0.0, 1.0 - np.exp(-h_s / np.where(t > 0.0, t, 1.0)), 1.0)
        return self._lag

    def rail_force_n(
        self, effort_n: np.ndarray, adhesion_mu: np.ndarray, effectiveness: np.ndarray, gravity_mps2: float
    ) -> np.ndarray:
        """Force the wheels put on the rail (N, + = brake) after effectiveness and adhesion."""
        f = np.where(effort_n > 0.0, effort_n * effectiveness, effort_n)
        if self.params.adhesion_limited:
            cap = adhesion_mu * self.mass_kg * gravity_mps2
            f = np.minimum(np.maximum(f, -cap), cap)
        return f
