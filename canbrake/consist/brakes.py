"""Brake equipment of the coupled (Chen) kernel as data (every part opt-in). In the scenario these are
parts of the brake component (``ideal``/``electro_pneumatic``: ``blending``, ``easing``, ``wsp``,
``ed_brake``) and the wheels component (``wheelsets``), e.g. ``scenarios/chen2023_case2_low_adhesion.yaml``::

    train:
      every_vehicle:
        brake:
          model: electro_pneumatic
          blending: {ed_max_decel_mps2: 1.0, fade_start_kmh: 10, fade_end_kmh: 3, friction_lag_s: 0.2}
          easing: {time_constant_s: 1.0}
          wsp: {enabled: true, slip_release: 0.2, slip_reapply: 0.1}
        wheels: {model: wheelsets, axles: 4, radius_m: 0.42, inertia_kgm2: 120}

Physics: :mod:`canbrake.physics.brakes` (blending, wheelsets, dump valve); ECU functions (easing,
wheel-slide protection): :mod:`canbrake.control.brake_functions`. Units in the field names.
"""
from __future__ import annotations

from typing import Annotated, Any, Literal, Union

from pydantic import Field, model_validator

from canbrake.consist.base import StrictModel


class EdPerMass(StrictModel):
    """An ED brake whose force is a capacity per unit mass, power-limited and fading at low speed
    (the blending's ``fade_start_kmh``/``fade_end_kmh``): F ≤ m·min(a, P/(m|v|))·fade(v)."""

    model: Literal["per_mass"] = "per_mass"
    max_decel_mps2: float = Field(..., ge=0, description="ED brake force per unit mass at full capacity")
    power_kw_per_t: float | None = Field(None, gt=0, description="ED power per tonne (F <= P/v; null: no limit)")


class EdEnvelope(StrictModel):
    """An ED brake with Li 2024's electric-brake envelope (eq. 2; kN with v in km/h, e.g. a
    locomotive's): F_B = ``brake_slope_kn_per_kmh``·v up to ``brake_linear_until_kmh``,
    ``brake_max_kn`` up to ``brake_constant_until_kmh``, ``power_kn_kmh``/v above. It has its own
    low-speed ramp, so the blending's fade does not apply to it."""

    model: Literal["envelope"]
    brake_slope_kn_per_kmh: float = Field(..., ge=0)
    brake_linear_until_kmh: float = Field(..., ge=0)
    brake_max_kn: float = Field(..., ge=0)
    brake_constant_until_kmh: float = Field(..., gt=0)
    power_kn_kmh: float = Field(..., gt=0)

    @model_validator(mode="after")
    def _order(self) -> "EdEnvelope":
        if self.brake_constant_until_kmh < self.brake_linear_until_kmh:
            raise ValueError(f"@brake_constant_until_kmh: must be at least brake_linear_until_kmh "
                             f"({self.brake_linear_until_kmh:g}), got {self.brake_constant_until_kmh:g}")
        return self

    def row_si(self) -> tuple[float, float, float, float, float]:
        """(slope N·s/m, v1 m/s, F_max N, v2 m/s, power W) as the brake kernel takes it."""
        return (self.brake_slope_kn_per_kmh * 1000.0 * 3.6, self.brake_linear_until_kmh / 3.6, self.brake_max_kn * 1000.0,
                self.brake_constant_until_kmh / 3.6, self.power_kn_kmh * 1000.0 / 3.6)


class EdNone(StrictModel):
    """No ED brake (a trailer car): the friction brake gives the whole demand."""

    model: Literal["none"]


#: an ED brake of one vehicle type (``vehicle_types.<type>.ed_brake``), by ``model``
EdBrake = Annotated[Union[EdPerMass, EdEnvelope, EdNone], Field(discriminator="model")]


