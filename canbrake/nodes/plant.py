"""The plant node: time master. Sends SYNC/REFERENCE/sensor frames, collects brake commands,
advances the physics model one control period at a time and writes ``signals.csv``.

It knows frames and timing, not train formulas: the physics is any object following
:class:`PlantModel`.
"""
from __future__ import annotations

import json
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Callable, Protocol

import can
import numpy as np

from canbrake.bus import dbc
from canbrake.bus.codec import FrameCodec
from canbrake.bus.e2e import E2EReceiver, E2EStatus, counter_of
from canbrake.nodes.base import CsvTrace, Node, exact_filter, frame


class PlantModel(Protocol):
    """The physics the plant node drives (SI units)."""

    n_cars: int

    def step(self, dt_s: float, brake_force_cmd_n: np.ndarray) -> None:
        """Advance by ``dt_s`` holding the commanded braking forces (N, shape (n,))."""

    def measurements(self) -> dict[str, np.ndarray]:
        """Current state: position_m, speed_mps, accel_mps2, applied_brake_n (n,);
        deflection_m, coupler_force_n (n-1,)."""


Reference = Callable[[float], tuple[float, float]]  # t_s -> (v* m/s, a* m/s^2)


@dataclass
class FailSafe:
    """Each car's brake unit reaction to lost commands: after ``timeout_ticks`` control periods
    without a valid (E2E-checked, in-sequence) command, apply ``force_n`` (N per car, + = brake).
    ``latch``: stay in fail-safe to the end of the run, else leave it on the next valid command."""

    timeout_ticks: int
    force_n: np.ndarray
    latch: bool = True


@dataclass
class PlantStats:
    ticks: int = 0
    commands_received: int = 0
    commands_missed: int = 0          # ticks x cars without a fresh command
    commands_missed_per_car: list[int] = field(default_factory=list)  # the same per car (a stopped ECU shows)
    commands_corrupted: int = 0       # failed CRC
    commands_out_of_sequence: int = 0
    deadline_misses: int = 0          # realtime: periods that ended before every command arrived
    late_periods: int = 0             # realtime: period started late by more than one period
    max_lateness_s: float = 0.0
    wall_time_s: float = 0.0
    failsafe_activations: int = 0     # car entries into fail-safe braking
    failsafe_ticks: int = 0           # ticks x cars spent in fail-safe braking
    failsafe_first_s: dict[str, float] = field(default_factory=dict)  # car -> first activation (s)
    status: str = "running"
    extra: dict[str, float] = field(default_factory=dict)


