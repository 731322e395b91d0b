"""Wheel–rail adhesion and driven-axle rotational dynamics (Cai et al. 2014, eqs. 10–15, 41–42).

Every function is vectorised over axles: arrays of shape ``(p,)`` (or anything that broadcasts).
Units are SI throughout: rad/s, m, m/s, N, N·m, kg·m², s. Slip ratio λ and adhesion coefficient μ
are dimensionless.

Model
-----
* slip (eq. 11): ``λ = (ωR − v) / max(ωR, v, v_floor)``. The paper's denominator ``max(ωR, v)`` is
  0/0 at standstill; we floor it at ``v_floor`` (default 0.1 m/s, our choice).
* slip curve (eq. 13): ``μ(λ) = b1 (1 − exp(−b2 |λ|)) − |λ|/b3``, made odd in λ so braking slip
  (λ < 0) gives a braking force.
* speed dependence (eqs. 14–15): ``μ(λ, v) = μ_max(v) / μ_max(0) · μ(λ)`` with
  ``μ_max(v) = c1 + c2 / (c3 + v)``.
* rail condition (eqs. 41–42): "dry" parameters while ``t`` is in the dry window (50–100 s in the
  paper), "wet" otherwise.
* adhesion force (eq. 10): ``F_a = μ N`` with ``N`` the axle's normal load (N).
* wheel (eq. 12): ``J ω̇ = T − F_a R``.

Two curve variants (``variant``):

``"paper"``
    the curve exactly as printed. Its peak is b1 ≈ 1.8 (dry) and 2.0 (wet) — an adhesion
    coefficient far above any wheel on rail (0.1–0.4) — and with c1..c3 the "dry" rail is *less*
    adhesive than the wet one at every speed (μ_max(0) = 0.154 dry vs 0.239 wet).
``"physical"``
    the same shapes (b2, b3 set where the peak lies) normalised to a unit peak and multiplied by a
    peak coefficient at standstill (``peak_mu0``: 0.35 dry, 0.25 wet, our choice) and by the same
    speed decay ``μ_max(v)/μ_max(0)`` of eq. 15. Dry is then more adhesive than wet.
"""
from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from typing import Literal

import numpy as np

G0 = 9.8  # m/s², the paper's g0 (117.6 kN = 12 t · 9.8 m/s²)


@dataclass(frozen=True)
class RailCondition:
    """Coefficients of eqs. 13 and 15 for one rail surface (dimensionless; c2, c3 in m/s)."""

    b1: float
    b2: float
    b3: float
    c1: float
    c2: float
    c3: float
    #: peak μ at standstill used by the "physical" variant (our choice, not in the paper)
    peak_mu0: float

    def mu_max(self, v_mps: np.ndarray | float) -> np.ndarray:
        """Eq. 15: μ_max(v) = c1 + c2/(c3 + |v|)."""
        return self.c1 + self.c2 / (self.c3 + np.abs(v_mps))

    @property
    def peak_slip(self) -> float:
        """Slip λ* at which the printed curve (eq. 13) peaks: b1 b2 e^{−b2 λ} = 1/b3."""
        return float(np.log(self.b1 * self.b2 * self.b3) / self.b2)

    @property
    def peak_curve(self) -> float:
        """Maximum of the printed curve μ(λ) of eq. 13 (dimensionless)."""
        lam = self.peak_slip
        return float(self.b1 * (1.0 - np.exp(-self.b2 * lam)) - lam / self.b3)


#: eq. 41, 50 s ≤ t ≤ 100 s
DRY = RailCondition(b1=1.786, b2=40.0, b3=10.0, c1=0.040, c2=3.78, c3=33.3, peak_mu0=0.35)
#: eq. 42, otherwise
WET = RailCondition(b1=2.046, b2=15.0, b3=10.0, c1=0.060, c2=12.9, c3=72.2, peak_mu0=0.25)

Variant = Literal["paper", "physical"]


def slip_ratio(omega_radps: np.ndarray, v_mps: np.ndarray | float, radius_m: float,
               v_floor_mps: float = 0.1) -> np.ndarray:
    """Eq. 11 with a floored denominator: λ = (ωR − v) / max(ωR, v, v_floor). Shape of ``omega``."""
    wr = np.asarray(omega_radps, dtype=float) * radius_m
    v = np.asarray(v_mps, dtype=float)
    return (wr - v) / np.maximum(np.maximum(np.abs(wr), np.abs(v)), v_floor_mps)


def mu_curve(lam: np.ndarray, cond: RailCondition) -> np.ndarray:
    """Eq. 13 as printed, odd in λ: sign(λ)·[b1 (1 − e^{−b2|λ|}) − |λ|/b3]."""
    a = np.abs(lam)
    return np.sign(lam) * (cond.b1 * (1.0 - np.exp(-cond.b2 * a)) - a / cond.b3)


def dmu_curve_dlam(lam: np.ndarray, cond: RailCondition) -> np.ndarray:
    """dμ/dλ of :func:`mu_curve` (even in λ)."""
    a = np.abs(lam)
    return cond.b1 * cond.b2 * np.exp(-cond.b2 * a) - 1.0 / cond.b3


def _scale(v_mps: np.ndarray | float, cond: RailCondition, variant: Variant) -> np.ndarray:
    """Factor multiplying the printed curve μ(λ) at speed v for the chosen variant."""
    speed = cond.mu_max(v_mps) / cond.mu_max(0.0)  # eq. 14
    if variant == "paper":
        return speed
    if variant == "physical":
        return speed * cond.peak_mu0 / cond.peak_curve
    raise ValueError(f"unknown adhesion variant {variant!r}; use 'paper' or 'physical'")


