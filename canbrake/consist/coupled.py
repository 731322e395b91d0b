"""The coupled (Chen) kernel's configuration: what :func:`canbrake.build.build_coupled_plant` needs.

Internal: the user writes ``train:`` as components (:mod:`canbrake.consist.components`); the
assembler lowers a train whose couplers are Chen's and whose brakes are ideal or
electro-pneumatic, or that mixes them with Li's draft gears, air brakes and per-weight resistance,
into a :class:`TrainConfig` (per-car lists, SI) and an :class:`ActuatorConfig`.
Also home of the strict base model every scenario section derives from (``_Model``).
"""
from __future__ import annotations

import math
from pathlib import Path
from typing import Any, Literal, Union

import numpy as np
from pydantic import BaseModel, ConfigDict, Field, field_validator, model_validator

from canbrake.consist.base import _INF_OK, StrictModel, check_air_braked_ecus  # noqa: F401 - re-exported for the scenario loader
from canbrake.consist import heavy_haul as hhs
from canbrake.consist.adhesion import AdhesionSpec, VehicleAxles
from canbrake.consist.brakes import BrakeSystemConfig

#: most vehicles (and ECUs) a scenario may have: the 29-bit identifier plan holds 4095 ECUs; the
#: limit is what a run can carry in memory and time, not the bus
MAX_VEHICLES = 1024


#: the strict base model every scenario section derives from (one definition: canbrake.consist.base)
_Model = StrictModel


PerCar = Union[float, list[float]]




class ActuatorConfig(_Model):
    """Brake actuator: ``ideal`` applies the command at once; ``realistic`` adds lag, jerk limit, saturation."""

    model: Literal["ideal", "realistic"] = "ideal"
    lag_s: float | list[float] = Field(0.3, description="first-order brake lag time constant (realistic; a list: "
                                       "per car, 0 = that car's brake applies the command at once)")
    jerk_limit_mps3: float | list[float | None] | None = Field(
        1.0, description="max |dF/dt|/m (realistic; null = none; a list: per car)")
    max_brake_decel_mps2: float | list[float | None] | None = Field(
        None, description="brake rating as force/mass (null = none; a list: per car)")
    max_traction_accel_mps2: float | list[float | None] | None = Field(
        None, description="traction rating as force/mass (null = none; a list: per car)")

    @model_validator(mode="after")
    def _signs(self) -> "ActuatorConfig":
        lag = self.lag_s
        for i, x in enumerate(lag if isinstance(lag, list) else [lag]):
            if not (x >= 0 if isinstance(lag, list) else x > 0):
                where = f"lag_s.{i}" if isinstance(lag, list) else "lag_s"
                raise ValueError(f"@{where}: must be {'>=' if isinstance(lag, list) else '>'} 0, got {x:g}")
        for name, strict in (("jerk_limit_mps3", True), ("max_brake_decel_mps2", True), ("max_traction_accel_mps2", False)):
            v = getattr(self, name)
            for i, x in enumerate(v if isinstance(v, list) else [v]):
                if x is not None and not (x > 0 if strict else x >= 0):
                    where = f"{name}.{i}" if isinstance(v, list) else name
                    raise ValueError(f"@{where}: must be {'>' if strict else '>='} 0, got {x:g}")
        return self

    def per_car(self, name: str, none: float = math.inf) -> float | tuple[float, ...]:
        """Field ``name`` as the physics takes it: a float, or a tuple per car; null -> ``none``."""
        v = getattr(self, name)
        if isinstance(v, list):
            return tuple(none if x is None else float(x) for x in v)
        return none if v is None else v
    adhesion_limited: bool = Field(False, description="cap the rail force at μ·m·g")
    adhesion_mu: PerCar = Field(0.3, description="base wheel-rail adhesion μ per car")


class CouplerConfig(_Model):
    """Nonlinear coupler Φ = κ (1 + ε Δl²) Δl between neighbouring cars."""

    stiffness_n_per_m: PerCar = Field(80000.0, description="κ per coupler (n-1 values or one)")
    epsilon_per_m2: PerCar = Field(-0.5, description="ε per coupler (1/m²; negative = softening)")
    spacing_m: PerCar | None = Field(None, description="nominal x_i - x_{i+1} at rest; default: from initial positions")
    end_stop_m: float | list[float | None] | None = Field(
        None, description="|Δl| at which the draft gear's travel ends and its buffer acts (none by default; a list: "
                          "per coupler, null = none on that coupler; docs/braking-models.md)")
    end_stop_stiffness_n_per_m: PerCar = Field(2.0e7, description="the buffer's loading stiffness beyond the end stop "
                                               "(a list: per coupler)")
    end_stop_absorption: PerCar = Field(0.6, description="share of an impact's energy the buffer absorbs "
                                        "(unloading stiffness (1 - a) x loading; a list: per coupler)")

    @model_validator(mode="after")
    def _end_stops(self) -> "CouplerConfig":
        for name, ok, says in (("end_stop_m", lambda x: x is None or x > 0, "> 0"),
                               ("end_stop_stiffness_n_per_m", lambda x: x > 0, "> 0"),
                               ("end_stop_absorption", lambda x: 0 <= x < 1, "in [0, 1)")):
            v = getattr(self, name)
            for i, x in enumerate(v if isinstance(v, list) else [v]):
                if not ok(x):
                    raise ValueError(f"@{name}{f'.{i}' if isinstance(v, list) else ''}: must be {says}, got {x:g}")
        return self

    @field_validator("stiffness_n_per_m")
    @classmethod
    def _positive_stiffness(cls, v: PerCar) -> PerCar:
        for x in (v if isinstance(v, list) else [v]):
            if not x > 0:
                raise ValueError(f"coupler stiffness must be > 0 N/m, got {x}")
        return v


