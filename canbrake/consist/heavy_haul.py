"""Li, Zeng & Yu 2024's train parts as configuration. Internal: the user writes ``train:`` as
components (:mod:`canbrake.consist.components`); the component models ``per_weight``, ``air``,
``envelope``, ``adhesion_limit`` and ``train.draft_gears``/``air_brake``/``track.route``/``disturbance``
reuse the schemas below, and the coupled kernel's configuration
(:class:`canbrake.consist.coupled.TrainConfig`) holds them for :class:`canbrake.physics.train.TrainPlant`.

Running resistance per unit weight (eq. 3), hysteretic draft gears (eqs. 7-9), a route from a CSV
table (grade ‰ and curve radius by position), the automatic air brake with its brake-pipe waves or
ECP (eqs. 10-15), the locomotive's traction and electric-brake envelopes (eqs. 1-2) and adhesion,
the disturbance of eq. (40). Units are in the field names; the paper's N/kN, km/h, mm and kPa
appear only where the paper gives them so.
"""
from __future__ import annotations

from pathlib import Path
from typing import Any, Literal

import numpy as np
from pydantic import Field, model_validator

from canbrake.consist.base import StrictModel, load_table
from canbrake.physics import heavy_haul as hh


class Resistance(StrictModel):
    """Basic running resistance per unit weight, eq. (3): w = A + B·v + C·v² (N/kN, v in km/h)."""

    a_n_per_kn: float = Field(ge=0)
    b_n_per_kn_per_kmh: float = Field(ge=0)
    c_n_per_kn_per_kmh2: float = Field(ge=0)


class DraftGear(StrictModel):
    """Hysteretic draft gear (eqs. 7-9): loading curve f_l (piecewise linear through the points),
    unloading curve f_u = ``unloading_ratio``·f_l, free slack each side, eq. (8) stiffness, solid
    stiffness beyond the stroke, viscous damping while engaged."""

    curve_mm: list[float] = Field(min_length=3)
    curve_kn: list[float] = Field(min_length=3)
    unloading_ratio: float = Field(gt=0, le=1)
    slack_mm: float = Field(ge=0)
    k_elastic_n_per_m: float = Field(gt=0)
    k_solid_n_per_m: float = Field(gt=0)
    damping_n_s_per_m: float = Field(ge=0)

    @model_validator(mode="after")
    def _curve(self) -> "DraftGear":
        if len(self.curve_mm) != len(self.curve_kn):
            raise ValueError("curve_mm and curve_kn need the same number of points")
        if self.curve_mm[0] != 0 or self.curve_kn[0] != 0 or any(b <= a for a, b in zip(self.curve_mm, self.curve_mm[1:])):
            raise ValueError("the loading curve starts at (0 mm, 0 kN) with increasing deflections")
        return self

    def physics(self, name: str) -> hh.DraftGear:
        return hh.DraftGear(name, tuple(x / 1000.0 for x in self.curve_mm), tuple(f * 1000.0 for f in self.curve_kn),
                            unloading_ratio=self.unloading_ratio, slack_m=self.slack_mm / 1000.0,
                            k_elastic_n_per_m=self.k_elastic_n_per_m, k_solid_n_per_m=self.k_solid_n_per_m,
                            damping_n_s_per_m=self.damping_n_s_per_m)


class BrakeEquipment(StrictModel):
    """Air-brake rigging of a vehicle type (Table 1; eqs. 13-15).

    ``shoe``: force per shoe K = π/4·d²·p·η·γ·(cylinders/shoes) (eq. 15), ``shoes`` blocks.
    ``disc``: force per cylinder at the tread K = r/R·π/4·d²·p·γ·η (eqs. 13-14), ``cylinders`` blocks.
    ``friction_coefficient``: the leading factor of eqs. (11)-(12) (0.441 HXD1, 0.481 C80 high-friction).
    """

    kind: Literal["shoe", "disc"]
    cylinder_diameter_mm: float = Field(gt=0)
    cylinder_pressure_kpa: float = Field(gt=0)
    lever_ratio: float = Field(gt=0)
    efficiency: float = Field(gt=0, le=1)
    cylinders: int = Field(ge=1)
    shoes: int = Field(ge=1)
    friction_coefficient: float = Field(gt=0)
    wheel_radius_mm: float | None = Field(None, gt=0)
    friction_radius_mm: float | None = Field(None, gt=0)

    @model_validator(mode="after")
    def _disc(self) -> "BrakeEquipment":
        if self.kind == "disc" and (self.wheel_radius_mm is None or self.friction_radius_mm is None):
            raise ValueError("a disc brake needs wheel_radius_mm and friction_radius_mm")
        return self

    def block_force_kn(self) -> float:
        """Force per shoe (shoe brake) or per cylinder referred to the tread (disc brake), kN, full pressure."""
        d, p = self.cylinder_diameter_mm, self.cylinder_pressure_kpa
        if self.kind == "disc":
            return hh.disc_block_force_kn(d, p, self.lever_ratio, self.efficiency, self.friction_radius_mm,  # type: ignore[arg-type]
                                          self.wheel_radius_mm)  # type: ignore[arg-type]
        return hh.shoe_block_force_kn(d, p, self.lever_ratio, self.efficiency, self.cylinders, self.shoes)

    def blocks(self) -> int:
        return self.cylinders if self.kind == "disc" else self.shoes


