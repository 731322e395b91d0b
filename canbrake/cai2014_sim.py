"""In-process simulation of Cai et al. 2014's reference run: 2 vehicles, 96 t, 0 → 200 km/h in 200 s.

The train is the paper's single-coordinate model (eq. 3: in-train forces cancel in the sum over
vehicles), m = 96 t, with p = 4 driven axles (the locomotive's), axle loads 117.6 kN ± 1.5 % / ± 2.5 %,
J = 80 kg·m², R = 0.495 m, resistance F_d = 0.407 + 0.2916 v + 0.0067 v² read as kN with v in m/s.
Rail: "dry" coefficients (eq. 41) for 50 s ≤ t ≤ 100 s, "wet" (eq. 42) otherwise.

Fixed step ``dt_s`` (1 ms default): each period the controller computes torques from the state, then
wheels and body advance by one jointly implicit (backward-Euler) step
(:meth:`canbrake.physics.wheel_adhesion.WheelSet.step_coupled`) and the position by the trapezoid rule.
Units are SI inside; km/h and kN appear only in :class:`CaiParams` defaults' comments and in plots.
"""
from __future__ import annotations

from dataclasses import dataclass, field, replace
from typing import Any

import numpy as np

from canbrake.control.cai2014 import PAPER_GAINS, CaiController, CaiGains
from canbrake.physics.wheel_adhesion import WheelSet, rail_condition

KMH = 1.0 / 3.6


@dataclass(frozen=True)
class CaiParams:
    """Reference run (section 4 of the paper), SI. ``variant``: "paper" or "physical" adhesion curve."""

    mass_kg: float = 96.0e3
    n_vehicles: int = 2
    axle_load_n: float = 117.6e3
    imbalance: tuple[float, ...] = (0.015, -0.015, 0.025, -0.025)  # ΔN_i/N_i0 of the 4 driven axles
    inertia_kgm2: float = 80.0
    radius_m: float = 0.495
    davis_n: tuple[float, float, float] = (407.0, 291.6, 6.7)  # N, N/(m/s), N/(m/s)²
    v_final_mps: float = 200.0 * KMH
    ramp_s: float = 200.0
    duration_s: float = 200.0
    dry_window_s: tuple[float, float] = (50.0, 100.0)
    variant: str = "paper"
    v_floor_mps: float = 0.1
    dt_s: float = 1.0e-3
    gains: CaiGains = PAPER_GAINS
    sigma: float = 1.0  # sign of eqs. 44–45: +1 as eq. 20, −1 as printed
    record_every: int = 10

    @property
    def n_axles(self) -> int:
        return len(self.imbalance)

    def resistance(self, v_mps: float) -> tuple[float, float]:
        """F_d(v) in N and dF_d/dv in N·s/m; the constant term opposes motion, zero at standstill."""
        a0, a1, a2 = self.davis_n
        sgn = float(np.sign(v_mps)) if abs(v_mps) > 1e-6 else 0.0
        return sgn * a0 + a1 * v_mps + a2 * v_mps * abs(v_mps), a1 + 2.0 * a2 * abs(v_mps)

    def reference(self, t_s: float) -> tuple[float, float, float]:
        """x* (m), v* (m/s), a* (m/s²): constant acceleration to ``v_final`` at ``ramp_s``, then cruise."""
        a = self.v_final_mps / self.ramp_s
        if t_s <= self.ramp_s:
            return 0.5 * a * t_s * t_s, a * t_s, a
        x1 = 0.5 * a * self.ramp_s ** 2
        return x1 + self.v_final_mps * (t_s - self.ramp_s), self.v_final_mps, 0.0


@dataclass
class CaiTrace:
    """Recorded signals, SI. Per-axle arrays have shape ``(n_samples, p)``; others ``(n_samples,)``."""

    case: int
    params: CaiParams
    time_s: np.ndarray
    position_m: np.ndarray
    ref_position_m: np.ndarray
    speed_mps: np.ndarray
    ref_speed_mps: np.ndarray
    omega_radps: np.ndarray
    slip: np.ndarray
    mu: np.ndarray
    adhesion_n: np.ndarray
    torque_nm: np.ndarray
    adhesion_hat_n: np.ndarray
    resistance_n: np.ndarray
    resistance_hat_n: np.ndarray
    lumped_n: np.ndarray  # F_dw = (J/R) Σ ω̇ + F_d (eq. 36), from the plant
    lumped_hat_n: np.ndarray
    extra: dict[str, Any] = field(default_factory=dict)

    @property
    def position_error_m(self) -> np.ndarray:
        return self.position_m - self.ref_position_m

    @property
    def speed_error_mps(self) -> np.ndarray:
        return self.speed_mps - self.ref_speed_mps

    def to_npz(self) -> dict[str, np.ndarray]:
        return {k: v for k, v in self.__dict__.items() if isinstance(v, np.ndarray)}