class BlendingConfig(StrictModel):
    """Electro-dynamic / friction blending with the ED brake fading at low speed."""

    ed_max_decel_mps2: float = Field(1.0, ge=0, description="ED brake force per unit mass at full capacity "
                                                            "(every car whose vehicle type sets no ed_brake)")
    ed_power_kw_per_t: float | None = Field(None, gt=0, description="ED power per tonne (F <= P/v; null: no limit)")
    fade_start_kmh: float = Field(10.0, gt=0, description="the ED force starts to fade below this speed")
    fade_end_kmh: float = Field(3.0, ge=0, description="the ED force is zero below this speed")
    friction_lag_s: float = Field(0.2, ge=0, description="first-order lag of the friction brake behind its share")
    per_car: list[EdBrake | None] | None = Field(
        None, description="the ED brake of each car, front first (filled from the vehicle types' ed_brake; "
                          "null entries: ed_max_decel_mps2 / ed_power_kw_per_t above)")

    @model_validator(mode="after")
    def _order(self) -> "BlendingConfig":
        if not self.fade_start_kmh > self.fade_end_kmh:
            raise ValueError(f"@fade_end_kmh: must be below fade_start_kmh ({self.fade_start_kmh:g}), "
                             f"got {self.fade_end_kmh:g}")
        return self


class EasingConfig(StrictModel):
    """Jerk-limited easing before standstill (an ECU function): below the speed where it bites, each
    car's brake demand is capped so that its deceleration falls as v / ``time_constant_s``, reaching
    zero at standstill; the cap anticipates the brake's lag (``lag_s``, default the actuator's)."""

    time_constant_s: float = Field(1.0, gt=0, description="deceleration cap = v / time_constant (1/s)")
    lag_s: float | None = Field(None, ge=0, description="brake lag the ECU anticipates (default: brake.lag_s "
                                                          "for a realistic actuator, 0 for an ideal one, plus "
                                                          "blending.friction_lag_s)")


class WheelsConfig(StrictModel):
    """Wheelsets of every car, with wheel–rail adhesion per axle (Cai 2014's slip curve, eqs. 10–15,
    its peak scaled to the car's μ: ``train.wheel_rail.adhesion_mu`` and rail events' ``adhesion_mu``)."""

    axles: int = Field(4, ge=1, le=8)
    radius_m: float = Field(0.42, gt=0, description="rolling radius (840 mm wheels)")
    inertia_kgm2: float = Field(120.0, gt=0, description="wheelset with discs, gear and motor rotor referred to the axle")
    v_floor_mps: float = Field(0.1, gt=0, description="floor of the slip denominator max(wR, v, floor)")
    b1: float = Field(1.786, gt=0, description="slip curve eq. 13 (Cai's dry rail, eq. 41)")
    b2: float = Field(40.0, gt=0)
    b3: float = Field(10.0, gt=0)
    c1: float = Field(0.040, ge=0, description="speed decay eq. 15 (Cai's dry rail)")
    c2: float = Field(3.78, ge=0)
    c3: float = Field(33.3, gt=0)


class WspConfig(StrictModel):
    """Wheel-slide protection (an ECU function driving each car's dump valves; needs ``wheels``):
    vents the brake when an axle's slip passes ``slip_release``, re-applies (ramping the valve shut
    at ``reapply_per_s``) once every axle's slip is back below ``slip_reapply``."""

    enabled: bool = True
    slip_release: float = Field(0.2, gt=0, lt=1, description="|λ| above which the brake is vented")
    slip_reapply: float = Field(0.1, gt=0, lt=1, description="|λ| below which the brake is re-applied")
    reapply_per_s: float = Field(4.0, gt=0, description="rate at which the valve closes again (1/s)")
    valve_lag_s: float = Field(0.05, ge=0, description="dump valve first-order lag (s)")
    min_speed_kmh: float = Field(3.0, ge=0, description="below this speed WSP is inactive (slip is ill-defined)")
    max_vent_s: float = Field(5.0, gt=0, description="dump-valve watchdog: a car's brake comes back after venting "
                                                     "this long without a break, whatever the ECU commands")

    @model_validator(mode="after")
    def _order(self) -> "WspConfig":
        if not self.slip_reapply < self.slip_release:
            raise ValueError(f"@slip_reapply: must be below slip_release ({self.slip_release:g}), got {self.slip_reapply:g}")
        return self


