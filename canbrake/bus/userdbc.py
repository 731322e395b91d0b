"""Run canbrake on the user's own DBC: map canbrake's roles onto the messages and signals of an
existing database (a supplier's), check the mapping, and build the run's layout from it.

canbrake's nodes speak in roles (SYNC, REFERENCE, each ECU's SENSOR / STATE / BRAKE_CMD pages,
heartbeats) and canbrake's own signal names. :func:`mapped_layout` keeps those names inside
the run but gives every mapped message the user's identifier (11- or 29-bit), length, byte
order, bit positions, scaling (with the unit converted: a speed in km/h, a force in kN) and
multiplexer page, so the frames on the bus are exactly the DBC's frames: cantools decodes them
with the user's file. Roles left unmapped keep canbrake's generated messages, and canbrake's
lockstep barrier frames (STATE_DONE/CMD_DONE) always keep canbrake's identifiers; both are
checked against every identifier of the user's DBC.

Rules (each violation is one :class:`~canbrake.errors.ScenarioError` line naming the file, the
message and the signal): the message and signal exist; a multiplexed message names its page; a
signal holds the physical range canbrake's own layout gives the role (bus/signals.py) at no
more than 100 times canbrake's resolution (integers: resolution 1); the E2E CRC is the 8 bits
of byte 0 and the alive counter the low nibble of byte 1 (AUTOSAR E2E profile 1's layout,
which canbrake's receivers check), and STATE/command pages have them; SYNC's tick is a 32-bit
unsigned Intel field at bit 0 (the lockstep protocol reads it there); a GenMsgCycleTime, where
given, equals the control period (heartbeats: the heartbeat period); no identifier is used by
two roles or clashes with a canbrake frame; no role, signal or DBC signal is mapped twice.
"""
from __future__ import annotations

import copy
import dataclasses
import math
from pathlib import Path
from typing import Any, Mapping

from cantools.database.can import Database, Message

from canbrake.bus.dbc import BusLayout, MessageSpec, SignalSpec
from canbrake.errors import ScenarioError

#: unit -> (dimension, factor): a value in this unit = factor x the value in the SI unit
UNITS: dict[str, tuple[str, float]] = {
    "m/s": ("speed", 1.0), "km/h": ("speed", 3.6), "kph": ("speed", 3.6), "kmh": ("speed", 3.6),
    "m": ("length", 1.0), "mm": ("length", 1000.0), "cm": ("length", 100.0), "km": ("length", 1e-3),
    "N": ("force", 1.0), "kN": ("force", 1e-3), "daN": ("force", 0.1),
    "m/s^2": ("accel", 1.0), "m/s2": ("accel", 1.0), "m/s²": ("accel", 1.0), "km/h/s": ("accel", 3.6),
    "Pa": ("pressure", 1.0), "kPa": ("pressure", 1e-3), "bar": ("pressure", 1e-5),
    "rad/s": ("angular speed", 1.0), "rpm": ("angular speed", 60.0 / (2.0 * math.pi)),
    "N.m": ("torque", 1.0), "Nm": ("torque", 1.0), "kN.m": ("torque", 1e-3), "kNm": ("torque", 1e-3),
}
#: most times canbrake's own resolution a mapped signal may be coarser by
MAX_COARSER = 100.0
#: roles with one message per ECU or per train: key in the mapping -> message kind of the layout
ECU_ROLES = {"sensors": "sensor", "state": "state", "commands": "cmd"}
#: the plant's roles: key -> (kind, {mapping signal key: canbrake signal name in the layout})
PLANT_ROLES = {"sync": ("sync", {"tick": "Tick"}),
               "reference": ("reference", {"ref_speed_mps": "RefSpeed", "ref_decel_mps2": "RefDecel"}),
               "reference_position": ("reference_pos", {"ref_position_m": "RefPosition"}),
               "plant_heartbeat": ("heartbeat", {"node_state": "NodeState"})}
#: physical ranges of canbrake's fields that have none in its layout (what canbrake puts there)
_FIELD_RANGES = {"NodeState": (0.0, 127.0), "Status": (0.0, 2.0), "Counter": (0.0, 14.0)}


