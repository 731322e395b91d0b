"""The CAN timing model in the loop of a lockstep run.

Every node of a lockstep run builds the same :class:`LockstepBusTiming` from the scenario. It
feeds the *nominal* traffic of each control period — SYNC and REFERENCE from the plant at t_k,
each ECU's STATE (and heartbeat) at t_k, each ECU's BRAKE_CMD at its decision instant t_k + c·T,
babbling nodes at their rates, and, if ``plant_io_on_bus``, the sensor frames — into a
:class:`~canbrake.bus.timing.BusTimingModel` (worst-case bit stuffing, arbitration by
identifier, per-node priority queues). A sender asks when its frame of tick k finishes on the
wire and adds that latency to the frame's release time, so a bus that cannot carry a period's
traffic in one period makes frames arrive ticks late, with the latency growing for as long as
the overload lasts — exactly as on a real bus, and deterministically.

Why replicate instead of modelling in the medium: the medium differs per backend (kernel vcan,
shared memory, python-can virtual), and results must agree across backends. The nominal
schedule depends only on the scenario, so every process computes the same latencies without
talking to the others. Approximation (documented): frames added, dropped or moved by
impairments other than babbling are not fed back into the replicated model; the lockstep
barrier frames (*_DONE) take no bus time.
"""
from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any

from canbrake.bus import dbc
from canbrake.bus.timing import BusTimingModel


@dataclass(frozen=True)
class BabbleSource:
    """A babbling node in the nominal schedule (emission j at start + j/rate)."""

    sender: str
    arbitration_id: int
    rate_hz: float
    dlc: int
    is_extended: bool
    start_s: float
    stop_s: float


class LockstepBusTiming:
    """Replicated deterministic bus timing for lockstep runs (simulated seconds)."""

    def __init__(self, layout: Any, dt_s: float, bitrate_bps: float, *, decision_offset_s: float,
                 heartbeat_every: int, plant_io_on_bus: bool = False, coupler_sensors: bool = False,
                 babblers: list[BabbleSource] | None = None, max_wait_ticks: int = 2_000) -> None:
        if isinstance(layout, int):  # a number of cars: Chen's default placement
            layout = dbc.BusLayout(dbc.default_ecus(layout, coupler_sensors=coupler_sensors))
        self.layout = layout
        self.n = len(layout.ecus)
        # nominal traffic per tick: (phase 0 at t_k | 1 at t_k | 2 at t_k + c, sender, id, extended, dlc, heartbeat?)
        self._traffic: list[tuple[int, str, int, bool, int, bool]] = []
        for msg in layout.messages:
            sender = "plant" if msg.ecu == 0 else layout.by_index[msg.ecu].name
            if msg.kind in ("sync", "reference", "reference_pos"):
                self._traffic.append((0, sender, msg.frame_id, msg.extended, msg.length, False))
            elif msg.kind == "sensor" and plant_io_on_bus:
                self._traffic.append((0, sender, msg.frame_id, msg.extended, msg.length, False))
            elif msg.kind == "heartbeat":
                self._traffic.append((0 if msg.ecu == 0 else 1, sender, msg.frame_id, msg.extended, msg.length, True))
            elif msg.kind == "state":
                self._traffic.append((1, sender, msg.frame_id, msg.extended, msg.length, False))
            elif msg.kind == "cmd":
                self._traffic.append((2, sender, msg.frame_id, msg.extended, msg.length, False))
        self.dt = dt_s
        self.c = decision_offset_s
        self.hb_every = max(1, heartbeat_every)
        self.plant_io = plant_io_on_bus
        self.coupler_sensors = coupler_sensors
        self.babblers = list(babblers or [])
        self.max_wait_ticks = max_wait_ticks
        self.model = BusTimingModel(bitrate_bps, stuffing="worst", record_history=False)
        self._next_tick = 0
        self._done: dict[tuple[int, str, int], float] = {}
        self._babble_next = [0] * len(self.babblers)
        self._query_tick = 0  # latest tick asked about; deliveries older than it are forgotten

    def _submit_tick(self, k: int) -> None:
        t = k * self.dt
        m = self.model
        sub = m.submit
        hb = k % self.hb_every == 0
        for phase, sender, fid, ext, dlc, is_hb in self._traffic:
            if is_hb and not hb:
                continue
            sub(sender, fid, ext, dlc, None, t + self.c if phase == 2 else t, tag=(k, sender, fid))
        t_end = t + self.dt
        for i, b in enumerate(self.babblers):
            j = self._babble_next[i]
            while True:
                te = b.start_s + j / b.rate_hz
                if te >= t_end or te >= b.stop_s:
                    break
                if te >= t:
                    sub(b.sender, b.arbitration_id, b.is_extended, b.dlc, None, te, tag=(k, b.sender, -1))
                j += 1
            self._babble_next[i] = j

    def _step(self) -> None:
        k = self._next_tick
        self._submit_tick(k)
        for d in self.model.advance((k + 1) * self.dt):
            tag = d.tag
            if tag[2] >= 0:
                self._done[tag] = d.t_end_s
        self._next_tick = k + 1
        if k % 256 == 0:  # forget deliveries nobody will ask for (other nodes' frames of past ticks)
            old = self._query_tick - 2
            self._done = {key: v for key, v in self._done.items() if key[0] >= old}

    def latency_s(self, k: int, node: str, msg_id: int, t_queue_s: float) -> float:
        """Bus latency (queueing + transmission, s) of ``node``'s frame ``msg_id`` of tick ``k``;
        ``math.inf`` if it would wait more than ``max_wait_ticks`` periods (starved)."""
        key = (k, node, msg_id)
        self._query_tick = max(self._query_tick, k)
        while key not in self._done:
            if self._next_tick > k + self.max_wait_ticks:
                return math.inf
            self._step()
        return self._done.pop(key) - t_queue_s


def build_bus_timing(scn: Any) -> LockstepBusTiming | None:
    """The in-loop timing model of ``scn`` (None unless lockstep with ``bus.timing: model``)."""
    if scn.mode != "lockstep" or scn.bus.timing != "model":
        return None
    from canbrake.bus.impair import BabbleSpec

    babblers = [BabbleSource(s.sender, s.arbitration_id, s.rate_hz, s.dlc, s.is_extended, s.start_s,
                             math.inf if getattr(s, "stop_s", None) is None else s.stop_s)
                for s in scn.bus.impairments if isinstance(s, BabbleSpec)]
    dt = scn.control_period_s
    from canbrake.build import bus_layout

    return LockstepBusTiming(bus_layout(scn), dt, scn.bus.bitrate_bps, decision_offset_s=scn.ecu.lockstep_deadline * dt,
                             heartbeat_every=int(round(scn.ecu.heartbeat_period_s / dt)),
                             plant_io_on_bus=scn.bus.plant_io_on_bus, coupler_sensors=scn.plant.coupler_sensors,
                             babblers=babblers)
