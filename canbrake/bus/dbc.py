"""The canbrake CAN database: message layout, identifiers, and DBC generation with cantools.

One database describes a train of ``n_cars`` carriages (1..63). Identifiers are 11-bit
standard and encode priority (lower wins arbitration)::

    0x010        SYNC            plant -> all     tick counter, starts control period k
    0x011        REFERENCE       plant -> all     v*(t_k), a*
    0x080 + i    BRAKE_CMD_Ci    ECU i -> plant   demanded braking force (E2E protected)
    0x0C0 + i    SENSOR_Ci       plant -> ECU i   measured speed and position of car i
    0x100 + i    COUPLER_Ci      plant -> ECU i   measured coupler deflections (optional sensor)
    0x140 + i    STATE_Ci        ECU i -> all     speed and position broadcast (E2E protected)
    0x700        HEARTBEAT_PLANT plant            node state (CANopen-style heartbeat ids)
    0x700 + i    HEARTBEAT_Ci    ECU i            node state
    0x780 + i    STATE_DONE_Ci   ECU i            simulation control: state phase of tick done
    0x7C0 + i    CMD_DONE_Ci     ECU i            simulation control: command phase of tick done

SYNC and brake commands rank above state frames, which rank above diagnostics, as the
architecture asks. SENSOR/COUPLER frames stand in for each car's local sensor wiring; the
*_DONE frames exist only to make lockstep runs deterministic and are exempt from impairment
(see docs/architecture.md).

All signals are little-endian (Intel) so a frame is one little-endian integer; that is what
lets :mod:`canbrake.bus.codec` encode without cantools on the hot path.

Scaling (why): speed 1e-4 m/s (0.00036 km/h, >1000x below the 0.5 km/h tracking tolerance),
position 1e-4 m (0.1 mm, 100x below the +-1 cm coupler bound), force 10 N (a metro car brakes
with ~20 kN, 10 N is 5e-4 of it; the range of +-84 MN covers the ideal-actuator "paper" profile,
whose first commands reach ~10 MN), deflection 5e-5 m.
"""
from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import cantools
from cantools.database.can import Database, Message, Node, Signal
from cantools.database.conversion import BaseConversion

MAX_CARS = 63

SYNC_ID = 0x010
REFERENCE_ID = 0x011
BRAKE_CMD_BASE = 0x080
SENSOR_BASE = 0x0C0
COUPLER_BASE = 0x100
STATE_BASE = 0x140
HEARTBEAT_BASE = 0x700
STATE_DONE_BASE = 0x780
CMD_DONE_BASE = 0x7C0

#: SYNC tick value that ends a simulation (every node shuts down cleanly on it).
SYNC_END_TICK = 0xFFFFFFFF

PLANT = "PLANT"


def ecu_name(car: int) -> str:
    """DBC node name of car ``car`` (1-based)."""
    return f"ECU{car}"


@dataclass(frozen=True)
class SignalSpec:
    """One signal: little-endian bit field ``[start, start+length)``; physical = raw*scale + offset."""

    name: str
    start: int
    length: int
    signed: bool = False
    scale: float = 1.0
    offset: float = 0.0
    minimum: float | None = None
    maximum: float | None = None
    unit: str | None = None
    comment: str | None = None


# E2E fields (AUTOSAR E2E profile 1 style: CRC in byte 0, counter in the low nibble of byte 1).
_CRC = SignalSpec("CRC", 0, 8, comment="CRC-8 SAE J1850 over data ID (= frame id, low byte first) and bytes 1..")
_COUNTER = SignalSpec("Counter", 8, 4, minimum=0, maximum=14, comment="alive counter 0..14, +1 per control period")
_SPEED = dict(length=20, scale=1e-4, minimum=0.0, maximum=104.8575, unit="m/s")
_POSITION = dict(length=32, scale=1e-4, offset=-10000.0, minimum=-10000.0, maximum=419496.7295, unit="m")


