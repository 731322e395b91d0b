"""The canbrake CAN database: message layout, identifiers, and DBC generation with cantools.

One database describes a train of ``n_cars`` carriages (1..63). Identifiers are 11-bit
standard and encode priority (lower wins arbitration)::

    0x010        SYNC            plant -> all     tick counter, starts control period k
    0x011        REFERENCE       plant -> all     v*(t_k), a*
    0x080 + i    BRAKE_CMD_Ci    ECU i -> plant   demanded braking force (E2E protected)
    0x0C0 + i    SENSOR_Ci       plant -> ECU i   measured speed and position of car i
    0x100 + i    COUPLER_Ci      plant -> ECU i   measured coupler deflections (optional sensor)
    0x140 + i    STATE_Ci        ECU i -> all     speed and position broadcast (E2E protected)
    0x180 + i    STATE_AUTH_Ci   ECU i -> all     with ``security:`` only: SecOC authenticator of STATE_Ci
    0x700        HEARTBEAT_PLANT plant            node state (CANopen-style heartbeat ids)
    0x700 + i    HEARTBEAT_Ci    ECU i            node state
    0x780 + i    STATE_DONE_Ci   ECU i            simulation control: state phase of tick done
    0x7C0 + i    CMD_DONE_Ci     ECU i            simulation control: command phase of tick done

SYNC and brake commands rank above state frames, which rank above diagnostics, as the
architecture asks. SENSOR/COUPLER frames stand in for each car's local sensor wiring; the
*_DONE frames exist only to make lockstep runs deterministic and are exempt from impairment
(see docs/architecture.md).

All generated signals are little-endian (Intel) so a frame is one little-endian integer; that
is what lets :mod:`canbrake.bus.codec` encode without cantools on the hot path. A user's own DBC
(:mod:`canbrake.bus.userdbc`) may move mapped roles onto Motorola signals, 29-bit identifiers and
multiplexer pages; the identifiers above are then read from the layout (``BusLayout.sync_id``, ...).

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
#: data bytes of SYNC (the 32-bit tick): the one frame every control period carries
SYNC_DLC = 4
REFERENCE_ID = 0x011
REFERENCE_POS_ID = 0x012
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
    choices: tuple[tuple[int, str], ...] | None = None  # value table (VAL_ in the DBC)
    #: a user's DBC (canbrake.bus.userdbc): Motorola fields ("big_endian", start = the MSB as in
    #: the DBC) and one page of a multiplexed message (this field's page, or its multiplexer)
    byte_order: str = "little_endian"
    multiplexer_ids: tuple[int, ...] | None = None
    is_multiplexer: bool = False


# ------------------------------------------------------------------------------------ placement
@dataclass(frozen=True)
class EcuSpec:
    """One ECU of the placement, as the bus sees it.

    ``index``: 1-based position in the identifier plan; ``vehicle``: 1-based vehicle it sits on;
    ``sensors`` / ``commands`` / ``broadcast``: signal names (:mod:`canbrake.bus.signals`) of its
    SENSOR frames (from the plant), command frames (to the plant) and STATE frames (to peers);
    ``listeners``: indices of the ECUs that listen to its STATE frames.
    """

    name: str
    index: int
    vehicle: int
    sensors: tuple[str, ...] = ("speed_mps", "position_m")
    commands: tuple[str, ...] = ("brake_force_n",)
    broadcast: tuple[str, ...] = ("speed_mps", "position_m")
    listeners: tuple[int, ...] = ()
    listens: tuple[int, ...] = ()

    @property
    def tag(self) -> str:
        """Suffix of its message names: ``C3`` for the default ``ecu3`` on vehicle 3, else the name."""
        if self.name == f"ecu{self.vehicle}" and self.index == self.vehicle:
            return f"C{self.vehicle}"
        return self.name.upper()

    @property
    def dbc_node(self) -> str:
        return ecu_name(self.vehicle) if self.tag.startswith("C") and self.tag[1:].isdigit() else self.name.upper()


def default_ecus(n_cars: int, coupler_sensors: bool = False) -> list[EcuSpec]:
    """Chen's placement: one ECU per car, each broadcasting speed and position to every other."""
    sensors = ("speed_mps", "position_m") + (("deflection_front_m", "deflection_rear_m") if coupler_sensors else ())
    return [EcuSpec(f"ecu{c}", c, c, sensors=sensors,
                    listeners=tuple(j for j in range(1, n_cars + 1) if j != c),
                    listens=tuple(j for j in range(1, n_cars + 1) if j != c))
            for c in range(1, n_cars + 1)]


