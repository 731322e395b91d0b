"""Per-car PI speed controller with feed-forward, no communication (ablation baseline), ``pi``.

    F_i = m_i (a* + kp (v_i − v*) + ki ∫(v_i − v*) dt)        (N, + = brake)

Each car tracks the reference alone: no peer data, no coupler information. Anti-windup by
conditional integration: the integral is frozen while the output is saturated in the direction the
error pushes it.
"""
from __future__ import annotations

import math

import numpy as np

from canbrake.control.base import ControlOutput, Controller, Observation, register


@register("pi")
class PISpeedController(Controller):
    """Parameters: ``kp`` (1/s), ``ki`` (1/s²), ``feedforward`` (bool, add m·a*),
    ``brake_force_max_n``, ``traction_force_max_n`` (N, inf = unlimited), ``brake_rating_mps2``,
    ``traction_rating_mps2`` (m/s², × this car's mass; the tighter limit wins).

    Defaults ``kp = 36`` (Chen's k) and ``ki = 0`` make it Chen's u_i3 without observer, consensus or
    potential field; for a realistic (0.3 s lag) brake use e.g. kp = 1.5, ki = 0.3.
    """

    diagnostic_names = ("speed_error_mps", "integral_m")

    def __init__(
        self,
        car_index: int,
        n_cars: int,
        mass_kg: float,
        dt_s: float,
        *,
        kp: float = 36.0,
        ki: float = 0.0,
        feedforward: bool = True,
        brake_force_max_n: float = math.inf,
        traction_force_max_n: float = math.inf,
        brake_rating_mps2: float = math.inf,
        traction_rating_mps2: float = math.inf,
    ) -> None:
        super().__init__(car_index, n_cars, mass_kg, dt_s)
        self.kp = float(kp)
        self.ki = float(ki)
        self.feedforward = bool(feedforward)
        self.brake_force_max_n = float(brake_force_max_n)
        self.traction_force_max_n = float(traction_force_max_n)
        # per-mass ratings (one value for a whole train in a scenario) tighten the force limits
        self.brake_force_max_n = min(self.brake_force_max_n, float(brake_rating_mps2) * self.mass_kg)
        self.traction_force_max_n = min(self.traction_force_max_n, float(traction_rating_mps2) * self.mass_kg)
        self.reset()

    def reset(self) -> None:
        """Zero the integral."""
        self.integral_m = 0.0

    def step(self, obs: Observation) -> ControlOutput:
        """Brake force (N) for this period."""
        e = obs.speed_mps - obs.ref_speed_mps
        ff = obs.ref_decel_mps2 if self.feedforward else 0.0
        trial_integral = self.integral_m + e * self.dt_s
        force = self.mass_kg * (ff + self.kp * e + self.ki * trial_integral)
        if force > self.brake_force_max_n:
            force = self.brake_force_max_n
            if e < 0:
                self.integral_m = trial_integral
        elif force < -self.traction_force_max_n:
            force = -self.traction_force_max_n
            if e > 0:
                self.integral_m = trial_integral
        else:
            self.integral_m = trial_integral
        return ControlOutput(brake_force_n=force, diagnostics={"speed_error_mps": e, "integral_m": self.integral_m})

    # ------------------------------------------------------------------ batch form
    def batchable(self) -> bool:
        """:meth:`step_batch` covers every configuration of this class (not a subclass's own step)."""
        return type(self).step is PISpeedController.step

    def step_batch(self, obs: Observation) -> ControlOutput:
        """:meth:`step` for P sweep points at once (:mod:`canbrake.batch`): every scalar of ``obs``
        has shape (P,), so do the fields of the result; the integral becomes one per point at the
        first call. The same operations in the same order as :meth:`step`: the same floats."""
        e = obs.speed_mps - obs.ref_speed_mps
        if np.ndim(self.integral_m) == 0:
            self.integral_m = np.full(np.shape(e), float(self.integral_m))
        ff = obs.ref_decel_mps2 if self.feedforward else 0.0
        trial = self.integral_m + e * self.dt_s
        force = self.mass_kg * (ff + self.kp * e + self.ki * trial)
        hi, lo = force > self.brake_force_max_n, force < -self.traction_force_max_n
        lo = lo & ~hi
        # conditional integration: frozen while saturated in the direction the error pushes
        keep = (hi & ~(e < 0)) | (lo & ~(e > 0))
        self.integral_m = np.where(keep, self.integral_m, trial)
        force = np.where(hi, self.brake_force_max_n, np.where(lo, -self.traction_force_max_n, force))
        return ControlOutput(brake_force_n=force, diagnostics={"speed_error_mps": e, "integral_m": self.integral_m})
