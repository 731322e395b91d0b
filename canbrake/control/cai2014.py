"""Cai et al. 2014: traction/braking control with force observers (eqs. 18, 22, 40, 43–46).

Pure code, no I/O: explicit state, ``step(...)`` per control period. SI units: m, s, m/s, m/s²,
N, N·m, kg, kg·m², rad/s. Arrays over driven axles have shape ``(p,)``.

Tracking error (eqs. 5–6): ``e = x − x*``, ``ė = v − v*``, ``s = ė + β e``. All four cases build
``u = −k0 s + m ẍ* − β ė + F`` (eq. 8/9) with ``F`` the true resistance ``F_d`` (cases 1, 2),
the resistance observer's ``F̂_d`` (case 3) or the lumped-disturbance observer's ``F̂_dw`` (case 4):

* case 1, model-based control (eq. 43): ``T_i = (R/p) u``
* case 2, MBC + adhesion-force control (eq. 44): ``F_i^cmd = σ u/p``, ``T_i = ka (F_i^cmd − F̂_ai) + F̂_ai R``
* case 3, double observer (eq. 45): as case 2 with ``F̂_d`` in ``u``
* case 4, simplified observer (eq. 46): ``T_i = (R/p) u`` with ``F̂_dw`` in ``u``

Readings (see docs/reproduction/cai2014.md):

* units — the gains only make sense with masses in tonnes and forces in kN (k0 = 50 kN per m/s);
  in SI that is ``k0 = 50 000 N·s/m``. β and g (1/s) and ka (m: N → N·m) do not depend on the
  choice. :data:`PAPER_GAINS` holds the SI values.
* sign of eqs. 44–45 — printed ``F^cmd = −(1/p)[…]``; eq. 20 (the same command in section 3.2)
  and eq. 25 have ``+``, and with ``−`` the command is opposite to the needed tractive force, so
  the train is driven backwards. ``sigma = +1`` (default, "corrected") follows eq. 20;
  ``sigma = −1`` reproduces the printed sign.
* ``β ė`` in eq. 8/43–46: the same printed β, read in kN per m/s (1000 N·s/m, ``edot_gain``).
  Eq. 7 should read ``m β ė``, so this term does not cancel it and the loop
  ``m ë + (k0 + edot_gain) ė + k0 β e = 0`` is under-damped (ζ ≈ 0.37, period ≈ 9 s); the
  settled errors do not depend on it.
* eq. 39 prints ``T = (1/p)[…]`` without R; eq. 46 (the same control in section 4) has ``R/p``,
  which is dimensionally right (N → N·m). We use ``R/p``.
"""
from __future__ import annotations

import math
from dataclasses import dataclass
from types import SimpleNamespace
from typing import Annotated, Literal

import numpy as np
from pydantic import Field, validate_call

from canbrake.control.base import ControlOutput, Controller, Observation, register

CASES = (1, 2, 3, 4)
CASE_NAMES = {
    1: "model-based control (eq. 43)",
    2: "MBC + adhesion-force control (eq. 44)",
    3: "double observer (eq. 45)",
    4: "simplified observer (eq. 46)",
}


@dataclass(frozen=True)
class CaiGains:
    """Control parameters in SI: ``k0`` N·s/m, ``ka`` m, ``beta`` 1/s, observer cut-off ``g`` 1/s.

    ``edot_gain`` (N·s/m) is the coefficient of ė in ``u = −k0 s + m ẍ* − β ė + F``: printed as
    the same β = 1, read in kN per m/s it is 1000 N·s/m. (Eq. 7 prints ``β ė`` where the
    derivative of ``m s`` gives ``m β ė``; the exact cancellation would need ``m β`` = 96 000 N·s/m.)
    """

    k0: float = 50.0e3
    ka: float = 2.0
    beta: float = 1.0
    g: float = 10.0
    edot_gain: float = 1.0e3


#: the paper's k0 = 50, ka = 2, β = 1, g_a = g_d = g_dw = 10, read in tonnes/kN and converted to SI
PAPER_GAINS = CaiGains()


def filter_gain(g: float, dt_s: float) -> float:
    """1 − e^{−g dt}: the exact step of ŷ̇ = g (u − ŷ) for an input held over ``dt_s``."""
    return 1.0 - math.exp(-g * dt_s)


# Discretisation of the observers. Each figure's structure is ``F̂ = g/(s+g)[g·M + U] − g·M`` with a
# momentum-like signal M (J ω, m v, …) and a torque term U; it equals g/(s+g)[U − Ṁ] (eqs. 18, 22, 40).
# A zero-order hold of the whole filter input ``g·M + U`` (M held over the period although it ramps)
# leaves a bias of ≈ −Ṁ·g·dt/2: with dt = 1 ms and case 4, 2.7 mm of position error per ms of period.
# We discretise exactly for U held and M varying linearly over the period:
#     F̂_{n+1} = F̂_n + (1 − e^{−g dt}) (U_n − (M_{n+1} − M_n)/dt),
# which uses only measured ω, v and the applied torques, like the figures.