class _MappedPlan:
    """The identifier plan of a mapped layout: canbrake's, with the mapped heartbeats' ids."""

    def __init__(self, base: Any, heartbeats: dict[int, int], extended: bool) -> None:
        self._base, self._hb, self.extended = base, heartbeats, extended
        self.n = base.n

    def frame(self, kind: str, index: int, page: int = 1) -> int:
        return self._base.frame(kind, index, page)

    def heartbeat(self, index: int) -> int:
        return self._hb.get(index, self._base.heartbeat(index))

    def state_done(self, index: int) -> int:
        return self._base.state_done(index)

    def cmd_done(self, index: int) -> int:
        return self._base.cmd_done(index)


def load_user_dbc(path: Path) -> Database:
    """The user's DBC (cantools, not strict about overlapping signals of other pages), or a
    one-line ScenarioError."""
    import cantools

    try:
        return cantools.database.load_file(str(path), strict=False)
    except FileNotFoundError:
        raise ScenarioError(f"bus.dbc.file: {path}: no such DBC file") from None
    except Exception as e:  # cantools raises several parse error types
        first = str(e).splitlines()[0] if str(e) else type(e).__name__
        raise ScenarioError(f"bus.dbc.file: {path}: not a readable DBC file: {first}") from None


class _Ctx:
    def __init__(self, path: Path, db: Database, period_ms: float, heartbeat_ms: float) -> None:
        self.path, self.db = path, db
        self.period_ms, self.heartbeat_ms = period_ms, heartbeat_ms
        self.by_name = {m.name: m for m in db.messages}
        self.used_signals: dict[tuple[str, str], str] = {}   # (message, DBC signal) -> role
        self.used_pages: dict[tuple[str, int | None], str] = {}  # (message, mux) -> role

    def fail(self, what: str) -> ScenarioError:
        return ScenarioError(f"{self.path}: {what}")


def _msg_label(m: Message) -> str:
    return f"message {m.name} ({m.frame_id:#x})"


def _unit_factor(ctx: _Ctx, m: Message, s: Any, si_unit: str | None) -> float:
    """user value = factor x SI value, from the DBC signal's unit (none given: canbrake's unit)."""
    if not s.unit or si_unit is None or s.unit == si_unit or si_unit not in UNITS:
        return 1.0  # no unit, canbrake's own, or a count (tick): as it is
    dim_si = UNITS.get(si_unit, (si_unit, 1.0))
    got = UNITS.get(s.unit.strip())
    if got is None or got[0] != dim_si[0]:
        raise ctx.fail(f"{_msg_label(m)} signal {s.name}: unit {s.unit!r} is not a unit of {si_unit} "
                       f"(known: {', '.join(u for u, (d, _f) in UNITS.items() if d == dim_si[0])})")
    return got[1] / dim_si[1]


def _check_range(ctx: _Ctx, m: Message, s: Any, spec: SignalSpec, k: float, role: str) -> None:
    """The DBC signal holds the physical range and resolution canbrake's layout gives ``spec``."""
    lo_raw, hi_raw = ((-(1 << (s.length - 1)), (1 << (s.length - 1)) - 1) if s.is_signed
                      else (0, (1 << s.length) - 1))
    ends = sorted((lo_raw * s.scale + s.offset, hi_raw * s.scale + s.offset))
    if s.minimum is not None:
        ends[0] = max(ends[0], s.minimum)
    if s.maximum is not None:
        ends[1] = min(ends[1], s.maximum)
    need = _FIELD_RANGES.get(spec.name)
    if need is None:
        lo = spec.minimum if spec.minimum is not None else spec.offset
        hi = spec.maximum if spec.maximum is not None else ((1 << spec.length) - 1) * spec.scale + spec.offset
        need = (lo, hi)
    lo_u, hi_u = need[0] * k, need[1] * k
    tol = 1e-9 * max(abs(lo_u), abs(hi_u), 1.0)
    unit = s.unit or spec.unit or ""
    if ends[0] > lo_u + tol or ends[1] < hi_u - tol:
        raise ctx.fail(f"{_msg_label(m)} signal {s.name}: range [{ends[0]:g}, {ends[1]:g}] {unit} cannot hold "
                       f"canbrake's {role} [{lo_u:g}, {hi_u:g}] {unit}".replace("  ", " "))
    integer = spec.scale == 1.0 and spec.offset == 0.0
    if integer:
        if s.scale != 1 or float(s.offset) != int(s.offset) or k != 1.0:
            raise ctx.fail(f"{_msg_label(m)} signal {s.name}: scale {s.scale:g}, offset {s.offset:g} cannot hold "
                           f"canbrake's {role} (integers: scale 1 and an integral offset)")
    elif s.scale / k > MAX_COARSER * spec.scale * (1 + 1e-9):
        raise ctx.fail(f"{_msg_label(m)} signal {s.name}: resolution {s.scale:g} {unit} is more than "
                       f"{MAX_COARSER:g} times canbrake's for {role} ({spec.scale * k:g} {unit})".replace("  ", " "))


