"""The recorder node: writes every frame on the bus to the run's frame log and measures bus load.

The log is written by python-can's own writer (``can.Logger`` picks the format by suffix:
``frames.log`` candump -L, ``.asc``, ``.blf``, ``.trc``, ``.mf4``), so candump/canplayer,
python-can, ``cantools decode``, CANoe and asammdf read it.

What a frame's timestamp means (lockstep mode) — simulated time, identical byte for byte between
runs and backends for the same seed, and never outside the frame's control period
[t_k, t_k + T) (the period in which the lockstep delivers it), so the log is monotonic:

* ``bus.timing: ideal`` (default): the instant the frame's last bit would leave an ideal bus
  carrying the control period's frames back to back from the period's start t_k, in the order a
  CAN bus would carry them if every node queued its frames of a phase at the same instant (phase
  by phase, then by identifier — arbitration; actual bit stuffing at the scenario's bit rate).
  When the period's frames need more wire time W than the period T (bus load > 100 %), their
  wire times are scaled by T/W so that the last one ends at t_k + T; ``bus_stats.json`` (and the
  summary's bus load) says by how much the traffic did not fit.
* ``bus.timing: model``: the modelled wire time — the instant the frame's transmission completes
  on the modelled bus (:mod:`canbrake.bus.schedule`, the same replica every sender uses for its
  latencies; worst-case stuffing, IFS included). A sender holds a frame until the model has it
  off the wire, so the frames the lockstep delivers in period k are the frames the model
  completes in (t_k − ε, t_k + T − ε] (ε = 1e-9 T, the senders' release horizon): the recorder
  gives the frames of each identifier seen in period k the model's completion times of that
  identifier in that window, in order (arrival order within an identifier). A frame the model does
  not carry in that window — the plant's sensor frames (local wiring unless
  ``bus.plant_io_on_bus``), a frame added or moved by an impairment other than babbling, a
  frame from outside the run, a plant frame the model finishes only after its period — is
  stamped at the start of its phase (t_k; a command at the decision instant t_k + c·T). The
  frames of a period are written in stamp order (ties: phase, identifier, payload).

Simulation-control frames (the lockstep barrier's STATE_DONE/CMD_DONE, which carry no train data
and are only sent when an impairment needs them) are never written to the log, so a log holds the
same train traffic whatever the configuration; they are counted in ``frames_by_kind``.

Realtime mode: frames are written as received, with their wall-clock receive timestamps.

Bus errors (``bit_error_rate`` / ``faulty_transceiver``, lockstep with the timing model): the
recorder keeps its own replica of the timing model (:mod:`canbrake.bus.schedule`), writes every
failed attempt as a python-can error frame (``is_error_frame=True``; SocketCAN error-frame
layout of ``linux/can/error.h``: protocol violation, controller state, TEC in byte 6 and REC
in byte 7) stamped with the replica's time of the attempt, and samples each node's error state
and counters at the end of every control period into ``can_errors.csv``.

Statistics (``bus_stats.json``, ``bus_load.csv``): bus load per control period and per 100 ms
window, frames per second by identifier and by sender, error frames per second.
"""
from __future__ import annotations

import csv
import json
from operator import itemgetter
from pathlib import Path
from typing import Any

import can

from canbrake.bus import dbc
from canbrake.bus._candump import write_candump
from canbrake.bus._wire import LoadSeries, ideal_period, ideal_tick, timed_bits_raw
from canbrake.bus.guard import FrameGuard, sync_verdict
from canbrake.bus.memory_shm import SLOT_BYTES
from canbrake.bus.rt_errors import error_frame  # noqa: F401  (built in the bus layer; also imported from here)
from canbrake.bus.timing import actual_frame_bits, frame_bits
from canbrake.nodes._trace import TAKE_SYNC, RecorderTaker, frame_key, key_fields, take_realtime_raw
from canbrake.atomic import write_text_atomic
from canbrake.nodes.base import LogHistogram, Node, rows_by_row, trim_partial_line  # noqa: F401  (LogHistogram, trim_partial_line: also imported from here)

#: lockstep phase of each message kind: 0 the plant's tick frames, 1 the ECUs' state phase,
#: 2 their command phase (frames a sender held back are written with the phase of their kind)
_PHASE = {"sync": 0, "reference": 0, "reference_pos": 0, "sensor": 0, "heartbeat": 1, "state": 1,
          "state_done": 1, "cmd": 2, "cmd_done": 2}
_KIND_NAME = {"cmd": "brake_cmd"}
#: bus order of a period's frames: phase, then identifier (arbitration), then payload
_BUS_ORDER = itemgetter(0, 1, 2)

