"""The recorder node: writes every frame on the bus to ``frames.log`` and measures bus load.

The log is written by python-can's own writer (``can.Logger`` picks .log/.asc/.blf/... by
suffix), so candump/canplayer, python-can and ``cantools decode`` read it.

Lockstep mode: frames of one control period are written in the order a CAN bus would carry
them if every node queued its frames of a phase at the same instant (phase by phase, then by
identifier — arbitration), stamped with simulated time: t_k plus the wire time of the frames
before them at the scenario's bit rate (actual bit stuffing). That makes frames.log identical
byte for byte between runs and backends for the same seed. Simulation-control frames
(*_DONE) take no wire time in this accounting. When a period's traffic does not fit in the
period, the bus stays busy into the next one and the timestamps show it.

Realtime mode: frames are written as received, with their wall-clock receive timestamps.
"""
from __future__ import annotations

import json
from pathlib import Path
from typing import Any

import can
import numpy as np

from canbrake.bus import dbc
from canbrake.bus.timing import frame_bits
from canbrake.nodes.base import Node

class RunningLoad:
    """Mean and peak of the per-period bus load in O(1) memory."""

    def __init__(self) -> None:
        self.n = 0
        self.total = 0.0
        self.peak = 0.0

    def add(self, x: float) -> None:
        self.n += 1
        self.total += x
        self.peak = max(self.peak, x)

    @property
    def mean(self) -> float:
        return self.total / self.n if self.n else 0.0


class LogHistogram:
    """Quantiles of positive durations (s) in bounded memory: logarithmic bins 0.1 % wide from
    1e-7 s to 1e4 s (~25 000 counters whatever the run length); a quantile is exact to 0.1 %,
    the maximum exactly."""

    LO_S, HI_S, RATIO = 1e-7, 1e4, 1.001

    def __init__(self) -> None:
        self._log_ratio = np.log(self.RATIO)
        self.bins = int(np.ceil(np.log(self.HI_S / self.LO_S) / self._log_ratio)) + 2
        self.counts = np.zeros(self.bins, dtype=np.int64)
        self.n = 0
        self.max = 0.0

    def add(self, x: float) -> None:
        self.n += 1
        if x > self.max:
            self.max = x
        if x <= self.LO_S:
            i = 0
        else:
            i = min(self.bins - 1, 1 + int(np.log(x / self.LO_S) / self._log_ratio))
        self.counts[i] += 1

    def quantile(self, q: float) -> float:
        """The ``q`` quantile (0..1), as the geometric middle of its bin (0 when empty)."""
        if not self.n:
            return 0.0
        k = int(np.searchsorted(np.cumsum(self.counts), max(1, int(np.ceil(q * self.n)))))
        if k == 0:
            return min(self.LO_S, self.max)
        return float(min(self.max, self.LO_S * self.RATIO ** (k - 0.5)))


#: lockstep phase of each message kind: 0 the plant's tick frames, 1 the ECUs' state phase,
#: 2 their command phase (frames a sender held back are written with the phase of their kind)
_PHASE = {"sync": 0, "reference": 0, "reference_pos": 0, "sensor": 0, "heartbeat": 1, "state": 1,
          "state_done": 1, "cmd": 2, "cmd_done": 2}
_KIND_NAME = {"cmd": "brake_cmd"}


def is_sim_control(aid: int, layout: Any = None) -> bool:
    """True for the lockstep barrier frames (STATE_DONE/CMD_DONE), which carry no train data."""
    if layout is not None:
        m = layout.by_id.get(aid)
        return m is not None and m.kind in ("state_done", "cmd_done")
    return dbc.STATE_DONE_BASE < aid < dbc.STATE_DONE_BASE + 0x80