class Envelope(StrictModel):
    """Traction and electric-brake envelopes, eqs. (1)-(2) (kN, km/h); see
    :class:`canbrake.physics.heavy_haul.TractionEnvelope`."""

    traction_start_kn: float = Field(gt=0)
    traction_start_until_kmh: float = Field(ge=0)
    traction_intercept_kn: float
    traction_slope_kn_per_kmh: float
    traction_linear_until_kmh: float = Field(gt=0)
    brake_slope_kn_per_kmh: float = Field(ge=0)
    brake_linear_until_kmh: float = Field(ge=0)
    brake_max_kn: float = Field(ge=0)
    brake_constant_until_kmh: float = Field(gt=0)
    power_kn_kmh: float = Field(gt=0)

    def physics(self) -> hh.TractionEnvelope:
        return hh.TractionEnvelope(**self.model_dump())


class Adhesion(StrictModel):
    """Wheel–rail adhesion limit of a locomotive's traction and dynamic brake, |u| ≤ μ(v)·m·g: μ = ``mu``
    (``constant``) or Curtius–Kniffler's μ(v) = 0.161 + 7.5/(v + 44) (v km/h) scaled to μ(0) = ``mu``."""

    mu: float = Field(0.33, gt=0, le=1)
    curve: Literal["constant", "curtius_kniffler"] = "constant"

    def physics(self) -> hh.LocoAdhesion:
        return hh.LocoAdhesion(mu0=self.mu, curve=self.curve)


class Route(StrictModel):
    """Grade and curvature by position from a CSV file (columns ``position_m, grade_permille,
    curve_radius_m``; 0 = straight; see :meth:`canbrake.physics.heavy_haul.Route.from_table`), and the
    line-data rule of the ``downgrade_ahead`` sensor: a downgrade steeper than
    ``long_downgrade_permille`` and at least ``long_downgrade_min_length_m`` long, under the train or
    within ``lookahead_m`` ahead."""

    file: str
    lookahead_m: float = Field(2500.0, ge=0)
    long_downgrade_permille: float = Field(8.0, gt=0)
    long_downgrade_min_length_m: float = Field(500.0, ge=0)

    def load(self, base_dir: Path | None) -> hh.Route:
        """The route of the file (relative to ``base_dir``); ValueError naming the file."""
        t = load_table(self.file, ("position_m", "grade_permille", "curve_radius_m"), base_dir)
        try:
            return hh.Route.from_table(t["position_m"], t["grade_permille"], t["curve_radius_m"])
        except ValueError as e:
            raise ValueError(f"{self.file}: {e}") from None

    def line_rule(self) -> tuple[float, float, float]:
        """(look-ahead m, steepest grade ‰, least length m) of the ``downgrade_ahead`` sensor."""
        return (self.lookahead_m, self.long_downgrade_permille, self.long_downgrade_min_length_m)


class BrakePipe(StrictModel):
    """Brake-pipe pressure along the train (:class:`canbrake.physics.heavy_haul.BrakePipe`): the driver's
    valve lowers the pipe from ``pressure_kpa`` by ``reduction_kpa``; the change reaches vehicle k after
    D_k / wave speed and then drains (recharges) with the lag ``tau_s + tau_per_km_s · D_k``; each control
    valve sets its cylinder to ``ratio`` × the local pipe reduction (capped at the full cylinder pressure)."""

    pressure_kpa: float = Field(600.0, gt=0)
    reduction_kpa: float = Field(170.0, gt=0)
    ratio: float = Field(2.6, gt=0)
    tau_s: float = Field(1.0, gt=0)
    tau_per_km_s: float = Field(4.0, ge=0)

    @model_validator(mode="after")
    def _below(self) -> "BrakePipe":
        if self.reduction_kpa >= self.pressure_kpa:
            raise ValueError(f"@reduction_kpa: must be below pressure_kpa ({self.pressure_kpa:g}), got {self.reduction_kpa:g}")
        return self

    def physics(self) -> hh.BrakePipe:
        return hh.BrakePipe(p0_pa=1000.0 * self.pressure_kpa, reduction_pa=1000.0 * self.reduction_kpa,
                            ratio=self.ratio, tau_s=self.tau_s, tau_per_km_s=self.tau_per_km_s)


