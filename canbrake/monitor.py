"""``canbrake monitor``: a live terminal view of a train on a CAN bus (rich).

It is one more listener on the bus (python-can), so it attaches to any run on the in-memory bus
(``--channel`` as printed by ``canbrake run``) or on a vcan/CAN interface, and it reads nothing
but frames, decoded with the DBC (by message name, so a different identifier plan still works):

per car   speed (STATE_Ci) against v* (REFERENCE), brake force (BRAKE_CMD_Ci, + brakes),
          coupler deflection between neighbours (positions in STATE frames, minus the nominal
          spacing from ``--scenario``, else the first gap seen) against its bound,
          E2E errors (frames of the car whose CRC is wrong)
per node  frame rate (frames/s over the last second)
bus       load over the last second at the bit rate (actual stuffing), control periods seen,
          periods in which a car's brake command did not arrive before the next SYNC

:class:`MonitorState` is the pure part (frames in, a snapshot out) and is what the tests drive;
:func:`render` turns a snapshot into a rich renderable; :func:`monitor` runs the loop.
"""
from __future__ import annotations

import collections
import re
import time
from dataclasses import dataclass, field
from typing import Any, Deque

import can
import cantools

from canbrake.bus.e2e import check_crc
from canbrake.bus.timing import frame_bits

KMH = 3.6  # km/h per m/s
_CAR = re.compile(r"^(STATE|BRAKE_CMD|SENSOR|HEARTBEAT|STATE_DONE|CMD_DONE)_C(\d+)$")


@dataclass
class CarView:
    """What the bus says about one car (SI)."""

    speed_mps: float = float("nan")
    position_m: float = float("nan")
    brake_force_n: float = float("nan")
    e2e_errors: int = 0
    cmd_seen_tick: int = -1
    #: positions by control period (the last few), so that a deflection compares two cars at the
    #: same period: between two SYNCs some cars have sent this period's STATE and some not yet
    #: (at 25 m/s and 1 ms, one period apart reads as 2.5 cm of deflection)
    positions_m: dict[int, float] = field(default_factory=dict)


