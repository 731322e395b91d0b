"""Locomotive speed/position tracking controllers of Li, Zeng & Yu 2024 (section 2).

Pure controllers, no I/O, SI units (m, m/s, m/s², N, kg). Each has explicit state and
``step(obs) -> (u_n, diagnostics)``; the command is saturated by the HXD1 envelope
(:func:`canbrake.physics.heavy_haul.saturate_control_n`).

* :class:`LiPID` — PID on the speed error, gains 1e7, 1, 1 (N per m/s, N per m, N per m/s²).
* :class:`LiSlidingMode` — SMC (eq. 22), optionally with the RBF network (eqs. 23-29,
  ``rbf=True``) and the nonlinear disturbance observer (eqs. 30-35, ``ndo=True``).

Sliding surface (19): s = ė + λ1 e + λ2 ∫e with e = x − x_d (m), ė = v − v_d (m/s).
Reaching law (21) is printed ṡ = −ζ|s|^α sgn(s) − ζ sgn(s) with ζ both "= 0.005" and
"= κ·tansig(|e|)", tansig(x) = (1 − e^{−x})/(1 + e^{−x}). Two readings are implemented
(``reading``):

* ``"listed"``: ṡ = −ζ0 |s|^α sgn(s) − κ·tansig(|e|) sgn(s), ζ0 = 0.005 (the listed ζ multiplies the
  power term, the adaptive gain the switching term);
* ``"adaptive-power"``: ṡ = −κ·tansig(|e|) |s|^α sgn(s) − ζ0 sgn(s) (the other assignment).

The model term f(x) = −(F_C0 + F_W0 + F_f0 + F_a0)/m0 is computed by the caller from measured /
nominal locomotive forces (coupler force measured) and passed in ``Obs.f_nominal_mps2``.
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from canbrake.physics.heavy_haul import saturate_control_n

READINGS = ("listed", "adaptive-power")


@dataclass(frozen=True)
class Obs:
    """What the locomotive controller knows at one step (SI)."""

    time_s: float
    x_m: float
    v_mps: float
    x_ref_m: float
    v_ref_mps: float
    a_ref_mps2: float
    f_nominal_mps2: float  # f(x) of eq. (17) from nominal model + measured coupler force


def tansig(x: float) -> float:
    """(1 − e^{−x})/(1 + e^{−x}) as printed under eq. (21)."""
    return (1.0 - math.exp(-x)) / (1.0 + math.exp(-x))


class LiPID:
    """PID on the speed error e_v = v_ref − v; u = Kp e_v + Ki ∫e_v + Kd ė_v, saturated."""

    name = "pid"

    def __init__(self, dt_s: float, kp: float = 1e7, ki: float = 1.0, kd: float = 1.0):
        self.dt, self.kp, self.ki, self.kd = dt_s, kp, ki, kd
        self.integ = 0.0
        self.prev = None

    def step(self, o: Obs) -> tuple[float, dict[str, float]]:
        ev = o.v_ref_mps - o.v_mps
        self.integ += ev * self.dt
        de = 0.0 if self.prev is None else (ev - self.prev) / self.dt
        self.prev = ev
        u = self.kp * ev + self.ki * self.integ + self.kd * de
        return saturate_control_n(u, o.v_mps), {"u_raw_n": u}


class LiSlidingMode:
    """SMC / RBFNN-SMC / RBFNN-SMC + NDO on the locomotive (eqs. 19-35).

    ``m0_kg`` locomotive mass; gains as in section 3.1. ``rbf`` adds δ̂ = Ŵᵀh(χ), χ = [e, ė], with
    the adaptation Ŵ̇ = γ s h (eq. 28, explicit Euler); ``ndo`` adds d̂ from eq. (30) with
    p(x) = ω v. With ω = 1000 s⁻¹ and our 10 ms step explicit Euler on eq. (30) would be unstable
    (ω·dt = 10), so the observer's linear error dynamics d̂̇ = ω(d − d̂) are integrated exactly over
    the step with d held (zero-order hold); in z = d̂ − ω v coordinates this is eq. (30).
    """

    def __init__(self, dt_s: float, m0_kg: float, *, rbf: bool = False, ndo: bool = False,
                 reading: str = "listed", lam1: float = 1.0, lam2: float = 0.1, zeta0: float = 0.005,
                 kappa: float = 0.05, alpha: float = 5.0, gamma: float = 0.01, b: float = 0.005,
                 centers=(-1.0, -0.5, 0.0, 0.5, 1.0), center_scale: float = 0.01, omega: float = 1000.0):
        if reading not in READINGS:
            raise ValueError(f"unknown reading {reading!r}; use one of {READINGS}")
        self.dt, self.m0 = dt_s, m0_kg
        self.rbf, self.ndo, self.reading = rbf, ndo, reading
        self.lam1, self.lam2, self.zeta0, self.kappa, self.alpha = lam1, lam2, zeta0, kappa, alpha
        self.gamma, self.b, self.omega = gamma, b, omega
        c = center_scale * np.asarray(centers, dtype=float)
        self.c = np.vstack([c, c])  # (2, 5): c1 = c2
        self.W = np.zeros(c.size)
        self.int_e = 0.0
        self.d_hat = 0.0
        self.z = 0.0
        self._prev: tuple[float, float, float] | None = None  # (v, f, u) of the last step
        self.name = "rbfnn-smc" + ("+ndo" if ndo else "") if rbf else ("smc+ndo" if ndo else "smc")

    def basis(self, e: float, de: float) -> np.ndarray:
        """Eq. (25): h_j = exp(−‖χ − c_j‖² / (2 b²)), shape (5,)."""
        d2 = (e - self.c[0]) ** 2 + (de - self.c[1]) ** 2
        return np.exp(-d2 / (2.0 * self.b ** 2))

    def step(self, o: Obs) -> tuple[float, dict[str, float]]:
        e = o.x_m - o.x_ref_m
        de = o.v_mps - o.v_ref_mps
        self.int_e += e * self.dt
        s = de + self.lam1 * e + self.lam2 * self.int_e
        zeta_ad = self.kappa * tansig(abs(e))
        sg = math.copysign(1.0, s) if s != 0.0 else 0.0
        if self.reading == "listed":
            reach = self.zeta0 * abs(s) ** self.alpha * sg + zeta_ad * sg
        else:
            reach = zeta_ad * abs(s) ** self.alpha * sg + self.zeta0 * sg
        delta_hat = 0.0
        if self.rbf:
            h = self.basis(e, de)
            delta_hat = float(self.W @ h)
            self.W = self.W + self.gamma * s * h * self.dt
        if self.ndo:
            if self._prev is not None:
                v0, f0, u0 = self._prev
                d_meas = (o.v_mps - v0) / self.dt - f0 - u0 / self.m0
                self.d_hat += (d_meas - self.d_hat) * (1.0 - math.exp(-self.omega * self.dt))
            self.z = self.d_hat - self.omega * o.v_mps
        u_raw = -self.m0 * (o.f_nominal_mps2 + delta_hat + self.d_hat - o.a_ref_mps2
                            + self.lam1 * de + self.lam2 * e + reach)
        u = saturate_control_n(u_raw, o.v_mps)
        self._prev = (o.v_mps, o.f_nominal_mps2, u)
        return u, {"s": s, "delta_hat": delta_hat, "d_hat": self.d_hat, "u_raw_n": u_raw}


def make_controller(name: str, dt_s: float, m0_kg: float, reading: str = "listed"):
    """``pid`` | ``smc`` | ``rbfnn-smc`` | ``rbfnn-smc+ndo`` | ``smc+ndo``."""
    if name == "pid":
        return LiPID(dt_s)
    table = {"smc": (False, False), "smc+ndo": (False, True), "rbfnn-smc": (True, False),
             "rbfnn-smc+ndo": (True, True)}
    if name not in table:
        raise KeyError(f"unknown Li 2024 controller {name!r}; available: pid, {', '.join(table)}")
    rbf, ndo = table[name]
    return LiSlidingMode(dt_s, m0_kg, rbf=rbf, ndo=ndo, reading=reading)