def _find(ctx: _Ctx, where: str, page: Mapping[str, Any]) -> tuple[Message, int | None]:
    name = page["message"]
    m = ctx.by_name.get(name)
    if m is None:
        raise ctx.fail(f"{where}: message {name} is missing (the DBC has "
                       f"{', '.join(sorted(ctx.by_name)[:6])}{', ...' if len(ctx.by_name) > 6 else ''})")
    mux = page.get("multiplexer")
    muxed = any(s.is_multiplexer for s in m.signals)
    if muxed and mux is None:
        pages = sorted({i for s in m.signals for i in (s.multiplexer_ids or ())})
        raise ctx.fail(f"{where}: {_msg_label(m)} is multiplexed: name its page with multiplexer: (one of {pages})")
    if not muxed and mux is not None:
        raise ctx.fail(f"{where}: {_msg_label(m)} is not multiplexed (multiplexer: {mux} given)")
    if muxed and not any(mux in (s.multiplexer_ids or ()) for s in m.signals):
        raise ctx.fail(f"{where}: {_msg_label(m)} has no multiplexer page {mux}")
    key = (m.name, mux)
    if key in ctx.used_pages:
        raise ctx.fail(f"{where}: {_msg_label(m)}" + ("" if mux is None else f" page {mux}")
                       + f" is mapped twice ({ctx.used_pages[key]} and {where})")
    ctx.used_pages[key] = where
    return m, mux


def _signal(ctx: _Ctx, where: str, m: Message, mux: int | None, name: str) -> Any:
    try:
        s = m.get_signal_by_name(name)
    except KeyError:
        raise ctx.fail(f"{where}: {_msg_label(m)} has no signal {name}") from None
    if s.multiplexer_ids and mux not in s.multiplexer_ids:
        raise ctx.fail(f"{where}: {_msg_label(m)} signal {name} is on multiplexer page "
                       f"{', '.join(map(str, s.multiplexer_ids))}, not {mux}")
    if s.is_multiplexer:
        raise ctx.fail(f"{where}: {_msg_label(m)} signal {name} is the multiplexer")
    if (m.name, name) in ctx.used_signals:
        raise ctx.fail(f"{where}: {_msg_label(m)} signal {name} is mapped twice "
                       f"({ctx.used_signals[(m.name, name)]} and {where})")
    ctx.used_signals[(m.name, name)] = where
    return s


def _check_cycle(ctx: _Ctx, where: str, m: Message, heartbeat: bool) -> None:
    want = ctx.heartbeat_ms if heartbeat else ctx.period_ms
    if m.cycle_time is not None and m.cycle_time > 0 and abs(m.cycle_time - want) > 1e-6 * want:
        what = "the heartbeat period" if heartbeat else "the control period"
        raise ctx.fail(f"{where}: {_msg_label(m)} has GenMsgCycleTime {m.cycle_time} ms; canbrake sends it every "
                       f"{want:g} ms ({what})")


