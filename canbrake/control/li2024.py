"""Locomotive speed/position tracking controllers of Li, Zeng & Yu 2024 (section 2).

Pure controllers, no I/O, SI units (m, m/s, m/s², N, kg). Each has explicit state and
``step(obs) -> (u_n, diagnostics)``; the command is saturated by the HXD1 envelope
(:func:`saturate_control_n`, HXD1's eqs. 1-2).

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
from typing import Any

import numpy as np

from canbrake.control.base import ControlOutput, Controller, Observation, register
from canbrake.physics.heavy_haul import KMH, TractionEnvelope

#: HXD1's envelopes, eqs. (1)-(2) (kN, km/h): the controllers' knowledge of their locomotive (they
#: saturate their command with it). The plant takes its own envelope from the scenario's vehicle type.
HXD1_ENVELOPE = TractionEnvelope(760.0, 5.0, 779.0, 3.8, 65.0, 92.2, 5.0, 461.0, 75.0, 34560.0)


def traction_envelope_kn(v_kmh):
    """Eq. (1): HXD1 maximum traction force in kN at speed ``v_kmh`` (km/h), array or scalar."""
    return HXD1_ENVELOPE.traction_kn(v_kmh)


def electric_brake_envelope_kn(v_kmh):
    """Eq. (2): HXD1 maximum electric brake force in kN at speed ``v_kmh`` (km/h)."""
    return HXD1_ENVELOPE.electric_brake_kn(v_kmh)


def traction_envelope_n(v_mps):
    """Maximum traction force (N) at speed ``v_mps`` (m/s)."""
    return 1000.0 * traction_envelope_kn(np.asarray(v_mps, dtype=float) / KMH)


def electric_brake_envelope_n(v_mps):
    """Maximum electric brake force (N, positive) at speed ``v_mps`` (m/s)."""
    return 1000.0 * electric_brake_envelope_kn(np.asarray(v_mps, dtype=float) / KMH)


def saturate_control_n(u_n: float, v_mps: float) -> float:
    """Clip a locomotive force command (N, > 0 traction) into HXD1's [−F_B(v), F_T(v)]."""
    return HXD1_ENVELOPE.saturate_n(u_n, v_mps)

READINGS = ("listed", "adaptive-power")
#: NDO discretisation: "exact" (error dynamics integrated exactly over a step, zero-order hold) or
#: "euler" (explicit Euler of eq. 30 as printed; unstable when ω·dt > 2)
OBSERVER_READINGS = ("exact", "euler")
#: what the NDO's model F(x) contains: "nominal" (f(x) only, so d̂ absorbs the model error Δf as well as
#: d) or "printed" (eq. 17/30 as printed: F(x) = [v, f(x) + Δf], so d̂ estimates d only and Δf is left
#: to the RBF network; Δf = ``model_uncertainty``·f(x), the plant's δ, known to this reading's observer)
NDO_MODELS = ("nominal", "printed")


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
                 centers=(-1.0, -0.5, 0.0, 0.5, 1.0), center_scale: float = 0.01, omega: float = 1000.0,
                 observer: str = "exact", ndo_model: str = "nominal", model_uncertainty: float = 0.01):
        if ndo_model not in NDO_MODELS:
            raise ValueError(f"ndo_model: unknown NDO model {ndo_model!r}; use one of {NDO_MODELS}")
        self.ndo_model, self.model_uncertainty = ndo_model, float(model_uncertainty)
        if reading not in READINGS:
            raise ValueError(f"reading: unknown reading {reading!r}; use one of {READINGS}")
        if observer not in OBSERVER_READINGS:
            raise ValueError(f"observer: unknown observer reading {observer!r}; use one of {OBSERVER_READINGS}")
        self.observer = observer
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
                if self.ndo_model == "printed":  # F(x) includes Δf: the residual is d alone
                    d_meas -= self.model_uncertainty * f0
                gain = (1.0 - math.exp(-self.omega * self.dt)) if self.observer == "exact" else self.omega * self.dt
                self.d_hat += (d_meas - self.d_hat) * gain
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