class PlantNode(Node):
    """Time master and physics host."""

    name = "plant"

    def __init__(self, model: PlantModel, codec: FrameCodec, *, dt_s: float, n_ticks: int,
                 reference: Reference, mode: str = "lockstep", coupler_sensors: bool = False,
                 heartbeat_period_s: float = 0.1, out_dir: str | Path | None = None,
                 flush_every: int = 500, progress: Any = None, hosted: list[Any] | None = None,
                 barrier: bool = True, failsafe: FailSafe | None = None) -> None:
        self.model = model
        self.codec = codec
        self.n = model.n_cars
        self.dt = dt_s
        self.n_ticks = n_ticks
        self.reference = reference
        self.mode = mode
        self.coupler_sensors = coupler_sensors
        self.heartbeat_every = max(1, int(round(heartbeat_period_s / dt_s)))
        self.out_dir = Path(out_dir) if out_dir else None
        self.flush_every = flush_every
        self.progress = progress  # optional shared value (``.value``) the supervisor watches
        # send paths of traffic sources the plant hosts (babbling nodes that are not real nodes)
        self.hosted = list(hosted or [])
        # barrier=False: commands cannot be lost or delayed, so the commands themselves close the tick
        self.barrier = barrier
        self.k = 0
        self.stats = PlantStats(commands_missed_per_car=[0] * self.n)
        self.cmd_n = np.zeros(self.n)
        self._fresh = np.zeros(self.n, dtype=bool)
        self._done = 0  # bit i set: CMD_DONE of car i seen this tick
        self._all_done = (1 << self.n) - 1
        self._e2e = [E2EReceiver(dbc.BRAKE_CMD_BASE + c) for c in range(1, self.n + 1)]
        self._last_counter = [-1] * self.n  # tick of each car's newest accepted command
        self.failsafe = failsafe
        self._in_failsafe = np.zeros(self.n, dtype=bool)
        self._sync = codec["SYNC"]
        self._ref = codec["REFERENCE"]
        self._sensor = [codec[f"SENSOR_C{c}"] for c in range(1, self.n + 1)]
        self._coupler = [codec[f"COUPLER_C{c}"] for c in range(1, self.n + 1)]
        self._cmd_codec = {dbc.BRAKE_CMD_BASE + c: codec[f"BRAKE_CMD_C{c}"] for c in range(1, self.n + 1)}
        self._hb = codec["HEARTBEAT_PLANT"]
        self._t0_wall: float | None = None
        self._t_start_wall: float | None = None
        self._trace: CsvTrace | None = None

    # ---------------------------------------------------------------- frames
    def filters(self) -> list[dict]:
        ids = [dbc.BRAKE_CMD_BASE + c for c in range(1, self.n + 1)]
        if self.barrier:
            ids += [dbc.CMD_DONE_BASE + c for c in range(1, self.n + 1)]
        return [exact_filter(i) for i in ids]

    def _tick_frames(self) -> list[can.Message]:
        k = self.k
        t = k * self.dt
        meas = self.model.measurements()
        v_ref, a_ref = self.reference(t)
        out = [frame(dbc.SYNC_ID, self._sync.encode({"Tick": k})),
               frame(dbc.REFERENCE_ID, self._ref.encode({"RefSpeed": v_ref, "RefDecel": a_ref}))]
        if k % self.heartbeat_every == 0:
            out.append(frame(dbc.HEARTBEAT_BASE, self._hb.encode({"NodeState": 5})))
        x, v = meas["position_m"], meas["speed_mps"]
        if self.coupler_sensors:
            d = meas["deflection_m"]
            for i in range(self.n):
                front = float(d[i - 1]) if i > 0 else 0.0
                rear = float(d[i]) if i < self.n - 1 else 0.0
                out.append(frame(dbc.COUPLER_BASE + i + 1, self._coupler[i].encode({"DeflFront": front, "DeflRear": rear})))
        for i in range(self.n):
            out.append(frame(dbc.SENSOR_BASE + i + 1,
                             self._sensor[i].encode({"Speed": float(v[i]), "Position": float(x[i])})))
        for sp in self.hosted:
            out += sp.release(t)
        return out

    def _end_frames(self) -> list[can.Message]:
        return [frame(dbc.SYNC_ID, self._sync.encode({"Tick": dbc.SYNC_END_TICK}))]

    def start(self, now: float) -> list[can.Message]:
        self._open_trace()
        self._t0_wall = now
        self._t_start_wall = now
        return self._tick_frames()

    def handle(self, msg: can.Message, now: float) -> list[can.Message]:
        aid = msg.arbitration_id
        if dbc.BRAKE_CMD_BASE < aid <= dbc.BRAKE_CMD_BASE + self.n:
            i = aid - dbc.BRAKE_CMD_BASE - 1
            if self._on_command(i, msg) and not self.barrier and self.mode == "lockstep":
                self._done |= 1 << i
                if self._done == self._all_done:
                    return self._advance(now)
            return []
        if self.mode == "lockstep" and dbc.CMD_DONE_BASE < aid <= dbc.CMD_DONE_BASE + self.n:
            tick = self.codec.by_id[aid].decode(msg.data)["Tick"]
            if tick == (self.k & 0xFFFF):
                self._done |= 1 << (aid - dbc.CMD_DONE_BASE - 1)
                if self._done == self._all_done:
                    return self._advance(now)
        return []

    def _on_command(self, i: int, msg: can.Message) -> bool:
        """Take a brake command; True if it is this tick's."""
        status = self._e2e[i].check(msg.data)
        if status is E2EStatus.WRONG_CRC:
            self.stats.commands_corrupted += 1
            return False
        if status is E2EStatus.WRONG_SEQUENCE:
            self.stats.commands_out_of_sequence += 1
        # The sender's counter is its tick mod 15; accept only the frame of the current tick or a
        # newer-looking one, never an older (delayed/reordered) one.
        c = counter_of(msg.data)
        lag = (self.k - c) % 15
        if lag > 7:  # from the future is impossible; treat as very old
            return False
        origin = self.k - lag
        if origin <= self._last_counter[i]:
            return False
        self._last_counter[i] = origin
        self.cmd_n[i] = self._cmd_codec[msg.arbitration_id].decode(msg.data)["BrakeForce"]
        self.stats.commands_received += 1
        if origin == self.k:
            self._fresh[i] = True
            return True
        return False

    # ---------------------------------------------------------------- time
    def next_deadline(self) -> float | None:
        if self.mode != "realtime" or self._t0_wall is None or self.finished:
            return None
        return self._t0_wall + (self.k + 1) * self.dt

    def on_timer(self, now: float) -> list[can.Message]:
        if self.mode != "realtime" or self.finished:
            return []
        if not self._fresh.all():
            self.stats.deadline_misses += 1
        lateness = now - self.next_deadline()  # type: ignore[operator]
        self.stats.max_lateness_s = max(self.stats.max_lateness_s, lateness)
        if lateness > self.dt:
            self.stats.late_periods += 1
        return self._advance(now)

    def _applied_commands(self) -> np.ndarray:
        """The force each car's brake unit applies this tick (N): the newest command, or the
        fail-safe force for cars whose commands have stopped."""
        fs = self.failsafe
        if fs is None:
            return self.cmd_n.copy()
        age = self.k - np.asarray(self._last_counter)  # ticks since the newest valid command
        if not fs.latch:
            self._in_failsafe &= ~self._fresh
        entering = (age > fs.timeout_ticks) & ~self._in_failsafe
        for i in np.flatnonzero(entering):
            self.stats.failsafe_activations += 1
            self.stats.failsafe_first_s.setdefault(f"c{i + 1}", round(self.k * self.dt, 9))
        self._in_failsafe |= entering
        self.stats.failsafe_ticks += int(self._in_failsafe.sum())
        return np.where(self._in_failsafe, fs.force_n, self.cmd_n)

    def _advance(self, now: float) -> list[can.Message]:
        self.stats.commands_missed += int((~self._fresh).sum())
        for i in np.flatnonzero(~self._fresh):
            self.stats.commands_missed_per_car[i] += 1
        applied = self._applied_commands()
        self._record()
        try:
            self.model.step(self.dt, applied)
        except FloatingPointError as e:
            # The closed loop went unstable (a result, not a crash): end the run for every node.
            self.finished = True
            self.stats.status = "diverged"
            self.stats.extra["diverged_at_s"] = self.k * self.dt
            self.stats.extra["message"] = str(e)  # type: ignore[assignment]
            return self._end_frames()
        self.k += 1
        self.stats.ticks = self.k
        if self.progress is not None:
            self.progress.value = self.k
        self._fresh[:] = False
        self._done = 0
        if self.k >= self.n_ticks:
            self._record(final=True)
            self.finished = True
            self.stats.status = "ok"
            if self._t_start_wall is not None:
                self.stats.wall_time_s = now - self._t_start_wall
            return self._end_frames()
        return self._tick_frames()

    # ---------------------------------------------------------------- trace
    def columns(self) -> list[str]:
        cols = ["tick", "t_s", "ref_speed_mps", "ref_decel_mps2"]
        for c in range(1, self.n + 1):
            cols += [f"position_m_c{c}", f"speed_mps_c{c}", f"accel_mps2_c{c}",
                     f"brake_cmd_n_c{c}", f"brake_applied_n_c{c}"]
        for c in range(1, self.n):
            cols += [f"deflection_m_k{c}", f"coupler_force_n_k{c}"]
        if self.failsafe is not None:
            cols += [f"failsafe_c{c}" for c in range(1, self.n + 1)]
        return cols

    def _open_trace(self) -> None:
        self._trace = CsvTrace(None if self.out_dir is None else self.out_dir / "signals.csv", self.columns(),
                               self.flush_every)

    def _record(self, final: bool = False) -> None:
        m = self.model.measurements()
        t = self.k * self.dt
        v_ref, a_ref = self.reference(t)
        row: list[float] = [self.k, t, v_ref, a_ref]
        cmd = np.full(self.n, np.nan) if final else self.cmd_n
        for i in range(self.n):
            row += [m["position_m"][i], m["speed_mps"][i], m["accel_mps2"][i], cmd[i], m["applied_brake_n"][i]]
        for j in range(self.n - 1):
            row += [m["deflection_m"][j], m["coupler_force_n"][j]]
        if self.failsafe is not None:
            row += [int(f) for f in self._in_failsafe]
        if self._trace is not None:
            self._trace.append(row)
            if final:
                self._trace.flush()

    def close(self, status: str = "ok") -> None:
        if self._trace is not None:
            self._trace.close()
        if self.stats.status == "running":
            self.stats.status = status
        if self.out_dir is not None:
            (self.out_dir / "plant_stats.json").write_text(json.dumps(self.stats.__dict__, indent=1))
