"""The adhesion kernel's configuration: Cai et al. 2014's rigidly coupled train with driven axles and
wheel–rail adhesion (:class:`canbrake.physics.wheel_adhesion.AdhesionTrain`). Internal: the user
writes ``train:`` as components (:mod:`canbrake.consist.components`: ``coupler: {model: rigid}``,
``wheels: {model: driven_axles, wheel, axles}``, ``train.wheel_rail``), assembled into an
:class:`AdhesionTrainConfig`; the wheel, axle and rail-condition schemas below serve both.
"""
from __future__ import annotations

from pathlib import Path
from typing import Any, Literal

import numpy as np
from pydantic import Field, model_validator

from canbrake.consist.base import StrictModel, VehicleEntry, expand_vehicles


class AdhesionDavis(StrictModel):
    """Running resistance of one vehicle: c0 sgn(v) + c1 v + c2 v|v| (N, v in m/s)."""

    c0_n: float = Field(0.0, ge=0)
    c1_n_s_per_m: float = Field(0.0, ge=0)
    c2_n_s2_per_m2: float = Field(0.0, ge=0)


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


class AdhesionVehicleType(StrictModel):
    """A vehicle: mass (kg), resistance, driven axles (none for a trailer) and their default wheel.
    Every axle has a wheel (its own or ``wheel``): checked where the user writes them, the
    ``driven_axles`` wheels component (:class:`canbrake.consist.components.DrivenAxles`)."""

    mass_kg: float = Field(gt=0)
    davis: AdhesionDavis = AdhesionDavis()
    resistance_table: list[list[float]] | None = Field(None, description="[speeds m/s, forces N] (components' "
                                                       "resistance table, validated there), added to davis")
    wheel: Wheel | None = None
    axles: list[Axle] = []


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


class AdhesionTrainConfig(StrictModel):
    """A train of rigidly coupled vehicles (Cai 2014, eq. 3) with driven axles and wheel–rail adhesion."""

    model: Literal["adhesion"] = "adhesion"
    vehicle_types: dict[str, AdhesionVehicleType]
    vehicles: list[VehicleEntry] = Field(min_length=1)
    wheel_rail: AdhesionSpec

    @model_validator(mode="after")
    def _types_known(self) -> "AdhesionTrainConfig":
        expand_vehicles(self.vehicle_types, self.vehicles)
        return self

    def expanded(self) -> list[AdhesionVehicleType]:
        """One vehicle type per vehicle, front first."""
        return [t for _, t in expand_vehicles(self.vehicle_types, self.vehicles)]

    def vehicle_count(self) -> int:
        return sum(v.count for v in self.vehicles)

    def vehicle_masses_kg(self) -> np.ndarray:
        return np.array([t.mass_kg for t in self.expanded()], dtype=float)

    def axle_counts(self) -> list[int]:
        """Driven axles per vehicle, front first."""
        return [len(t.axles) for t in self.expanded()]

    def check_ecus(self, placed: list[Any], dt_s: float = 1e-3) -> None:
        """ValueError (one line) for an ECU whose controller drives or reads more axles than its
        vehicle has (``axle<j>_torque_nm`` / ``axle<j>_speed_radps`` beyond the vehicle's driven
        axles, e.g. a traction controller on a trailer): the plant would ignore its torques."""
        import re

        from canbrake.control.base import make_controller

        counts, names = self.axle_counts(), [name for name, _ in expand_vehicles(self.vehicle_types, self.vehicles)]
        masses = self.vehicle_masses_kg()
        for i, p in enumerate(placed):
            if not 1 <= p.vehicle <= len(counts):
                continue  # reported by the placement check
            try:  # its signal names may depend on its parameters (cai2014's axles)
                ctrl = make_controller(p.controller.name, p.controller.params, car_index=i, n_cars=len(placed),
                                       mass_kg=float(masses[p.vehicle - 1]), dt_s=dt_s)
            except Exception:  # noqa: BLE001 - an unknown or mis-parameterised controller is reported on its own
                continue
            sigs = tuple(getattr(ctrl, "command_names", ())) + tuple(getattr(ctrl, "sensor_names", ()))
            need = max((int(m.group(1)) for s in sigs if (m := re.fullmatch(r"axle(\d+)_\w+", s))), default=0)
            have = counts[p.vehicle - 1]
            if need > have:
                what = "no driven axles" if have == 0 else f"{have} driven axle{'s' * (have > 1)}"
                raise ValueError(f"ecus: ECU {p.name} on vehicle {p.vehicle} ({names[p.vehicle - 1]}) runs "
                                 f"{p.controller.name} for {need} driven axle{'s' * (need > 1)}, but vehicle "
                                 f"{p.vehicle} has {what} (train.vehicle_types.{names[p.vehicle - 1]}.wheels): "
                                 f"place it on a vehicle with axles or give that vehicle type its axles")

    def make_plant(self, *, speed_mps: float = 0.0, position_m: float = 0.0, substeps: int = 1) -> Any:
        """The :class:`~canbrake.physics.wheel_adhesion.AdhesionTrain` of this consist (SI)."""
        from canbrake.physics.wheel_adhesion import AdhesionTrain, DrivenAxles

        vts = self.expanded()
        axles = []
        for t in vts:
            wheels = [a.wheel or t.wheel for a in t.axles]
            axles.append(DrivenAxles(
                normal_load_n=np.array([a.load_n * (1.0 + a.imbalance) for a in t.axles], dtype=float),
                inertia_kgm2=np.array([w.inertia_kgm2 for w in wheels], dtype=float),  # type: ignore[union-attr]
                radius_m=np.array([w.radius_m for w in wheels], dtype=float)))  # type: ignore[union-attr]
        davis = np.array([[t.davis.c0_n, t.davis.c1_n_s_per_m, t.davis.c2_n_s2_per_m2] for t in vts], dtype=float)
        tables = [None if t.resistance_table is None else (t.resistance_table[0], t.resistance_table[1]) for t in vts]
        return AdhesionTrain(self.vehicle_masses_kg(), axles, davis, self.wheel_rail.schedule(),
                             variant=self.wheel_rail.curve, v_floor_mps=self.wheel_rail.v_floor_mps,
                             speed_mps=speed_mps, position_m=position_m, substeps=substeps,
                             resistance_table=None if all(t is None for t in tables) else tables)

    def build_plant(self, scn: Any, base_dir: Path | None = None) -> Any:
        """The plant of scenario ``scn``: the train starts at the front vehicle's initial speed and
        position (one coordinate for the rigid train)."""
        v0 = float(np.asarray(scn.initial_speed_mps(), dtype=float).reshape(-1)[0])
        x = scn.initial.position_m
        x0 = 0.0 if x is None else float(np.asarray(x, dtype=float).reshape(-1)[0])
        return self.make_plant(speed_mps=v0, position_m=x0, substeps=scn.plant.substeps)