def _e2e_field(ctx: _Ctx, where: str, m: Message, s: Any, role: str) -> None:
    """CRC: the 8 bits of byte 0; counter: bits 0-3 of byte 1 (profile 1's layout); unsigned raw."""
    big = s.byte_order == "big_endian"
    want = (7 if big else 0, 8) if role == "CRC" else (11 if big else 8, 4)
    if (s.start, s.length) != want or s.is_signed or s.scale != 1 or s.offset != 0:
        place = "the 8 bits of byte 0" if role == "CRC" else "the low 4 bits of byte 1"
        raise ctx.fail(f"{where}: {_msg_label(m)} signal {s.name}: canbrake's E2E check needs the "
                       f"{'CRC' if role == 'CRC' else 'alive counter'} as {place}, unsigned, scale 1 (AUTOSAR E2E "
                       f"profile 1 layout); it is {s.length} bits at bit {s.start}")


def _page(ctx: _Ctx, where: str, page: Mapping[str, Any], base: list[MessageSpec],
          wanted: dict[str, tuple[str, SignalSpec]], protected: bool, heartbeat: bool = False,
          ) -> tuple[Message, MessageSpec]:
    """One mapped page: the user's message with canbrake's names for the mapped signals.
    ``wanted``: mapping key -> (canbrake signal or "", canbrake's spec of it)."""
    m, mux = _find(ctx, where, page)
    _check_cycle(ctx, where, m, heartbeat)
    if m.is_extended_frame and m.frame_id <= 0x7FF:
        raise ctx.fail(f"{where}: {_msg_label(m)} is a 29-bit identifier at or below 0x7FF: canbrake tells "
                       f"11-bit and 29-bit frames apart by value")
    if m.is_fd or m.length > 8:
        raise ctx.fail(f"{where}: {_msg_label(m)} has {m.length} bytes: only classical CAN frames (<= 8 bytes)")
    sigs: list[tuple[str, SignalSpec]] = []
    fields = dict(page.get("signals") or {})
    for key in ("crc", "counter", "status"):
        if page.get(key):
            fields[key] = page[key]
    if protected and not (page.get("crc") and page.get("counter")):
        raise ctx.fail(f"{where}: {_msg_label(m)}: map the E2E crc: and counter: signals (canbrake's receivers "
                       f"check every STATE and command frame)")
    for key, dbc_sig in fields.items():
        if key not in wanted:
            raise ctx.fail(f"{where}: {_msg_label(m)}: {key} is not a signal of this role "
                           f"(expected {', '.join(k for k in wanted if k not in ('crc', 'counter', 'status'))})")
        sig, spec = wanted[key]
        s = _signal(ctx, where, m, mux, dbc_sig)
        if spec.name in ("CRC", "Counter"):
            _e2e_field(ctx, where, m, s, spec.name)
        if spec.name == "Tick" and (s.byte_order != "little_endian" or s.start != 0 or s.length != 32
                                    or s.is_signed or s.scale != 1 or s.offset != 0):
            raise ctx.fail(f"{where}: {_msg_label(m)} signal {s.name}: canbrake's lockstep reads the tick as a 32-bit "
                           f"unsigned Intel field at bit 0 (scale 1); it is {s.length} bits at bit {s.start}, "
                           f"{s.byte_order}")
        k = _unit_factor(ctx, m, s, spec.unit)
        label = f"{where} {key}" if not sig else sig
        _check_range(ctx, m, s, spec, k, label)
        sigs.append((sig, dataclasses.replace(
            spec, start=s.start, length=s.length, signed=s.is_signed, scale=float(s.scale) / k,
            offset=float(s.offset) / k, minimum=None, maximum=None,
            comment=f"{m.name}.{s.name} of {ctx.path.name}" + (f" ({s.unit})" if s.unit else ""),
            byte_order=s.byte_order, multiplexer_ids=tuple(s.multiplexer_ids) if s.multiplexer_ids else None)))
    if mux is not None:
        ms = next(s for s in m.signals if s.is_multiplexer)
        sigs.insert(0, ("", SignalSpec(ms.name, ms.start, ms.length, ms.is_signed, comment=f"multiplexer, page {mux}",
                                       byte_order=ms.byte_order, is_multiplexer=True)))
        if not any(sp.multiplexer_ids for _s, sp in sigs):
            raise ctx.fail(f"{where}: {_msg_label(m)}: no mapped signal is on multiplexer page {mux}")
    b = base[0]
    return m, dataclasses.replace(b, frame_id=m.frame_id, length=m.length, signals=tuple(sigs),
                                  comment=f"{b.comment} As {m.name} of {ctx.path.name}.",
                                  cycle_ms=b.cycle_ms, extended=m.is_extended_frame)