def check_log_format(fmt: str) -> None:
    """Raise ValueError when python-can cannot write ``fmt`` here (MF4 needs asammdf)."""
    if fmt == "mf4":
        try:
            import asammdf  # noqa: F401
        except ImportError:
            raise ValueError("bus.log_format: mf4 needs asammdf (pip install 'canbrake[mf4]' or pip install "
                             "asammdf)") from None


def log_channels(fmt: str, names: list[str]) -> dict[str, str | int]:
    """The channel each bus (or bus segment, in ``names`` order) gets in a frame log of format ``fmt``.

    candump ``.log``: the name itself (the interface column; candump writes several interfaces so).
    ``.asc``/``.blf``/``.trc``/``.mf4``: the numbers 1..n in ``names`` order, as CANoe numbers its
    channels (CAN 1, CAN 2, ...) and asammdf's bus logging expects (0 there means "any channel").
    A name is never read for a number: python-can's writers would take a name's trailing digits
    (``train999`` -> 999, overflowing MF4's uint8 BusChannel; ``car1`` -> 1 beside ``backbone`` -> the
    default 1), so the recorder hands them integers: python-can's 0-based convention for ASC, BLF
    and TRC (their writers add 1) and the 1-based number itself for MF4 (its writer stores it as given).
    """
    if fmt == "log":
        return {n: n for n in names}
    base = 1 if fmt == "mf4" else 0
    return {n: base + i for i, n in enumerate(names)}


def is_sim_control(aid: int, layout: Any = None) -> bool:
    """True for the lockstep barrier frames (STATE_DONE/CMD_DONE), which carry no train data."""
    if layout is not None:
        m = layout.by_id.get(aid)
        return m is not None and m.kind in ("state_done", "cmd_done")
    return dbc.STATE_DONE_BASE < aid < dbc.STATE_DONE_BASE + 0x80


def _log_writer(path: str | Path) -> can.io.generic.MessageWriter:
    """python-can's writer for ``path`` as ``can.Logger(path)`` picks it: candump ``.log`` made
    directly (``can.Logger`` reads every installed package's entry points to find the writer
    plug-ins, ~7 ms at each run's start), every other format through ``can.Logger``."""
    if Path(path).suffix.lower() == ".log":
        return can.CanutilsLogWriter(str(path))
    return can.Logger(str(path))