def simulate(case: int, params: CaiParams | None = None, **overrides: Any) -> CaiTrace:
    """Run one control case (1–4) of the reference profile; ``overrides`` replace fields of ``params``."""
    pr = replace(params or CaiParams(), **overrides)
    p, dt = pr.n_axles, pr.dt_s
    loads = pr.axle_load_n * (1.0 + np.asarray(pr.imbalance, dtype=float))
    wheels = WheelSet(loads, pr.inertia_kgm2, pr.radius_m, np.zeros(p), variant=pr.variant,
                      v_floor_mps=pr.v_floor_mps)
    ctrl = CaiController(case, mass_kg=pr.mass_kg, n_axles=p, radius_m=pr.radius_m,
                         inertia_kgm2=pr.inertia_kgm2, gains=pr.gains, sigma=pr.sigma)
    n = int(round(pr.duration_s / dt))
    k = max(1, int(pr.record_every))
    m = n // k + 1
    rec = {name: np.zeros(m) for name in ("t", "x", "xr", "v", "vr", "fd", "fdh", "fdw", "fdwh")}
    rec_ax = {name: np.zeros((m, p)) for name in ("w", "lam", "mu", "fa", "T", "fah")}
    x, v = 0.0, 0.0
    J_R = pr.inertia_kgm2 / pr.radius_m
    j = 0
    for i in range(n + 1):
        t = i * dt
        xr, vr, ar = pr.reference(t)
        fd, _ = pr.resistance(v)
        cond = rail_condition(t, pr.dry_window_s)
        w_old = wheels.omega_radps
        out = ctrl.step(position_m=x, speed_mps=v, omega_radps=w_old, ref_position_m=xr, ref_speed_mps=vr,
                        ref_accel_mps2=ar, resistance_n=fd, dt_s=dt)
        if i % k == 0:
            lam, mu, fa = wheels.adhesion(v, cond)
            rec["t"][j], rec["x"][j], rec["xr"][j], rec["v"][j], rec["vr"][j] = t, x, xr, v, vr
            rec["fd"][j], rec["fdh"][j], rec["fdwh"][j] = fd, out.diagnostics["resistance_hat_n"], \
                out.diagnostics["lumped_hat_n"]
            rec_ax["w"][j], rec_ax["lam"][j], rec_ax["mu"][j], rec_ax["fa"][j] = w_old, lam, mu, fa
            rec_ax["T"][j], rec_ax["fah"][j] = out.torque_nm, out.diagnostics["adhesion_hat_n"]
        if i == n:
            break
        v_new, _ = wheels.step_coupled(out.torque_nm, v, cond, dt, mass_kg=pr.mass_kg,
                                       resistance=pr.resistance)
        if i % k == 0:
            # F_dw over this step (eq. 36): wheel-inertia term from the step's mean ω̇ plus F_d
            rec["fdw"][j] = J_R * float(np.sum(wheels.omega_radps - w_old)) / dt + fd
            j += 1
        x += 0.5 * dt * (v + v_new)
        v = v_new
    if j < m:  # last sample (i == n) has no step after it: carry the previous F_dw
        rec["fdw"][j] = rec["fdw"][j - 1] if j > 0 else 0.0
        j += 1
    sl = slice(0, j)
    return CaiTrace(case=case, params=pr, time_s=rec["t"][sl], position_m=rec["x"][sl],
                    ref_position_m=rec["xr"][sl], speed_mps=rec["v"][sl], ref_speed_mps=rec["vr"][sl],
                    omega_radps=rec_ax["w"][sl], slip=rec_ax["lam"][sl], mu=rec_ax["mu"][sl],
                    adhesion_n=rec_ax["fa"][sl], torque_nm=rec_ax["T"][sl], adhesion_hat_n=rec_ax["fah"][sl],
                    resistance_n=rec["fd"][sl], resistance_hat_n=rec["fdh"][sl], lumped_n=rec["fdw"][sl],
                    lumped_hat_n=rec["fdwh"][sl])


def error_metrics(tr: CaiTrace, t0_s: float = 0.0) -> dict[str, float]:
    """Mean and max |position error| (m), mean and max |speed error| (m/s) for t ≥ ``t0_s``."""
    sel = tr.time_s >= t0_s
    e, de = np.abs(tr.position_error_m[sel]), np.abs(tr.speed_error_mps[sel])
    return {"mean_abs_pos_err_m": float(np.mean(e)), "max_abs_pos_err_m": float(np.max(e)),
            "mean_abs_speed_err_mps": float(np.mean(de)), "max_abs_speed_err_mps": float(np.max(de)),
            "rms_pos_err_m": float(np.sqrt(np.mean(e * e)))}
