"""The plant node: time master. Sends SYNC/REFERENCE/sensor frames, collects brake commands,
advances the physics model one control period at a time and writes ``signals.csv``.

It knows frames and timing, not train formulas: the physics is any object following
:class:`PlantModel`.
"""
from __future__ import annotations

import json
import math
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Callable, Protocol

import can
import numpy as np

from canbrake.bus import dbc
from canbrake.bus.codec import FrameCodec
from canbrake.bus._codec import (CMD_BAD_COUNTER, CMD_BAD_CRC, CMD_FRESH, CMD_OUT_OF_SEQUENCE, CMD_SLOT_COMPLETE,
                                  TAKE_BATCH_END, TAKE_BATCH_OTHER, TAKE_BATCH_TICK, CommandTable, SensorPages,
                                  TickFrames)
from canbrake.bus._ring import messages_of
from canbrake.bus.guard import FrameGuard, sign_control
from canbrake.bus.memory_shm import SLOT_BYTES
from canbrake.nodes._trace import csv_pick_row, csv_row, hist_add_bits, write_text
from canbrake.atomic import write_text_atomic
from canbrake.nodes.base import CsvTrace, LogHistogram, Node, exact_filter, frame


from canbrake.physics.contract import PlantModel  # noqa: E402  (the contract every model implements)


def _joined(a: list[can.Message] | bytes, b: list[can.Message] | bytes) -> list[can.Message] | bytes:
    """Frames ``a`` then ``b`` (each a list of messages or slot images): images if both are,
    else messages (the images' made by :func:`canbrake.bus._ring.messages_of`)."""
    if not b:
        return a
    if not a:
        return b
    if type(a) is bytes and type(b) is bytes:
        return a + b
    return ((messages_of(a) if type(a) is bytes else list(a))
            + (messages_of(b) if type(b) is bytes else list(b)))


Reference = Callable[[float], tuple[float, float]]  # t_s -> (v* m/s, a* m/s^2); may have .position(t_s) -> x* m


@dataclass
class FailSafe:
    """Each car's brake unit reaction to lost commands: after ``timeout_ticks`` control periods
    without a valid (E2E-checked, in-sequence) command, apply ``force_n`` (N per car, + = brake).
    ``latch``: stay in fail-safe to the end of the run, else leave it on the next valid command."""

    timeout_ticks: int
    force_n: np.ndarray
    latch: bool = True
    #: commands the brake unit applies in fail-safe instead of ``force_n`` (name -> value for every
    #: vehicle in fail-safe, e.g. ``{"ecp_demand": 1.0}``); empty: ``brake_force_n = force_n``
    values: dict[str, float] = field(default_factory=dict)


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
    # realtime: wall seconds the period grid was moved on after late periods (no catch-up burst)
    slipped_s: float = 0.0
    wall_time_s: float = 0.0
    failsafe_activations: int = 0     # car entries into fail-safe braking
    failsafe_ticks: int = 0           # ticks x cars spent in fail-safe braking
    failsafe_first_s: dict[str, float] = field(default_factory=dict)  # car -> first activation (s)
    status: str = "running"
    extra: dict[str, float] = field(default_factory=dict)
    guard: dict = field(default_factory=dict)  # canbrake.bus.guard: rejected frames by reason
    #: external ECUs (not started by canbrake): per name first heartbeat, periods without their
    #: commands, lockstep time-outs, entries into "silent" (see PlantNode)
    external: dict = field(default_factory=dict)
    #: wall time from a period's SYNC to each ECU's complete commands (s): p50/p99/max per ECU
    response_s: dict = field(default_factory=dict)
    time_scale: float = 1.0
    #: wall time of the plant model's step per period (s): n, mean, p50, p99, max, total
    #: (LogHistogram.figures); the physics' execution time on this host, preemption included
    model_step_s: dict = field(default_factory=dict)