class AdhesionForceObserver:
    """Eq. 18 (Fig. 2), per axle: F̂_a = (1/R)[g/(s+g)(T + g J ω) − g J ω] = g/(s+g) (T − J ω̇)/R.

    Inputs: torque T (N·m) applied over the last period and wheel speeds ω (rad/s) at its ends,
    shape ``(p,)``; estimate in N, starting at 0.
    """

    def __init__(self, g: float, inertia_kgm2: float, radius_m: float, n_axles: int) -> None:
        self.g, self.J, self.R = float(g), float(inertia_kgm2), float(radius_m)
        self.estimate_n = np.zeros(n_axles)

    def update(self, torque_nm: np.ndarray, omega_prev: np.ndarray, omega_now: np.ndarray, dt_s: float) -> None:
        u = (torque_nm - self.J * (omega_now - omega_prev) / dt_s) / self.R
        self.estimate_n = self.estimate_n + filter_gain(self.g, dt_s) * (u - self.estimate_n)


class ResistanceObserver:
    """Eq. 22 (Fig. 3): F̂_d = g/(s+g)[g m v + (1/R) Σ(T + g J ω)] − g(m v + (J/R) Σ ω)
    = g/(s+g)[(1/R) Σ T − m v̇ − (J/R) Σ ω̇]. Inputs v (m/s), ω and T per axle; estimate in N.
    """

    def __init__(self, g: float, mass_kg: float, inertia_kgm2: float, radius_m: float) -> None:
        self.g, self.m, self.J, self.R = float(g), float(mass_kg), float(inertia_kgm2), float(radius_m)
        self.estimate_n = 0.0

    def update(self, torque_nm: np.ndarray, v_prev: float, v_now: float, omega_prev: np.ndarray,
               omega_now: np.ndarray, dt_s: float) -> None:
        dmom = self.m * (v_now - v_prev) + self.J / self.R * float(np.sum(omega_now - omega_prev))
        u = float(np.sum(torque_nm)) / self.R - dmom / dt_s
        self.estimate_n += filter_gain(self.g, dt_s) * (u - self.estimate_n)


class LumpedDisturbanceObserver:
    """Eq. 40 (Fig. 4): F̂_dw = g/(s+g)[g m v + (1/R) Σ T] − g m v = g/(s+g)[(1/R) Σ T − m v̇].

    Estimates F_dw = (J/R) Σ ω̇ + F_d (eq. 36) from v (m/s) and the torques only; N.
    """

    def __init__(self, g: float, mass_kg: float, radius_m: float) -> None:
        self.g, self.m, self.R = float(g), float(mass_kg), float(radius_m)
        self.estimate_n = 0.0

    def update(self, torque_nm: np.ndarray, v_prev: float, v_now: float, dt_s: float) -> None:
        u = float(np.sum(torque_nm)) / self.R - self.m * (v_now - v_prev) / dt_s
        self.estimate_n += filter_gain(self.g, dt_s) * (u - self.estimate_n)


@dataclass
class CaiOutput:
    """One control period: torques per axle (N·m), shape ``(p,)``, and named SI diagnostics."""

    torque_nm: np.ndarray
    diagnostics: dict[str, float | np.ndarray]