class CarBrakes(StrictModel):
    """One car's blending, easing and wheel-slide protection where the vehicle types differ in them
    (``vehicle_type`` names the car's type for messages); None: the car has none."""

    vehicle_type: str
    blending: BlendingConfig | None = None
    easing: EasingConfig | None = None
    wsp: WspConfig | None = None


class BrakeSystemConfig(StrictModel):
    """The coupled kernel's brake equipment (assembled from the brake and wheels components); every
    part is off unless given. ``cars``: None where every car has the same blending, easing and wsp
    (the fields above); else one entry per car, front first, and the fields above are those of the
    first car that has each (they say the train has it)."""

    blending: BlendingConfig | None = None
    easing: EasingConfig | None = None
    wheels: WheelsConfig | None = None
    wsp: WspConfig | None = None
    cars: list[CarBrakes] | None = None
    wheels_per_car: list[WheelsConfig | None] | None = Field(
        None, description="None where every car has ``wheels``; else per car its wheelsets (None: no wheels), "
                          "each with its own slip curve and v_floor_mps (``wheels``: the first car's that has them)")

    def car_wheels(self, i: int) -> WheelsConfig | None:
        """Car ``i``'s (0-based) wheelsets (None: none)."""
        return self.wheels if self.wheels_per_car is None else self.wheels_per_car[i]

    def car(self, i: int) -> CarBrakes:
        """Car ``i``'s (0-based) blending, easing and wsp."""
        if self.cars is not None:
            return self.cars[i]
        return CarBrakes(vehicle_type="", blending=self.blending, easing=self.easing, wsp=self.wsp)

    @model_validator(mode="after")
    def _wsp_needs_wheels(self) -> "BrakeSystemConfig":
        if self.wsp is not None and self.wsp.enabled and self.wheels is None:
            raise ValueError("@wsp: wheel-slide protection needs wheels (the wheels component)")
        return self


def easing_lag_s(brakes: BrakeSystemConfig, actuator: Any) -> float:
    """The brake lag (s) easing anticipates: ``easing.lag_s`` if given, else the realistic actuator's
    lag (0 for an ideal one) plus the friction brake's lag behind the blend."""
    e = brakes.easing
    if e is not None and e.lag_s is not None:
        return float(e.lag_s)
    lag_s = getattr(actuator, "lag_s", 0.0)
    if isinstance(lag_s, list) and getattr(actuator, "model", "ideal") == "realistic":
        raise ValueError("@train.every_vehicle.brake.easing.lag_s: easing anticipates one brake lag, and this "
                         f"train's vehicles have different ones ({', '.join(f'{x:g}' for x in sorted(set(lag_s)))} s; "
                         "an ideal brake is 0): give the lag easing anticipates")
    lag = float(lag_s) if getattr(actuator, "model", "ideal") == "realistic" else 0.0
    if brakes.blending is not None:
        lag += brakes.blending.friction_lag_s
    return lag


def car_easing_lag_s(brakes: BrakeSystemConfig, actuator: Any, i: int) -> float:
    """The brake lag (s) car ``i``'s easing anticipates where the cars' brake functions differ
    (``brakes.cars``): its ``easing.lag_s`` if given, else its own brake lag (0 for an ideal
    brake) plus its own blending's friction lag; :func:`easing_lag_s` otherwise."""
    if brakes.cars is None:
        return easing_lag_s(brakes, actuator)
    c = brakes.cars[i]
    if c.easing is not None and c.easing.lag_s is not None:
        return float(c.easing.lag_s)
    lag = 0.0
    if getattr(actuator, "model", "ideal") == "realistic":
        lag_s = actuator.lag_s
        lag = float(lag_s[i] if isinstance(lag_s, list) else lag_s)
    if c.blending is not None:
        lag += c.blending.friction_lag_s
    return lag