def _layout(n_cars: int) -> list[tuple[int, str, int, str, list[str], list[SignalSpec], str, int | None]]:
    """(frame id, name, dlc, sender, receivers, signals, comment, cycle ms) for every message."""
    ecus = [ecu_name(c) for c in range(1, n_cars + 1)]
    msgs: list[tuple[int, str, int, str, list[str], list[SignalSpec], str, int | None]] = [
        (SYNC_ID, "SYNC", 4, PLANT, ecus, [
            SignalSpec("Tick", 0, 32, unit="tick",
                       comment=f"control period counter k; {SYNC_END_TICK:#x} ends the simulation"),
        ], "Starts control period k (plant is the time master).", None),
        (REFERENCE_ID, "REFERENCE", 5, PLANT, ecus, [
            SignalSpec("RefSpeed", 0, **_SPEED, comment="reference speed v*(t_k)"),  # type: ignore[arg-type]
            SignalSpec("RefDecel", 20, 16, signed=True, scale=1e-4, minimum=-3.2768, maximum=3.2767,
                       unit="m/s^2", comment="reference deceleration a* (positive slows down)"),
        ], "Braking reference of the virtual leader.", None),
    ]
    for c in range(1, n_cars + 1):
        ecu = ecu_name(c)
        msgs += [
            (BRAKE_CMD_BASE + c, f"BRAKE_CMD_C{c}", 5, ecu, [PLANT], [
                _CRC, _COUNTER,
                SignalSpec("Status", 12, 4, minimum=0, maximum=15,
                           comment="0 normal, 1 degraded (stale peers), 2 fail-safe"),
                SignalSpec("BrakeForce", 16, 24, signed=True, scale=10.0, minimum=-83886080, maximum=83886070,
                           unit="N", comment="demanded braking force; positive decelerates, negative is traction"),
            ], f"Brake command of car {c}.", None),
            (SENSOR_BASE + c, f"SENSOR_C{c}", 7, PLANT, [ecu], [
                SignalSpec("Speed", 0, **_SPEED, comment="measured speed of the car"),  # type: ignore[arg-type]
                SignalSpec("Position", 20, **_POSITION, comment="measured position along the track"),  # type: ignore[arg-type]
            ], f"Local speed/position sensors of car {c} (plant I/O).", None),
            (COUPLER_BASE + c, f"COUPLER_C{c}", 4, PLANT, [ecu], [
                SignalSpec("DeflFront", 0, 16, signed=True, scale=5e-5, minimum=-1.6384, maximum=1.63835, unit="m",
                           comment="deflection of the coupler to the car ahead (0 if none)"),
                SignalSpec("DeflRear", 16, 16, signed=True, scale=5e-5, minimum=-1.6384, maximum=1.63835, unit="m",
                           comment="deflection of the coupler to the car behind (0 if none)"),
            ], f"Local coupler deflection sensors of car {c} (plant I/O, optional).", None),
            (STATE_BASE + c, f"STATE_C{c}", 8, ecu, [e for e in ecus if e != ecu], [
                _CRC, _COUNTER,
                SignalSpec("Speed", 12, **_SPEED, comment="speed of the car as its ECU measured it"),  # type: ignore[arg-type]
                SignalSpec("Position", 32, **_POSITION, comment="position of the car as its ECU measured it"),  # type: ignore[arg-type]
            ], f"State of car {c}, broadcast to every other car.", None),
            (HEARTBEAT_BASE + c, f"HEARTBEAT_C{c}", 1, ecu, [PLANT], [
                SignalSpec("NodeState", 0, 8, comment="CANopen NMT state: 0 boot, 4 stopped, 5 operational, 127 pre-op"),
            ], f"Heartbeat of ECU {c}.", 100),
            (STATE_DONE_BASE + c, f"STATE_DONE_C{c}", 2, ecu, [e for e in ecus if e != ecu], [
                SignalSpec("Tick", 0, 16, unit="tick", comment="low 16 bits of k"),
            ], f"Simulation control (lockstep barrier): ECU {c} has sent all state-phase frames of tick k.", None),
            (CMD_DONE_BASE + c, f"CMD_DONE_C{c}", 2, ecu, [PLANT], [
                SignalSpec("Tick", 0, 16, unit="tick", comment="low 16 bits of k"),
            ], f"Simulation control (lockstep barrier): ECU {c} has sent all command-phase frames of tick k.", None),
        ]
    msgs.append((HEARTBEAT_BASE, "HEARTBEAT_PLANT", 1, PLANT, ecus, [
        SignalSpec("NodeState", 0, 8, comment="CANopen NMT state: 0 boot, 4 stopped, 5 operational, 127 pre-op"),
    ], "Heartbeat of the plant.", 100))
    return sorted(msgs, key=lambda m: m[0])


def build_database(n_cars: int) -> Database:
    """Build the cantools database for a train of ``n_cars`` (1..63)."""
    if not 1 <= n_cars <= MAX_CARS:
        raise ValueError(f"n_cars must be between 1 and {MAX_CARS}, got {n_cars}")
    messages = []
    for frame_id, name, dlc, sender, receivers, specs, comment, cycle in _layout(n_cars):
        signals = [
            Signal(
                name=s.name, start=s.start, length=s.length, byte_order="little_endian", is_signed=s.signed,
                conversion=BaseConversion.factory(scale=s.scale, offset=s.offset),
                minimum=s.minimum, maximum=s.maximum, unit=s.unit, comment=s.comment, receivers=list(receivers),
            )
            for s in specs
        ]
        messages.append(Message(frame_id=frame_id, name=name, length=dlc, signals=signals, comment=comment,
                                senders=[sender], cycle_time=cycle, is_extended_frame=False))
    nodes = [Node(PLANT, comment="train plant simulator (time master)")]
    nodes += [Node(ecu_name(c), comment=f"brake ECU of car {c}") for c in range(1, n_cars + 1)]
    return Database(messages=messages, nodes=nodes, version=f"canbrake-{n_cars}cars")


def dbc_text(n_cars: int) -> str:
    """DBC file text of :func:`build_database` (deterministic)."""
    return build_database(n_cars).as_dbc_string()


def write_dbc(n_cars: int, path: str | Path) -> Path:
    """Write the DBC for ``n_cars`` to ``path``."""
    p = Path(path)
    p.write_text(dbc_text(n_cars))
    return p


def load_dbc(path: str | Path) -> Database:
    """Load a DBC with cantools."""
    return cantools.database.load_file(str(path))


def n_cars_of(db: Database) -> int:
    """Number of cars a canbrake database describes (count of STATE_C* messages)."""
    return sum(1 for m in db.messages if m.name.startswith("STATE_C"))