class CaiLaw:
    """The control law of :class:`Cai2014Controller`: one of the four cases for ``p`` driven axles
    (one law per train, as in the paper's single-coordinate model eq. 3), in plain arrays.

    ``sigma`` is the sign of eqs. 44–45 (+1: eq. 20's reading, −1: as printed). All three observers
    run in every case (their estimates are reported); only the case's own ones enter the control.
    """

    def __init__(self, case: int, *, mass_kg: float, n_axles: int, radius_m: float, inertia_kgm2: float,
                 gains: CaiGains = PAPER_GAINS, sigma: float = 1.0) -> None:
        if case not in CASES:
            raise ValueError(f"case must be one of {CASES}, got {case!r}")
        self.case, self.gains, self.sigma = case, gains, float(sigma)
        self.m, self.p, self.R, self.J = float(mass_kg), int(n_axles), float(radius_m), float(inertia_kgm2)
        self.obs_adhesion = AdhesionForceObserver(gains.g, self.J, self.R, self.p)
        self.obs_resistance = ResistanceObserver(gains.g, self.m, self.J, self.R)
        self.obs_lumped = LumpedDisturbanceObserver(gains.g, self.m, self.R)
        self._prev: tuple[float, np.ndarray, np.ndarray, float] | None = None  # v, ω, T, dt of last period

    def step(self, *, position_m: float, speed_mps: float, omega_radps: np.ndarray, ref_position_m: float,
             ref_speed_mps: float, ref_accel_mps2: float, resistance_n: float, dt_s: float) -> CaiOutput:
        """Advance the observers over the last period, then compute this period's torques.

        ``resistance_n`` is the true F_d(·) (only cases 1 and 2, the "ideal MBC", use it).
        ``dt_s`` is the length of the period that starts now.
        """
        gn = self.gains
        omega_radps = np.asarray(omega_radps, dtype=float)
        if self._prev is not None:
            v0, w0, t0, dt0 = self._prev
            self.obs_adhesion.update(t0, w0, omega_radps, dt0)
            self.obs_resistance.update(t0, v0, speed_mps, w0, omega_radps, dt0)
            self.obs_lumped.update(t0, v0, speed_mps, dt0)
        e = position_m - ref_position_m
        de = speed_mps - ref_speed_mps
        s = de + gn.beta * e
        fa_hat = self.obs_adhesion.estimate_n.copy()
        fd_hat = self.obs_resistance.estimate_n
        fdw_hat = self.obs_lumped.estimate_n
        f_comp = {1: resistance_n, 2: resistance_n, 3: fd_hat, 4: fdw_hat}[self.case]
        u = -gn.k0 * s + self.m * ref_accel_mps2 - gn.edot_gain * de + f_comp
        if self.case in (1, 4):
            torque = np.full(self.p, self.R / self.p * u)
            f_cmd = np.full(self.p, u / self.p)
        else:
            f_cmd = np.full(self.p, self.sigma * u / self.p)
            torque = gn.ka * (f_cmd - fa_hat) + fa_hat * self.R
        self._prev = (float(speed_mps), omega_radps.copy(), torque, float(dt_s))
        return CaiOutput(torque, {"s": s, "force_cmd_n": f_cmd, "adhesion_hat_n": fa_hat,
                                  "resistance_hat_n": fd_hat, "lumped_hat_n": fdw_hat})


# ------------------------------------------------------------------------------ engine controller
#: a positive real parameter (the controller's schema is its constructor's signature)
Positive = Annotated[float, Field(gt=0)]


