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
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass, field
from typing import Literal

import math

import numpy as np

from canbrake.physics import _adhesion_kernel
from canbrake.physics.contract import PlantDiverged

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


# ------------------------------------------------------------------------------ the plant model
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


class AdhesionTrain:
    """Cai et al. 2014's train as a plant model (:class:`canbrake.physics.contract.PlantModel`).

    Single-coordinate body (eq. 3: the vehicles are rigidly coupled, in-train forces cancel in the
    sum): one position x and speed v for the whole train, ``m v̇ = Σ F_a − Σ F_d,i(v)`` with
    ``m = Σ m_i`` and per-vehicle Davis resistance ``F_d,i = c0_i sgn v + c1_i v + c2_i v|v|`` (N),
    plus ``sgn v · T_i(|v|)`` for a vehicle with a resistance table (linear, flat beyond its ends).
    Every driven axle k has its own wheel speed, ``J_k ω̇_k = T_k − F_a,k R_k`` (eq. 12) with
    ``F_a,k = μ(λ_k, v) N_k`` (eqs. 10–15) on the rail condition of the moment (:class:`RailSchedule`).

    Integration, as the paper's reference run needs it: each sub-step (``dt_s / substeps``) solves
    wheels and body jointly by backward Euler (:meth:`WheelSet.step_coupled`, the rail condition of
    the sub-step's start) and advances x by the trapezoid rule.

    Commands: ``axle<j>_torque_nm`` (N·m, + drives forward) per vehicle, for its j-th driven axle
    (1-based); NaN (not commanded) or a missing name is zero torque.

    Measurements (per vehicle, shape (n,)): ``position_m`` (the train's coordinate x, the same for
    every vehicle: rigid coupling, no lengths), ``speed_mps`` (and the same as ``ground_speed_mps``,
    the speed over ground a radar gives, which has a finer CAN format), ``accel_mps2`` (over the last control
    step), ``applied_brake_n`` (−Σ F_a of its axles: traction is negative), ``resistance_n`` (F_d,i),
    ``wheel_inertia_force_n`` (Σ J_k ω̇_k / R_k of its axles over the last step: with Σ F_d,i the
    lumped disturbance F_dw of eq. 36), and per driven axle j ``axle<j>_speed_radps``,
    ``axle<j>_slip``, ``axle<j>_mu``, ``axle<j>_adhesion_n`` (N), ``axle<j>_applied_torque_nm``
    (NaN where the vehicle has fewer than j driven axles). Per coupler (n−1,): ``deflection_m`` (0:
    rigid) and ``coupler_force_n`` (the force the rigid coupling carries, + compression:
    ``C_j = m_{1..j} a − Σ_{i≤j} (F_a,i − F_d,i)`` at the end of the last sub-step).
    """

    def __init__(self, mass_kg: np.ndarray, axles: list[DrivenAxles], davis_n: np.ndarray, rail: RailSchedule,
                 *, variant: Variant = "paper", v_floor_mps: float = 0.1, speed_mps: float = 0.0,
                 position_m: float = 0.0, substeps: int = 1,
                 resistance_table: Sequence[tuple[Sequence[float], Sequence[float]] | None] | None = None) -> None:
        """``mass_kg`` (n,) kg; ``axles`` one :class:`DrivenAxles` per vehicle; ``davis_n`` (n, 3):
        c0 (N), c1 (N·s/m), c2 (N·s²/m²) per vehicle; ``resistance_table``: per vehicle (speeds m/s
        increasing, forces N) or None, added to its Davis terms; ``speed_mps`` and ``position_m``
        the initial state (wheels start rolling without slip)."""
        self.mass_kg = np.asarray(mass_kg, dtype=float)
        self.n_vehicles = int(self.mass_kg.size)
        if len(axles) != self.n_vehicles:
            raise ValueError(f"axles: {len(axles)} entries for {self.n_vehicles} vehicles")
        self.davis_n = np.asarray(davis_n, dtype=float).reshape(self.n_vehicles, 3)
        self._davis_sum = self.davis_n.sum(axis=0)
        self._davis_terms = tuple(float(a) for a in self._davis_sum)  # (a0, a1, a2) of :meth:`resistance`
        self.total_mass_kg = float(self.mass_kg.sum())
        #: the vehicles' tables as offsets and flat arrays (measurements), and summed on the union of
        #: their speeds (the body's F_d: a sum of piecewise-linear, flat-ended curves is one, exactly)
        self._tab: tuple[np.ndarray, np.ndarray, np.ndarray] | None = None
        self._table_sum: tuple[np.ndarray, np.ndarray] | None = None
        if resistance_table is not None and any(t is not None for t in resistance_table):
            if len(resistance_table) != self.n_vehicles:
                raise ValueError(f"resistance_table: {len(resistance_table)} entries for {self.n_vehicles} vehicles")
            tabs = [None if t is None else (np.asarray(t[0], dtype=float), np.asarray(t[1], dtype=float))
                    for t in resistance_table]
            have = [t for t in tabs if t is not None]
            start = np.concatenate([[0], np.cumsum([0 if t is None else t[0].size for t in tabs])]).astype(np.intp)
            self._tab = (start, np.concatenate([t[0] for t in have]), np.concatenate([t[1] for t in have]))
            union = np.unique(self._tab[1])
            self._table_sum = (union, np.sum([np.interp(union, t[0], t[1]) for t in have], axis=0))
        self.rail = rail
        self.substeps = int(substeps)
        veh, num = [], []
        for i, ax in enumerate(axles):
            veh += [i] * len(ax.normal_load_n)
            num += list(range(1, len(ax.normal_load_n) + 1))
        self.axle_vehicle = np.asarray(veh, dtype=np.int64)      # (P,) vehicle of each axle, 0-based
        self.axle_number = np.asarray(num, dtype=np.int64)       # (P,) axle number within its vehicle, 1-based
        self.max_axles = int(self.axle_number.max()) if num else 0
        self.command_names = tuple(f"axle{j}_torque_nm" for j in range(1, self.max_axles + 1))

        def cat(attr: str) -> np.ndarray:
            return np.concatenate([np.asarray(getattr(a, attr), dtype=float) for a in axles]) if num else np.zeros(0)

        radius = cat("radius_m")
        self.wheels = WheelSet(cat("normal_load_n"), cat("inertia_kgm2"), radius, np.full(len(num), speed_mps / radius)
                               if num else np.zeros(0), variant=variant, v_floor_mps=v_floor_mps)
        self._sel = {j: np.flatnonzero(self.axle_number == j) for j in range(1, self.max_axles + 1)}
        self.position_m = float(position_m)
        self.speed_mps = float(speed_mps)
        self.torque_nm = np.zeros(len(num))
        self.time_s = 0.0
        self._t0, self._k, self._h = 0.0, 0, 0.0
        self._accel = 0.0
        self._a_last = 0.0  # the body's acceleration over the last sub-step (m/s²)
        #: the wheel speeds before the last step and its length (s): the wheels' inertia force
        self._w_start: np.ndarray | None = None
        self._dt_last = 1.0
        self._fa_step: np.ndarray | None = None
        self._meas: dict[str, np.ndarray] | None = None  # measurements of the current state (cached)
        self._mass_cumsum = np.cumsum(self.mass_kg)
        #: the measurements' names in the order of the kernel's rows (canbrake.physics._adhesion_kernel.measure)
        self._meas_keys = ["position_m", "speed_mps", "ground_speed_mps", "accel_mps2", "applied_brake_n",
                           "resistance_n", "wheel_inertia_force_n", "deflection_m", "coupler_force_n"] + [
            f"axle{j}_{name}" for name in ("speed_radps", "slip", "mu", "adhesion_n", "applied_torque_nm")
            for j in range(1, self.max_axles + 1)]

    # ---------------------------------------------------------------- physics
    def resistance(self, v_mps: float) -> tuple[float, float]:
        """Train resistance Σ F_d,i(v) (N) and its slope (N·s/m); the constant term opposes motion."""
        a0, a1, a2 = self._davis_sum
        sgn = float(np.sign(v_mps)) if abs(v_mps) > 1e-6 else 0.0
        fd, dfd = sgn * a0 + a1 * v_mps + a2 * v_mps * abs(v_mps), a1 + 2.0 * a2 * abs(v_mps)
        if self._table_sum is not None:
            tv, tf = self._table_sum
            s = abs(v_mps)
            k = int(np.clip(np.searchsorted(tv, s, side="right") - 1, 0, max(tv.size - 2, 0)))
            inside = tv.size > 1 and tv[0] < s < tv[-1]
            fd += sgn * float(np.interp(s, tv, tf))
            dfd += float((tf[k + 1] - tf[k]) / (tv[k + 1] - tv[k])) if inside else 0.0
        return fd, dfd

    def vehicle_resistance_n(self, v_mps: float) -> np.ndarray:
        """F_d,i(v) per vehicle (N), shape (n,)."""
        c0, c1, c2 = self.davis_n.T
        sgn = float(np.sign(v_mps)) if abs(v_mps) > 1e-6 else 0.0
        fd = sgn * c0 + c1 * v_mps + c2 * v_mps * abs(v_mps)
        if self._tab is not None:  # each vehicle's own table, compiled (the coupled kernel's interpolation)
            from canbrake.physics._train_kernel import with_table_resistance

            fd = fd + sgn * with_table_resistance(self._tab[0], self._tab[1], self._tab[2],
                                                  np.full(self.n_vehicles, abs(v_mps)), np.zeros(self.n_vehicles))
        return fd

    def step(self, dt_s: float, commands: Mapping[str, np.ndarray]) -> None:
        """Advance by ``dt_s`` (s) holding the axle torque commands (see the class docstring)."""
        torque = _adhesion_kernel.axle_torques([commands.get(c) for c in self.command_names], self.axle_vehicle,
                                               self.axle_number)  # not commanded (NaN or absent): no torque
        self.torque_nm = torque
        self._meas = None
        h = dt_s / self.substeps
        if h != self._h:
            self._t0, self._k, self._h = self.time_s, 0, h
        wheels = self.wheels
        v_start, w_start = self.speed_mps, _axle_array(wheels.omega_radps, self.axle_vehicle.size)
        for _ in range(self.substeps):
            cond = self.rail.at(self.time_s)
            v_new, fa = wheels.step_coupled(torque, self.speed_mps, cond, h, mass_kg=self.total_mass_kg,
                                            davis=self._davis_terms, table=self._table_sum)
            self._a_last = (v_new - self.speed_mps) / h
            self.position_m += 0.5 * h * (self.speed_mps + v_new)
            self.speed_mps = v_new
            self._fa_step = fa
            self._k += 1
            self.time_s = self._t0 + self._k * h
        self._accel = (self.speed_mps - v_start) / dt_s
        self._w_start, self._dt_last = w_start, dt_s
        if not (math.isfinite(self.speed_mps) and math.isfinite(self.position_m) and wheels.finite):
            raise PlantDiverged(f"adhesion train: non-finite state at t = {self.time_s:g} s")

    # ---------------------------------------------------------------- outputs
    def measurements(self) -> dict[str, np.ndarray]:
        """Current state by name (see the class docstring); arrays are shared, do not modify them."""
        if self._meas is None:
            self._meas = self._measure()
        return dict(self._meas)

    def _measure(self) -> dict[str, np.ndarray]:
        """Every measurement of the current state in one compiled call (fresh arrays per state: a
        caller may keep them), rows of two blocks (per vehicle, per coupler)."""
        n, v, w = self.n_vehicles, self.speed_mps, self.wheels
        cond = self.rail.at(self.time_s)
        last = getattr(w, "last_adhesion", None)
        if last is not None and last[0] is cond and last[1] == v and last[2] is w.omega_radps:
            lam, mu, fa = last[3]  # the step's own evaluation at this state
        else:
            lam, mu, fa = (np.ascontiguousarray(x, dtype=float) for x in w.adhesion(v, cond))
        table = None
        if self._tab is not None:  # each vehicle's own table, compiled (the coupled kernel's interpolation)
            from canbrake.physics._train_kernel import with_table_resistance

            table = with_table_resistance(self._tab[0], self._tab[1], self._tab[2], np.full(n, abs(v)), np.zeros(n))
        (J, R, _N), _c = w._kernel_args(cond)
        p = J.shape[0]
        rows = np.empty((7 + 5 * self.max_axles, n))
        couplers = np.empty((2, max(n - 1, 0)))
        _adhesion_kernel.measure(rows, couplers, self.position_m, v, self._accel, self._a_last, self._fa_step, lam,
                                 mu, fa, _axle_array(w.omega_radps, p), self.torque_nm, self._w_start,
                                 self._dt_last, J, R, self.axle_vehicle, self.axle_number, self.davis_n, table,
                                 self._mass_cumsum)
        per = list(rows)
        return dict(zip(self._meas_keys, per[:7] + list(couplers) + per[7:]))