#: frame kinds of the identifier plan, highest priority first; "state_auth" (the SecOC
#: authenticator of each STATE page, canbrake.bus.secoc) exists only in secured layouts
KINDS = ("cmd", "sensor", "state", "state_auth")
#: 11-bit plan with 64-id blocks (up to 63 ECUs): base of (kind, page); page 2 of "sensor" is
#: 0x100 (COUPLER_C* in the original six-car layout)
_PLAN64 = {("cmd", 1): BRAKE_CMD_BASE, ("sensor", 1): SENSOR_BASE, ("sensor", 2): COUPLER_BASE,
           ("state", 1): STATE_BASE}
_FREE64 = [0x180 + 0x40 * i for i in range((0x700 - 0x180) // 0x40)]
#: 11-bit plan with 128-id blocks (64..127 ECUs)
_FREE128 = [0x080 + 0x80 * i for i in range((0x600 - 0x080) // 0x80)]
MAX_ECUS_11BIT = 127
MAX_ECUS = 4095


class IdPlan:
    """Frame identifiers of a run (priority = numeric order, lower wins arbitration).

    Up to 63 ECUs: the original 11-bit layout with 64-id blocks (see the module docstring);
    up to 127 ECUs: 11-bit, 128-id blocks — command pages first, then sensor, then state pages,
    from 0x080, barrier frames at 0x600/0x680 + i, heartbeats at 0x700 + i (CANopen);
    beyond: 29-bit identifiers ``kind << 24 | page << 16 | index`` (kind 1 command, 2 sensor,
    3 state, 4 state authenticator, 0x18 heartbeat, 0x1E state done, 0x1F command done), so
    commands still win. Secured layouts (``security:``) add a "state_auth" block per state page,
    allocated right after the state pages of the same page number (11-bit plans: the first free
    block, 0x180 + i for page 1 with up to 63 ECUs); unsecured layouts are unchanged.
    SYNC 0x010, REFERENCE 0x011, REFERENCE_POS 0x012 and HEARTBEAT_PLANT 0x700 in every plan.
    """

    def __init__(self, n_ecus: int, pages: dict[str, int]) -> None:
        if not 1 <= n_ecus <= MAX_ECUS:
            raise ValueError(f"between 1 and {MAX_ECUS} ECUs, got {n_ecus}")
        self.n = n_ecus
        self.extended = n_ecus > MAX_ECUS_11BIT
        self._base: dict[tuple[str, int], int] = {}
        if self.extended:
            return
        if n_ecus <= MAX_CARS:
            self._base.update(_PLAN64)
            free = list(_FREE64)
        else:
            free = list(_FREE128)
        order = [(k, p) for p in range(1, 9) for k in KINDS if p <= pages.get(k, 0 if k == "state_auth" else 1)]
        for key in order:
            if key in self._base:
                continue
            if not free:
                raise ValueError(f"{n_ecus} ECUs with {pages} frame pages do not fit the 11-bit plan")
            self._base[key] = free.pop(0)
        self.state_done_base = STATE_DONE_BASE if n_ecus <= MAX_CARS else 0x600
        self.cmd_done_base = CMD_DONE_BASE if n_ecus <= MAX_CARS else 0x680

    def frame(self, kind: str, index: int, page: int = 1) -> int:
        if self.extended:
            code = {"cmd": 1, "sensor": 2, "state": 3, "state_auth": 4}[kind]
            return (code << 24) | (page << 16) | index
        return self._base[(kind, page)] + index

    def heartbeat(self, index: int) -> int:
        return (0x18 << 24) | index if self.extended else HEARTBEAT_BASE + index

    def state_done(self, index: int) -> int:
        return (0x1E << 24) | index if self.extended else self.state_done_base + index

    def cmd_done(self, index: int) -> int:
        return (0x1F << 24) | index if self.extended else self.cmd_done_base + index


_CRC = SignalSpec("CRC", 0, 8, comment="CRC-8 SAE J1850 over data ID (= frame id, low byte first) and bytes 1..")
_COUNTER = SignalSpec("Counter", 8, 4, minimum=0, maximum=14, comment="alive counter 0..14, +1 per control period")
_STATUS = SignalSpec("Status", 12, 4, minimum=0, maximum=15, comment="0 normal, 1 degraded (stale peers), 2 fail-safe",
                     choices=((0, "normal"), (1, "degraded"), (2, "fail_safe")))
#: most bits of the counter extension (the spare bits of a protected frame's last byte)
COUNTER_EXT_MAX_BITS = 7


def _with_counter_ext(pages: list[list[tuple[str, SignalSpec]]]) -> list[list[tuple[str, SignalSpec]]]:
    """Give each protected page whose last byte has spare bits a ``CounterExt`` field there: the
    alive counter then counts tick mod 15·2^m (low nibble: tick mod 15 as before, CounterExt:
    floor(tick / 15) mod 2^m), so it aliases after 15·2^m periods instead of 15. The frame's
    length is unchanged (canbrake.bus.e2e.counter_modulus)."""
    out = []
    for sigs in pages:
        used = max(s.start + s.length for _, s in sigs)
        spare = min(-used % 8, COUNTER_EXT_MAX_BITS)
        if spare:
            sigs = sigs + [("", SignalSpec(
                "CounterExt", used, spare, minimum=0, maximum=(1 << spare) - 1,
                comment=f"alive counter extension: floor(tick / 15) mod {1 << spare}; with Counter the "
                        f"sender's tick mod {15 << spare} (aliases after {15 << spare} periods)"))]
        out.append(sigs)
    return out


_NMT = "CANopen NMT state: 0 boot, 4 stopped, 5 operational, 127 pre-op"
_NMT_CHOICES = ((0, "boot"), (4, "stopped"), (5, "operational"), (127, "pre_operational"))


def _state_auth_signals(state: str) -> list[tuple[str, SignalSpec]]:
    """Signals of the authenticator frame of state page ``state`` (layout: canbrake.bus.secoc)."""
    return [("", SignalSpec("CRC", 0, 8, comment="CRC-8 SAE J1850 over data ID (= this frame's id, low byte "
                                                 "first) and bytes 1..7 (computed after the MAC)")),
            ("", SignalSpec("FreshnessTick", 8, 32, unit="tick",
                            comment=f"the sender's tick k when it sent {state} (the full 32-bit freshness "
                                    f"counter; no aliasing within 2^32 periods)")),
            ("", SignalSpec("MAC", 40, 24, minimum=0, maximum=(1 << 24) - 1,
                            comment=f"SecOC: first 24 bits of AES-128-CMAC over {state}'s data ID (LE16) | "
                                    f"freshness (session BE32, FreshnessTick BE32) | {state} bytes 1..DLC-1; "
                                    f"bytes in MAC order"))]


def _num(x: float | None) -> float | int | None:
    """Integral limits as ints (the DBC then prints 10, not 10.0)."""
    return int(x) if x is not None and float(x).is_integer() else x


def _pack(names: tuple[str, ...], first_bit: int, header: list[SignalSpec], what: str) -> list[list[tuple[str, SignalSpec]]]:
    """Pack signals in order into 64-bit pages, each starting with ``header`` then bit ``first_bit``."""
    from canbrake.bus.signals import signal_format

    pages: list[list[tuple[str, SignalSpec]]] = []
    cur: list[tuple[str, SignalSpec]] = [("", h) for h in header]
    bit = first_bit
    for name in names:
        try:
            f = signal_format(name)
        except KeyError as e:
            raise ValueError(f"{what}: {e.args[0]}") from None
        if bit + f.length > 64:
            pages.append(cur)
            cur, bit = [("", h) for h in header], first_bit
        cur.append((name, SignalSpec(f.dbc_name, bit, f.length, f.signed, f.scale, f.offset, _num(f.minimum),
                                     _num(f.maximum), f.unit, f.comment)))
        bit += f.length
    if len(cur) > len(header) or not pages:
        pages.append(cur)
    return pages


@dataclass(frozen=True)
class MessageSpec:
    """One message of the layout. ``signals``: (signal name or "" for protocol fields, spec)."""

    frame_id: int
    name: str
    length: int
    sender: str
    receivers: tuple[str, ...]
    signals: tuple[tuple[str, SignalSpec], ...]
    comment: str
    cycle_ms: int | None
    extended: bool
    kind: str           # sync, reference, reference_pos, cmd, sensor, state, heartbeat, state_done, cmd_done
    ecu: int = 0        # ECU index (0: plant)
    page: int = 1


class BusLayout:
    """Every message of a run, derived from the placement (``ecus``) — the DBC's source.

    ``period_ms``: the control period, written as ``GenMsgCycleTime`` of the periodic messages;
    ``ref_position``: send REFERENCE_POS (x*) for controllers that need it; ``secured``: add a
    STATE_AUTH message per STATE page (``security:``, layout in :mod:`canbrake.bus.secoc`).
    """

    def __init__(self, ecus: list[EcuSpec], *, period_ms: float = 1.0, ref_position: bool = False,
                 heartbeat_ms: int = 100, secured: bool = False) -> None:
        self.ecus = list(ecus)
        self.by_index = {e.index: e for e in self.ecus}
        n = len(self.ecus)
        sens = {e.index: _pack(e.sensors, 0, [], f"ECU {e.name} sensors") for e in self.ecus}
        cmds = {e.index: _with_counter_ext(_pack(e.commands, 16, [_CRC, _COUNTER, _STATUS], f"ECU {e.name} commands"))
                for e in self.ecus}
        states = {e.index: (_with_counter_ext(_pack(e.broadcast, 12, [_CRC, _COUNTER], f"ECU {e.name} broadcast"))
                            if e.listeners and e.broadcast else []) for e in self.ecus}
        pages = {"sensor": max(len(v) for v in sens.values()), "cmd": max(len(v) for v in cmds.values()),
                 "state": max([len(v) for v in states.values()] + [1])}
        if secured:
            pages["state_auth"] = pages["state"]
        self.secured = secured
        self.plan = IdPlan(n, pages)
        ext = self.plan.extended
        cyc = max(1, int(round(period_ms)))
        names = [e.dbc_node for e in self.ecus]
        msgs: list[MessageSpec] = [
            MessageSpec(SYNC_ID, "SYNC", SYNC_DLC, PLANT, tuple(names), (("", SignalSpec(
                "Tick", 0, 32, unit="tick", comment=f"control period counter k; {SYNC_END_TICK:#x} ends the simulation")),),
                "Starts control period k (plant is the time master).", cyc, False, "sync"),
            MessageSpec(REFERENCE_ID, "REFERENCE", 5, PLANT, tuple(names), (
                ("ref_speed_mps", SignalSpec("RefSpeed", 0, 20, scale=1e-4, minimum=0.0, maximum=104.8575, unit="m/s",
                                             comment="reference speed v*(t_k)")),
                ("ref_decel_mps2", SignalSpec("RefDecel", 20, 20, signed=True, scale=1e-5, minimum=-5.24288,
                                              maximum=5.24287, unit="m/s^2",
                                              comment="reference deceleration a* (positive slows down)"))),
                "Braking reference of the virtual leader.", cyc, False, "reference"),
            MessageSpec(HEARTBEAT_BASE, "HEARTBEAT_PLANT", 1, PLANT, tuple(names),
                        (("", SignalSpec("NodeState", 0, 8, comment=_NMT, choices=_NMT_CHOICES)),), "Heartbeat of the plant.",
                        heartbeat_ms, False, "heartbeat"),
        ]
        self.ref_position = ref_position
        if ref_position:
            msgs.append(MessageSpec(REFERENCE_POS_ID, "REFERENCE_POS", 5, PLANT, tuple(names), (
                ("ref_position_m", SignalSpec("RefPosition", 0, 40, signed=True, scale=1e-5, minimum=-5497558.13888,
                                              maximum=5497558.13887, unit="m", comment="reference position x*(t_k)")),),
                "Reference position of the virtual leader.", cyc, False, "reference_pos"))
        for e in self.ecus:
            node, tag = e.dbc_node, e.tag
            peers = tuple(self.by_index[j].dbc_node for j in e.listeners)
            for p, sigs in enumerate(cmds[e.index], start=1):
                msgs.append(self._msg(self.plan.frame("cmd", e.index, p), f"BRAKE_CMD_{tag}", p, sigs, 16, node,
                                      (PLANT,), f"Commands of ECU {e.name} (vehicle {e.vehicle}).", cyc, ext, "cmd", e.index))
            for p, sigs in enumerate(sens[e.index], start=1):
                name = (f"COUPLER_{tag}" if p == 2 and not ext and n <= MAX_CARS and
                        [s for s, _ in sigs] == ["deflection_front_m", "deflection_rear_m"] else f"SENSOR_{tag}")
                msgs.append(self._msg(self.plan.frame("sensor", e.index, p), name, 1 if name.startswith("COUPLER") else p,
                                      sigs, 0, PLANT, (node,),
                                      f"Local sensors of vehicle {e.vehicle} for ECU {e.name} (plant I/O).", cyc, ext,
                                      "sensor", e.index, page_no=p))
            for p, sigs in enumerate(states[e.index], start=1):
                msgs.append(self._msg(self.plan.frame("state", e.index, p), f"STATE_{tag}", p, sigs, 12, node, peers,
                                      f"State of ECU {e.name} (vehicle {e.vehicle}), broadcast to its listeners.",
                                      cyc, ext, "state", e.index))
                if secured:
                    msgs.append(self._msg(self.plan.frame("state_auth", e.index, p), f"STATE_AUTH_{tag}", p,
                                          _state_auth_signals(f"STATE_{tag}" + ("" if p == 1 else f"_P{p}")), 64,
                                          node, peers, f"SecOC authenticator of STATE_{tag}"
                                          + ("" if p == 1 else f"_P{p}") + " (sent right after it).", cyc, ext,
                                          "state_auth", e.index))
            msgs.append(MessageSpec(self.plan.heartbeat(e.index), f"HEARTBEAT_{tag}", 1, node, (PLANT,),
                                    (("", SignalSpec("NodeState", 0, 8, comment=_NMT, choices=_NMT_CHOICES)),),
                                    f"Heartbeat of ECU {e.name}.", heartbeat_ms, ext, "heartbeat", e.index))
            tick = (("", SignalSpec("Tick", 0, 16, unit="tick", comment="low 16 bits of k")),)
            if states[e.index]:  # only an ECU that broadcasts to listeners closes a state phase
                msgs.append(MessageSpec(self.plan.state_done(e.index), f"STATE_DONE_{tag}", 2, node, peers,
                                        tick, f"Simulation control (lockstep barrier): ECU {e.name} has sent all "
                                              f"state-phase frames of tick k.", None, ext, "state_done", e.index))
            msgs.append(MessageSpec(self.plan.cmd_done(e.index), f"CMD_DONE_{tag}", 2, node, (PLANT,), tick,
                                    f"Simulation control (lockstep barrier): ECU {e.name} has sent all "
                                    f"command-phase frames of tick k.", None, ext, "cmd_done", e.index))
        self.messages = sorted(msgs, key=lambda m: (m.frame_id, m.name))
        #: identifiers of the plant's frames the nodes address directly (a user's DBC moves them)
        self.sync_id, self.reference_id, self.reference_pos_id = SYNC_ID, REFERENCE_ID, REFERENCE_POS_ID
        self.plant_heartbeat_id = HEARTBEAT_BASE
        self.by_id = {m.frame_id: m for m in self.messages}
        self.by_name = {m.name: m for m in self.messages}
        if len(self.by_id) != len(self.messages) or len(self.by_name) != len(self.messages):
            raise ValueError("ECU names give two messages the same name or identifier")

    @staticmethod
    def _msg(fid: int, base: str, page: int, sigs: list[tuple[str, SignalSpec]], first_bit: int, sender: str,
             receivers: tuple[str, ...], comment: str, cyc: int, ext: bool, kind: str, ecu: int,
             page_no: int | None = None) -> MessageSpec:
        bits = max([first_bit] + [s.start + s.length for _, s in sigs])
        return MessageSpec(fid, base if page == 1 else f"{base}_P{page}", (bits + 7) // 8, sender, receivers,
                           tuple(sigs), comment, cyc, ext, kind, ecu, page_no or page)

    def counter_ext(self) -> dict[int, tuple[int, int]]:
        """Protected frames with a counter extension: frame id -> (start bit, bits)."""
        return {m.frame_id: (s.start, s.length) for m in self.messages for _, s in m.signals if s.name == "CounterExt"}

    def ids(self, kind: str, ecu: int | None = None) -> list[int]:
        """Frame ids of ``kind`` (of one ECU index, or all), in page order."""
        return [m.frame_id for m in self.messages if m.kind == kind and (ecu is None or m.ecu == ecu)]

    def database(self) -> Database:
        """The cantools database of this layout."""
        messages = []
        for m in self.messages:
            mux = next((s.name for _, s in m.signals if s.is_multiplexer), None)
            signals = [Signal(name=s.name, start=s.start, length=s.length, byte_order=s.byte_order,
                              is_signed=s.signed, conversion=BaseConversion.factory(
                                  scale=s.scale, offset=s.offset, choices=dict(s.choices) if s.choices else None),
                              minimum=s.minimum, maximum=s.maximum, unit=s.unit, comment=s.comment,
                              receivers=list(m.receivers), is_multiplexer=s.is_multiplexer,
                              multiplexer_ids=list(s.multiplexer_ids) if s.multiplexer_ids else None,
                              multiplexer_signal=mux if s.multiplexer_ids else None)
                       for _, s in m.signals]
            messages.append(Message(frame_id=m.frame_id, name=m.name, length=m.length, signals=signals,
                                    comment=m.comment, senders=[m.sender], cycle_time=m.cycle_ms,
                                    is_extended_frame=m.extended))
        nodes = [Node(PLANT, comment="train plant simulator (time master)")]
        nodes += [Node(e.dbc_node, comment=f"ECU {e.name} on vehicle {e.vehicle}") for e in self.ecus]
        return Database(messages=messages, nodes=nodes, version=f"canbrake-{len(self.ecus)}ecus")


def build_database(n_cars: int) -> Database:
    """The cantools database of Chen's default placement for ``n_cars`` (1..63): a shortcut."""
    if not 1 <= n_cars <= MAX_CARS:
        raise ValueError(f"n_cars must be between 1 and {MAX_CARS}, got {n_cars}")
    return BusLayout(default_ecus(n_cars, coupler_sensors=True)).database()


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
    """Number of ECUs a canbrake database describes (count of CMD_DONE_* messages; one per ECU,
    which is one per car in Chen's layout)."""
    return sum(1 for m in db.messages if m.name.startswith("CMD_DONE_"))