class DavisConfig(_Model):
    """Running resistance per car: c0 + c1 |v| + c2 v² (N, v in m/s)."""

    c0_n: PerCar = 0.0
    c1_n_s_per_m: PerCar = 0.0
    c2_n_s2_per_m2: PerCar = 0.0


class TrainConfig(_Model):
    """The coupled kernel's train (physics/train.py, Chen 2023): cars joined by nonlinear couplers,
    per-car lists front first (internal: assembled from the components)."""

    model: Literal["coupled"] = "coupled"
    mass_kg: list[float] = Field(default_factory=list, max_length=MAX_VEHICLES)
    davis: DavisConfig | None = Field(None, description="default: Davis (1926) multiple-unit coefficients per mass")
    coupler: CouplerConfig = CouplerConfig()
    grade_permille: float = Field(0.0, ge=-100, le=100, description="track grade, positive uphill (‰)")
    curve_resistance_n: PerCar = Field(0.0, description="extra resistance per car, e.g. 0.004·m·D_c (N)")
    brakes: BrakeSystemConfig | None = Field(None, description="brake equipment: blending, easing, wheels with "
                                                               "adhesion, wheel-slide protection (canbrake.consist.brakes)")
    actuator: ActuatorConfig = Field(default_factory=ActuatorConfig, description="every car's brake/traction equipment")
    resistance_table: list[Any] | None = Field(None, description="per car: a resistance table (speed_mps, force_n; "
                                               "components.TableResistance) added to its Davis terms, or None")
    traction_envelope: list[Any] | None = Field(None, description="per car: a traction envelope (heavy_haul.Envelope, "
                                                "Li 2024 eq. 1) limiting its traction, or None")
    rigid: bool = Field(False, description="rigid couplers: the train moves as one body (Cai 2014 eq. 3)")
    driven_axles: list[VehicleAxles | None] | None = Field(None, description="per car (rigid train): its driven "
                                                          "axles (Cai 2014) or None")
    wheel_rail: AdhesionSpec | None = Field(None, description="rigid train: the slip curve and its rail conditions "
                                            "over time (Cai 2014 eqs. 13-15, 41-42)")
    vehicle_names: list[str] | None = Field(None, description="per car: its vehicle type (for messages)")
    draft_gears: dict[str, hhs.DraftGear] = Field(default_factory=dict, description="Li's draft gears by name")
    coupler_gear: list[str | None] | None = Field(None, description="per coupler: the name of its draft gear "
                                                  "(Li 2024, eqs. 7-9) or None (Chen's coupler)")
    air_brake: hhs.AirBrake | None = Field(None, description="the automatic air brake / ECP of the air-braked cars")
    air_rigging: list[hhs.BrakeEquipment | None] | None = Field(None, description="per car: its air brake rigging "
                                                                "(Li 2024 Table 1) or None")
    length_m: list[float] | None = Field(None, description="per car: length over couplers (m), spaces the brake pipe")
    # Li 2024's line and locomotive on the coupled plant (a train with draft gears or air brakes)
    route: hhs.Route | None = Field(None, description="the route file: grade and curves by position")
    start_position_m: float = Field(0.0, description="with a route: the first car's centre on it (m)")
    static_couplers: bool = Field(False, description="start with each coupler carrying the resistance behind it")
    electric_brake_envelope: bool = Field(False, description="the traction envelopes' electric brake F_B caps "
                                          "the brake effort of their cars")
    loco_adhesion: list[hhs.Adhesion | None] | None = Field(None, description="per car: μ(v)·m·g caps its "
                                                            "traction and electric brake, or None")
    uncertainty: float = Field(0.0, ge=-0.5, le=0.5, description="δ on the non-control forces")
    disturbance: hhs.Disturbance | None = Field(None, description="Li 2024 eq. 40 (None: off)")
    max_substep_s: float | None = Field(None, gt=0, description="the integration step (None: the control "
                                        "period over plant.substeps)")

    @field_validator("mass_kg")
    @classmethod
    def _positive_mass(cls, v: list[float]) -> list[float]:
        for i, m in enumerate(v):
            if not m > 0:
                raise ValueError(f"car {i + 1}: mass must be > 0 kg, got {m}")
        return v

    @model_validator(mode="after")
    def _vehicles(self) -> "TrainConfig":
        if not self.mass_kg:
            raise ValueError("no vehicles")
        return self

    @property
    def n_cars(self) -> int:
        return len(self.mass_kg)

    def vehicle_count(self) -> int:
        return len(self.mass_kg)

    def vehicle_masses_kg(self) -> np.ndarray:
        return np.asarray(self.mass_kg, dtype=float)

    @property
    def mixed(self) -> bool:
        """Whether the train has Li's draft gears or air brakes among its couplers and brakes."""
        return self.air_brake is not None or any(g is not None for g in self.coupler_gear or [])

    def air_brake_physics(self) -> Any:
        """The :class:`canbrake.physics.heavy_haul.AirBrake` over every car (None without air
        brakes): a car without rigging has no blocks; the pipe runs the cars' lengths from the head."""
        from canbrake.physics import heavy_haul as hh

        if self.air_brake is None or self.air_rigging is None or self.length_m is None:
            return None
        n = self.n_cars
        z = np.zeros(n)
        consist = hh.Consist(mass_kg=np.asarray(self.mass_kg, dtype=float), length_m=np.asarray(self.length_m, dtype=float),
                             davis_a=z, davis_b=z, davis_c=z, is_loco=np.zeros(n, dtype=bool))
        return self.air_brake.physics(consist, self.air_rigging)

    def load_route(self, base_dir: Path | None) -> Any:
        """The :class:`canbrake.physics.route.Route` of ``route`` (file relative to ``base_dir``), or None."""
        return None if self.route is None else self.route.load(base_dir)

    def _wagon(self, vehicle: int) -> bool:
        """Whether car ``vehicle`` (1-based) is an air-braked car without traction (a wagon)."""
        rig, env = self.air_rigging, self.traction_envelope
        return (1 <= vehicle <= self.n_cars and rig is not None and rig[vehicle - 1] is not None
                and (env is None or env[vehicle - 1] is None))

    def ecp_unit_params(self, vehicle: int) -> dict[str, float] | None:
        """An ECP air-braked car's brake data for its ECU's brake unit (:class:`canbrake.control.ecp.EcpUnit`),
        vehicle ``vehicle`` 1-based; None for a car without air brake, with traction, or a pneumatic train."""
        if self.air_brake is None or not self._wagon(vehicle):
            return None
        return self.air_brake.ecp_unit(self.air_rigging[vehicle - 1])  # type: ignore[index]

    def axle_counts(self) -> list[int]:
        """Driven axles per vehicle, front first (rigid trains; 0 elsewhere)."""
        return [0 if a is None else len(a.axles) for a in (self.driven_axles or [None] * self.n_cars)]

    def check_ecus(self, placed: list[Any], dt_s: float | None = None) -> None:
        """ValueError (one line) for an ECU whose commands its vehicle cannot take (trains with air
        brakes: :func:`canbrake.consist.base.check_air_braked_ecus`; rigid trains: :meth:`_check_axle_ecus`)."""
        if self.rigid:
            self._check_axle_ecus(placed, 1e-3 if dt_s is None else dt_s)
        if self.air_brake is None:
            return
        check_air_braked_ecus(placed, self.air_brake.mode, self._wagon)

    def _check_axle_ecus(self, placed: list[Any], dt_s: float) -> None:
        """ValueError (one line) for an ECU whose controller drives or reads more axles than its
        vehicle has (``axle<j>_torque_nm`` / ``axle<j>_speed_radps`` beyond the vehicle's driven
        axles, e.g. a traction controller on a trailer): the plant would ignore its torques."""
        import re

        from canbrake.control.base import make_controller

        counts = self.axle_counts()
        names = self.vehicle_names or [f"vehicle {i + 1}" for i in range(self.n_cars)]
        for i, p in enumerate(placed):
            if not 1 <= p.vehicle <= len(counts):
                continue  # reported by the placement check
            try:  # its signal names may depend on its parameters (cai2014's axles)
                ctrl = make_controller(p.controller.name, p.controller.params, car_index=i, n_cars=len(placed),
                                       mass_kg=float(self.mass_kg[p.vehicle - 1]), dt_s=dt_s)
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

    def build_plant(self, scn: Any, base_dir: Path | None = None) -> Any:
        from canbrake.build import build_coupled_plant

        return build_coupled_plant(scn)