@register("cai2014")
class Cai2014Controller(Controller):
    """Cai et al. 2014's traction ECU: the four control cases (eqs. 43–46) with their observers
    (eqs. 18, 22, 40), one ECU for the powered vehicle's ``axles`` driven axles.

    Reads ``ground_speed_mps`` (the train's speed over ground, a radar: the wheels slip, so their speed
    is not the train's), ``position_m`` and ``axle<j>_speed_radps`` (its vehicle's sensors) and the
    reference x*, v*, a*; commands ``axle<j>_torque_nm`` (N·m). Cases 1–2 (the "ideal MBC") use the
    resistance of its own model F_d(v) = c0 sgn v + c1 v + c2 v|v| at the measured speed; with the
    model equal to the plant (as in the paper) that is the true resistance.

    **One ECU per powered vehicle** (``share`` = w_i = p_i/p < 1): ECU i runs the same law on a model
    scaled by w_i — mass w_i m, resistance w_i F_d, k0 and the ė gain × w_i (ka, β, g unchanged) — over
    its own p_i axles, so u_i = w_i(−k0 s − k_ė ė) + w_i m ẍ* + F_i. Every ECU measures the same s and
    ė (one rigid body), and the observers are linear filters of their inputs with Σ_i m_i = m, so
    Σ_i u_i = u of the centralised law whenever Σ_i F_i = F: for F_d (cases 1, 2) by construction;
    for F̂_d and F̂_dw (cases 3, 4) because their inputs (1/R) Σ_own T − m_i v̇ (− (J/R) Σ_own ω̇) sum to
    the centralised inputs as long as the total torque does, which holds by induction from the first
    period. The torque per axle (R/p_i) u_i (cases 1, 4) and the force command σ u_i/p_i (case 2) then
    equal the centralised (R/p) u and σ u/p; in case 3 only their sum does (F̂_d,i follows the ECU's
    own axles). ``tests/test_cai2014.py`` checks this against the one-ECU law.
    """

    needs_ref_position = True
    broadcast_names: tuple[str, ...] = ()

    @validate_call
    def __init__(self, car_index: int, n_cars: int, mass_kg: float, dt_s: float, *,
                 case: Literal[1, 2, 3, 4],
                 axles: Annotated[int, Field(ge=1, le=16)],
                 train_mass_kg: Positive,
                 wheel_radius_m: Positive,
                 wheel_inertia_kgm2: Positive,
                 davis: tuple[float, float, float],
                 k0: Positive = PAPER_GAINS.k0,
                 ka: Positive = PAPER_GAINS.ka,
                 beta: Positive = PAPER_GAINS.beta,
                 g: Positive = PAPER_GAINS.g,
                 edot_gain: Annotated[float, Field(ge=0)] = PAPER_GAINS.edot_gain,
                 sigma: Literal[1, -1] = 1,
                 share: Annotated[float, Field(gt=0, le=1)] = 1.0) -> None:
        """``case`` 1–4; ``axles`` p driven axles it commands (axle1..axle<p>); the controller's model of
        the train: ``train_mass_kg`` (kg), ``wheel_radius_m`` (m), ``wheel_inertia_kgm2`` (kg·m²),
        ``davis`` (c0 N, c1 N·s/m, c2 N·s²/m²); gains ``k0`` (N·s/m), ``ka`` (m), ``beta`` (1/s), observer
        cut-off ``g`` (1/s), ``edot_gain`` (N·s/m), all defaulting to the paper's readings
        (:data:`PAPER_GAINS`); ``sigma`` the sign of eqs. 44–45 (+1 as eq. 20, −1 as printed); ``share``
        the fraction of the train's traction this ECU provides (see above)."""
        super().__init__(car_index, n_cars, mass_kg, dt_s)
        self.params = SimpleNamespace(case=case, axles=axles, train_mass_kg=train_mass_kg, wheel_radius_m=wheel_radius_m,
                                      wheel_inertia_kgm2=wheel_inertia_kgm2, davis=davis, k0=k0, ka=ka, beta=beta, g=g,
                                      edot_gain=edot_gain, sigma=sigma, share=share)
        p = axles
        self.sensor_names = ("ground_speed_mps", "position_m") + tuple(f"axle{j}_speed_radps" for j in range(1, p + 1))
        self.command_names = tuple(f"axle{j}_torque_nm" for j in range(1, p + 1))
        self.diagnostic_names = (("s_mps", "resistance_model_n", "resistance_hat_n", "lumped_hat_n")
                                 + tuple(f"axle{j}_force_cmd_n" for j in range(1, p + 1))
                                 + tuple(f"axle{j}_adhesion_hat_n" for j in range(1, p + 1)))
        self.reset()

    def reset(self) -> None:
        """Observers at zero, no previous period."""
        pr = self.params
        w = pr.share
        self.law = CaiLaw(pr.case, mass_kg=w * pr.train_mass_kg, n_axles=pr.axles, radius_m=pr.wheel_radius_m,
                          inertia_kgm2=pr.wheel_inertia_kgm2,
                          gains=CaiGains(k0=w * pr.k0, ka=pr.ka, beta=pr.beta, g=pr.g, edot_gain=w * pr.edot_gain),
                          sigma=float(pr.sigma))

    def model_resistance_n(self, v_mps: float) -> float:
        """F_d(v) of the controller's model (N), × ``share``."""
        a0, a1, a2 = self.params.davis
        sgn = float(np.sign(v_mps)) if abs(v_mps) > 1e-6 else 0.0
        return self.params.share * (sgn * a0 + a1 * v_mps + a2 * v_mps * abs(v_mps))

    def step(self, obs: Observation) -> ControlOutput:
        """Axle torques (N·m) for this period."""
        p = self.params.axles
        omega = np.array([obs.sensors[f"axle{j}_speed_radps"] for j in range(1, p + 1)], dtype=float)
        v = obs.sensors["ground_speed_mps"]
        fd = self.model_resistance_n(v)
        out = self.law.step(position_m=obs.sensors["position_m"], speed_mps=v, omega_radps=omega,
                            ref_position_m=obs.ref_position_m, ref_speed_mps=obs.ref_speed_mps,
                            ref_accel_mps2=-obs.ref_decel_mps2, resistance_n=fd, dt_s=self.dt_s)
        d = out.diagnostics
        diag = {"s_mps": float(d["s"]), "resistance_model_n": fd, "resistance_hat_n": float(d["resistance_hat_n"]),
                "lumped_hat_n": float(d["lumped_hat_n"])}
        for j in range(p):
            diag[f"axle{j + 1}_force_cmd_n"] = float(d["force_cmd_n"][j])
            diag[f"axle{j + 1}_adhesion_hat_n"] = float(d["adhesion_hat_n"][j])
        torque = out.torque_nm
        # brake_force_n: the equivalent force at the rail (N, + brakes), for the trace only
        return ControlOutput(brake_force_n=-float(np.sum(torque)) / self.params.wheel_radius_m, diagnostics=diag,
                             commands={f"axle{j + 1}_torque_nm": float(torque[j]) for j in range(p)})
