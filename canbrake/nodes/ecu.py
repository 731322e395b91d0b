"""The ECU node: one carriage's brake controller on the bus.

It turns frames into an :class:`~canbrake.control.base.Observation`, calls the controller,
and turns the result into frames. Peer values carry their age, derived from the E2E alive
counter: every sender's counter is its tick modulo 15, so a frame received at tick k with
counter c was sent at tick k - ((k - c) mod 15) (valid while frames are less than 15 periods
old; older ones are indistinguishable and the peer is reported stale anyway).
"""
from __future__ import annotations

import json
import math
from dataclasses import dataclass, field
from typing import Any
from pathlib import Path

import can
import numpy as np

from canbrake.bus import dbc
from canbrake.bus.codec import FrameCodec
from canbrake.bus.e2e import COUNTER_MODULO
from canbrake.bus.guard import FrameGuard, sign_control, sign_protected, sync_verdict
from canbrake.control.base import Controller, Observation
from canbrake.nodes.base import CsvTrace, Node, PassThrough, SendPath, exact_filter, frame


@dataclass
class EcuStats:
    ticks: int = 0
    peer_frames: int = 0
    peer_corrupted: int = 0
    peer_stale_or_duplicate: int = 0
    peer_missing: int = 0        # (tick, peer) pairs computed without a value from that tick
    deadline_misses: int = 0     # realtime: computed before every peer's state arrived
    frames_starved: int = 0      # timing model: frames that never won arbitration
    status: str = "running"
    bus_latency: dict = field(default_factory=dict)  # timing model: per kind p50/p99/max (s)
    guard: dict = field(default_factory=dict)    # canbrake.bus.guard: rejected frames by reason
    fallback_entries: int = 0    # times peers were lost (older than safety.peer_hold_periods)
    fallback_ticks: int = 0      # ticks computed on own sensors with at least one peer dropped


def _kind(aid: int) -> str:
    if dbc.STATE_BASE < aid <= dbc.STATE_BASE + dbc.MAX_CARS:
        return "state"
    if dbc.BRAKE_CMD_BASE < aid <= dbc.BRAKE_CMD_BASE + dbc.MAX_CARS:
        return "brake_cmd"
    if dbc.HEARTBEAT_BASE <= aid <= dbc.HEARTBEAT_BASE + dbc.MAX_CARS:
        return "heartbeat"
    return "other"