class RecorderNode(Node):
    """Listens to everything; writes ``frames.log`` and ``bus_stats.json``."""

    name = "recorder"

    def __init__(self, layout: Any, *, dt_s: float, bitrate_bps: int, mode: str = "lockstep",
                 log_path: str | Path | None = None, channel: str = "can0", epoch_s: float = 0.0,
                 plant_io_on_bus: bool = False, barrier: bool = True) -> None:
        if isinstance(layout, int):  # a number of cars: Chen's default placement
            layout = dbc.BusLayout(dbc.default_ecus(layout, coupler_sensors=True))
        self.layout = layout
        self._kinds = {m.frame_id: m.kind for m in layout.messages}
        self.dt = dt_s
        self.bitrate = float(bitrate_bps)
        self.mode = mode
        self.log_path = Path(log_path) if log_path else None
        self.channel = channel
        self.epoch = epoch_s
        self.plant_io_on_bus = plant_io_on_bus
        self.barrier = barrier  # without barrier frames, the n-th STATE frame ends phase 1
        self._writer: can.Listener | None = None
        self._k = -1
        self._tick_frames: list[can.Message] = []
        self._bus_free_s = 0.0
        self.frames = 0
        self.frames_by_kind: dict[str, int] = {}
        self._load = RunningLoad()
        self._latency = LogHistogram()
        self._rt_bits = 0
        self._rt_tick_start: float | None = None

    def start(self, now: float) -> list[can.Message]:
        if self.log_path is not None:
            self._writer = can.Logger(str(self.log_path))
        return []

    # ---------------------------------------------------------------- receive
    def handle(self, msg: can.Message, now: float) -> list[can.Message]:
        self.frames += 1
        aid = msg.arbitration_id
        kind = self._kinds.get(aid, "other") if not msg.is_error_frame else "error"
        name = _KIND_NAME.get(kind, kind)
        self.frames_by_kind[name] = self.frames_by_kind.get(name, 0) + 1
        if self.mode == "realtime":
            self._realtime(msg, now)
            return []
        if aid == dbc.SYNC_ID and not msg.is_extended_id:
            self._flush_tick()
            tick = int.from_bytes(msg.data[:4], "little")
            if tick == dbc.SYNC_END_TICK:
                self._write([self._stamp(msg, self._k + 1, 0.0)])
                self.finished = True
                return []
            self._k = tick
        phase = 0 if aid == dbc.HEARTBEAT_BASE and not msg.is_extended_id else _PHASE.get(kind, 1)
        self._tick_frames.append((phase, aid, bytes(msg.data), msg))  # type: ignore[arg-type]
        return []

    def _flush_tick(self) -> None:
        if self._k < 0 or not self._tick_frames:
            self._tick_frames = []
            return
        t_k = self._k * self.dt
        t = max(t_k, self._bus_free_s)
        ordered = sorted(self._tick_frames, key=lambda f: (f[0], f[1], f[2]))
        out = []
        busy = 0.0
        for _phase, aid, data, msg in ordered:
            if not self._untimed(aid):
                dur = frame_bits(aid, msg.is_extended_id, msg.dlc, data, stuffing="actual") / self.bitrate
                t += dur
                busy += dur
                self._latency.add(t - t_k)
            out.append(self._stamp(msg, None, t))
        self._bus_free_s = t
        self._load.add(busy / self.dt)
        self._write(out)
        self._flush_file()
        self._tick_frames = []

    def _stamp(self, msg: can.Message, tick: int | None, t_s: float) -> can.Message:
        if tick is not None:
            t_s = max(tick * self.dt, self._bus_free_s)
        return can.Message(timestamp=self.epoch + t_s, arbitration_id=msg.arbitration_id,
                           is_extended_id=msg.is_extended_id, is_remote_frame=msg.is_remote_frame,
                           is_error_frame=msg.is_error_frame, dlc=msg.dlc, data=msg.data,
                           channel=self.channel, is_rx=True)

    def _realtime(self, msg: can.Message, now: float) -> None:
        m = self._stamp(msg, None, 0.0)
        m.timestamp = msg.timestamp or now
        self._write([m])
        aid = msg.arbitration_id
        if aid == dbc.SYNC_ID:
            if self._rt_tick_start is not None:
                self._load.add(self._rt_bits / self.bitrate / self.dt)
                self._flush_file()
            self._rt_bits = 0
            self._rt_tick_start = m.timestamp
            if int.from_bytes(msg.data[:4], "little") == dbc.SYNC_END_TICK:
                self.finished = True
        if not self._untimed(aid):
            self._rt_bits += frame_bits(aid, msg.is_extended_id, msg.dlc, bytes(msg.data), stuffing="actual")

    def _untimed(self, aid: int) -> bool:
        """Frames that take no bus time in the accounting: barrier frames, and the plant's sensor
        frames unless they are declared bus traffic (they stand in for local wiring)."""
        kind = self._kinds.get(aid)
        if kind in ("state_done", "cmd_done"):
            return True
        return not self.plant_io_on_bus and kind == "sensor"

    def _write(self, msgs: list[can.Message]) -> None:
        if self._writer is not None:
            for m in msgs:
                self._writer.on_message_received(m)

    # ---------------------------------------------------------------- results
    def _flush_file(self) -> None:
        """Hand the tick's lines to the OS (one write per control period), so a killed recorder
        loses at most the current period. Binary formats (.blf: compressed containers) keep
        python-can's own buffering."""
        f = getattr(self._writer, "file", None)
        if f is not None and isinstance(self._writer, can.io.generic.TextIOMessageWriter):
            f.flush()

    def bus_stats(self) -> dict:
        load = self._load
        lat = self._latency
        return {
            "frames": self.frames,
            "frames_by_kind": self.frames_by_kind,
            "bitrate_bps": self.bitrate,
            "bus_load_mean": load.mean,
            "bus_load_peak": load.peak,
            "plant_io_on_bus": self.plant_io_on_bus,
            "latency_model": "lockstep: all frames of a phase queued at t_k, arbitration order, actual stuffing"
            if self.mode == "lockstep" else "not modelled in realtime mode",
            "latency_p50_s": lat.quantile(0.50),
            "latency_p99_s": lat.quantile(0.99),
            "latency_max_s": lat.max,
        }

    def close(self, status: str = "ok") -> None:
        if self.mode == "lockstep" and not self.finished:
            self._flush_tick()
        if self._writer is not None:
            self._writer.stop()
            self._writer = None
        if self.log_path is not None:
            stats = self.bus_stats()
            stats["status"] = "ok" if self.finished else status
            (self.log_path.parent / "bus_stats.json").write_text(json.dumps(stats, indent=1))