# ------------------------------------------------------------------------------------ engine controllers
# The same laws as engine controllers (canbrake.control.base.Controller), for the locomotive ECU.
# Sign convention of the engine: brake_force_n > 0 brakes, so brake_force_n = −u.


def _schedule(airbrake_schedule: Any) -> list[tuple[float, float]]:
    """Validate ``airbrake_schedule``: a list of [time_s, apply] (apply 1 or 0), times ascending."""
    out: list[tuple[float, float]] = []
    for i, ev in enumerate(airbrake_schedule or ()):
        try:
            t, a = float(ev[0]), float(ev[1])
            if len(ev) != 2:
                raise ValueError
        except (TypeError, ValueError, IndexError):
            raise ValueError(f"airbrake_schedule.{i}: expected [time_s, apply], got {ev!r}") from None
        if a not in (0.0, 1.0) or not math.isfinite(t):
            raise ValueError(f"airbrake_schedule.{i}: apply must be 1 or 0 and time finite, got {ev!r}")
        if out and t < out[-1][0]:
            raise ValueError(f"airbrake_schedule.{i}: times must ascend ({t} after {out[-1][0]})")
        out.append((t, a))
    return out


class _AirBrakeReplay:
    """The driver's-valve state at time t of a recorded (time_s, apply) list; released before the first."""

    def __init__(self, events: list[tuple[float, float]]):
        self.events, self.i, self.state = events, 0, 0.0

    def at(self, t_s: float) -> float:
        while self.i < len(self.events) and self.events[self.i][0] <= t_s + 1e-9:
            self.state = self.events[self.i][1]
            self.i += 1
        return self.state


class _LiLocomotive(Controller):
    """Base of Li's locomotive controllers: senses speed, position and the passive force, commands the
    locomotive force and the driver's valve (replayed from ``airbrake_schedule``)."""

    sensor_names = ("speed_mps", "position_m", "passive_force_n")
    command_names = ("brake_force_n", "airbrake_apply")
    broadcast_names = ()

    def __init__(self, car_index: int, n_cars: int, mass_kg: float, dt_s: float,
                 airbrake_schedule: Any = ()) -> None:
        super().__init__(car_index, n_cars, mass_kg, dt_s)
        self._events = _schedule(airbrake_schedule)
        self.replay = _AirBrakeReplay(self._events)

    def _law_obs(self, obs: Observation) -> Obs:
        f = obs.sensors.get("passive_force_n", float("nan"))
        return Obs(obs.time_s, obs.position_m, obs.speed_mps, obs.ref_position_m, obs.ref_speed_mps,
                   -obs.ref_decel_mps2, float(f) / self.mass_kg)

    def step(self, obs: Observation) -> ControlOutput:
        u, diag = self.law.step(self._law_obs(obs))  # type: ignore[attr-defined]
        diag = {**diag, "u_n": u, "speed_error_mps": obs.speed_mps - obs.ref_speed_mps}
        return ControlOutput(-u, {k: float(diag.get(k, float("nan"))) for k in self.diagnostic_names},
                             commands={"airbrake_apply": self.replay.at(obs.time_s)})

    def reset(self) -> None:
        self.__init__(self.car_index, self.n_cars, self.mass_kg, self.dt_s, **self._params)  # type: ignore[misc]


