"""Brake equipment of a coupled (metro) car beyond a force actuator: electro-dynamic / friction
blending, wheelsets with wheel–rail adhesion under braking, the wheel-slide-protection dump valve.

Vectorised over cars (shape ``(n,)``) and axles (shape ``(n, p)``); SI throughout (m, s, m/s, N,
N·m, kg·m², rad/s). No CAN here: the wheel-slide-protection *logic* is an ECU function
(:mod:`canbrake.control.brake_functions`); the plant only has the valve it drives.

Blending (:class:`BrakeBlending`)
    The car's brake demand (the actuator's effort, + brakes) goes first to the electro-dynamic (ED)
    brake of its traction motors, up to what the ED brake can give at the car's speed,
    ``F_ed,max(v) = m · min(a_ed, P/(m|v|)) · fade(v)``, with ``fade`` rising linearly from 0 at
    ``fade_end_mps`` to 1 at ``fade_start_mps`` (an ED brake loses its force as the motor's back-EMF
    vanishes near standstill). The friction brake supplies the rest and follows its share with a
    first-order lag ``friction_lag_s`` (relay valve and cylinder fill), so when the ED brake fades
    the total dips by about ``friction_lag_s · dF_ed/dt`` until the friction brake catches up. Traction
    (a negative effort) is not blended.

Wheelsets (:class:`Wheelsets`)
    ``p`` axles per car, each with its own angular speed ω, radius R, inertia J and normal load
    N = m g / p. The brake torque T_b (the car's brake force · R / p) acts on the wheel as Coulomb
    friction (it opposes ω and holds a locked wheel up to its magnitude); the rail acts on the
    wheel with the creep force F = μ(λ, v) N of Cai et al. 2014 (eqs. 10–15, the "physical" variant
    of :mod:`canbrake.physics.wheel_adhesion`: the printed slip curve scaled to a peak μ per car,
    times the speed decay μ_max(v)/μ_max(0)). Braking gives negative creep λ = (ωR − v)/max(ωR, v,
    v_floor) < 0. When T_b exceeds what the rail can take (≈ μ_peak N R) the wheel decelerates
    faster than the car, λ runs past the adhesion peak, μ falls and the wheel locks: a skid is the
    physical result of low μ, not a force cap. Wheels and car body are solved together by backward
    Euler (Newton on the arrow-shaped Jacobian, as :meth:`WheelSet.step_coupled`), because the
    creep force is stiff near standstill (time constants below a millisecond).

Dump valve (:func:`valve_step`)
    Wheel-slide protection vents the brake cylinders of a car through its dump valves: the brake
    torque is multiplied by ``1 − r`` with r the valve opening, which follows the ECU's
    ``wsp_release`` command (0..1) with a first-order lag (default 0.05 s); the dump valve acts
    downstream of the brake control, so it bypasses the service brake's jerk limit.
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from canbrake.physics.wheel_adhesion import RailCondition

#: Cai 2014's dry-rail slip curve (eq. 41), the default shape of the coupled train's wheels
CAI_DRY = RailCondition(b1=1.786, b2=40.0, b3=10.0, c1=0.040, c2=3.78, c3=33.3, peak_mu0=0.35)


@dataclass(frozen=True)
class BrakeBlending:
    """ED / friction blending parameters (per unit mass, the same for every car).

    ``ed_max_decel_mps2``: ED brake force / m at full capacity (m/s²); ``ed_power_w_per_kg``: ED
    power limit per unit mass (W/kg; inf = none); ``fade_start_mps`` / ``fade_end_mps``: the ED
    force fades linearly to zero between these speeds (m/s); ``friction_lag_s``: first-order lag of
    the friction brake behind its share of the demand (s; 0 = immediate).
    """

    ed_max_decel_mps2: float = 1.0
    ed_power_w_per_kg: float = math.inf
    fade_start_mps: float = 10.0 / 3.6
    fade_end_mps: float = 3.0 / 3.6
    friction_lag_s: float = 0.2

    def __post_init__(self) -> None:
        if not self.fade_start_mps > self.fade_end_mps >= 0.0:
            raise ValueError("blending: need fade_start > fade_end >= 0")
        if self.ed_max_decel_mps2 < 0 or self.friction_lag_s < 0:
            raise ValueError("blending: ED capacity and friction lag must be >= 0")

    def ed_available_n(self, mass_kg: np.ndarray, v_mps: np.ndarray) -> np.ndarray:
        """Largest ED brake force per car (N) at speeds ``v_mps``."""
        s = np.abs(v_mps)
        fade = np.clip((s - self.fade_end_mps) / (self.fade_start_mps - self.fade_end_mps), 0.0, 1.0)
        with np.errstate(divide="ignore"):
            per_kg = np.minimum(self.ed_max_decel_mps2, self.ed_power_w_per_kg / np.maximum(s, 1e-9))
        return mass_kg * per_kg * fade


class BlendingState:
    """Blending of every car: friction-brake state (N) and the last split."""

    def __init__(self, params: BrakeBlending, mass_kg: np.ndarray) -> None:
        self.params = params
        self.mass_kg = mass_kg
        self.friction_n = np.zeros_like(mass_kg)
        self.ed_n = np.zeros_like(mass_kg)

    def advance(self, effort_n: np.ndarray, v_mps: np.ndarray, h_s: float) -> np.ndarray:
        """Split the brake effort over ``h_s``; returns the total force (N, + brakes, − traction)."""
        demand = np.maximum(effort_n, 0.0)
        self.ed_n = np.minimum(demand, self.params.ed_available_n(self.mass_kg, v_mps))
        share = demand - self.ed_n
        lag = self.params.friction_lag_s
        if lag > 0.0:
            self.friction_n = self.friction_n + (share - self.friction_n) * (1.0 - math.exp(-h_s / lag))
        else:
            self.friction_n = share
        return self.ed_n + self.friction_n + np.minimum(effort_n, 0.0)


def valve_step(opening: np.ndarray, command: np.ndarray, h_s: float, lag_s: float) -> np.ndarray:
    """Dump-valve opening after ``h_s`` (first-order lag ``lag_s`` towards ``command`` clipped to 0..1;
    NaN = not commanded = closed)."""
    target = np.clip(np.where(np.isnan(command), 0.0, command), 0.0, 1.0)
    if lag_s <= 0.0:
        return target
    return opening + (target - opening) * (1.0 - math.exp(-h_s / lag_s))


class Wheelsets:
    """The axles of every car of a coupled train: ω of shape ``(n, p)`` (see the module docstring).

    ``mass_kg`` (n,) car masses (the normal load per axle is m g / p); ``radius_m``, ``inertia_kgm2``
    per wheelset; ``curve`` the slip-curve shape (peak scaled to each car's μ); ``v_floor_mps`` the
    slip denominator's floor; ``speed_mps`` (n,) initial speeds (wheels roll without slip).
    """

    def __init__(self, mass_kg: np.ndarray, axles: int, radius_m: float, inertia_kgm2: float,
                 speed_mps: np.ndarray, *, curve: RailCondition = CAI_DRY, v_floor_mps: float = 0.1,
                 gravity_mps2: float = 9.81, newton_iters: int = 5) -> None:
        if axles < 1 or radius_m <= 0 or inertia_kgm2 <= 0:
            raise ValueError("wheelsets: need axles >= 1, radius > 0, inertia > 0")
        self.p = int(axles)
        self.R = float(radius_m)
        self.J = float(inertia_kgm2)
        self.curve = curve
        self.v_floor = float(v_floor_mps)
        self.N = np.repeat((np.asarray(mass_kg, dtype=float) * gravity_mps2 / axles)[:, None], axles, axis=1)
        self.omega = np.repeat((np.asarray(speed_mps, dtype=float) / radius_m)[:, None], axles, axis=1)
        self.iters = int(newton_iters)
        c = curve
        self._mu0 = float(c.mu_max(0.0))
        self._peak_curve = c.peak_curve
        self.force_n = np.zeros_like(self.omega)
        self.slip = np.zeros_like(self.omega)

    def creep(self, w: np.ndarray, v: np.ndarray, mu_peak: np.ndarray) -> tuple[np.ndarray, ...]:
        """(λ, F, ∂F/∂ω, ∂F/∂v) per axle, shape (n, p): the creep force F (N, + forward) at wheel
        speeds ``w`` (n, p) and car speeds ``v`` (n,), for peak μ ``mu_peak`` (n,) at standstill."""
        c, R, floor = self.curve, self.R, self.v_floor
        vv = v[:, None]
        wr = w * R
        awr, av = np.abs(wr), np.abs(vv)
        den = np.maximum(np.maximum(awr, av), floor)
        lam = (wr - vv) / den
        use_wr = (awr >= av) & (awr >= floor)
        use_v = ~use_wr & (av >= floor)
        safe_wr2 = np.where(use_wr, wr * wr, 1.0)
        dlam_dw = np.where(use_wr, R * av / safe_wr2, R / den)
        dlam_dv = np.where(use_v, -wr / (den * den), -1.0 / den)
        scale = (c.c1 + c.c2 / (c.c3 + av)) / self._mu0 * (mu_peak[:, None] / self._peak_curve)
        a = np.abs(lam)
        ex = np.exp(-c.b2 * a)
        sn = scale * self.N
        f = np.sign(lam) * sn * (c.b1 * (1.0 - ex) - a / c.b3)
        dmu = sn * (c.b1 * c.b2 * ex - 1.0 / c.b3)
        return lam, f, dmu * dlam_dw, dmu * dlam_dv

    def step(self, h_s: float, v0: np.ndarray, mass_kg: np.ndarray, other_n: np.ndarray, brake_torque_nm: np.ndarray,
             drive_torque_nm: np.ndarray, mu_peak: np.ndarray) -> np.ndarray:
        """One backward-Euler step of wheels and car bodies; returns the new car speeds (n,).

        Solves J(ω − ω0) = h(T_d − T_b sgn ω − F R) per axle and m(v − v0) = h(Σ F + other) per car
        (``other_n``: the car's forces besides the creep forces, held over the step). A wheel whose ω
        would pass through zero under the brake locks (ω = 0) and stays locked while the brake torque
        holds it against the rail (Coulomb friction). Creep forces are left in :attr:`force_n`.
        """
        R, J = self.R, self.J
        w0 = self.omega
        _, f0, _, _ = self.creep(w0, v0, mu_peak)
        spin = drive_torque_nm - f0 * R  # torque on the wheel besides the brake
        at_zero = w0 == 0.0
        locked = at_zero & (np.abs(spin) <= brake_torque_nm)
        s = np.where(at_zero, np.sign(spin), np.sign(w0))
        tb = brake_torque_nm * s
        w, v = np.where(locked, 0.0, w0), v0.copy()
        for attempt in range(2):
            free = ~locked
            for _ in range(self.iters):
                lam, f, fw, fv = self.creep(w, v, mu_peak)
                r_w = J * (w - w0) - h_s * (drive_torque_nm - tb - f * R)
                a = J + h_s * R * fw
                a = np.where(a > 0.1 * J, a, J)  # past the adhesion peak the slope is negative: damped step
                a = np.where(free, a, 1.0)
                r_w = np.where(free, r_w, 0.0)
                b = np.where(free, h_s * R * fv, 0.0)
                cc = np.where(free, -h_s * fw, 0.0)
                r_v = mass_kg * (v - v0) - h_s * (f.sum(axis=1) + other_n)
                d = mass_kg - h_s * fv.sum(axis=1)
                dv = (-r_v + (cc * r_w / a).sum(axis=1)) / (d - (cc * b / a).sum(axis=1))
                w = w + (-r_w - b * dv[:, None]) / a
                v = v + dv
            over = free & (w * s < 0.0)  # the brake stopped the wheel within the step: it locks
            if not over.any():
                break
            locked = locked | over
            w = np.where(locked, 0.0, w)
        self.omega = w
        lam, f, _, _ = self.creep(w, v, mu_peak)
        self.force_n, self.slip = f, lam
        return v
