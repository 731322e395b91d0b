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
    "deflection_front_m": _signed("DeflFront", 16, 5e-5, "m", "deflection of the coupler to the vehicle ahead"),
    "deflection_rear_m": _signed("DeflRear", 16, 5e-5, "m", "deflection of the coupler to the vehicle behind"),
}

#: indexed names: (regex, factory(match) -> SignalFormat)
PATTERNS: list[tuple[re.Pattern[str], "object"]] = []


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