@register("li2024_pid")
class LiPIDController(_LiLocomotive):
    """Li 2024's PID on the speed error (gains N per m/s, N per m, N per m/s²)."""

    #: u_raw_n / u_n: locomotive force before / after the envelope (N, + traction); speed_error_mps:
    #: v − v* as the ECU sees it
    diagnostic_names = ("u_raw_n", "u_n", "speed_error_mps")
    sensor_names = ("speed_mps", "position_m")

    def __init__(self, car_index: int, n_cars: int, mass_kg: float, dt_s: float, *, kp: float = 1e7,
                 ki: float = 1.0, kd: float = 1.0, airbrake_schedule: Any = ()) -> None:
        super().__init__(car_index, n_cars, mass_kg, dt_s, airbrake_schedule)
        self._params = dict(kp=kp, ki=ki, kd=kd, airbrake_schedule=self._events)
        self.law = LiPID(dt_s, kp=float(kp), ki=float(ki), kd=float(kd))


class _LiSMCBase(_LiLocomotive):
    diagnostic_names = ("s", "delta_hat", "d_hat", "u_raw_n", "u_n", "speed_error_mps")
    needs_ref_position = True
    _rbf = False
    _ndo = False

    def __init__(self, car_index: int, n_cars: int, mass_kg: float, dt_s: float, *, reading: str = "listed",
                 observer: str = "exact", lam1: float = 1.0, lam2: float = 0.1, zeta0: float = 0.005,
                 kappa: float = 0.05, alpha: float = 5.0, gamma: float = 0.01, b: float = 0.005,
                 centers: Any = (-1.0, -0.5, 0.0, 0.5, 1.0), center_scale: float = 0.01, omega: float = 1000.0,
                 ndo_model: str = "nominal", model_uncertainty: float = 0.01, airbrake_schedule: Any = ()) -> None:
        super().__init__(car_index, n_cars, mass_kg, dt_s, airbrake_schedule)
        self._params = dict(reading=reading, observer=observer, lam1=lam1, lam2=lam2, zeta0=zeta0, kappa=kappa,
                            alpha=alpha, gamma=gamma, b=b, centers=tuple(centers), center_scale=center_scale,
                            omega=omega, ndo_model=ndo_model, model_uncertainty=model_uncertainty,
                            airbrake_schedule=self._events)
        if len(self._params["centers"]) < 1:
            raise ValueError("centers: at least one RBF centre")
        for name in ("b", "omega"):
            if not float(self._params[name]) > 0:
                raise ValueError(f"{name}: must be > 0, got {self._params[name]!r}")
        self.law = LiSlidingMode(dt_s, self.mass_kg, rbf=self._rbf, ndo=self._ndo, reading=reading,
                                 observer=observer, lam1=float(lam1), lam2=float(lam2), zeta0=float(zeta0),
                                 kappa=float(kappa), alpha=float(alpha), gamma=float(gamma), b=float(b),
                                 centers=tuple(float(c) for c in centers), center_scale=float(center_scale),
                                 omega=float(omega), ndo_model=ndo_model,
                                 model_uncertainty=float(model_uncertainty))


@register("li2024_smc")
class LiSMCController(_LiSMCBase):
    """Li 2024's sliding-mode control (eq. 22) on the locomotive."""


@register("li2024_rbfnn_smc")
class LiRBFNNSMCController(_LiSMCBase):
    """SMC with the RBF network estimate of the model uncertainty (eqs. 23-29)."""

    _rbf = True


@register("li2024_rbfnn_smc_ndo")
class LiRBFNNSMCNDOController(_LiSMCBase):
    """RBFNN-SMC with the nonlinear disturbance observer (eqs. 30-35)."""

    _rbf = True
    _ndo = True