def mapped_layout(base: BusLayout, db: Database, path: Path, mapping: Mapping[str, Any], *,
                  period_ms: float, heartbeat_ms: float) -> BusLayout:
    """``base`` (canbrake's generated layout of the scenario) with the roles of ``mapping`` moved
    onto the messages of ``db`` (the user's DBC read from ``path``).

    ``mapping``: {"sync" | "reference" | "reference_position" | "plant_heartbeat": page,
    "ecus": {ECU name: {"sensors" | "state" | "commands": [page, ...], "heartbeat": page}}} with
    page = {"message", "multiplexer" (or None), "signals": {canbrake name: DBC signal},
    "crc", "counter", "status"}. Raises ScenarioError (one line) on any broken rule."""
    if base.secured:
        raise ScenarioError(f"{path}: bus.dbc: a mapping onto the user's DBC cannot be combined with security: yet")
    ctx = _Ctx(path, db, period_ms, heartbeat_ms)
    replaced: dict[int, tuple[Message, MessageSpec] | None] = {}   # id(base MessageSpec) -> new (None: dropped)
    extra: list[tuple[Message, MessageSpec, str]] = []   # pages beyond canbrake's own count
    roles_of: dict[int, str] = {}
    by_kind: dict[tuple[str, int], list[MessageSpec]] = {}
    for bm in base.messages:
        by_kind.setdefault((bm.kind, bm.ecu), []).append(bm)

    for key, (kind, fields) in PLANT_ROLES.items():
        page = mapping.get(key)
        if not page:
            continue
        bms = by_kind.get((kind, 0))
        if not bms:
            raise ScenarioError(f"{path}: bus.dbc.{key}: this scenario sends no {kind} frame (no controller needs it)")
        wanted = {fk: ("" if kind in ("sync", "heartbeat") else _sig_of(bms[0], sn), _spec(bms[0], sn))
                  for fk, sn in fields.items()}
        new = _page(ctx, f"bus.dbc.{key}", page, bms, wanted, protected=False, heartbeat=kind == "heartbeat")
        missing = [fk for fk in fields if fk not in (page.get("signals") or {})]
        if missing:
            raise ctx.fail(f"bus.dbc.{key}: {_msg_label(new[0])}: map {', '.join(missing)} (signals:)")
        replaced[id(bms[0])] = new
        roles_of[id(bms[0])] = f"bus.dbc.{key}"

    hb_ids: dict[int, int] = {}
    names = {e.name: e for e in base.ecus}
    for ename, roles in (mapping.get("ecus") or {}).items():
        e = names.get(ename)
        if e is None:
            raise ScenarioError(f"{path}: bus.dbc.ecus.{ename}: no ECU of that name in the placement "
                                f"(ECUs: {', '.join(list(names)[:6])}{', ...' if len(names) > 6 else ''})")
        for role, kind in ECU_ROLES.items():
            pages = roles.get(role)
            if not pages:
                continue
            where = f"bus.dbc.ecus.{ename}.{role}"
            bms = by_kind.get((kind, e.index), [])
            if not bms:
                raise ScenarioError(f"{path}: {where}: ECU {ename} sends no {kind} frame (nobody listens to it)")
            specs = {sig: sp for bm in bms for sig, sp in bm.signals if sig}
            proto = {sp.name: sp for bm in bms for sig, sp in bm.signals if not sig}
            wanted: dict[str, tuple[str, SignalSpec]] = {sig: (sig, sp) for sig, sp in specs.items()}
            for fk, sn in (("crc", "CRC"), ("counter", "Counter"), ("status", "Status")):
                if sn in proto:
                    wanted[fk] = ("", proto[sn])
            seen: dict[str, int] = {}
            news = []
            for i, page in enumerate(pages, start=1):
                pw = f"{where}[{i - 1}]" if len(pages) > 1 else where
                for sig in page.get("signals") or {}:
                    if sig in seen:
                        raise ScenarioError(f"{path}: {pw}: canbrake signal {sig} is mapped twice "
                                            f"(pages {seen[sig]} and {i - 1})")
                    seen[sig] = i - 1
                m, spec = _page(ctx, pw, page, bms, wanted, protected=kind in ("cmd", "state"))
                news.append((m, dataclasses.replace(spec, page=i, name=bms[0].name if i == 1 else f"{bms[0].name}_P{i}")))
            missing = [sig for sig in specs if sig not in seen]
            if missing:
                raise ScenarioError(f"{path}: {where}: canbrake signal {', '.join(missing)} of ECU {ename} is not "
                                    f"mapped (map every signal of the role: {', '.join(specs)})")
            # the mapped pages replace all of canbrake's pages of the role
            for j, bm in enumerate(bms):
                replaced[id(bm)] = news[j] if j < len(news) else None
                roles_of[id(bm)] = where
            extra += [(m, spec, where) for m, spec in news[len(bms):]]
        hb = roles.get("heartbeat")
        if hb:
            bms = by_kind.get(("heartbeat", e.index), [])
            where = f"bus.dbc.ecus.{ename}.heartbeat"
            new = _page(ctx, where, hb, bms, {"node_state": ("", _spec(bms[0], "NodeState"))},
                        protected=False, heartbeat=True)
            if "node_state" not in (hb.get("signals") or {}):
                raise ctx.fail(f"{where}: {_msg_label(new[0])}: map node_state (signals:)")
            replaced[id(bms[0])] = new
            roles_of[id(bms[0])] = where
            hb_ids[e.index] = new[1].frame_id

    # the run's messages: the mapped ones and canbrake's own for the rest
    msgs: list[MessageSpec] = []
    origin: dict[int, str] = {}
    for bm in base.messages:
        if id(bm) not in replaced:
            msgs.append(bm)
            origin[len(msgs) - 1] = f"canbrake's {bm.name}"
        elif replaced[id(bm)] is not None:
            um, spec = replaced[id(bm)]  # type: ignore[misc]
            msgs.append(spec)
            origin[len(msgs) - 1] = f"{roles_of[id(bm)]} ({um.name})"
    for um, spec, where in extra:
        msgs.append(spec)
        origin[len(msgs) - 1] = f"{where} ({um.name})"
    # identifier clashes: between the run's messages, and canbrake's own with the user's DBC
    seen_id: dict[int, str] = {}
    user_ids = {m.frame_id: m for m in db.messages}
    mapped_names = {n for n, _mux in ctx.used_pages}
    for i, m in enumerate(msgs):
        if m.frame_id in seen_id:
            raise ScenarioError(f"{path}: identifier clash: {origin[i]} and {seen_id[m.frame_id]} both use "
                                f"{m.frame_id:#x}")
        seen_id[m.frame_id] = origin[i]
        um = user_ids.get(m.frame_id)
        if origin[i].startswith("canbrake's") and um is not None and um.name not in mapped_names:
            raise ScenarioError(f"{path}: identifier clash: {origin[i]} ({m.frame_id:#x}) has the identifier of "
                                f"{_msg_label(um)} of the DBC (map that role onto it, or move the message)")
    out = copy.copy(base)
    out.messages = sorted(msgs, key=lambda m: (m.frame_id, m.name))
    out.by_id = {m.frame_id: m for m in out.messages}
    out.by_name = {m.name: m for m in out.messages}
    ext = base.plan.extended or any(m.frame_id > 0x7FF for m in out.messages)
    out.plan = _MappedPlan(base.plan, hb_ids, ext)
    for attr, kind in (("sync_id", "sync"), ("reference_id", "reference"), ("reference_pos_id", "reference_pos")):
        ids = [m.frame_id for m in out.messages if m.kind == kind]
        if ids:
            setattr(out, attr, ids[0])
    out.plant_heartbeat_id = next(m.frame_id for m in out.messages if m.kind == "heartbeat" and m.ecu == 0)
    out.user_dbc = path
    return out


def _spec(m: MessageSpec, name: str) -> SignalSpec:
    return next(sp for _sig, sp in m.signals if sp.name == name)


def _sig_of(m: MessageSpec, name: str) -> str:
    return next(sig for sig, sp in m.signals if sp.name == name)