class RecorderNode(Node):
    """Listens to everything; writes ``frames.log`` and ``bus_stats.json``."""

    name = "recorder"

    def __init__(self, layout: Any, *, dt_s: float, bitrate_bps: int, mode: str = "lockstep",
                 log_path: str | Path | None = None, channel: str = "can0", epoch_s: float = 0.0,
                 plant_io_on_bus: bool = False, barrier: bool = True, bus_timing: Any = None, secoc: Any = None,
                 n_ticks: int | None = None, segments: Any = None, external: frozenset[int] = frozenset()) -> None:
        if isinstance(layout, int):  # a number of cars: Chen's default placement
            layout = dbc.BusLayout(dbc.default_ecus(layout, coupler_sensors=True))
        self.layout = layout
        self._kinds = {m.frame_id: m.kind for m in layout.messages}
        self._untimed_memo: dict[int, bool] = {}
        self._sim_control_memo: dict[int, bool] = {}
        self.dt = dt_s
        self.bitrate = float(bitrate_bps)
        self.mode = mode
        self.log_path = Path(log_path) if log_path else None
        self.channel = channel
        fmt = self.log_path.suffix.lstrip(".").lower() if self.log_path is not None else "log"
        #: the channel frames carry into the log (module function :func:`log_channels`)
        self._log_ch: str | int = log_channels(fmt, [channel])[channel]
        self.epoch = epoch_s
        self.plant_io_on_bus = plant_io_on_bus
        self.barrier = barrier  # without barrier frames, the n-th STATE frame ends phase 1
        for m in layout.messages:  # every identifier the layout knows; the rest are neither (ideal_period)
            self._untimed(m.frame_id)
            self._sim_control(m.frame_id)
        self._writer: can.Listener | None = None
        self._k = -1
        # a tick is complete once every CMD_DONE (without barrier: every command frame) is seen;
        # only then does a SYNC or END count (canbrake.bus.guard.sync_verdict)
        self._closing_kind = "cmd_done" if barrier else "cmd"
        # (external ECUs' frames close no tick: the plant may go on without them, see PlantNode)
        self._closing_ids = {m.frame_id for m in layout.messages
                             if m.kind == self._closing_kind and m.ecu not in external}
        self._closing_total = len(self._closing_ids)
        self._closing_seen = 0
        self.guard = FrameGuard(secoc)
        self.final_tick = None if n_ticks is None else n_ticks - 1
        #: frames received and each kind's phase, by frame_key (identifier, extended, error frame)
        self._counts: dict[int, int] = {}
        self._phase_of: dict[int, int] = {}
        self._tick_frames: list[can.Message] = []
        #: the lockstep receive loop, compiled: handle_batch's and handle_raw's (nodes._trace)
        self._taker = RecorderTaker(self)
        self._bus_free_s = 0.0
        # per-period series in compact arrays (8 bytes per period each); latencies in a histogram
        # of fixed size whatever the run length
        self._series = LoadSeries(None if log_path is None else Path(log_path).parent / "bus_load.csv", dt_s)
        self._latency = LogHistogram()
        self._rt_bits = 0
        self._rt_tick_start: float | None = None
        self._flush_each = True
        self._text_file: Any = None
        self._text_fd = -1  # frames.log's descriptor when ideal_tick writes its lines straight to it
        # the timing model (canbrake.bus.schedule.LockstepBusTiming, the recorder's own replica):
        # modelled wire times for the stamps and, with bus errors, the error frames
        self.wire_model = bus_timing if bus_timing is not None and mode == "lockstep" else None
        self._wire_done: list[tuple[float, int, bool]] = []  # model completions not matched yet
        if self.wire_model is not None:
            self.wire_model.delivery_log = self._wire_done
        self.timing = bus_timing if bus_timing is not None and getattr(bus_timing, "faults", None) else None
        self._ev_i = 0
        self.error_frames = 0
        self._err_nodes = ["plant"] + [e.name for e in layout.ecus]
        self._err_file: Any = None  # can_errors.csv, written per period as the states change
        # bus segments (canbrake.bus.segments): (Topology, decision offset c·T in s, tx_buffers)
        self.net: Any = None
        if segments is not None:
            from canbrake.bus.segments import SegmentedNetwork, message_routes

            self.topo, self._cmd_offset_s, tx_buffers = segments
            self.net = SegmentedNetwork(self.topo, stuffing="actual", tx_buffers=tx_buffers)
            self.routes = message_routes(layout, self.topo, plant_io_on_bus)
            self._seg_writers: dict[str, Any] = {}
            self._seg_series = {seg: LoadSeries(None, dt_s) for seg in self.topo.names}
            self._seg_frames = {seg: 0 for seg in self.topo.names}
            self.wire_model = None  # the stamps come from the segmented network
            self._seg_ch = log_channels(fmt, list(self.topo.names))

    def start(self, now: float) -> list[can.Message]:
        #: hand each period's lines to the OS as it ends (a recorder in its own process); the
        #: in-process engine's files are written through their buffers (canbrake.nodes.base.buffered_traces)
        self._flush_each = rows_by_row()
        if self.log_path is not None:
            self._writer = _log_writer(self.log_path)
            writers = [self._writer]
            if self.net is not None:
                for seg in self.topo.names:
                    self._seg_writers[seg] = _log_writer(self._seg_log(seg))
                    writers.append(self._seg_writers[seg])
            # the text log's file, flushed each period (binary formats keep python-can's buffering)
            w0 = self._writer
            self._text_file = (getattr(w0, "file", None)
                               if isinstance(w0, can.io.generic.TextIOMessageWriter) else None)
            if self._flush_each and type(w0) is can.CanutilsLogWriter and self._images_kept():
                # each period's lines go straight to the file (one write(2), no Python buffer): the
                # writer's buffers stay empty, every other line (the END) is written after the last period
                self._text_file.flush()
                self._text_fd = self._text_file.fileno()
            for w in writers:
                if self.mode == "lockstep" and isinstance(w, can.ASCWriter):
                    # ASC stamps are relative to the start of measurement: make that simulated time 0
                    w.log_event("canbrake: simulated time", timestamp=self.epoch)
        return []

    def _seg_log(self, seg: str) -> Path:
        assert self.log_path is not None
        return self.log_path.with_name(f"{self.log_path.stem}_{seg}{self.log_path.suffix}")

    # ---------------------------------------------------------------- receive
    def handle(self, msg: can.Message, now: float) -> list[can.Message]:
        return self.handle_batch([msg], now)

    def handle_batch(self, msgs: list[can.Message], now: float) -> list[can.Message]:
        """Count each frame by (identifier, extended, error frame) and keep it for its period's
        log lines (lockstep: written, in bus order, when the next SYNC or END comes)."""
        counts = self._counts
        if self.mode == "realtime":
            for msg in msgs:
                key = frame_key(msg.arbitration_id, msg.is_extended_id, msg.is_error_frame)
                counts[key] = counts.get(key, 0) + 1
                self._realtime(msg, now)
            return []
        # the frames in one compiled loop, back here at a SYNC and at a key not seen before
        if type(msgs) is not list:
            msgs = list(msgs)
        return self._taker(msgs, now)

    def handle_raw(self, frames: bytes | bytearray, now: float, message: Any) -> list[can.Message]:
        """:meth:`handle_batch` for the memory bus's slot images (``MemoryBus.recv_raw``: the
        receive and its wait in one compiled call), counted and kept by
        :class:`~canbrake.nodes._trace.RecorderTaker` (keys and payloads read from the images);
        ``message(frames, i)`` makes image i the ``can.Message`` the bus's ``recv`` gives (kept
        for the log; realtime: every frame)."""
        n = len(frames) // SLOT_BYTES
        if self.mode == "realtime":
            return self._realtime_raw(frames, n, now, message)
        # the period's frames kept as their slot images (no Message each) where only the ideal
        # accounting and the candump text read them (_wire.ideal_period, _candump.write_candump)
        return self._taker.raw(frames, None if self._images_kept() else message, message)

    def _realtime_raw(self, frames: bytes | bytearray, n: int, now: float, message: Any) -> list[can.Message]:
        """Realtime :meth:`handle_batch` over the ``n`` slot images ``frames``: the frames between
        SYNCs counted, logged and their bits added in compiled loops
        (:func:`~canbrake.nodes._trace.take_realtime_raw`, :func:`~canbrake.bus._wire.timed_bits_raw`,
        candump lines by :meth:`_write_stamped`), no ``can.Message`` each; each SYNC, which ends a
        period's load, as a ``Message`` through :meth:`_realtime`. Other log formats take the
        ``Message`` path."""
        if not (self._writer is None or type(self._writer) is can.CanutilsLogWriter):
            return self.handle_batch([message(frames, i) for i in range(n)], now)
        i = 0
        while i < n:
            stamped: list[tuple[float, bytes]] = []
            j, errors = take_realtime_raw(frames, i, now, self._counts, self._sim_control_memo,
                                          self.layout.sync_id, stamped)
            self._write_stamped(stamped)  # type: ignore[arg-type]
            self.error_frames += errors
            self._rt_bits += timed_bits_raw(frames, i, j, self._untimed_memo)
            if j >= n:
                break
            self.handle_batch([message(frames, j)], now)  # the SYNC: counted, logged, the period's load
            i = j + 1
        return []

    def _images_kept(self) -> bool:
        """Whether a period's frames may be kept as slot images: no segments, timing model or
        error frames (which read messages), and the log candump -L or none."""
        return (self.net is None and self.wire_model is None and self.timing is None
                and (self._writer is None or type(self._writer) is can.CanutilsLogWriter))

    def batch_handler(self) -> Any:
        """:meth:`handle_batch` as the in-process Router calls it: in lockstep, the receive loop
        as one compiled call (:class:`~canbrake.nodes._trace.RecorderTaker`, the same work)."""
        return self.handle_batch if self.mode == "realtime" else self._taker

    def _on_event(self, ev: int, msg: can.Message) -> bool:
        """What the compiled receive loop stopped at: a SYNC (:meth:`_on_sync`; True if it was the
        END) or a key with no phase yet (its phase set)."""
        if ev == TAKE_SYNC:
            return self._on_sync(msg)
        aid, ext = msg.arbitration_id, msg.is_extended_id
        kind = "error" if msg.is_error_frame else self._kinds.get(aid, "other")
        self._phase_of[frame_key(aid, ext, msg.is_error_frame)] = (
            0 if aid == self.layout.plant_heartbeat_id and ext == (aid > 0x7FF) else _PHASE.get(kind, 1))
        return False

    def _on_sync(self, msg: can.Message) -> bool:
        """A SYNC frame (lockstep): a trusted one ends the period (its frames are written) and
        starts the next; True if it was the END (the recorder has finished)."""
        verdict = sync_verdict(self.guard, msg.arbitration_id, msg.data, self._k, lockstep=True,
                               final_tick=self.final_tick,
                               tick_complete=self._k < 0 or self._closing_seen >= self._closing_total)
        if verdict is None:
            return False
        self._flush_tick()
        tick = int.from_bytes(msg.data[:4], "little")
        if tick == dbc.SYNC_END_TICK:
            t_end = (self._k + 1) * self.dt + self._wire_s(msg)
            if self.net is not None:  # the last frames first, then END on the plant's segment
                t_end = max(t_end, self._drain_segments())
                self._write_segments([(self.topo.plant_segment, self._stamp(msg, t_end))])
            else:
                self._write([self._stamp(msg, t_end)])
            self.finished = True
            return True
        self._k = tick
        self._closing_seen = 0
        return False

    # what was received, derived from the counts by (identifier, extended, error frame)
    @property
    def frames(self) -> int:
        return sum(self._counts.values())

    @property
    def frames_by_kind(self) -> dict[str, int]:
        out: dict[str, int] = {}
        for key, n in self._counts.items():
            aid, _ext, err = key_fields(key)
            kind = "error" if err else self._kinds.get(aid, "other")
            name = _KIND_NAME.get(kind, kind)
            out[name] = out.get(name, 0) + n
        return dict(sorted(out.items()))  # by name: the same file whatever order frames arrived in

    @property
    def frames_by_id(self) -> dict[int, int]:
        out: dict[int, int] = {}
        for key, n in self._counts.items():
            out[key >> 2] = out.get(key >> 2, 0) + n
        return out

    @property
    def other_ids(self) -> dict[str, int]:
        """Frames on identifiers outside the database, by identifier: who flooded or inserted."""
        out: dict[str, int] = {}
        for key, n in self._counts.items():
            aid, ext, err = key_fields(key)
            if not err and aid not in self._kinds:
                k = f"{aid:#05x}" if not ext else f"{aid:#010x}"
                out[k] = out.get(k, 0) + n
        return out

    def _wire_s(self, msg: can.Message) -> float:
        """The frame's time on the wire (s), actual stuffing; 0 for frames the accounting leaves out."""
        if self._untimed(msg.arbitration_id):
            return 0.0
        return actual_frame_bits(msg.arbitration_id, msg.is_extended_id, msg.dlc, bytes(msg.data)) / self.bitrate

    def _flush_tick(self) -> None:
        if self.net is not None:
            self._flush_tick_segmented()
            return
        if self._k < 0 or not self._tick_frames:
            self._tick_frames = []
            return
        t_k = self._k * self.dt
        # the accounting (compiled, one call per period): a busy bus carries over into this
        # period; frames back to back in bus order, actual stuffing; stamps kept in [t_k, t_k + T]
        if self._images_kept():  # the common case: order, accounting and candump lines in one call
            t, busy, n_timed, latencies = ideal_tick(
                self._tick_frames, self._untimed_memo, self._sim_control_memo, max(t_k, self._bus_free_s), t_k,
                self.dt, self.bitrate, self.epoch, self._writer, self._log_ch, self._series, self._text_fd)
            self._latency.add_many(latencies)
            self._bus_free_s = t
            if self._flush_each:  # frames.log's lines are written already (_text_fd), or there is no log
                self._series.flush()
            self._tick_frames = []
            return
        ordered = sorted(self._tick_frames, key=_BUS_ORDER)
        t, busy, n_timed, latencies, out = ideal_period(
            ordered, self._untimed_memo, self._sim_control_memo, max(t_k, self._bus_free_s), t_k, self.dt,
            self.bitrate, self.epoch)
        self._latency.add_many(latencies)
        self._bus_free_s = t
        if self.wire_model is not None:
            seen = {id(f[3]): i for i, f in enumerate(self._tick_frames)}
            # each logged frame's place in the order frames arrived
            out = self._model_stamps(out, [seen[id(m)] for _ts, m in out], t_k)
        n_out = len(out)
        if self.timing is not None:
            out = self._with_errors(out)
        self._series.add(busy / self.dt, n_timed, len(out) - n_out)
        self._write_stamped(out)
        self._flush_file()
        self._tick_frames = []

    # ---------------------------------------------------------------- segments
    def _flush_tick_segmented(self) -> None:
        """Bus segments: the period's frames go through the recorder's own segmented network
        (actual stuffing), queued at t_k (phase 0/1) or at the decision instant t_k + c·T
        (commands) on their sender's segment and forwarded by the gateways; each end of frame on
        a segment is one line, stamped with that time, channel = the segment's name (its number
        in the numbered formats, :func:`log_channels`)."""
        if self._k < 0:
            self._tick_frames = []
            return
        t_k = self._k * self.dt
        local: list[tuple[str, can.Message]] = []
        plant_seg = self.topo.plant_segment
        for phase, aid, _data, msg in sorted(self._tick_frames, key=lambda f: (f[0], f[1], f[2])):
            if is_sim_control(aid, self.layout):
                continue
            node, src, dests = self.routes.get(aid, ("other", plant_seg, frozenset({plant_seg})))
            if self._untimed(aid):  # local wiring: on its segment's log, no bus time
                local.append((src, self._stamp(msg, t_k)))
                continue
            t_q = t_k + (self._cmd_offset_s if phase == 2 else 0.0)
            self.net.submit(node, aid, msg.is_extended_id, msg.dlc, bytes(msg.data), t_q, src=src, dests=dests,
                            tag=msg)
        self._tick_frames = []
        self._segment_period(local, self.net.advance(t_k + self.dt))
        self._flush_file()
        for w in self._seg_writers.values():
            f = getattr(w, "file", None)
            if f is not None and isinstance(w, can.io.generic.TextIOMessageWriter):
                f.flush()

    def _segment_period(self, local: list[tuple[str, can.Message]], deliveries: list[Any],
                        period: bool = True) -> None:
        busy = {seg: 0.0 for seg in self.topo.names}
        count = {seg: 0 for seg in self.topo.names}
        out = list(local)
        for seg, d in deliveries:
            busy[seg] += d.t_end_s - d.t_start_s
            count[seg] += 1
            self._latency.add(d.t_end_s - d.tag.t_queue)
            out.append((seg, self._stamp(d.tag.tag, d.t_end_s)))
        for seg in self.topo.names:
            if period:
                self._seg_series[seg].add(busy[seg] / self.dt, count[seg], 0)
            self._seg_frames[seg] += count[seg]
        if period:
            self._series.add(max(busy.values()) / self.dt, sum(count.values()), 0)
        self._write_segments(out)

    def _drain_segments(self, max_periods: int = 1000) -> float:
        """Carry the frames still queued or on the wire to their last segment (at the end of a
        run); returns the time the network reached."""
        n = 0
        while self.net.pending() and n < max_periods:
            self._segment_period([], self.net.advance(self.net.now_s + self.dt), period=False)
            n += 1
        return self.net.now_s

    def _write_segments(self, out: list[tuple[str, can.Message]]) -> None:
        order = {seg: i for i, seg in enumerate(self.topo.names)}
        out.sort(key=lambda sm: (sm[1].timestamp, order[sm[0]]))
        for seg, m in out:
            m.channel = self._seg_ch[seg]
        self._write([m for _seg, m in out])
        for seg, m in out:
            w = self._seg_writers.get(seg)
            if w is not None:
                w.on_message_received(m)

    def _segment_stats(self) -> dict:
        from canbrake.bus.segments import forwarding_tables

        fmt = self.log_path.suffix if self.log_path is not None else ".log"
        return {
            "segments": {seg: {"bitrate_bps": self.topo.bitrate[seg], "frames": self._seg_frames[seg],
                               "bus_load_mean": float(self._seg_series[seg].mean),
                               "bus_load_peak": float(self._seg_series[seg].peak),
                               "bus_load_peak_window": max([self._seg_series[seg].peak_window,
                                                            *self._seg_series[seg].window_list()]),
                               "nodes": sorted(n for n, g in self.topo.segment_of.items() if g == seg),
                               "log": f"frames_{seg}{fmt}",
                               # its number in .asc/.blf/.trc/.mf4 logs (CANoe's CAN 1..n)
                               "channel": i + 1} for i, seg in enumerate(self.topo.names)},
            "gateways": {gw: {"delay_s": d, "frames_forwarded": self.net.forwarded.get(gw, 0)}
                         for gw, d in sorted(self.topo.delay.items())},
            "forwarding_tables": forwarding_tables(self.layout, self.topo),
        }

    def _model_stamps(self, out: list[tuple[float, can.Message]], arrival: list[int],
                      t_k: float) -> list[tuple[float, can.Message]]:
        """Restamp the period's frames with the timing model's completion times (module
        docstring, ``bus.timing: model``) and put them in stamp order."""
        horizon = t_k + self.dt * (1 - 1e-9)  # the senders' last release horizon of the period
        self.wire_model.simulate_through(t_k + self.dt)
        done: dict[tuple[int, bool], list[float]] = {}
        later = []
        for t_end, aid, ext in self._wire_done:
            if t_end <= horizon:
                done.setdefault((aid, ext), []).append(t_end)
            else:
                later.append((t_end, aid, ext))
        self._wire_done[:] = later  # the rest ends in a later period; unmatched ones are dropped
        phase_start = {2: t_k + self.wire_model.c}
        stamped = []
        for _n, (_ts, m) in sorted(zip(arrival, out), key=lambda x: x[0]):  # arrival order within an identifier
            aid = m.arbitration_id
            phase = (0 if aid == self.layout.plant_heartbeat_id and m.is_extended_id == (aid > 0x7FF)
                     else _PHASE.get(self._kinds.get(aid, "other"), 1))
            times = done.get((m.arbitration_id, m.is_extended_id))
            t = min(max(times.pop(0), t_k), horizon) if times else phase_start.get(phase, t_k)
            stamped.append((t, phase, m.arbitration_id, bytes(m.data), self.epoch + t, m))
        stamped.sort(key=lambda x: x[:4])
        return [x[4:] for x in stamped]

    def _with_errors(self, out: list[tuple[float, can.Message]]) -> list[tuple[float, can.Message]]:
        """Add the error frames of tick ``self._k`` (in time order) and sample the error states."""
        fc = self.timing.faults
        t_next = (self._k + 1) * self.dt
        self.timing.simulate_through(t_next)
        events = fc.events
        new = []
        while self._ev_i < len(events) and events[self._ev_i].t_start_s < t_next:
            ev = events[self._ev_i]
            new.append((self.epoch + ev.t_start_s, error_frame(ev, self.epoch + ev.t_start_s, self._log_ch)))
            self._ev_i += 1
        self.error_frames += len(new)
        row = [self._k]
        for name in self._err_nodes:
            c = fc.nodes.get(name)
            row += [0, 0, 0] if c is None else [{"active": 0, "passive": 1, "bus_off": 2}[c.state], c.tec, c.rec]
        self._error_row(row)
        if not new:
            return out
        return sorted(out + new, key=lambda sm: sm[0])

    def _col_suffix(self, name: str) -> str:
        """Column suffix of a node: ``plant``, ``c3`` for the default ECU of car 3, else its name."""
        if name == "plant":
            return "plant"
        e = next((e for e in self.layout.ecus if e.name == name), None)
        return e.tag.lower() if e is not None else name

    def _error_row(self, row: list[int]) -> None:
        """One period of every node's error state, appended to can_errors.csv at once."""
        if self.log_path is None:
            return
        if self._err_file is None:
            header = ["tick"]
            for name in self._err_nodes:
                sfx = self._col_suffix(name)
                header += [f"can_state_{sfx}", f"tec_{sfx}", f"rec_{sfx}"]
            self._err_file = open(self.log_path.parent / "can_errors.csv", "w", newline="")
            self._err_writer = csv.writer(self._err_file)
            self._err_writer.writerow(header)
        self._err_writer.writerow(row)

    def _fps_by_sender(self, span: float) -> dict[str, float]:
        """Frames per second by sending node (the layout's sender of each identifier)."""
        out: dict[str, float] = {}
        for aid, n in self.frames_by_id.items():
            if self._untimed(aid):
                continue
            m = self.layout.by_id.get(aid)
            who = "other" if m is None else ("plant" if m.ecu == 0 else self.layout.by_index[m.ecu].name)
            out[who] = out.get(who, 0.0) + n / span
        return dict(sorted(out.items()))

    def _stamp(self, msg: can.Message, t_s: float) -> can.Message:
        return self._stamped(msg, self.epoch + t_s)

    def _stamped(self, msg: can.Message, timestamp: float) -> can.Message:
        """``msg`` as the log holds it: ``timestamp`` (s), the recorder's channel, received
        (:func:`canbrake.bus._candump.write_candump` writes the same for frames.log)."""
        return can.Message(timestamp=timestamp, arbitration_id=msg.arbitration_id,
                           is_extended_id=msg.is_extended_id, is_remote_frame=msg.is_remote_frame,
                           is_error_frame=msg.is_error_frame, dlc=msg.dlc, data=msg.data,
                           channel=self._log_ch, is_rx=True)

    def _realtime(self, msg: can.Message, now: float) -> None:
        m = self._stamp(msg, 0.0)
        m.timestamp = msg.timestamp or now
        aid = msg.arbitration_id
        if not is_sim_control(aid, self.layout):
            self._write([m])
        if aid == self.layout.sync_id:
            if self._rt_tick_start is not None:
                self._series.add(self._rt_bits / self.bitrate / self.dt, "", 0)
                self._flush_file()
            self._rt_bits = 0
            self._rt_tick_start = m.timestamp
            verdict = sync_verdict(self.guard, aid, msg.data, self._k, lockstep=False, tick_complete=True,
                                   final_tick=self.final_tick)
            if verdict == "end":
                self.finished = True
            elif verdict == "tick":
                self._k = int.from_bytes(msg.data[:4], "little")
        if msg.is_error_frame:  # realtime bus errors (canbrake.bus.rt_errors): logged, counted, no wire model
            self.error_frames += 1
        elif not self._untimed(aid):
            self._rt_bits += frame_bits(aid, msg.is_extended_id, msg.dlc, bytes(msg.data), stuffing="actual",
                                        is_remote=msg.is_remote_frame)

    def _sim_control(self, aid: int) -> bool:
        """:func:`is_sim_control` of the layout, memoised per identifier."""
        r = self._sim_control_memo.get(aid)
        if r is None:
            r = self._sim_control_memo[aid] = is_sim_control(aid, self.layout)
        return r

    def _untimed(self, aid: int) -> bool:
        """Frames that take no bus time in the accounting: barrier frames, and the plant's sensor
        frames unless they are declared bus traffic (they stand in for local wiring)."""
        memo = self._untimed_memo
        r = memo.get(aid)
        if r is None:
            kind = self._kinds.get(aid)
            r = memo[aid] = kind in ("state_done", "cmd_done") or (not self.plant_io_on_bus and kind == "sensor")
        return r

    def _write(self, msgs: list[can.Message]) -> None:
        if self._writer is not None:
            for m in msgs:
                self._writer.on_message_received(m)

    def _write_stamped(self, stamped: list[tuple[float, can.Message]]) -> None:
        """Write a period's (timestamp, frame) pairs, each as :meth:`_stamp` makes it (the
        recorder's channel, received). candump -L (``frames.log``): the period's lines in one
        compiled call that writes what python-can's ``CanutilsLogWriter`` writes, into its file
        (:mod:`canbrake.bus._candump`); every other format through python-can's writer."""
        w = self._writer
        if w is None:
            return
        if type(w) is can.CanutilsLogWriter:
            write_candump(w, stamped, self._log_ch)
            return
        for ts, m in stamped:
            w.on_message_received(self._stamped(m, ts))

    # ---------------------------------------------------------------- results
    def _flush_file(self) -> None:
        """Hand the tick's lines to the OS (one write per control period), so a killed recorder
        loses at most the current period. Binary formats (.blf: compressed containers) keep
        python-can's own buffering."""
        if not self._flush_each:
            return
        if self._text_file is not None and self._writer is not None:
            self._text_file.flush()
        self._series.flush()
        if self._err_file is not None:
            self._err_file.flush()

    def bus_stats(self) -> dict:
        ser = self._series
        lat = self._latency
        span = max(self.dt * max(ser.n, 1), 1e-12)
        return {
            "frames": self.frames,
            "frames_by_kind": self.frames_by_kind,
            "frames_by_unknown_id": dict(sorted(self.other_ids.items(), key=lambda kv: -kv[1])[:20]),
            "bitrate_bps": self.bitrate,
            "bus_load_mean": float(ser.mean),
            "bus_load_peak": float(ser.peak),
            "plant_io_on_bus": self.plant_io_on_bus,
            "latency_model": ("lockstep, bus segments: per segment (bus load = the most loaded segment), frames "
                              "queued at t_k / t_k + c*T on their sender's segment and forwarded by the gateways, "
                              "actual stuffing" if self.net is not None else
                              "lockstep: all frames of a phase queued at t_k, arbitration order, actual stuffing")
            if self.mode == "lockstep" else "not modelled in realtime mode",
            "latency_p50_s": lat.quantile(0.50),
            "latency_p99_s": lat.quantile(0.99),
            "latency_max_s": lat.max,
            "bus_load_window_s": ser.window_s,
            "bus_load_windows": ser.window_list(),
            "bus_load_peak_window": max([ser.peak_window, *ser.window_list()]),
            "frames_per_s_by_id": {f"0x{aid:03X}": n / span for aid, n in sorted(self.frames_by_id.items())
                                   if not self._untimed(aid)},
            "frames_per_s_by_sender": self._fps_by_sender(span),
            "error_frames_per_s": float(ser.errors if self.mode == "lockstep" else self.error_frames) / span,
            "error_frames_received": self.error_frames,
            **({"errors": {**self.timing.faults.summary(self.timing.model.now_s),
                           "error_frames_logged": self.error_frames,
                           "state_codes": {"active": 0, "passive": 1, "bus_off": 2}}}
               if self.timing is not None else {}),
            **(self._segment_stats() if self.net is not None else {}),
        }

    def close(self, status: str = "ok") -> None:
        try:
            if self.mode == "lockstep" and not self.finished:
                self._flush_tick()
                if self.net is not None:
                    self._drain_segments()
            if self._writer is not None:
                self._writer.stop()
            for w in getattr(self, "_seg_writers", {}).values():
                w.stop()
        finally:
            self._writer = None
            self._text_fd = -1
            if self.net is not None:
                self._seg_writers = {}
                if self.log_path is not None and self.log_path.suffix == ".log":
                    for seg in self.topo.names:
                        trim_partial_line(self._seg_log(seg))
            if self.log_path is not None and self.log_path.suffix == ".log":
                trim_partial_line(self.log_path)
        self._series.close()
        if self._err_file is not None:
            self._err_file.close()
            self._err_file = None
        if self.log_path is not None:
            stats = self.bus_stats()
            stats["status"] = "ok" if self.finished else status
            stats["guard"] = self.guard.stats()
            if self.scheduling is not None:
                stats["scheduling"] = self.scheduling
            write_text_atomic(self.log_path.parent / "bus_stats.json", json.dumps(stats, indent=1))