@dataclass
class MonitorState:
    """Frames in (:meth:`feed`), a snapshot out (:meth:`snapshot`). Times are frame timestamps (s)."""

    db: Any
    bitrate_bps: float = 500_000.0
    spacing_m: list[float] | None = None      # nominal x_i − x_{i+1} per coupler; None: first gap seen
    bound_m: float | None = None              # deflection bound (m): the scenario's verdict bound; None: none
    window_s: float = 1.0
    cars: dict[int, CarView] = field(default_factory=dict)
    ref_speed_mps: float = float("nan")
    tick: int = -1
    periods: int = 0
    missed_commands: int = 0
    frames: int = 0
    _by_id: dict[int, tuple[Any, str, int]] = field(default_factory=dict)
    _recent: Deque[tuple[float, str, int]] = field(default_factory=collections.deque)
    _first_gap: dict[int, float] = field(default_factory=dict)
    _now: float = 0.0
    sync_id: int = -1

    def __post_init__(self) -> None:
        for m in self.db.messages:
            k = _CAR.match(m.name)
            kind, car = (k.group(1), int(k.group(2))) if k else (m.name, 0)
            self._by_id[m.frame_id] = (m, kind, car)
            if kind == "SYNC":
                self.sync_id = m.frame_id
            if kind == "STATE":
                self.cars.setdefault(car, CarView())

    def feed(self, msg: can.Message) -> None:
        """Take one frame off the bus."""
        if msg.is_error_frame or msg.is_remote_frame:
            return
        self.frames += 1
        t = float(msg.timestamp or time.time())
        self._now = max(self._now, t)
        entry = self._by_id.get(msg.arbitration_id) if not msg.is_extended_id else None
        node = "unknown"
        bits = frame_bits(msg.arbitration_id, msg.is_extended_id, msg.dlc, bytes(msg.data), stuffing="actual")
        if entry is not None:
            m, kind, car = entry
            node = (m.senders[0] if m.senders else "?")
            data = bytes(msg.data)
            if kind in ("STATE", "BRAKE_CMD") and not check_crc(msg.arbitration_id, data):
                self.cars.setdefault(car, CarView()).e2e_errors += 1
                kind = "corrupt"
            try:
                values = m.decode(data, decode_choices=False) if kind != "corrupt" else {}
            except Exception:  # noqa: BLE001 - a frame that does not fit its DBC entry
                values = {}
            self._apply(kind, car, values)
        self._recent.append((t, node, bits))
        while self._recent and self._recent[0][0] < self._now - self.window_s:
            self._recent.popleft()

    def _apply(self, kind: str, car: int, v: dict[str, Any]) -> None:
        if kind == "SYNC" and "Tick" in v:
            tick = int(v["Tick"])
            if tick == 0xFFFFFFFF:
                return
            if self.tick >= 0:
                self.periods += 1
                self.missed_commands += sum(1 for c in self.cars.values() if c.cmd_seen_tick < self.tick)
            self.tick = tick
        elif kind == "REFERENCE" and "RefSpeed" in v:
            self.ref_speed_mps = float(v["RefSpeed"])
        elif kind == "STATE" and "Speed" in v:
            c = self.cars.setdefault(car, CarView())
            c.speed_mps, c.position_m = float(v["Speed"]), float(v["Position"])
            c.positions_m[self.tick] = c.position_m
            if len(c.positions_m) > 4:
                del c.positions_m[min(c.positions_m)]
        elif kind == "BRAKE_CMD" and "BrakeForce" in v:
            c = self.cars.setdefault(car, CarView())
            c.brake_force_n, c.cmd_seen_tick = float(v["BrakeForce"]), self.tick

    def deflections_m(self) -> list[float]:
        """Δl_j = x_j − x_{j+1} − spacing_j per coupler (m, + stretched), from the two cars' positions
        of the latest control period both have reported; NaN until then."""
        out = []
        n = max(self.cars) if self.cars else 0
        for j in range(1, n):
            a, b = self.cars.get(j), self.cars.get(j + 1)
            both = sorted(set(a.positions_m) & set(b.positions_m)) if a and b else []
            gap = (a.positions_m[both[-1]] - b.positions_m[both[-1]]) if both else float("nan")
            if self.spacing_m is not None and j - 1 < len(self.spacing_m):
                nominal = self.spacing_m[j - 1]
            else:
                if j not in self._first_gap and gap == gap:
                    self._first_gap[j] = gap
                nominal = self._first_gap.get(j, float("nan"))
            out.append(gap - nominal)
        return out

    def snapshot(self) -> dict[str, Any]:
        """Everything the view shows, as plain numbers (SI; rates in 1/s, load as a fraction)."""
        span = self.window_s
        if self._recent:
            span = max(min(self.window_s, self._now - self._recent[0][0]), 1e-9)
        rates: dict[str, float] = collections.Counter()
        bits = 0
        for _t, node, b in self._recent:
            rates[node] += 1
            bits += b
        return {
            "tick": self.tick, "periods": self.periods, "frames": self.frames,
            "ref_speed_mps": self.ref_speed_mps,
            "cars": {i: vars(c).copy() for i, c in sorted(self.cars.items())},
            "deflections_m": self.deflections_m(), "bound_m": self.bound_m,
            "rates_hz": {k: v / span for k, v in sorted(rates.items())},
            "bus_load": bits / span / self.bitrate_bps if self._recent else 0.0,
            "missed_commands": self.missed_commands,
        }


