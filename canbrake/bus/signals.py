"""The signal catalogue: how each named physical quantity travels in a CAN frame.

Sensor, command and broadcast signals are named as in :mod:`canbrake.physics.contract`
(SI names with the unit as suffix). The DBC generator (:mod:`canbrake.bus.dbc`) packs the
signals an ECU needs into its frames using the format given here, so adding a quantity to the
bus is one entry in :data:`CATALOGUE` (or :data:`PATTERNS` for indexed names such as
``axle3_torque_nm``).

Every signal is a little-endian (Intel) bit field; physical = raw * scale + offset. Values out
of range saturate at the raw limits (as an ECU's conversion would).
"""
from __future__ import annotations

import re
from dataclasses import dataclass, replace


@dataclass(frozen=True)
class SignalFormat:
    """Format of one signal in a frame: DBC name, bit length, scaling, range (physical) and unit."""

    dbc_name: str
    length: int
    scale: float = 1.0
    offset: float = 0.0
    signed: bool = False
    minimum: float | None = None
    maximum: float | None = None
    unit: str | None = None
    comment: str | None = None


def _signed(dbc_name: str, length: int, scale: float, unit: str, comment: str) -> SignalFormat:
    half = 1 << (length - 1)
    return SignalFormat(dbc_name, length, scale, 0.0, True, -half * scale, (half - 1) * scale, unit, comment)


def _unsigned(dbc_name: str, length: int, scale: float, unit: str, comment: str, offset: float = 0.0) -> SignalFormat:
    return SignalFormat(dbc_name, length, scale, offset, False, offset, offset + ((1 << length) - 1) * scale,
                        unit, comment)


#: Scaling (why): speed 1e-4 m/s (0.00036 km/h, >1000x below a 0.5 km/h tracking tolerance),
#: position 1e-4 m (0.1 mm, 100x below a +-1 cm coupler bound), force 10 N (a metro car brakes
#: with ~20 kN; +-84 MN covers the ideal-actuator "paper" profile), deflection 5e-5 m.
CATALOGUE: dict[str, SignalFormat] = {
    "speed_mps": SignalFormat("Speed", 20, 1e-4, 0.0, False, 0.0, 104.8575, "m/s", "speed of the vehicle"),
    "position_m": SignalFormat("Position", 32, 1e-4, -10000.0, False, -10000.0, 419496.7295, "m",
                               "position along the track"),
    "brake_force_n": SignalFormat("BrakeForce", 24, 10.0, 0.0, True, -83886080.0, 83886070.0, "N",
                                  "demanded force; positive decelerates, negative is traction"),
    # Li 2024 heavy haul. passive_force_n: 10 N like BrakeForce (a locomotive's coupler carries up to
    # ~2.5 MN; 10 N is 5e-5 m/s^2 on a 184 t locomotive, far below the eq. 40 disturbance).
    "passive_force_n": _signed("PassiveForce", 24, 10.0, "N",
                               "non-control force on the vehicle: measured coupler force + nominal resistances"),
    # driver's brake valve and the line-data flag are on/off
    "airbrake_apply": SignalFormat("AirBrakeApply", 1, 1.0, 0.0, False, 0.0, 1.0, None,
                                   "driver's brake valve: 1 apply, 0 release"),
    "downgrade_ahead": SignalFormat("DowngradeAhead", 1, 1.0, 0.0, False, 0.0, 1.0, None,
                                    "line data: 1 = long downgrade under the train or within the look-ahead"),
    # ECP demand: 0.1 % of a full service application (10 bits, 0..1.023)
    "ecp_demand": SignalFormat("EcpDemand", 10, 0.001, 0.0, False, 0.0, 1.023, None,
                               "ECP brake demand, fraction of full service"),
    # cylinder pressure: 10 Pa (Table 1's cylinders run at 430-450 kPa; 16 bits reach 655 kPa)
    "brake_cylinder_pressure_pa": _unsigned("CylPressure", 16, 10.0, "Pa", "brake cylinder pressure"),
    # Cai 2014's traction ECU: speed over ground as a Doppler radar gives it (the wheels slip, so
    # their speed is not the train's). 1e-6 m/s because the force observers differentiate it:
    # g m q = 10 1/s x 96 t x 1e-6 m/s ~ 1 N of estimation noise (1e-4 m/s would give ~100 N, a few
    # % of the resistance); signed, +-134 m/s, because a wrong-signed control drives the train backwards.
    "ground_speed_mps": _signed("GroundSpeed", 28, 1e-6, "m/s", "speed of the train over ground (radar)"),
    # wheel-slide protection: dump-valve command of a car's brake unit, 1/1000 of full venting
    # (10 bits, like EcpDemand: the valve's own lag, ~50 ms, smooths far coarser steps)
    "wsp_release": SignalFormat("WspRelease", 10, 0.001, 0.0, False, 0.0, 1.023, None,
                                "wheel-slide protection: dump valve opening, 0 closed .. 1 vented"),
    "deflection_front_m": _signed("DeflFront", 16, 5e-5, "m", "deflection of the coupler to the vehicle ahead"),
    "deflection_rear_m": _signed("DeflRear", 16, 5e-5, "m", "deflection of the coupler to the vehicle behind"),
}

def _axle_signal(m: re.Match[str]) -> SignalFormat:
    """``axle<j>_speed_radps`` and ``axle<j>_torque_nm`` (Cai 2014's traction ECU)."""
    j, quantity = int(m.group(1)), m.group(2)
    if quantity == "speed_radps":
        # 1e-4 rad/s: 0.05 mm/s at a 0.495 m wheel, ~1/1000 of the creep speeds; the adhesion observer
        # differentiates it: J q/(R dt) = 16 N per 1 ms sample, ~0.2 N after its 10 1/s filter, against
        # ~7 kN per axle. +-839 rad/s covers 200 km/h (112 rad/s) with any slip, forwards and backwards.
        return _signed(f"Axle{j}Speed", 24, 1e-4, "rad/s", f"angular speed of driven axle {j}")
    # 0.1 N.m: 0.2 N of force at the rail (a traction axle gives ~7 kN); +-839 kN.m, far above any drive
    return _signed(f"Axle{j}Torque", 24, 0.1, "N.m", f"torque demand on driven axle {j}; positive drives forward")


#: indexed names: (regex, factory(match) -> SignalFormat)
PATTERNS: list[tuple[re.Pattern[str], "object"]] = [
    (re.compile(r"axle([1-9][0-9]?)_(speed_radps|torque_nm)"), _axle_signal),
]


def signal_format(name: str) -> SignalFormat:
    """The on-bus format of signal ``name``; KeyError naming the signal if it has none."""
    fmt = CATALOGUE.get(name)
    if fmt is not None:
        return fmt
    for rx, factory in PATTERNS:
        m = rx.fullmatch(name)
        if m:
            return factory(m)  # type: ignore[operator]
    raise KeyError(f"signal {name!r} has no CAN format (canbrake.bus.signals.CATALOGUE)")


def known(name: str) -> bool:
    """Whether ``name`` can travel on the bus."""
    try:
        signal_format(name)
    except KeyError:
        return False
    return True


def renamed(fmt: SignalFormat, dbc_name: str) -> SignalFormat:
    return replace(fmt, dbc_name=dbc_name)
