"""ECU functions of a car's brake control around its train controller: easing before standstill
and wheel-slide protection (WSP). No CAN here; SI throughout.

:class:`BrakeFunctions` wraps any :class:`~canbrake.control.base.Controller` (Chen's consensus
controller, a PI, ...). Each control period it runs the wrapped controller, then

* **easing** caps the brake demand at ``m · v / τ_e · (1 − τ_a / τ_e)``: with a brake of
  first-order lag τ_a, a demand of that size makes the applied deceleration follow ``v / τ_e`` (the
  lag's own deceleration rate is anticipated), so the deceleration fades continuously to zero as
  the car comes to rest and the jerk while it fades is at most ``a / τ_e`` (a the deceleration
  when the cap starts to bite, at v = a·τ_e). The cap never touches traction, and at standstill
  the full demand passes again (the holding brake; a brake at rest only holds, see
  :mod:`canbrake.physics.train`).
* **wheel-slide protection** reads the car's axle speeds ``axle<j>_speed_radps`` and its speed
  over ground (``speed_mps``, e.g. from a radar or a non-braked reference axle), computes each
  axle's slip λ = (ωR − v)/max(ωR, v, v_floor), and drives the car's dump valves with the command
  ``wsp_release`` (0 closed .. 1 vented): vent at once when any axle's |λ| exceeds
  ``slip_release``, hold while it is between the thresholds, close again at ``reapply_per_s`` once
  every axle is below ``slip_reapply``. The valve acts on the brake cylinders downstream of the
  brake control (:mod:`canbrake.physics.brakes`, the dump valve). Below ``min_speed`` WSP is off.

Simplifications (docs/braking-models.md): one valve per car (real WSP has one per bogie or axle);
the speed over ground is measured, not estimated from the axles; no wheel-deceleration criterion.
"""
from __future__ import annotations

from typing import Any

import numpy as np

from canbrake.control.base import ControlOutput, Controller, Observation