def render(snap: dict[str, Any], title: str = "") -> Any:
    """A rich renderable of a :meth:`MonitorState.snapshot`."""
    from rich.console import Group
    from rich.table import Table
    from rich.text import Text

    def num(x: float, fmt: str) -> str:
        return "–" if x != x else format(x, fmt)

    cars = Table(title=f"train — tick {snap['tick']}  v* {num(snap['ref_speed_mps'] * KMH, '.2f')} km/h",
                 expand=False)
    for col in ("car", "speed (km/h)", "v − v* (km/h)", "brake force (kN, + brakes)", "Δl to next (cm)",
                "E2E errors"):
        cars.add_column(col, justify="right")
    defl = snap["deflections_m"]
    bound = snap["bound_m"]
    for i, c in snap["cars"].items():
        err = (c["speed_mps"] - snap["ref_speed_mps"]) * KMH
        d = defl[i - 1] if i - 1 < len(defl) else float("nan")
        over = bound is not None and abs(d) > bound
        dtxt = Text(num(d * 100, "+.3f"), style="bold red" if over else ("green" if bound is not None else "")) \
            if d == d else Text("–")
        etxt = Text(str(c["e2e_errors"]), style="bold red" if c["e2e_errors"] else "")
        cars.add_row(str(i), num(c["speed_mps"] * KMH, ".2f"),
                     Text(num(err, "+.3f"), style="yellow" if abs(err) > 0.5 else ""),
                     num(c["brake_force_n"] / 1000, ".1f"), dtxt, etxt)
    nodes = Table(title="nodes", expand=False)
    nodes.add_column("sender")
    nodes.add_column("frames/s", justify="right")
    for name, r in snap["rates_hz"].items():
        nodes.add_row(name, f"{r:.0f}")
    load = snap["bus_load"]
    foot = Text(f"bus load {load * 100:.1f} % (last second)   periods {snap['periods']}   "
                f"commands missing at the next SYNC {snap['missed_commands']}   frames {snap['frames']}   "
                + (f"Δl bound ±{bound * 100:g} cm" if bound is not None
                   else "Δl bound: none (--scenario with safety.max_abs_deflection_m)"),
                style="bold red" if load > 1 else "")
    parts = ([Text(title, style="bold")] if title else []) + [cars, nodes, foot]
    return Group(*parts)


def monitor(bus: can.BusABC, state: MonitorState, *, title: str = "", refresh_hz: float = 4.0,
            duration_s: float | None = None, console: Any = None, stop_at_end: bool = True) -> dict[str, Any]:
    """Show the live view until Ctrl-C, ``duration_s`` (wall) or the run's end-of-run SYNC; returns
    the last snapshot."""
    from rich.live import Live

    t_end = None if duration_s is None else time.monotonic() + duration_s
    ended = False
    with Live(render(state.snapshot(), title), console=console, refresh_per_second=refresh_hz,
              auto_refresh=False) as live:
        last = 0.0
        try:
            while not ended and (t_end is None or time.monotonic() < t_end):
                msg = bus.recv(timeout=0.1)
                if msg is not None:
                    state.feed(msg)
                    if stop_at_end and state.tick >= 0 and msg.arbitration_id == state.sync_id \
                            and bytes(msg.data[:4]) == b"\xff\xff\xff\xff":
                        ended = True
                now = time.monotonic()
                if ended or now - last >= 1.0 / refresh_hz:
                    live.update(render(state.snapshot(), title), refresh=True)
                    last = now
        except KeyboardInterrupt:
            pass
    return state.snapshot()


def load_database(dbc_path: str | None, scenario: Any = None) -> Any:
    """The DBC given, else the scenario's train's, else the 6-car database."""
    from canbrake.bus import dbc

    if dbc_path:
        return cantools.database.load_file(dbc_path)
    if scenario is not None:
        from canbrake.build import bus_layout

        return bus_layout(scenario).database()
    return dbc.build_database(6)


def spacing_from_scenario(scn: Any) -> list[float]:
    """Nominal x_i − x_{i+1} per coupler (m): the vehicle types' lengths, else the initial gaps."""
    import numpy as np

    sp = scn.consist.coupler.spacing_m
    n = scn.n_cars
    if getattr(scn.consist, "rigid", False):  # one body: the vehicles share one coordinate
        return [0.0] * max(n - 1, 0)
    if sp is not None:
        return [float(v) for v in np.broadcast_to(np.asarray(sp, dtype=float), (max(n - 1, 0),))]
    x = scn.initial_position_m()
    return [float(v) for v in x[:-1] - x[1:]]


def open_monitor_bus(channel: str, interface: str | None) -> can.BusABC:
    """A listening bus: ``interface`` as given, else socketcan for vcan*/can* channels, else canbrake's
    in-memory bus."""
    if interface is None:
        interface = "socketcan" if re.match(r"^(v?can|slcan)\d+$", channel) else "canbrake"
    return can.Bus(interface=interface, channel=channel, receive_own_messages=False)