class EcuNode(Node):
    """Brake ECU of car ``car`` (1-based)."""

    def __init__(self, car: int, n_cars: int, controller: Controller, codec: FrameCodec, *, dt_s: float,
                 mode: str = "lockstep", send_path: SendPath | None = None, heartbeat_period_s: float = 0.1,
                 compute_deadline: float = 0.5, out_dir: str | Path | None = None, flush_every: int = 1000,
                 crash_at_tick: int | None = None, lockstep_deadline: float = 0.5, bus_timing: Any = None,
                 barrier: bool = True, rx_path: Any = None, secoc: Any = None,
                 peer_hold_periods: int | None = None, n_ticks: int | None = None) -> None:
        self.car = car
        self.i = car - 1
        self.n = n_cars
        self.name = f"ecu{car}"
        self.controller = controller
        self.codec = codec
        self.dt = dt_s
        self.mode = mode
        self.send_path = send_path or PassThrough()
        self.heartbeat_every = max(1, int(round(heartbeat_period_s / dt_s)))
        self.compute_deadline = compute_deadline
        self.out_dir = Path(out_dir) if out_dir else None
        self.flush_every = flush_every
        self.stats = EcuStats()
        self.crash_at_tick = crash_at_tick
        self.lockstep_deadline = lockstep_deadline
        self.bus_timing = bus_timing  # canbrake.bus.schedule.LockstepBusTiming or None
        # barrier=False: nothing can lose or delay a state frame (no impairment, ideal timing), so
        # the state frames themselves are the lockstep barrier and *_DONE frames are not sent.
        self.barrier = barrier
        # per-link impairments on what this ECU receives (canbrake.bus.impair.SendPath, direction rx)
        self.rx_path = rx_path
        # receiver checks (E2E, SecOC, protocol) and the peer-loss fallback (canbrake.bus.guard)
        self.secoc = secoc
        self.guard = FrameGuard(secoc)
        self.peer_hold_periods = peer_hold_periods
        self.final_tick = None if n_ticks is None else n_ticks - 1  # unauthenticated END only after it
        self._in_fallback = False
        self._latency: dict[str, list[float]] = {}
        self._t0_wall: float | None = None
        self.k = -1
        self.phase = 0  # 0 waiting for sensor, 1 waiting for peers, 2 done for this tick
        self.speed = np.nan
        self.position = np.nan
        self.defl_front: float | None = None
        self.defl_rear: float | None = None
        self.v_ref = 0.0
        self.a_ref = 0.0
        self.peer_speed = np.full(n_cars, np.nan)
        self.peer_pos = np.full(n_cars, np.nan)
        self.peer_origin = np.full(n_cars, -(10 ** 12), dtype=np.int64)
        self._peers = [j for j in range(n_cars) if j != self.i]
        self._all_done = (1 << n_cars) - 1  # bit j set: STATE_DONE of car j seen this tick
        self._done = 1 << self.i
        self._state_codec = codec[f"STATE_C{car}"]
        self._cmd_codec = codec[f"BRAKE_CMD_C{car}"]
        self._sdone = codec[f"STATE_DONE_C{car}"]
        self._cdone = codec[f"CMD_DONE_C{car}"]
        self._hb = codec[f"HEARTBEAT_C{car}"]
        self._sensor_id = dbc.SENSOR_BASE + car
        self._coupler_id = dbc.COUPLER_BASE + car
        self._deadline: float | None = None
        self._trace: CsvTrace | None = None

    def filters(self) -> list[dict]:
        ids = [dbc.SYNC_ID, dbc.REFERENCE_ID, self._sensor_id, self._coupler_id]
        for j in self._peers:
            ids.append(dbc.STATE_BASE + j + 1)
            if self.barrier:
                ids.append(dbc.STATE_DONE_BASE + j + 1)
        return [exact_filter(i) for i in ids]

    def start(self, now: float) -> list[can.Message]:
        self._trace = CsvTrace(None if self.out_dir is None else self.out_dir / f"ecu_c{self.car}.csv",
                               ["tick", "brake_cmd_n", *self.controller.diagnostic_names,
                                "max_peer_age_s", "peers_fresh"], self.flush_every)
        return []

    # ---------------------------------------------------------------- receive
    def handle(self, msg: can.Message, now: float) -> list[can.Message]:
        aid = msg.arbitration_id
        if aid == dbc.SYNC_ID:
            verdict = sync_verdict(self.guard, aid, msg.data, self.k, lockstep=self.mode == "lockstep",
                                   tick_complete=self.phase == 2 or self.k < 0, final_tick=self.final_tick)
            if verdict is None:
                return []
            if verdict == "end":
                self.finished = True
                return []
            self.k = int(self.codec.by_id[aid].decode(msg.data)["Tick"])
            self.phase = 0
            self._done = 1 << self.i
            return []
        if aid == self._sensor_id:
            d = self.codec.by_id[aid].decode(msg.data)
            self.speed, self.position = d["Speed"], d["Position"]
            return self._phase1(now)
        if aid == dbc.REFERENCE_ID:
            d = self.codec.by_id[aid].decode(msg.data)
            self.v_ref, self.a_ref = d["RefSpeed"], d["RefDecel"]
            return []
        if aid == self._coupler_id:
            d = self.codec.by_id[aid].decode(msg.data)
            self.defl_front = d["DeflFront"] if self.i > 0 else None
            self.defl_rear = d["DeflRear"] if self.i < self.n - 1 else None
            return []
        if dbc.STATE_BASE < aid <= dbc.STATE_BASE + self.n:
            j = aid - dbc.STATE_BASE - 1
            if self.rx_path is not None:
                self._receive_linked(msg, j, now)
                return []
            if self._on_state(j, msg) and not self.barrier:
                self._done |= 1 << j
                if self.phase == 1 and self._done == self._all_done:
                    return self._phase2(now)
            return []
        if dbc.STATE_DONE_BASE < aid <= dbc.STATE_DONE_BASE + self.n:
            tick = self.codec.by_id[aid].decode(msg.data)["Tick"]
            if tick != (self.k & 0xFFFF):
                self.guard.reject("sync")
            elif self.guard.control(aid, msg.data, self.k):
                self._done |= 1 << (aid - dbc.STATE_DONE_BASE - 1)
                if self.phase == 1 and self._done == self._all_done:
                    return self._phase2(now)
        return []

    def _receive_linked(self, msg: can.Message, j: int, now: float) -> None:
        """A peer's state frame through this ECU's per-link impairments: frames the link delays
        are taken in a later phase (see :meth:`_release_linked`). Peer frames arrive in phase 0/1."""
        from canbrake.bus.impair import TxFrame

        t, horizon = self._times(now, 1)
        self.rx_path.submit(TxFrame.from_message(msg, f"ecu{j + 1}", t))
        self._release_linked(horizon)

    def _release_linked(self, horizon: float) -> None:
        if self.rx_path is None:
            return
        for f in self.rx_path.release(horizon):
            m = f.to_message()
            self._on_state(m.arbitration_id - dbc.STATE_BASE - 1, m)

    def _on_state(self, j: int, msg: can.Message) -> bool:
        """Take a peer's state frame; True if it is this tick's."""
        origin = self.guard.origin(msg.arbitration_id, msg.data, self.k, int(self.peer_origin[j]))
        if origin is None:
            if self.guard.last_reason == "crc":
                self.stats.peer_corrupted += 1
            else:
                self.stats.peer_stale_or_duplicate += 1
            return False
        d = self.codec.by_id[msg.arbitration_id].decode(msg.data)
        self.peer_speed[j], self.peer_pos[j], self.peer_origin[j] = d["Speed"], d["Position"], origin
        self.stats.peer_frames += 1
        return origin == self.k

    # ---------------------------------------------------------------- send
    def _emit(self, msg: can.Message, t_s: float, out: list[can.Message]) -> None:
        if self.bus_timing is not None:
            lat = self.bus_timing.latency_s(self.k, self.name, msg.arbitration_id, t_s)
            self._latency.setdefault(_kind(msg.arbitration_id), []).append(lat)
            if not math.isfinite(lat):  # starved by higher-priority traffic: never gets on the bus
                self.stats.frames_starved += 1
                return
            t_s += lat
        out.extend(self.send_path.submit(msg, t_s))

    def _times(self, now: float, phase: int) -> tuple[float, float]:
        """(submit time, release horizon) of a phase, in simulated seconds (lockstep) or seconds
        since the first SYNC (realtime). See canbrake.bus.sendpath for the lockstep rule."""
        if self.mode == "lockstep":
            t_k = self.k * self.dt
            c = self.lockstep_deadline * self.dt
            return (t_k, t_k + c) if phase == 1 else (t_k + c, t_k + self.dt * (1 - 1e-9))
        if self._t0_wall is None:
            self._t0_wall = now
        t = now - self._t0_wall
        return t, t

    def _phase1(self, now: float) -> list[can.Message]:
        if self.phase != 0 or self.k < 0:
            return []
        if self.crash_at_tick is not None and self.k >= self.crash_at_tick:
            raise RuntimeError(f"injected crash of {self.name} at tick {self.k} (ecu.crash in the scenario)")
        t, horizon = self._times(now, 1)
        self._release_linked(horizon)
        out: list[can.Message] = []
        if self.k % self.heartbeat_every == 0:
            self._emit(frame(dbc.HEARTBEAT_BASE + self.car, self._hb.encode({"NodeState": 5})), t, out)
        state = self._state_codec.encode({"Speed": self.speed, "Position": self.position},
                                         counter=self.k % COUNTER_MODULO)
        self._emit(frame(dbc.STATE_BASE + self.car, state), t, out)
        out += self.send_path.release(horizon)
        if self.barrier:
            sid = dbc.STATE_DONE_BASE + self.car
            out.append(frame(sid, sign_control(self.secoc, sid, self._sdone.encode({"Tick": self.k & 0xFFFF}), self.k)))
        self.phase = 1
        if self.mode == "realtime":
            self._deadline = now + self.compute_deadline * self.dt
        if self._done == self._all_done:
            out += self._phase2(now)
        return out

    def _phase2(self, now: float) -> list[can.Message]:
        self.phase = 2
        self._deadline = None
        t, horizon = self._times(now, 2)
        self._release_linked(self._times(now, 1)[1])
        speed = self.peer_speed.copy()
        pos = self.peer_pos.copy()
        speed[self.i], pos[self.i] = self.speed, self.position
        origin = self.peer_origin.copy()
        origin[self.i] = self.k
        if self.peer_hold_periods is not None:
            self._peer_fallback(origin, speed, pos)
        age = np.where(np.isnan(speed), np.inf, (self.k - origin) * self.dt)
        fresh = int((origin == self.k).sum())
        self.stats.peer_missing += self.n - fresh
        obs = Observation(tick=self.k, time_s=self.k * self.dt, speed_mps=self.speed, position_m=self.position,
                          ref_speed_mps=self.v_ref, ref_decel_mps2=self.a_ref, peer_speed_mps=speed,
                          peer_position_m=pos, peer_age_s=age, deflection_front_m=self.defl_front,
                          deflection_rear_m=self.defl_rear)
        result = self.controller.step(obs)
        out: list[can.Message] = []
        cmd = self._cmd_codec.encode({"Status": 1 if self._in_fallback else 0, "BrakeForce": result.brake_force_n},
                                     counter=self.k % COUNTER_MODULO)
        cid = dbc.BRAKE_CMD_BASE + self.car
        self._emit(frame(cid, sign_protected(self.secoc, cid, cmd, self.k)), t, out)
        out += self.send_path.release(horizon)
        if self.barrier:
            did = dbc.CMD_DONE_BASE + self.car
            out.append(frame(did, sign_control(self.secoc, did, self._cdone.encode({"Tick": self.k & 0xFFFF}), self.k)))
        self.stats.ticks += 1
        if self._trace is not None:
            finite_age = age[np.isfinite(age)]
            self._trace.append([self.k, result.brake_force_n,
                                *(result.diagnostics.get(n, np.nan) for n in self.controller.diagnostic_names),
                                float(finite_age.max()) if finite_age.size else np.inf, fresh])
        return out

    def _peer_fallback(self, origin: np.ndarray, speed: np.ndarray, pos: np.ndarray) -> None:
        """Peers whose newest value is older than ``peer_hold_periods`` are dropped (NaN: the
        controller runs on its own sensors for them); counts entries and ticks in fallback."""
        lost = (self.k - origin) > self.peer_hold_periods
        lost[self.i] = False
        speed[lost] = np.nan
        pos[lost] = np.nan
        now = bool(lost.any())
        if now and not self._in_fallback:
            self.stats.fallback_entries += 1
        self.stats.fallback_ticks += int(now)
        self._in_fallback = now

    # ---------------------------------------------------------------- realtime
    def next_deadline(self) -> float | None:
        return self._deadline if self.phase == 1 else None

    def on_timer(self, now: float) -> list[can.Message]:
        if self.phase != 1:
            return []
        self.stats.deadline_misses += 1
        return self._phase2(now)

    # ---------------------------------------------------------------- trace
    def close(self, status: str = "ok") -> None:
        if self._trace is not None:
            self._trace.close()
        self.stats.status = "ok" if self.finished else status
        self.stats.guard = self.guard.stats()
        for kind, vals in self._latency.items():
            a = np.asarray(vals)
            fin = a[np.isfinite(a)]
            self.stats.bus_latency[kind] = {
                "n": int(a.size), "starved": int(a.size - fin.size),
                "p50_s": float(np.percentile(fin, 50)) if fin.size else None,
                "p99_s": float(np.percentile(fin, 99)) if fin.size else None,
                "max_s": float(fin.max()) if fin.size else None,
                "late_frames": int((fin >= self.lockstep_deadline * self.dt).sum())}
        if self.out_dir is not None:
            (self.out_dir / f"ecu_c{self.car}_stats.json").write_text(json.dumps(self.stats.__dict__, indent=1))
