"""Schemas of Cai et al. 2014's driven axles and wheel–rail adhesion: wheels, axles, a vehicle's
driven axles and the rail conditions of the slip curve over time. The user writes them as
components (:mod:`canbrake.consist.components`: ``wheels: {model: driven_axles, wheel, axles}``,
``train.wheel_rail``); a rigidly coupled train (``coupler: {model: rigid}``) runs on the coupled
plant (:class:`canbrake.physics.train.TrainPlant`, its rigid coupling with driven axles).
"""
from __future__ import annotations

from typing import Any, Literal

import numpy as np
from pydantic import Field, model_validator

from canbrake.consist.base import StrictModel


class Wheel(StrictModel):
    """A driven wheelset: rolling radius (m) and moment of inertia of the drive (wheels, gear, motor; kg·m²)."""

    radius_m: float = Field(gt=0)
    inertia_kgm2: float = Field(gt=0)


class Axle(StrictModel):
    """One driven axle: nominal axle load N_0 (N), imbalance ΔN/N_0 (load N = N_0 (1 + imbalance)); the
    wheel, when given, overrides the vehicle type's."""

    load_n: float = Field(gt=0)
    imbalance: float = Field(0.0, gt=-1, lt=1)
    wheel: Wheel | None = None


class VehicleAxles(StrictModel):
    """A vehicle's driven axles (Cai 2014): their loads, imbalances and wheels (``wheel`` the default
    of those without their own)."""

    wheel: Wheel | None = None
    axles: list[Axle] = Field(min_length=1)

    @model_validator(mode="after")
    def _wheels_known(self) -> "VehicleAxles":
        for k, a in enumerate(self.axles):
            if a.wheel is None and self.wheel is None:
                raise ValueError(f"@axles.{k}: no wheel (give the axle's or the component's `wheel`)")
        return self

    def physics(self) -> Any:
        """The :class:`~canbrake.physics.wheel_adhesion.DrivenAxles` of these axles (SI): load N_0 (1 + imbalance)."""
        from canbrake.physics.wheel_adhesion import DrivenAxles

        wheels = [a.wheel or self.wheel for a in self.axles]
        return DrivenAxles(normal_load_n=np.array([a.load_n * (1.0 + a.imbalance) for a in self.axles], dtype=float),
                           inertia_kgm2=np.array([w.inertia_kgm2 for w in wheels], dtype=float),  # type: ignore[union-attr]
                           radius_m=np.array([w.radius_m for w in wheels], dtype=float))  # type: ignore[union-attr]


class RailConditionSpec(StrictModel):
    """Coefficients of the slip curve (eq. 13: b1, b2, b3) and its speed scaling (eq. 15: c1, c2 in
    m/s, c3 in m/s), and the standstill peak μ used by the ``physical`` curve variant."""

    b1: float = Field(gt=0)
    b2: float = Field(gt=0)
    b3: float = Field(gt=0)
    c1: float = Field(ge=0)
    c2: float = Field(ge=0)
    c3: float = Field(gt=0)
    peak_mu0: float = Field(0.3, gt=0, le=1)


class RailWindowSpec(StrictModel):
    """Rail condition ``condition`` for start_s ≤ t ≤ stop_s (s, inclusive)."""

    condition: str
    start_s: float = Field(ge=0)
    stop_s: float

    @model_validator(mode="after")
    def _order(self) -> "RailWindowSpec":
        if self.stop_s < self.start_s:
            raise ValueError(f"stop_s ({self.stop_s}) is before start_s ({self.start_s})")
        return self


class AdhesionSpec(StrictModel):
    """Wheel–rail adhesion: the curve (``paper``: eqs. 13–15 as printed; ``physical``: the same
    shapes scaled to ``peak_mu0``), the slip denominator's floor (m/s), the rail conditions by name,
    the one in force by default and the time windows of the others."""

    curve: Literal["paper", "physical"] = "paper"
    v_floor_mps: float = Field(0.1, gt=0)
    conditions: dict[str, RailConditionSpec]
    base: str
    windows: list[RailWindowSpec] = []

    @model_validator(mode="after")
    def _names(self) -> "AdhesionSpec":
        known = ", ".join(sorted(self.conditions)) or "none"
        if self.base not in self.conditions:
            raise ValueError(f"base: unknown rail condition {self.base!r} (conditions: {known})")
        for k, w in enumerate(self.windows):
            if w.condition not in self.conditions:
                raise ValueError(f"windows.{k}.condition: unknown rail condition {w.condition!r} (conditions: {known})")
        return self

    def schedule(self) -> Any:
        """The :class:`~canbrake.physics.wheel_adhesion.RailSchedule` of this spec."""
        from canbrake.physics.wheel_adhesion import RailCondition, RailSchedule, RailWindow

        conds = {k: RailCondition(**c.model_dump()) for k, c in self.conditions.items()}
        return RailSchedule(conds[self.base], tuple(RailWindow(conds[w.condition], w.start_s, w.stop_s)
                                                    for w in self.windows))
