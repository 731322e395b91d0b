"""Electronically controlled pneumatic (ECP) braking over CAN on a heavy-haul train.

* :class:`EcpWagon` (``ecp_wagon``) — a wagon's brake ECU: applies the brake demand the locomotive
  ECU broadcasts (``ecp_demand`` in its STATE frame) to its own cylinder (command ``ecp_demand``).
  Before any demand has arrived it keeps the brake released.
* :class:`BrakeTest` (``heavy_haul_brake_test``) — the locomotive ECU of a stop test: from
  ``brake_at_s`` on it demands a brake application of ``demand`` (fraction of full service) — over
  CAN to the wagons (broadcast ``ecp_demand``), through the brake pipe (``airbrake_apply``, for a
  pneumatic train) and on its own cylinder (``ecp_demand``) — and holds the electric brake at
  ``electric_brake_n`` (0: air brake only).

Pure controllers (no I/O), SI units.
"""
from __future__ import annotations

import math

import numpy as np

from canbrake.control.base import ControlOutput, Controller, Observation, register


@register("ecp_wagon")
class EcpWagon(Controller):
    """Applies the broadcast ECP demand of ECU ``source_ecu`` (1-based index in the placement)."""

    sensor_names = ("speed_mps",)
    command_names = ("ecp_demand",)
    broadcast_names = ()
    diagnostic_names = ("ecp_demand",)

    def __init__(self, car_index: int, n_cars: int, mass_kg: float, dt_s: float, *, source_ecu: int = 1) -> None:
        super().__init__(car_index, n_cars, mass_kg, dt_s)
        if not 1 <= int(source_ecu) <= n_cars:
            raise ValueError(f"source_ecu: must be an ECU index 1..{n_cars}, got {source_ecu!r}")
        self.source = int(source_ecu) - 1
        self.demand = 0.0

    def step(self, obs: Observation) -> ControlOutput:
        got = obs.peer_signals.get("ecp_demand")
        if got is not None and self.source < len(got):
            d = float(got[self.source])
            if math.isfinite(d):
                self.demand = 0.0 if d < 0.0 else (1.0 if d > 1.0 else d)  # np.clip to [0, 1], without its call cost
        return ControlOutput(0.0, {"ecp_demand": self.demand}, commands={"ecp_demand": self.demand})

    def reset(self) -> None:
        self.demand = 0.0


@register("heavy_haul_brake_test")
class BrakeTest(Controller):
    """Stop test on the locomotive: a brake application of ``demand`` from ``brake_at_s`` on."""

    sensor_names = ("speed_mps",)
    command_names = ("brake_force_n", "airbrake_apply", "ecp_demand")
    broadcast_names = ("ecp_demand",)
    diagnostic_names = ("ecp_demand",)

    def __init__(self, car_index: int, n_cars: int, mass_kg: float, dt_s: float, *, brake_at_s: float = 5.0,
                 demand: float = 1.0, electric_brake_n: float = 0.0) -> None:
        super().__init__(car_index, n_cars, mass_kg, dt_s)
        if not 0.0 <= float(demand) <= 1.0:
            raise ValueError(f"demand: a fraction of full service 0..1, got {demand!r}")
        if float(electric_brake_n) < 0:
            raise ValueError(f"electric_brake_n: must be >= 0, got {electric_brake_n!r}")
        self.brake_at, self.full, self.eb = float(brake_at_s), float(demand), float(electric_brake_n)

    def step(self, obs: Observation) -> ControlOutput:
        on = obs.time_s >= self.brake_at - 1e-9
        d = self.full if on else 0.0
        moving = obs.speed_mps > 0.05
        return ControlOutput(self.eb if (on and moving) else 0.0, {"ecp_demand": d},
                             commands={"airbrake_apply": 1.0 if on else 0.0, "ecp_demand": d},
                             broadcast={"ecp_demand": d})


class EcpUnit(Controller):
    """A wagon's ECP brake unit driven by a force-commanding controller (``inner``, e.g. Chen's
    consensus controller): each period it converts the inner controller's brake force (N) into the
    unit's cylinder demand ``ecp_demand`` (fraction of full service) by inverting the wagon's air
    brake force law at the measured speed (:func:`canbrake.physics.heavy_haul.ecp_fill_for_force`,
    the wagon's block force, blocks, friction coefficient and β_c). A wagon has no traction, so a
    negative (traction) demand releases the brake; demands beyond full service are capped at it.
    The cylinder's own lag (``train.air_brake.cylinder_tau_s``) is the plant's, not modelled here.

    Wrapped around a wagon ECU's controller by :func:`canbrake.build.build_controller` when the train
    brakes by ECP and the controller commands ``brake_force_n`` (which a wagon cannot take)."""

    def __init__(self, inner: Controller, *, k_full_kn: float, n_blocks: float, friction_coef: float,
                 beta_c: float) -> None:
        super().__init__(inner.car_index, inner.n_cars, inner.mass_kg, inner.dt_s)
        if not (k_full_kn > 0 and n_blocks > 0 and friction_coef > 0 and beta_c > 0):
            raise ValueError("an ECP unit needs a positive block force, block count, friction coefficient and beta_c")
        self.inner = inner
        self.brake = (float(k_full_kn), float(n_blocks), float(friction_coef), float(beta_c))
        self.sensor_names = tuple(inner.sensor_names) + (() if "speed_mps" in inner.sensor_names else ("speed_mps",))
        self.command_names = tuple(c for c in inner.command_names if c != "brake_force_n") + ("ecp_demand",)
        self.broadcast_names = tuple(inner.broadcast_names)
        self.needs_ref_position = inner.needs_ref_position
        self.diagnostic_names = tuple(inner.diagnostic_names) + ("force_demand_n", "ecp_demand")

    def reset(self) -> None:
        self.inner.reset()

    def step(self, obs: Observation) -> ControlOutput:
        from canbrake.physics.heavy_haul import ecp_fill_for_force

        out = self.inner.step(obs)
        f = float(out.brake_force_n)
        d = ecp_fill_for_force(f, float(obs.speed_mps), *self.brake) if math.isfinite(f) else math.nan
        diag = dict(out.diagnostics)
        diag["force_demand_n"] = f
        diag["ecp_demand"] = d
        cmds = {k: v for k, v in out.commands.items() if k != "brake_force_n"}
        cmds["ecp_demand"] = d
        return ControlOutput(0.0, diag, commands=cmds, broadcast=out.broadcast)