class PlantNode(Node):
    """Time master and physics host."""

    name = "plant"
    time_master = True

    def __init__(self, model: PlantModel, codec: FrameCodec, *, layout: Any, dt_s: float, n_ticks: int,
                 reference: Reference, mode: str = "lockstep",
                 heartbeat_period_s: float = 0.1, out_dir: str | Path | None = None,
                 flush_every: int = 500, progress: Any = None, hosted: list[Any] | None = None,
                 barrier: bool = True, failsafe: FailSafe | None = None, secoc: Any = None,
                 trace_every: int = 1, external: frozenset[int] = frozenset(),
                 external_start_timeout_s: float = 30.0, external_timeout_s: float = 1.0,
                 time_scale: float = 1.0) -> None:
        self.model = model
        self.trace_every = max(1, int(trace_every))
        self.codec = codec
        self.layout = layout
        self.n = model.n_vehicles
        self.ecus = list(layout.ecus)
        self.n_ecus = len(self.ecus)
        self.dt = dt_s
        self.n_ticks = n_ticks
        self.reference = reference
        self.mode = mode
        self.heartbeat_every = max(1, int(round(heartbeat_period_s / dt_s)))
        self.out_dir = Path(out_dir) if out_dir else None
        self.flush_every = flush_every
        self.progress = progress  # optional shared value (``.value``) the supervisor watches
        # send paths of traffic sources the plant hosts (babbling nodes that are not real nodes)
        self.hosted = list(hosted or [])
        # barrier=False: commands cannot be lost or delayed, so the commands themselves close the tick
        self.barrier = barrier
        self.k = 0
        self.stats = PlantStats(commands_missed_per_car=[0] * self.n_ecus)
        self._model_time = LogHistogram(1.01)  # the model step's wall time per period, 1 % bins
        # commands by name, per vehicle (NaN: no ECU commands it); 0 until a vehicle's first command
        self.command_names = sorted({c for e in self.ecus for c in e.commands})
        self.commands = {c: np.full(self.n, np.nan) for c in self.command_names}
        for e in self.ecus:
            for c in e.commands:
                self.commands[c][e.vehicle - 1] = 0.0
        if "brake_force_n" not in self.commands:
            self.commands["brake_force_n"] = np.full(self.n, np.nan)
        self.cmd_n = self.commands["brake_force_n"]
        # command frames: id -> (ECU slot, page, codec, [(signal, dbc name)])
        self._cmd_pages: dict[int, tuple[int, int, Any, list[tuple[str, str]]]] = {}
        self._pages_per_ecu = np.zeros(self.n_ecus, dtype=np.int64)
        for m in layout.messages:
            if m.kind == "cmd":
                slot = m.ecu - 1
                self._cmd_pages[m.frame_id] = (slot, m.page, codec[m.name],
                                               [(sig, sp.name) for sig, sp in m.signals if sig])
                self._pages_per_ecu[slot] += 1
        self._cmd_done_ids = {layout.plan.cmd_done(e.index): e.index - 1 for e in self.ecus}
        self._veh = np.asarray([e.vehicle - 1 for e in self.ecus], dtype=np.int64)
        self._fresh_pages = np.zeros(self.n_ecus, dtype=np.int64)
        self._n_pages = int(self._pages_per_ecu.sum())  # command pages of one tick, every ECU
        self._fresh = np.zeros(self.n_ecus, dtype=bool)
        self._done = 0  # bit i set: CMD_DONE of ECU slot i seen this tick
        self._all_done = (1 << self.n_ecus) - 1
        self._last_counter = np.full(self.n_ecus, -1, dtype=np.int64)  # tick of each ECU's newest command
        self.failsafe = failsafe
        # brake-unit receive checks (E2E window of 7 periods, SecOC) and rejection counters
        self.secoc = secoc
        self.guard = FrameGuard(secoc, max_lag=7)
        self.guard.counter_ext = layout.counter_ext()
        # the command pages' E2E receivers, origin windows and decoding into self.commands, compiled
        # (canbrake.bus._codec.CommandTable: one call per frame, the arrays updated in place)
        self._cmd_table = CommandTable(self._fresh_pages, self._pages_per_ecu, self._fresh, self._last_counter,
                                       self.guard.max_lag)
        for fid, (slot, _p, cdc, sigs) in self._cmd_pages.items():
            v = int(self._veh[slot])
            self._cmd_table.add_page(fid, slot, cdc._c, [(dn, self.commands[sig], v) for sig, dn in sigs],
                                     self.guard.counter_ext.get(fid))
        self._last_sync_k = -1
        # command identifiers of ECUs this train does not have (11-bit plan): unknown senders
        self._foreign_cmd_ids = ([dbc.BRAKE_CMD_BASE + i for i in range(self.n_ecus + 1, dbc.MAX_CARS + 1)]
                                 if not layout.plan.extended else [])
        self._in_failsafe = np.zeros(self.n_ecus, dtype=bool)
        self._sync = codec["SYNC"]
        self._ref = codec["REFERENCE"]
        self._ref_pos = codec["REFERENCE_POS"] if layout.ref_position else None
        self._sensor_msgs = [(m.frame_id, codec[m.name], m.ecu, [(sig, sp.name) for sig, sp in m.signals if sig])
                             for m in layout.messages if m.kind == "sensor"]
        self._sensor_arrays = sorted({"deflection_m" if sig in ("deflection_front_m", "deflection_rear_m") else sig
                                      for *_x, sigs in self._sensor_msgs for sig, _d in sigs})
        # every sensor page of a period in one compiled call (arrays in, payloads out): per signal
        # the measurement array and element it reads (a coupler's deflection: the one in front of
        # or behind the vehicle; 0.0 at the train's ends)
        src_of = {name: i for i, name in enumerate(self._sensor_arrays)}
        pages = []
        for _fid, cdc, ecu, sigs in self._sensor_msgs:
            v = self.ecus[ecu - 1].vehicle - 1
            fields = []
            for sig, dbc_name in sigs:
                if sig == "deflection_front_m":
                    fields.append((dbc_name, src_of["deflection_m"], v - 1) if v > 0 else (dbc_name, -1, 0))
                elif sig == "deflection_rear_m":
                    fields.append((dbc_name, src_of["deflection_m"], v) if v < self.n - 1 else (dbc_name, -1, 0))
                else:
                    fields.append((dbc_name, src_of[sig], v))
            pages.append((cdc._c, fields))
        self._sensor_pages = SensorPages(pages)
        self._sensor_ids = [fid for fid, *_x in self._sensor_msgs]
        # the frames of a period's start (SYNC, references, heartbeat, sensor pages) in one compiled call
        self._tick = TickFrames(self._sync._c, layout.sync_id, self._ref._c, layout.reference_id,
                                None if self._ref_pos is None else self._ref_pos._c, layout.reference_pos_id,
                                codec["HEARTBEAT_PLANT"]._c, layout.plant_heartbeat_id, self._sensor_pages,
                                self._sensor_ids, self._sensor_arrays, messages_of)
        self._hb = codec["HEARTBEAT_PLANT"]
        self._t0_wall: float | None = None
        self._t_start_wall: float | None = None
        self._trace: CsvTrace | None = None
        self._row_fd = -1  # signals.csv's descriptor where each row goes straight to the OS (_open_trace)
        #: the trace row taken at the last tick and not yet written (see _record / after_send)
        self._pending_row: tuple[Any, ...] | None = None
        self._extra_meas: list[str] | None = None
        #: (tick, v*, a*, x* or None) of the last tick's frames, for its trace row
        self._ref_of_tick: tuple[int, float, float, float | None] | None = None
        #: the commands written to the trace (besides brake_force_n), and their ECUs' vehicles
        self._row_cmds = [(name, [e.vehicle - 1 for e in self.ecus if name in e.commands])
                          for name in self.command_names if name != "brake_force_n"]
        #: where the trace row's floats are in its arrays, and where its fail-safe flags go (:meth:`_plan_pairs`)
        self._row_plan: tuple[np.ndarray, int] | None = None
        # realtime: wall time the current period's SYNC was sent, and per period the time from it
        # to the last command of the period (s; command latency, `canbrake bench`)
        self._sync_wall: float | None = None
        # realtime: the period's SYNC not yet on the bus (after_send stamps it); the wall time
        # from the period's timer to that moment (the plant's own step, measurements and send)
        self._sync_unsent = False
        self._sync_delay = LogHistogram(1.01)  # 1 % bins
        # realtime: each period's command latency (s) in bounded memory, and the periods whose
        # commands did not all come in time (infinitely late)
        self._cmd_latency = LogHistogram()
        self._cmd_late = 0
        # external ECUs (indices 1-based): the first tick waits for each one's heartbeat; in lockstep a
        # period waits at most external_timeout_s (wall) for their commands once every other ECU's are
        # in, then goes on and treats them as silent (not waited for) until their frames are on time
        self.time_scale = float(time_scale)
        self.stats.time_scale = self.time_scale
        self._ext_slots = sorted(i - 1 for i in external)
        self._ext_mask = sum(1 << s for s in self._ext_slots)
        self._ext_timeout = float(external_timeout_s)
        self._ext_start_timeout = float(external_start_timeout_s)
        self._hb_of_ext = {layout.plan.heartbeat(i): i - 1 for i in external}
        self._unheard = set(self._ext_slots)
        self._start_deadline: float | None = None
        self._ext_deadline: float | None = None
        self._lost = 0  # bit i: external ECU slot i is silent (not waited for)
        self._tick_wall = 0.0

        self._resp = [LogHistogram() for _ in self.ecus]
        for s_ in self._ext_slots:
            self.stats.external[self.ecus[s_].name] = {"first_heartbeat_wall_s": None, "periods_missed": 0,
                                                       "timeouts": 0, "silent_entries": 0, "late_frames": 0}

    # ---------------------------------------------------------------- frames
    def filters(self) -> list[dict]:
        ids = list(self._cmd_pages)
        if self.barrier:
            ids += list(self._cmd_done_ids)
        ids += [i for i in self._foreign_cmd_ids if i not in self.layout.by_id]
        ids += [i for i in self._hb_of_ext if i not in ids]
        return [exact_filter(i) for i in ids]

    def _tick_frames(self, images: bool = False) -> list[can.Message] | bytes:
        """The frames of tick k's start; ``images``: as the memory bus's slot images (bytes,
        :meth:`canbrake.bus._codec.TickFrames.images`) unless a hosted source adds its frames."""
        k = self.k
        t = k * self.dt
        meas = self.model.measurements()
        v_ref, a_ref = self.reference(t)
        x_ref = self.reference.position(t) if self._ref_pos is not None else None
        self._ref_of_tick = (k, v_ref, a_ref, x_ref)  # the trace row of tick k reads them again
        self._last_sync_k = k
        sync = None if self.secoc is None else sign_control(self.secoc, self.layout.sync_id,
                                                            self._sync.encode({"Tick": k}), k)
        if images and not self.hosted:
            return self._tick.images(k, v_ref, a_ref, x_ref, k % self.heartbeat_every == 0, meas, sync)
        out = self._tick.frames(k, v_ref, a_ref, x_ref, k % self.heartbeat_every == 0, meas, sync)
        for sp in self.hosted:
            rogue = sp.release(t)
            out += rogue
            self._hear_hosted(rogue)
        return out

    def _hear_hosted(self, frames: list[can.Message]) -> None:
        """A hosted source is another node on the bus: the brake units hear its command frames
        too (a driver never hands a node the frames it sent itself)."""
        for m in frames:
            if m.arbitration_id in self._cmd_pages or m.arbitration_id in self._foreign_cmd_ids:
                self.handle(m, 0.0)

    def _end_frames(self) -> list[can.Message]:
        end = self._sync.encode({"Tick": dbc.SYNC_END_TICK})
        return [frame(self.layout.sync_id, sign_control(self.secoc, self.layout.sync_id, end, self._last_sync_k))]

    def start(self, now: float) -> list[can.Message]:
        self._open_trace()
        self._t0_wall = now
        self._t_start_wall = now
        if self._unheard:  # wait for every external ECU's first heartbeat
            self._start_deadline = now + self._ext_start_timeout
            return []
        return self._first_tick(now)

    def _first_tick(self, now: float) -> list[can.Message]:
        self._start_deadline = None
        self._t0_wall = now
        self._t_start_wall = now
        self._tick_wall = now
        self._sync_wall = now
        self._sync_unsent = self.mode == "realtime"
        out = self._tick_frames()
        self._arm_external(now)
        return out

    def missing_external(self) -> list[str]:
        """Names of the external ECUs not heard yet (before the first tick)."""
        return [self.ecus[s].name for s in sorted(self._unheard)]

    def _complete(self) -> bool:
        return (self._done | self._lost) == self._all_done

    def _arm_external(self, now: float) -> None:
        """Lockstep: once only external ECUs are missing, wait for them at most external_timeout_s."""
        if self.mode != "lockstep" or not self._ext_mask or self._ext_deadline is not None:
            return
        missing = self._all_done & ~(self._done | self._lost)
        if missing & ~self._ext_mask:
            return
        if missing:
            self._ext_deadline = now + self._ext_timeout
        else:  # only silent external ECUs are outstanding: go on (at once if canbrake has ECUs of its own)
            self._ext_deadline = now + (0.0 if self._ext_mask != self._all_done else 0.1 * self._ext_timeout)

    def _slot_done(self, slot: int, now: float) -> list[can.Message]:
        self._done |= 1 << slot
        self._lost &= ~(1 << slot)  # a silent external ECU on time again
        if self._complete():
            return self._advance(now)
        self._arm_external(now)
        return []

    def handle(self, msg: can.Message, now: float) -> list[can.Message]:
        aid = msg.arbitration_id
        if self._unheard or self._start_deadline is not None:
            slot = self._hb_of_ext.get(aid)
            if slot is not None:
                self._unheard.discard(slot)
                self.stats.external[self.ecus[slot].name]["first_heartbeat_wall_s"] = round(
                    now - (self._t_start_wall or now), 6)
                if not self._unheard:
                    return self._first_tick(now)
            return []
        page = self._cmd_pages.get(aid)
        if page is not None:
            slot = page[0]
            ext = bool(self._ext_mask >> slot & 1)
            r = self._on_command(aid, msg)
            if r & 3 == CMD_FRESH:
                if r & CMD_SLOT_COMPLETE:
                    self._resp[slot].add(max(now - self._tick_wall, 0.0))
                if self.mode == "realtime" and self._sync_wall is not None and self._fresh.all():
                    self._cmd_latency.add(now - self._sync_wall)
                    self._sync_wall = None  # one latency per period
                    if not self._sync_unsent:
                        self._write_row()  # the period's row, now that the CPUs are free (after_send)
                if (not self.barrier or ext) and self.mode == "lockstep" and not self._done >> slot & 1:
                    if self._fresh_pages[slot] >= self._pages_per_ecu[slot]:
                        return self._slot_done(slot, now)
            elif ext and self.stats.external:
                self.stats.external[self.ecus[slot].name]["late_frames"] += 1
            return []
        if aid in self._foreign_cmd_ids and aid not in self.layout.by_id:
            self.guard.unknown(aid)
            return []
        slot = self._cmd_done_ids.get(aid)
        if slot is not None and self.mode == "lockstep":
            tick = self.codec.by_id[aid].decode(msg.data)["Tick"]
            if tick != (self.k & 0xFFFF):
                if self._ext_mask >> slot & 1:  # an external ECU late for a period already gone
                    self.stats.external[self.ecus[slot].name]["late_frames"] += 1
                else:
                    self.guard.reject("sync")
            elif self.guard.control(aid, msg.data, self.k) and not self._done >> slot & 1:
                return self._slot_done(slot, now)
        return []

    def _only_commands_close(self) -> bool:
        """Nothing but the commands themselves closes an ECU's slot (no SecOC, no barrier frames, no
        external ECU, started): every page of every ECU is due each tick."""
        return (self.secoc is None and not self.barrier and not self._ext_mask
                and not self._unheard and self._start_deadline is None)

    def _commands_close_slots(self) -> bool:
        """:meth:`_only_commands_close` in lockstep (the compiled command loop's case)."""
        return self.mode == "lockstep" and self._only_commands_close()

    def frames_wanted(self) -> int:
        """The command pages still missing this tick, when nothing but the commands closes an
        ECU's slot (:meth:`_only_commands_close`; in realtime too: there the period's timer ends
        the wait for pages that do not come), so the plant is woken once a period, not at each
        ECU's command; else 1."""
        if self.finished or not self._only_commands_close():
            return 1
        return max(1, self._n_pages - self._cmd_table.fresh_total())

    def handle_batch(self, msgs: list[can.Message], now: float) -> list[can.Message]:
        """:meth:`handle` for each frame, the command pages (most of what the plant hears) taken
        in one compiled loop (:meth:`canbrake.bus._codec.CommandTable.take_batch`) without
        :meth:`handle`'s other branches where nothing but the lockstep rule applies (no SecOC, no
        external ECU, every ECU's commands close its slot); back here for any other frame, a
        rejected or out-of-sequence command and the command that completes the tick."""
        if not self._commands_close_slots():
            return super().handle_batch(msgs, now)
        if type(msgs) is not list:
            msgs = list(msgs)
        return self._take_batch(self._cmd_table.take_batch, msgs, len(msgs), msgs.__getitem__, now)

    def handle_raw(self, frames: bytes | bytearray, now: float, message: Any) -> list[can.Message]:
        """:meth:`handle_batch` for the memory bus's slot images (``MemoryBus.recv_raw``), the
        command pages taken by :meth:`~canbrake.bus._codec.CommandTable.take_batch_raw` without a
        ``can.Message`` per frame; ``message(frames, i)`` makes one of image i for the frames
        this node's Python handles (all of them where the compiled loop does not apply)."""
        n = len(frames) // SLOT_BYTES
        if not self._commands_close_slots():
            return super().handle_batch([message(frames, i) for i in range(n)], now)
        return self._take_batch(self._cmd_table.take_batch_raw, frames, n, lambda i: message(frames, i), now,
                                images=True)

    def _take_batch(self, take_batch: Any, batch: Any, n: int, message_at: Any, now: float,
                    images: bool = False) -> list[can.Message] | bytes:
        """The ``n`` frames of ``batch`` through ``take_batch`` (the command table's compiled
        loop), acting where it stops; ``message_at(i)``: frame i as a ``can.Message``. ``images``
        (the memory bus): the next tick's frames as slot images, no ``Message`` made (the frames
        to send are then bytes, or a list of messages if other frames join them)."""
        out: list[can.Message] | bytes = []
        i = 0
        while i < n:
            i, ev, r, completed, accepted = take_batch(batch, i, self.k)
            self.stats.commands_received += accepted
            if completed:  # slots whose commands are complete: closed (their response time)
                hist_add_bits(self._resp, completed, max(now - self._tick_wall, 0.0))
                self._done |= completed
            if ev == TAKE_BATCH_END:
                break
            if ev == TAKE_BATCH_TICK:
                out = _joined(out, self._advance(now, images))
            elif ev == TAKE_BATCH_OTHER:
                out = _joined(out, self.handle(message_at(i), now))
            else:  # TAKE_BATCH_RESULT: a command taken with a rejection or a counter jump
                r = self._taken(r)
                if r & 3 == CMD_FRESH:
                    slot = self._cmd_pages[message_at(i).arbitration_id][0]
                    if r & CMD_SLOT_COMPLETE:
                        self._resp[slot].add(max(now - self._tick_wall, 0.0))
                    if not self._done >> slot & 1 and self._fresh_pages[slot] >= self._pages_per_ecu[slot]:
                        out = _joined(out, self._slot_done(slot, now))
            if self.finished:
                break
            i += 1
        return out

    def _on_command(self, aid: int, msg: can.Message) -> int:
        """Take a command frame: CMD_FRESH if it is this tick's (| CMD_SLOT_COMPLETE when it
        completes its ECU's pages), CMD_OLD if accepted from an earlier tick, CMD_BAD_CRC or
        CMD_BAD_COUNTER if rejected (counted here); :class:`canbrake.bus._codec.CommandTable`."""
        table = self._cmd_table
        if self.secoc is None:
            return self._taken(table.take(aid, msg.data, self.k))
        r, origin = table.check(aid, msg.data, self.k)
        if r & CMD_OUT_OF_SEQUENCE:
            self.stats.commands_out_of_sequence += 1
        res = r & 3
        if res == CMD_BAD_CRC or res == CMD_BAD_COUNTER:
            return self._taken(r & 3)
        # only an authentic frame of exactly its tick (canbrake.bus.guard)
        if not self.guard.authentic(aid, msg.data, origin):
            return CMD_BAD_COUNTER  # counted by the guard
        return self._taken(table.apply(aid, msg.data, origin, self.k))

    def _taken(self, r: int) -> int:
        """Count a command frame taken with result ``r`` (CommandTable.take/apply): out of
        sequence, rejected (CRC or counter) or received; returns ``r`` (rejections: the result alone)."""
        if r & CMD_OUT_OF_SEQUENCE:
            self.stats.commands_out_of_sequence += 1
        res = r & 3
        if res == CMD_BAD_CRC:
            self.stats.commands_corrupted += 1
            self.guard.reject("crc")
            return res
        if res == CMD_BAD_COUNTER:
            self.guard.reject("counter")
            return res
        self.stats.commands_received += 1
        return r

    # ---------------------------------------------------------------- time
    def next_deadline(self) -> float | None:
        if self.finished:
            return None
        if self._start_deadline is not None:
            return self._start_deadline
        if self.mode != "realtime":
            return self._ext_deadline
        if self._t0_wall is None:
            return None
        return self._t0_wall + (self.k + 1) * self.dt / self.time_scale

    def on_timer(self, now: float) -> list[can.Message] | bytes:
        if self.finished:
            return []
        if self._start_deadline is not None:
            if now < self._start_deadline:
                return []
            # an external ECU never appeared: the run ends before its first tick (the orchestrator
            # reports which one, on which channel)
            self.finished = True
            self.stats.status = "external_missing"
            self.stats.extra["missing"] = self.missing_external()  # type: ignore[assignment]
            return []
        if self.mode != "realtime":
            if self._ext_deadline is None or now < self._ext_deadline:
                return []
            missing = self._all_done & ~(self._done | self._lost)
            for s_ in self._ext_slots:
                if missing >> s_ & 1:
                    self.stats.external[self.ecus[s_].name]["timeouts"] += 1
                    self.stats.external[self.ecus[s_].name]["silent_entries"] += 1
            self._lost |= missing
            return self._advance(now)
        if not self._fresh.all():
            self.stats.deadline_misses += 1
            self._cmd_late += 1  # the period's commands did not all arrive in time
        lateness = now - self.next_deadline()  # type: ignore[operator]
        self.stats.max_lateness_s = max(self.stats.max_lateness_s, lateness)
        if lateness > self.dt / self.time_scale:
            self.stats.late_periods += 1
            # a period missed as a whole (a late wake-up): move the grid on instead of catching up
            # with a burst of back-to-back periods no ECU could answer in time; the next period
            # gets its full length and simulated time falls behind the wall clock by `slipped_s`
            self._t0_wall += lateness
            self.stats.slipped_s += lateness
        return self._advance(now, self.sends_images)  # (the SYNC burst as slot images on the memory bus)

    def _applied_commands(self) -> dict[str, np.ndarray]:
        """The commands each vehicle's equipment applies this tick: the newest command, or the
        fail-safe brake force for vehicles whose ECU's commands have stopped (without a fail-safe:
        the node's own arrays, which a model only reads during its step, see the plant contract)."""
        fs = self.failsafe
        if fs is None:
            return self.commands
        cmds = {c: a.copy() for c, a in self.commands.items()}
        age = self.k - self._last_counter  # ticks since the newest valid command, per ECU
        if not fs.latch:
            self._in_failsafe &= ~self._fresh
        entering = (age > fs.timeout_ticks) & ~self._in_failsafe
        for i in np.flatnonzero(entering):
            self.stats.failsafe_activations += 1
            self.stats.failsafe_first_s.setdefault(f"c{self.ecus[i].vehicle}", round(self.k * self.dt, 9))
        self._in_failsafe |= entering
        self.stats.failsafe_ticks += int(self._in_failsafe.sum())
        veh = self._veh[self._in_failsafe]
        if not fs.values:
            cmds["brake_force_n"][veh] = fs.force_n[veh]
        for name, value in fs.values.items():
            cmds.setdefault(name, np.full(self.n, np.nan))[veh] = value
        return cmds

    def _advance(self, now: float, images: bool = False) -> list[can.Message] | bytes:
        """End the tick: apply the commands, step the model, and return the next tick's frames
        (``images``: as slot images, :meth:`_tick_frames`) or the END frame."""
        self._ext_deadline = None
        if not self._cmd_table.all_fresh():  # (most periods: every ECU's commands came)
            missed = np.flatnonzero(~self._fresh)
            self.stats.commands_missed += missed.size
            for i in missed:
                self.stats.commands_missed_per_car[i] += 1
                if self._ext_mask >> int(i) & 1:
                    self.stats.external[self.ecus[int(i)].name]["periods_missed"] += 1
        applied = self._applied_commands()
        if self.k % self.trace_every == 0:
            self._record()
        t0 = time.perf_counter()
        try:
            self.model.step(self.dt, applied)
        except FloatingPointError as e:
            # The closed loop went unstable (a result, not a crash): end the run for every node.
            self.finished = True
            self.stats.status = "diverged"
            self.stats.extra["diverged_at_s"] = self.k * self.dt
            self.stats.extra["message"] = str(e)  # type: ignore[assignment]
            return self._end_frames()
        self._model_time.add(time.perf_counter() - t0)
        self.k += 1
        self.stats.ticks = self.k
        if self.progress is not None:
            self.progress.value = self.k
        self._cmd_table.new_tick()  # fresh[:] = False, fresh_pages[:] = 0
        self._done = 0
        self._sync_wall = now
        self._sync_unsent = self.mode == "realtime"
        if self.k >= self.n_ticks:
            self._record(final=True)
            self.finished = True
            self.stats.status = "ok"
            if self._t_start_wall is not None:
                self.stats.wall_time_s = now - self._t_start_wall
            return self._end_frames()
        self._tick_wall = now
        out = self._tick_frames(images)
        self._arm_external(now)
        return out

    # ---------------------------------------------------------------- trace
    _STANDARD = ("position_m", "speed_mps", "accel_mps2", "applied_brake_n", "deflection_m", "coupler_force_n")

    def _extra_measurements(self) -> list[str]:
        """Per-vehicle measurement arrays beyond the standard ones, in a stable order."""
        if self._extra_meas is None:
            m = self.model.measurements()
            self._extra_meas = sorted(k for k, v in m.items()
                                      if k not in self._STANDARD and np.shape(v) == (self.n,))
        return self._extra_meas

    def columns(self) -> list[str]:
        cols = ["tick", "t_s", "ref_speed_mps", "ref_decel_mps2"]
        if self._ref_pos is not None:
            cols.append("ref_position_m")
        for c in range(1, self.n + 1):
            cols += [f"position_m_c{c}", f"speed_mps_c{c}", f"accel_mps2_c{c}",
                     f"brake_cmd_n_c{c}", f"brake_applied_n_c{c}"]
        for c in range(1, self.n):
            cols += [f"deflection_m_k{c}", f"coupler_force_n_k{c}"]
        if self.failsafe is not None:
            cols += [f"failsafe_c{e.vehicle}" for e in self.ecus]
        for name in self.command_names:
            if name != "brake_force_n":
                cols += [f"cmd_{name}_c{e.vehicle}" for e in self.ecus if name in e.commands]
        for name in self._extra_measurements():
            cols += [f"{name}_c{c}" for c in range(1, self.n + 1)]
        return cols

    def _open_trace(self) -> None:
        self._trace = CsvTrace(None if self.out_dir is None else self.out_dir / "signals.csv", self.columns(),
                               self.flush_every)
        self._row_fd = self._trace.row_fd()  # a node process: each row straight to the OS (write_text)

    def _record(self, final: bool = False) -> None:
        """Take this tick's trace row: the state, the reference and the commands applied, copied
        now; its text is made and written by :meth:`after_send` (once the tick's frames are on
        the bus: in a node process, while the ECUs compute) or before anything else happens here."""
        self._write_row()
        m = self.model.measurements()  # (arrays made per state: the next step leaves them alone)
        # brake_force_n, then each traced command, over the vehicles (copied in one call)
        n_cmd = self.n * (1 + len(self._row_cmds))
        cmds = np.full(n_cmd, np.nan) if final else np.concatenate(
            [self.cmd_n, *[self.commands[name] for name, _v in self._row_cmds]]) if self._row_cmds \
            else self.cmd_n.copy()
        fs = self._in_failsafe.copy() if self.failsafe is not None else None
        self._pending_row = (self.k, m, cmds, fs)
        if final:
            self._write_row()
            if self._trace is not None:
                self._trace.flush()

    def _plan_row(self, sizes: list[int]) -> tuple[int, np.ndarray, np.ndarray, np.ndarray]:
        """Where the trace row's floats are in the concatenation of :meth:`after_send`'s arrays
        (sizes ``sizes``): per vehicle position, speed, accel, command, applied; per coupler
        deflection, force (then the fail-safe flags, not floats); each traced command of its ECUs'
        vehicles; the extra measurements whole, in their order. (size, the indices before the
        flags, after them, both)."""
        n = self.n
        start = np.concatenate([[0], np.cumsum(sizes)]).astype(np.intp)
        pos, speed, accel, applied, defl, force, cmds = start[:7]
        per_vehicle = np.column_stack([pos + np.arange(n), speed + np.arange(n), accel + np.arange(n),
                                       cmds + np.arange(n), applied + np.arange(n)]).ravel()
        nc = sizes[4]
        per_coupler = np.column_stack([defl + np.arange(nc), force + np.arange(sizes[5])]).ravel()
        after = [cmds + n * (1 + i) + np.asarray(veh, dtype=np.intp) for i, (_name, veh) in enumerate(self._row_cmds)]
        after.append(np.arange(start[7], start[-1], dtype=np.intp))
        first = np.concatenate([per_vehicle, per_coupler]).astype(np.intp)
        second = np.concatenate(after).astype(np.intp)
        return int(start[-1]), first, second, np.concatenate([first, second])

    def after_send(self) -> None:
        """Write the trace row taken by :meth:`_record`, if one is pending (the drivers call this
        once a node's frames are sent); in realtime, first, the time the period's SYNC went out:
        its commands' latency counts from there (``cmd_latency_*``), the time from the period's
        timer to it is the plant's own delay (``sync_delay_*``); there the row waits until the
        period's commands are in (:meth:`handle`) or the next period's row is taken: just after
        SYNC the ECUs need the CPUs (the plant's too), and after their commands the plant idles."""
        if self._sync_unsent:
            self._sync_unsent = False
            if self._sync_wall is not None:
                t = time.time()  # (the node driver's clock)
                self._sync_delay.add(t - self._sync_wall)
                self._sync_wall = t
            if self._pending_row is not None and not self._fresh.all():
                return  # (realtime: the commands of this period still to come)
        self._write_row()

    def _write_row(self) -> None:
        """Write the trace row taken by :meth:`_record`, if one is pending."""
        pending = self._pending_row
        if pending is None:
            return
        self._pending_row = None
        k, m, cmds, fs = pending
        t = k * self.dt
        ref = self._ref_of_tick
        if ref is not None and ref[0] == k:
            v_ref, a_ref, x_ref = ref[1:]
        else:  # the last row (no tick frames after it)
            v_ref, a_ref = self.reference(t)
            x_ref = self.reference.position(t) if self._ref_pos is not None else None
        head: list[float] = [k, t, v_ref, a_ref]
        if self._ref_pos is not None:
            head.append(x_ref)
        # the row's floats read straight from its arrays, in the row's order (per vehicle and
        # per coupler interleaved), and its text made in one compiled call (_trace.csv_pick_row)
        parts = [m["position_m"], m["speed_mps"], m["accel_mps2"], m["applied_brake_n"], m["deflection_m"],
                 m["coupler_force_n"], cmds, *[m[name] for name in self._extra_measurements()]]
        head_text = csv_row(head)
        if self._trace is None or head_text is None:
            if self._trace is not None:
                self._trace.append(self._row_list(head, parts, fs))
            return
        plan = self._row_plan
        text = None if plan is None else csv_pick_row(head_text[:-2], parts, plan[0], fs, plan[1])
        if text is None:  # no plan yet (or the arrays' sizes changed): make it
            plan = self._row_plan = self._plan_pairs([np.size(a) for a in parts])
            text = csv_pick_row(head_text[:-2], parts, plan[0], fs, plan[1])
        if self._row_fd >= 0:
            write_text(self._row_fd, text)
        else:
            self._trace.append_text(text)

    def _plan_pairs(self, sizes: list[int]) -> tuple[np.ndarray, int]:
        """:meth:`_plan_row` as (array, element) pairs for :func:`csv_pick_row`, and where the
        fail-safe flags go among them."""
        _size, first, second, both = self._plan_row(sizes)
        start = np.concatenate([[0], np.cumsum(sizes)]).astype(np.intp)
        which = np.searchsorted(start, both, side="right") - 1
        pairs = np.ascontiguousarray(np.column_stack([which, both - start[which]]), dtype=np.intp)
        return pairs, int(first.size)

    def _row_list(self, head: list[float], parts: list[Any], fs: np.ndarray | None) -> list[Any]:
        """The trace row as a list (for a row whose head the compiled writer does not take)."""
        values = np.concatenate(parts, dtype=float)
        _size, first, second, both = self._plan_row([np.size(a) for a in parts])
        if fs is None:
            return head + values.take(both).tolist()
        return head + values.take(first).tolist() + [int(x) for x in fs] + values.take(second).tolist()

    def close(self, status: str = "ok") -> None:
        try:
            self._write_row()  # the last period's row (a full disk: the close below trims it)
        finally:
            if self._trace is not None:
                self._trace.close()
        if self.stats.status == "running":
            self.stats.status = status
        self.stats.guard = self.guard.stats()
        self.stats.model_step_s = self._model_time.figures()
        h, late = self._cmd_latency, self._cmd_late
        if h.n or late:
            # the late periods count as infinitely late, ranked last: a quantile (nearest rank)
            # that falls among them is null (JSON), as is the maximum then
            n = h.n + late
            for key, q in (("p50", 0.5), ("p99", 0.99)):
                r = max(1, math.ceil(q * n))
                self.stats.extra[f"cmd_latency_{key}_s"] = h.ranked(r) if r <= h.n else None  # type: ignore[assignment]
            self.stats.extra["cmd_latency_max_s"] = None if late else h.max  # type: ignore[assignment]
            self.stats.extra["cmd_latency_periods"] = n
            self.stats.extra["cmd_latency_missing"] = late
        if self._sync_delay.n:
            h = self._sync_delay
            for key, val in (("p50", h.quantile(0.5)), ("p99", h.quantile(0.99)), ("max", h.max)):
                self.stats.extra[f"sync_delay_{key}_s"] = float(val)  # type: ignore[assignment]
        for e, h in zip(self.ecus, self._resp):
            if h.n:
                self.stats.response_s[e.name] = {"n": h.n, "p50_s": h.quantile(0.5), "p99_s": h.quantile(0.99),
                                                 "max_s": h.max}
        if self.out_dir is not None:
            write_text_atomic(self.out_dir / "plant_stats.json", json.dumps(self.stats.__dict__, indent=1))