def adhesion_coefficient(lam: np.ndarray, v_mps: np.ndarray | float, cond: RailCondition,
                         variant: Variant = "paper") -> np.ndarray:
    """μ(λ, v) of eqs. 13–15 for the chosen variant (dimensionless)."""
    return _scale(v_mps, cond, variant) * mu_curve(lam, cond)


def rail_condition(t_s: float, dry_window_s: tuple[float, float] = (50.0, 100.0)) -> RailCondition:
    """Eqs. 41–42: the dry coefficients inside ``dry_window_s`` (inclusive), wet otherwise."""
    return DRY if dry_window_s[0] <= t_s <= dry_window_s[1] else WET


@dataclass
class WheelSet:
    """Driven axles of a train: parameters and state, all arrays of shape ``(p,)``.

    ``normal_load_n`` N (axle load), ``inertia_kgm2`` J, ``radius_m`` R, ``omega_radps`` state.
    """

    normal_load_n: np.ndarray
    inertia_kgm2: float
    radius_m: float
    omega_radps: np.ndarray
    variant: Variant = "paper"
    v_floor_mps: float = 0.1

    def adhesion(self, v_mps: float, cond: RailCondition,
                 omega_radps: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """(λ, μ, F_a in N) per axle at body speed ``v_mps``; ``omega`` defaults to the state."""
        om = self.omega_radps if omega_radps is None else omega_radps
        lam = slip_ratio(om, v_mps, self.radius_m, self.v_floor_mps)
        mu = adhesion_coefficient(lam, v_mps, cond, self.variant)
        return lam, mu, mu * self.normal_load_n

    def step(self, torque_nm: np.ndarray, v_mps: float, cond: RailCondition, dt_s: float,
             newton_iters: int = 4) -> np.ndarray:
        """Advance ω by one backward-Euler step of J ω̇ = T − F_a(ω, v) R with the body speed held.

        Returns F_a (N) per axle at the new ω. ``torque_nm`` has shape ``(p,)``.
        """
        return self.step_coupled(torque_nm, v_mps, cond, dt_s, mass_kg=None, newton_iters=newton_iters)[1]

    def step_coupled(self, torque_nm: np.ndarray, v_mps: float, cond: RailCondition, dt_s: float,
                     mass_kg: float | None, resistance: Callable[[float], tuple[float, float]] | None = None,
                     newton_iters: int = 4) -> tuple[float, np.ndarray]:
        """One backward-Euler step of the wheels and (unless ``mass_kg`` is None) the train body.

        Solves jointly, for ω (shape ``(p,)``, rad/s) and v (m/s)::

            J (ω − ω0) = dt (T − F_a(ω, v) R)
            m (v − v0) = dt (Σ F_a(ω, v) − F_d(v))

        with ``resistance(v) -> (F_d in N, dF_d/dv in N·s/m)``. Both equations are stiff through
        the slip: dF_a/dω ∝ N μ' R / v and dF_a/dv ∝ −N μ'/v give time constants of microseconds
        (wheel) and fractions of a millisecond (body) near standstill, so an explicit step of 1 ms
        is unstable there. Newton on the arrow-shaped Jacobian (Schur complement on v) solves the
        step; the speed-dependence of μ_max is left out of the Jacobian (it only slows Newton).
        Returns (v_new in m/s, F_a in N per axle); ω is updated in place.
        """
        J, R, N = self.inertia_kgm2, self.radius_m, self.normal_load_n
        w0 = self.omega_radps
        v0 = float(v_mps)
        w, v = w0.copy(), v0
        torque = np.asarray(torque_nm, dtype=float)
        for _ in range(newton_iters):
            scale = _scale(v, cond, self.variant)
            wr = w * R
            awr, av = np.abs(wr), abs(v)
            den = np.maximum(np.maximum(awr, av), self.v_floor_mps)
            lam = (wr - v) / den
            on_wr = (awr >= av) & (awr >= self.v_floor_mps)
            on_v = ~on_wr & (av >= self.v_floor_mps)
            safe = np.where(on_wr, wr * wr, 1.0)
            dlam_dw = np.where(on_wr, R * av / safe, R / den)
            dlam_dv = np.where(on_wr, -1.0 / den, np.where(on_v, -wr / (den * den), -1.0 / den))
            dmu = scale * dmu_curve_dlam(lam, cond) * N
            fa = scale * mu_curve(lam, cond) * N
            fw = dmu * dlam_dw
            fv = dmu * dlam_dv
            r_w = J * (w - w0) - dt_s * (torque - fa * R)
            a = J + dt_s * R * fw
            a = np.where(a > 0.1 * J, a, J)  # past the adhesion peak the slope is negative: damped step
            if mass_kg is None:
                w = w - r_w / a
                continue
            fd, dfd = resistance(v) if resistance is not None else (0.0, 0.0)
            b = dt_s * R * fv
            c = -dt_s * fw
            r_v = mass_kg * (v - v0) - dt_s * (float(np.sum(fa)) - fd)
            d = mass_kg - dt_s * (float(np.sum(fv)) - dfd)
            dv = (-r_v + float(np.sum(c * r_w / a))) / (d - float(np.sum(c * b / a)))
            w = w + (-r_w - b * dv) / a
            v = v + dv
        self.omega_radps = w
        return v, self.adhesion(v, cond, w)[2]