@register("li2024_driver")
class LiDriver(Controller):
    """The synthetic driver that makes Li 2024's reference (the paper's recorded driver is unpublished).

    P speed control towards ``cruise_kmh`` with at most ``envelope_share`` of HXD1's envelope and the
    force rate-limited to ``rate_n_per_s``; cyclic air braking by the rules of section 1.2: apply
    above ``apply_min_kmh`` when the line data shows a long downgrade (sensor ``downgrade_ahead``) and
    at least ``min_interval_s`` after the previous application; release ``release_drop_kmh`` below the
    applying speed but never below ``release_floor_kmh``. While the air brake is on it aims
    ``brake_target_drop_kmh`` below the applying speed. Diagnostic ``airbrake_apply`` is the valve state.
    """

    sensor_names = ("speed_mps", "position_m", "downgrade_ahead")
    command_names = ("brake_force_n", "airbrake_apply")
    broadcast_names = ()
    #: recorded_speed_mps: the locomotive speed as the ECU measured it (the recorder's curve that
    #: becomes the tracking reference)
    diagnostic_names = ("airbrake_apply", "traction_n", "recorded_speed_mps")

    def __init__(self, car_index: int, n_cars: int, mass_kg: float, dt_s: float, *, cruise_kmh: float = 70.0,
                 kp_n_per_mps: float = 3e6, envelope_share: float = 0.7, rate_n_per_s: float = 1e5,
                 brake_target_drop_kmh: float = 12.0, apply_min_kmh: float = 60.0, release_drop_kmh: float = 10.0,
                 release_floor_kmh: float = 35.0, min_interval_s: float = 160.0) -> None:
        super().__init__(car_index, n_cars, mass_kg, dt_s)
        if not 0.0 < float(envelope_share) <= 1.0:
            raise ValueError(f"envelope_share: must be in (0, 1], got {envelope_share!r}")
        if not float(rate_n_per_s) > 0:
            raise ValueError(f"rate_n_per_s: must be > 0, got {rate_n_per_s!r}")
        self.cruise, self.kp, self.share, self.rate = float(cruise_kmh), float(kp_n_per_mps), float(envelope_share), float(rate_n_per_s)
        self.drop_target = float(brake_target_drop_kmh)
        self.apply_min, self.release_drop = float(apply_min_kmh), float(release_drop_kmh)
        self.release_floor, self.min_interval = float(release_floor_kmh), float(min_interval_s)
        self._params = dict(cruise_kmh=cruise_kmh, kp_n_per_mps=kp_n_per_mps, envelope_share=envelope_share,
                            rate_n_per_s=rate_n_per_s, brake_target_drop_kmh=brake_target_drop_kmh,
                            apply_min_kmh=apply_min_kmh, release_drop_kmh=release_drop_kmh,
                            release_floor_kmh=release_floor_kmh, min_interval_s=min_interval_s)
        self.applied = False
        self.t_apply = -math.inf
        self.v_apply_kmh = 0.0
        self.u = 0.0

    def rules(self, t_s: float, v_mps: float, downgrade_ahead: bool) -> None:
        """Section 1.2's application and release rules on the locomotive's speed."""
        v = v_mps / KMH
        if not self.applied:
            if v > self.apply_min and t_s - self.t_apply >= self.min_interval and downgrade_ahead:
                self.applied, self.t_apply, self.v_apply_kmh = True, t_s, v
        elif v <= self.v_apply_kmh - self.release_drop and v >= self.release_floor:
            self.applied = False

    def step(self, obs: Observation) -> ControlOutput:
        v0 = obs.speed_mps
        self.rules(obs.time_s, v0, bool(obs.sensors.get("downgrade_ahead", 0.0) >= 0.5))
        tgt = (self.v_apply_kmh - self.drop_target) * KMH if self.applied else self.cruise * KMH
        want = min(max(self.kp * (tgt - v0), -self.share * float(electric_brake_envelope_n(v0))),
                   self.share * float(traction_envelope_n(v0)))
        self.u += min(max(want - self.u, -self.rate * self.dt_s), self.rate * self.dt_s)
        ab = 1.0 if self.applied else 0.0
        return ControlOutput(-self.u, {"airbrake_apply": ab, "traction_n": self.u, "recorded_speed_mps": v0},
                             commands={"airbrake_apply": ab})

    def reset(self) -> None:
        self.__init__(self.car_index, self.n_cars, self.mass_kg, self.dt_s, **self._params)  # type: ignore[misc]
