"""Sliding-mode disturbance observer of Chen 2023 (eqs. 11–22), discretised, with a boundary layer,
a low-pass on the estimate and anti-windup.

Continuous form (eq. 11, K_b u = brake force F in N):

    dx̂/dt = v̂ + γ1 sign(x − x̂)
    dv̂/dt = −F/m + γ2 sign(v − v̂)
    φ̂     = γ2 sign(v − v̂)                    (equivalent control, an acceleration in m/s²)

On the sliding surface v̂ = v, so γ2 sign(e2) equals φ/m, the lumped coupler + resistance +
disturbance acceleration. (Eq. 22 prints γ2 sign(γ1 sign(x − x̂)), i.e. the position channel; that
cannot carry the magnitude of φ, so we take the velocity channel of eq. 21.) The position channel is
kept for fidelity and reported, but the estimate uses the velocity channel only.

Discretisation at the control period ``dt``:

* ``sign`` is replaced by ``sat(e / b)`` (boundary layer ``b``): inside the layer the observer is a
  linear high-gain observer of bandwidth γ2/b (must satisfy dt·γ2/b < 2; defaults: 500 1/s,
  dt·γ2/b = 0.5 at 1 ms);
* the estimate is then low-passed with time constant ``filter_s`` (first order, exact discretisation);
* anti-windup: the observer is driven by the force actually *commanded after saturation* (the
  caller passes it), the estimate is clamped to ±``limit_mps2``, and the velocity estimate is kept
  within ±``error_limit_mps`` of the measurement. Without the last clamp a skid (the rail takes
  less force than commanded, which the controller cannot know) makes v̂ run away from v at
  (deficit − γ2); after adhesion returns the estimate then stays pinned at +γ2 for seconds and the
  whole train brakes too hard (seen in case 2: −0.08 km/h for > 5 s).

One step is "predict-correct" with the command of this period: at tick k the error uses the measured
v_k and the prediction v̂_k made at k−1 with the force held over [k−1, k].
"""
from __future__ import annotations

import math

import numpy as np

from canbrake.control import _observer


def _sat_many(z: np.ndarray) -> np.ndarray:
    """sat(z) = clip(z, -1, 1) elementwise, NaN staying NaN (the compiled scalar form's, :mod:`canbrake.control._observer`)."""
    return np.where(z > 1.0, 1.0, np.where(z < -1.0, -1.0, z))


class SlidingModeObserver:
    """Scalar observer for one carriage.

    Parameters: ``mass_kg`` (kg), ``dt_s`` (s), ``gamma1_mps`` (m/s), ``gamma2_mps2`` (m/s²),
    ``boundary_pos_m`` (m), ``boundary_vel_mps`` (m/s), ``filter_s`` (s, 0 = no low-pass),
    ``limit_mps2`` (m/s², clamp of the estimate), ``error_limit_mps`` (m/s, clamp of |v − v̂|).
    """

    def __init__(
        self,
        mass_kg: float,
        dt_s: float,
        *,
        gamma1_mps: float = 1.0,
        gamma2_mps2: float = 5.0,
        boundary_pos_m: float = 1e-3,
        boundary_vel_mps: float = 0.01,
        filter_s: float = 0.005,
        limit_mps2: float = 5.0,
        error_limit_mps: float = 0.05,
    ) -> None:
        self.mass_kg = float(mass_kg)
        self.dt_s = float(dt_s)
        self.gamma1_mps = float(gamma1_mps)
        self.gamma2_mps2 = float(gamma2_mps2)
        self.boundary_pos_m = float(boundary_pos_m)
        self.boundary_vel_mps = float(boundary_vel_mps)
        self.filter_s = float(filter_s)
        self.limit_mps2 = float(limit_mps2)
        self.error_limit_mps = float(error_limit_mps)
        if self.dt_s * self.gamma2_mps2 / self.boundary_vel_mps >= 2.0:
            raise ValueError("observer unstable when sampled: need dt·γ2/b_v < 2")
        self._alpha = 1.0 if self.filter_s <= 0 else 1.0 - math.exp(-self.dt_s / self.filter_s)
        self.reset()

    def reset(self) -> None:
        """Forget everything; the next :meth:`update` initialises on the measurement."""
        self.x_hat = math.nan
        self.v_hat = math.nan
        self.phi_hat_mps2 = 0.0
        self.phi_raw_mps2 = 0.0

    #: Correct with this tick's measurement (m, m/s); returns the filtered estimate φ̂ (m/s²).
    #: Compiled (:mod:`canbrake.control._observer`), the state in these attributes.
    update = _observer.update

    def reset_many(self, n_points: int) -> None:
        """Batch form (:mod:`canbrake.batch`): the state becomes arrays of shape (n_points,), one
        observer per sweep point; use :meth:`update_many` / :meth:`predict_many` from then on."""
        self.x_hat = np.full(n_points, np.nan)
        self.v_hat = np.full(n_points, np.nan)
        self.phi_hat_mps2 = np.zeros(n_points)
        self.phi_raw_mps2 = np.zeros(n_points)

    def update_many(self, position_m: np.ndarray, speed_mps: np.ndarray) -> np.ndarray:
        """:meth:`update` for every point at once (shape (P,)): the same operations in the same
        order, so each point's estimate equals its scalar observer's bit for bit."""
        init = np.isnan(self.v_hat)
        if init.any():
            self.x_hat = np.where(init, position_m, self.x_hat)
            self.v_hat = np.where(init, speed_mps, self.v_hat)
        e2 = speed_mps - self.v_hat
        emax = self.error_limit_mps
        hi, lo = e2 > emax, e2 < -emax
        wound = hi | lo
        if wound.any():
            e2 = np.where(hi, emax, np.where(lo, -emax, e2))
            self.v_hat = np.where(wound, speed_mps - e2, self.v_hat)
        raw = self.gamma2_mps2 * _sat_many(e2 / self.boundary_vel_mps)
        self.phi_raw_mps2 = raw
        phi = self.phi_hat_mps2 + self._alpha * (raw - self.phi_hat_mps2)
        lim = self.limit_mps2
        self.phi_hat_mps2 = np.where(phi > lim, lim, np.where(phi < -lim, -lim, phi))
        self._e1 = position_m - self.x_hat
        return self.phi_hat_mps2

    def predict_many(self, brake_force_n: np.ndarray) -> None:
        """:meth:`predict` for every point at once (shape (P,))."""
        dt = self.dt_s
        s1 = _sat_many(self._e1 / self.boundary_pos_m)
        self.x_hat = self.x_hat + dt * (self.v_hat + self.gamma1_mps * s1)
        self.v_hat = self.v_hat + dt * (-brake_force_n / self.mass_kg + self.phi_raw_mps2)

    #: Propagate to the next tick with the force held over the period (N, + = brake); compiled.
    predict = _observer.predict
