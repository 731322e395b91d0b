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
* rail condition (eqs. 41–42): the coefficients of a rail surface (:class:`RailCondition`) change
  over time (:class:`RailSchedule`; the paper: "dry" for 50–100 s, "wet" otherwise). The paper's
  values are data, in ``scenarios/cai2014_case*.yaml``.
* the plant: a rigidly coupled train with driven axles (:class:`DrivenAxles` per vehicle) is the
  coupled plant's rigid coupling (:meth:`canbrake.physics.train.TrainPlant._rigid_init`), which
  steps the axles' :class:`WheelSet` with the train body (compiled: :mod:`canbrake.physics._adhesion_kernel`).
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

import functools
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Literal

import numpy as np

from canbrake.physics import _adhesion_kernel

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


def _axle_array(x: np.ndarray | float, p: int) -> np.ndarray:
    """``x`` (a scalar or ``p`` values) as a C-contiguous float array of shape ``(p,)``."""
    a = np.asarray(x, dtype=float)
    if a.shape == (p,) and a.flags.c_contiguous:
        return a
    return np.full(p, float(a)) if a.ndim == 0 else np.ascontiguousarray(a.reshape(p))


@functools.lru_cache(maxsize=64)
def _curve_constants(cond: RailCondition, variant: Variant) -> tuple[float, ...]:
    """A rail condition's arguments of the compiled kernel (canbrake.physics._adhesion_kernel) for
    ``variant``: b1, b2, b3, c1, c2, c3, the Newton loop's peak factor and μ_max(0), then for the
    adhesion's own evaluation whether the variant is "physical", ``peak_mu0`` and the printed
    curve's peak (:func:`_scale`)."""
    if variant not in ("paper", "physical"):
        _scale(0.0, cond, variant)  # the message naming the variants
    peak = 1.0 if variant == "paper" else float(_scale(0.0, cond, variant))
    physical = variant == "physical"
    return (cond.b1, cond.b2, cond.b3, cond.c1, cond.c2, cond.c3, peak, float(cond.mu_max(0.0)), physical,
            cond.peak_mu0 if physical else 1.0, cond.peak_curve if physical else 1.0)


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
    #: the kernel's per-axle parameter arrays (J, R, N) and the last rail condition's constants, kept
    #: while the attributes they come from are the same objects (see :meth:`_kernel_args`)
    _args: tuple | None = field(default=None, init=False, repr=False, compare=False)
    _cond_args: tuple | None = field(default=None, init=False, repr=False, compare=False)

    def _kernel_args(self, cond: RailCondition) -> tuple[tuple[np.ndarray, np.ndarray, np.ndarray], tuple]:
        """((J, R, N) as arrays (p,), the rail condition's kernel constants (:func:`_curve_constants`)),
        made again only when an attribute they come from is replaced."""
        p = np.size(self.omega_radps)
        a = self._args
        if a is None or a[0] is not self.inertia_kgm2 or a[1] is not self.radius_m or a[2] is not self.normal_load_n \
                or a[3] != p:
            a = self._args = (self.inertia_kgm2, self.radius_m, self.normal_load_n, p,
                              tuple(_axle_array(x, p) for x in (self.inertia_kgm2, self.radius_m, self.normal_load_n)))
        c = self._cond_args
        if c is None or c[0] is not cond or c[1] != self.variant:
            c = self._cond_args = (cond, self.variant, _curve_constants(cond, self.variant))
        return a[4], c[2]

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
                     newton_iters: int = 4, davis: tuple[float, float, float] | None = None,
                     table: tuple[np.ndarray, np.ndarray] | None = None) -> tuple[float, np.ndarray]:
        """One backward-Euler step of the wheels and (unless ``mass_kg`` is None) the train body.

        Solves jointly, for ω (shape ``(p,)``, rad/s) and v (m/s)::

            J (ω − ω0) = dt (T − F_a(ω, v) R)
            m (v − v0) = dt (Σ F_a(ω, v) − F_d(v))

        with ``resistance(v) -> (F_d in N, dF_d/dv in N·s/m)``, or ``davis`` = (a0, a1, a2) for
        F_d = sgn(v) a0 + a1 v + a2 v|v| (sgn = 0 below 1e-6 m/s; evaluated in the compiled loop), plus
        sgn(v) T(|v|) for ``table`` = (speeds m/s, forces N): a resistance table (linear, flat beyond its ends). Both equations are stiff through
        the slip: dF_a/dω ∝ N μ' R / v and dF_a/dv ∝ −N μ'/v give time constants of microseconds
        (wheel) and fractions of a millisecond (body) near standstill, so an explicit step of 1 ms
        is unstable there. Newton on the arrow-shaped Jacobian (Schur complement on v) solves the
        step; the speed-dependence of μ_max is left out of the Jacobian (it only slows Newton).
        Returns (v_new in m/s, F_a in N per axle); ω is updated (a new array), ``finite`` says
        whether all of it is finite.
        """
        # compiled (canbrake.physics._adhesion_kernel): a train has a handful of driven axles, where
        # numpy's per-call overhead would cost ~10x the arithmetic (this runs every sub-step)
        (J, R, N), (b1, b2, b3, c1, c2, c3, peak, mu0, physical, peak_mu0, peak_curve) = self._kernel_args(cond)
        p = J.shape[0]
        v, w, lam, mu, fa, self.finite = _adhesion_kernel.step_coupled(
            _axle_array(self.omega_radps, p), J, R, N, _axle_array(torque_nm, p), float(v_mps), dt_s,
            0.0 if mass_kg is None else float(mass_kg), mass_kg is not None, b1, b2, b3, c1, c2, c3, peak, mu0,
            self.v_floor_mps, newton_iters, davis, resistance, table, physical, peak_mu0, peak_curve)
        self.omega_radps = w
        #: (condition, v, ω, (λ, μ, F_a)) of the last step, for a measurement of the same state: the
        #: kernel's evaluation, bit for bit :meth:`adhesion`'s
        self.last_adhesion = (cond, v, w, (lam, mu, fa))
        return v, fa


# ------------------------------------------------------------------------------ rail schedule, driven axles
@dataclass(frozen=True)
class RailWindow:
    """Rail surface ``condition`` for ``start_s ≤ t ≤ stop_s`` (s, both inclusive, as eqs. 41–42)."""

    condition: RailCondition
    start_s: float
    stop_s: float


@dataclass(frozen=True)
class RailSchedule:
    """The rail surface over time: ``base`` outside every window, the first matching window inside."""

    base: RailCondition
    windows: tuple[RailWindow, ...] = ()

    def at(self, t_s: float) -> RailCondition:
        """The rail condition at time ``t_s`` (s)."""
        for w in self.windows:
            if w.start_s <= t_s <= w.stop_s:
                return w.condition
        return self.base


@dataclass(frozen=True)
class DrivenAxles:
    """The driven axles of one vehicle, front first, arrays of shape ``(p_i,)``: axle load N (N),
    wheel(set) inertia J (kg·m², incl. transmission and motor), wheel radius R (m). ``p_i`` may be 0."""

    normal_load_n: np.ndarray
    inertia_kgm2: np.ndarray
    radius_m: np.ndarray