class EmergencyBrake(StrictModel):
    """The emergency application (:class:`canbrake.physics.heavy_haul.EmergencyBrake`), used when
    ``air_brake.application`` is ``emergency``: the signal's wave speed ``apply_wave_mps`` (the pipe
    vented at every control valve it reaches), the emergency cylinder fill lag ``cylinder_tau_s``, the
    emergency cylinder pressure as ``pressure_factor`` × the vehicle's full-service
    ``cylinder_pressure_kpa`` (the block force scales with it), eq. (10)'s coefficient ``brake_factor``
    in place of ``service_factor``, and with ``pipe`` the local venting lag ``vent_tau_s`` (pipe to 0)."""

    apply_wave_mps: float = Field(gt=0)
    cylinder_tau_s: float = Field(gt=0)
    pressure_factor: float = Field(1.0, ge=1.0, le=2.0)
    brake_factor: float = Field(1.0, gt=0, le=1)
    vent_tau_s: float = Field(0.5, gt=0)

    def physics(self) -> hh.EmergencyBrake:
        return hh.EmergencyBrake(apply_wave_mps=self.apply_wave_mps, cylinder_tau_s=self.cylinder_tau_s,
                                 pressure_factor=self.pressure_factor, brake_factor=self.brake_factor,
                                 vent_tau_s=self.vent_tau_s)


class AirBrake(StrictModel):
    """Automatic air brake (eqs. 10-15, section 1.2) or ECP.

    ``pneumatic``: the driver's valve (``airbrake_apply`` on vehicle 1) sends apply/release along the
    brake pipe at ``apply_wave_mps``/``release_wave_mps``; after the signal arrives each cylinder fills
    with a first-order lag ``cylinder_tau_s``. ``ecp``: each vehicle's cylinder follows its own
    ``ecp_demand`` with the same lag, no wave. ``service_factor`` is β_c of eq. (10).
    ``application``: what a full application of the run is, ``service`` (the fields above) or
    ``emergency`` (the ``emergency`` block's wave speed, cylinder lag, pressure and coefficient; the
    CAN layout carries a 1-bit driver's valve and an ECP demand of 0..1, so the kind of application
    is a property of the run, not a command).
    """

    mode: Literal["pneumatic", "ecp"] = "pneumatic"
    pipe: BrakePipe | None = Field(None, description="brake-pipe pressure per vehicle (null: the brake signal "
                                                       "plus one first-order cylinder fill)")
    apply_wave_mps: float = Field(gt=0)
    release_wave_mps: float = Field(gt=0)
    cylinder_tau_s: float = Field(gt=0)
    service_factor: float = Field(gt=0, le=1)
    application: Literal["service", "emergency"] = "service"
    emergency: EmergencyBrake | None = Field(None, description="the emergency application's brake (needed when "
                                                                 "application is emergency)")

    @model_validator(mode="after")
    def _emergency(self) -> "AirBrake":
        if self.application == "emergency" and self.emergency is None:
            raise ValueError("@emergency: application 'emergency' needs an emergency block "
                             "(apply_wave_mps, cylinder_tau_s, pressure_factor, brake_factor)")
        return self

    def physics(self, consist: hh.Consist, rigging: list[Any]) -> hh.AirBrake:
        """The air brake over ``consist``'s vehicles, each with its rigging (a ``BrakeEquipment``,
        or None: a vehicle without air brake, no blocks); the pipe runs the vehicles' lengths."""
        return hh.AirBrake(consist, apply_wave_mps=self.apply_wave_mps, release_wave_mps=self.release_wave_mps,
                           cylinder_tau_s=self.cylinder_tau_s, beta_c=self.service_factor, mode=self.mode,
                           block_force_kn=np.array([0.0 if r is None else r.block_force_kn() for r in rigging]),
                           n_blocks=np.array([0.0 if r is None else r.blocks() for r in rigging], dtype=float),
                           friction_coef=np.array([1.0 if r is None else r.friction_coefficient for r in rigging]),
                           cylinder_pressure_pa=np.array([1.0 if r is None else 1000.0 * r.cylinder_pressure_kpa
                                                          for r in rigging]),
                           pipe=None if self.pipe is None else self.pipe.physics(),
                           emergency=self.emergency.physics() if self.application == "emergency" else None)

    def ecp_unit(self, rigging: Any) -> dict[str, float] | None:
        """What an ECP wagon's brake unit needs to turn a force demand into its cylinder demand
        (:class:`canbrake.control.ecp.EcpUnit`) from its rigging; None in a pneumatic train."""
        if self.mode != "ecp":
            return None
        return {"k_full_kn": float(rigging.block_force_kn()), "n_blocks": float(rigging.blocks()),
                "friction_coef": float(rigging.friction_coefficient), "beta_c": float(self.service_factor)}


class Disturbance(StrictModel):
    """Eq. (40): σ_i = m_i {c0 + c1 sin(t+1) + c2 ∛v [sin(2t+2) + cos(3t+1)]} (N, v in m/s) on ``vehicles``
    (1-based); off unless ``enabled``."""

    enabled: bool = False
    vehicles: list[int] = Field(default_factory=list)
    c0_mps2: float = 0.002
    c1_mps2: float = 0.001
    c2: float = 0.0003