class BrakeFunctions(Controller):
    """``inner`` plus easing (``easing_tau_s`` τ_e, ``lag_s`` τ_a; None = off) and WSP (``wsp``: a
    :class:`canbrake.consist.brakes.WspConfig`-like object or None; ``axles``, ``wheel_radius_m``,
    ``v_floor_mps`` of the car's wheels)."""

    def __init__(self, inner: Controller, *, easing_tau_s: float | None = None, lag_s: float = 0.0,
                 wsp: Any = None, axles: int = 0, wheel_radius_m: float = 0.42, v_floor_mps: float = 0.1) -> None:
        super().__init__(inner.car_index, inner.n_cars, inner.mass_kg, inner.dt_s)
        self.inner = inner
        if easing_tau_s is not None and not easing_tau_s > lag_s:
            raise ValueError(f"brake.easing.time_constant_s ({easing_tau_s:g} s) must exceed the brake lag "
                             f"it anticipates ({lag_s:g} s)")
        self.easing_tau_s = easing_tau_s
        self.ease_gain = None if easing_tau_s is None else (1.0 - lag_s / easing_tau_s) / easing_tau_s
        self.wsp = wsp
        self.axles = int(axles) if wsp is not None else 0
        self.R = float(wheel_radius_m)
        self.v_floor = float(v_floor_mps)
        self.release = 0.0
        axle_sensors = tuple(f"axle{j}_speed_radps" for j in range(1, self.axles + 1))
        self.sensor_names = tuple(inner.sensor_names) + tuple(s for s in axle_sensors if s not in inner.sensor_names)
        self.command_names = tuple(inner.command_names) + (("wsp_release",) if wsp is not None else ())
        self.broadcast_names = tuple(inner.broadcast_names)
        self.needs_ref_position = inner.needs_ref_position
        extra = (("easing_cap_n",) if easing_tau_s is not None else ()) + (("wsp_slip",) if wsp is not None else ())
        self.diagnostic_names = tuple(inner.diagnostic_names) + extra

    def reset(self) -> None:
        self.inner.reset()
        self.release = 0.0

    def ease_cap_n(self, speed_mps: float) -> float:
        """Largest brake demand (N) the easing allows at ``speed_mps`` (inf when off or at rest)."""
        if self.ease_gain is None or speed_mps <= 1e-3:
            return float("inf")
        return self.mass_kg * self.ease_gain * abs(speed_mps)

    def wsp_step(self, speed_mps: float, axle_speeds_radps: list[float]) -> tuple[float, float]:
        """Advance the WSP state by one period; returns (valve command 0..1, worst |slip|)."""
        w = self.wsp
        v = abs(speed_mps)
        worst = 0.0
        for om in axle_speeds_radps:
            if om == om:  # not NaN
                wr = abs(om) * self.R
                worst = max(worst, (v - wr) / max(wr, v, self.v_floor))
        if v < w.min_speed_kmh / 3.6:
            self.release = max(0.0, self.release - w.reapply_per_s * self.dt_s)
        elif worst > w.slip_release:
            self.release = 1.0
        elif worst < w.slip_reapply:
            self.release = max(0.0, self.release - w.reapply_per_s * self.dt_s)
        return self.release, worst

    def step(self, obs: Observation) -> ControlOutput:
        out = self.inner.step(obs)
        diag = dict(out.diagnostics)
        if self.ease_gain is not None:
            cap = self.ease_cap_n(obs.speed_mps)
            if out.brake_force_n > cap:
                out.brake_force_n = cap
            diag["easing_cap_n"] = cap if cap != float("inf") else float("nan")
        if self.wsp is not None:
            axles = [float(obs.sensors.get(f"axle{j}_speed_radps", float("nan"))) for j in range(1, self.axles + 1)]
            r, worst = self.wsp_step(obs.speed_mps, axles)
            out.commands = dict(out.commands)
            out.commands["wsp_release"] = r
            diag["wsp_slip"] = worst
        out.diagnostics = diag
        return out

    # ------------------------------------------------------------------ batch form
    def batchable(self) -> bool:
        """:meth:`step_batch` covers easing around a controller that has a batch form (not WSP)."""
        inner_ok = getattr(self.inner, "batchable", None)
        return (self.wsp is None and type(self).step is BrakeFunctions.step and callable(inner_ok)
                and bool(inner_ok()))

    def step_batch(self, obs: Observation) -> ControlOutput:
        """:meth:`step` for P sweep points at once (:mod:`canbrake.batch`; arrays of shape (P,)):
        the inner controller's batch form, then the easing cap, the same operations as :meth:`step`."""
        out = self.inner.step_batch(obs)
        diag = dict(out.diagnostics)
        if self.ease_gain is not None:
            v = obs.speed_mps
            cap = np.where(v <= 1e-3, np.inf, self.mass_kg * self.ease_gain * np.abs(v))
            out.brake_force_n = np.where(out.brake_force_n > cap, cap, out.brake_force_n)
            diag["easing_cap_n"] = np.where(cap != np.inf, cap, np.nan)
        out.diagnostics = diag
        return out


def brake_functions_of(ctrl: Controller, brakes: Any, actuator: Any, car: int = 0) -> BrakeFunctions:
    """Wrap ``ctrl`` with the ECU functions configured in the brake component (a
    :class:`canbrake.consist.brakes.BrakeSystemConfig`) for vehicle ``car`` (0-based: its own
    easing and wsp where the vehicle types differ); ``actuator`` is the scenario's actuator
    section (its lag is what easing anticipates unless ``easing.lag_s`` is given)."""
    from canbrake.consist.brakes import car_easing_lag_s

    own = brakes.car(car)
    tau = lag = None
    if own.easing is not None:
        tau = own.easing.time_constant_s
        lag = car_easing_lag_s(brakes, actuator, car)
    wsp = own.wsp if own.wsp is not None and own.wsp.enabled else None
    w = brakes.car_wheels(car)
    return BrakeFunctions(ctrl, easing_tau_s=tau, lag_s=lag or 0.0, wsp=wsp,
                          axles=w.axles if w is not None else 0, wheel_radius_m=w.radius_m if w is not None else 0.42,
                          v_floor_mps=w.v_floor_mps if w is not None else 0.1)
