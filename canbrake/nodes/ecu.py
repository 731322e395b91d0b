"""The ECU node: one carriage's brake controller on the bus.

It turns frames into an :class:`~canbrake.control.base.Observation`, calls the controller,
and turns the result into frames. Peer values carry their age, derived from the E2E alive
counter: every sender's counter is its tick modulo 15, so a frame received at tick k with
counter c was sent at tick k - ((k - c) mod 15) (valid while frames are less than 15 periods
old; older ones are indistinguishable and the peer is reported stale anyway).
"""
from __future__ import annotations

import functools
import json
import math
import time
from dataclasses import dataclass, field
from typing import Any
from pathlib import Path

import can
import numpy as np

from canbrake.atomic import write_text_atomic
from canbrake.bus import dbc
from canbrake.bus._codec import REJECT_CRC, PeerTable
from canbrake.bus.codec import FrameCodec
from canbrake.bus.e2e import COUNTER_MODULO
from canbrake.bus.guard import FrameGuard, sign_control, sign_protected, sync_verdict
from canbrake.bus.secoc import state_authenticator
from canbrake.control.base import Controller, Observation
from canbrake.nodes._ecu import BatchTaker, EcuPeriod, take_batch
from canbrake.nodes.base import CsvTrace, LogHistogram, Node, PassThrough, SendPath, exact_filter, frame

#: the key of a command frame's Status field among the period's command values (not a name a
#: controller's command can have)
_STATUS = ("Status",)
_perf_counter = time.perf_counter


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
    timer_slips: int = 0         # realtime with ecu.clocks: periods whose timer instant fell past the next SYNC
    skipped_periods: int = 0     # realtime: periods that ended (the next SYNC came) before this ECU sent their commands
    can_errors: dict = field(default_factory=dict)  # realtime bus errors: state, TEC, error frames, bus-off
    scheduling: str | None = None  # realtime: SCHED_FIFO / fallback and CPUs obtained (canbrake.nodes.rt)
    external_timeouts: int = 0   # lockstep: periods computed without an external peer's state (it was late)
    #: wall time of the controller's step per period (s): n, mean, p50, p99, max, total
    #: (LogHistogram.figures); the host's execution time, preemption included
    control_step_s: dict = field(default_factory=dict)


class EcuNode(Node):
    """An ECU of the placement (``spec``: its :class:`~canbrake.bus.dbc.EcuSpec`), running one
    controller: SENSOR frames from its vehicle and STATE frames of the ECUs it listens to in,
    command frames to the plant and STATE frames to its listeners out."""

    #: realtime: its driver yields the CPU once its frames are sent, before its trace row
    #: (:func:`canbrake.nodes.driver.drive`), so the other ECUs of its priority compute first
    yield_after_send = True

    def __init__(self, spec: Any, layout: Any, controller: Controller, codec: FrameCodec, *, dt_s: float,
                 mode: str = "lockstep", send_path: SendPath | None = None, heartbeat_period_s: float = 0.1,
                 compute_deadline: float = 0.5, out_dir: str | Path | None = None, flush_every: int = 1000,
                 crash_at_tick: int | None = None, lockstep_deadline: float = 0.5, bus_timing: Any = None,
                 barrier: bool = True, rx_path: Any = None, secoc: Any = None,
                 peer_hold_periods: int | None = None, n_ticks: int | None = None, clock: Any = None,
                 rt_errors: Any = None, external: frozenset[int] = frozenset(), external_timeout_s: float = 1.0,
                 time_scale: float = 1.0) -> None:
        self.spec = spec
        self.layout = layout
        self.car = spec.vehicle            # vehicle number (trace suffix _c<vehicle>)
        self.index = spec.index            # position in the identifier plan (1-based)
        self.i = spec.index - 1
        self.n = len(layout.ecus)
        self.name = spec.name
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
        self._control_time = LogHistogram(1.01)  # the controller step's wall time per period, 1 % bins
        self._control_pending: list[float] = []  # its samples not yet added (added 1,024 at a time, compiled)
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
        self.guard.counter_ext = layout.counter_ext()
        self.peer_hold_periods = peer_hold_periods
        self.final_tick = None if n_ticks is None else n_ticks - 1  # unauthenticated END only after it
        self._in_fallback = False
        self._latency: dict[str, list[float]] = {}
        self._t0_wall: float | None = None
        self.k = -1
        self.phase = 0  # 0 waiting for sensors, 1 waiting for peers, 2 done for this tick
        self.sensors: dict[str, float] = {n: math.nan for n in spec.sensors}
        # frames in: sensor pages (the last one starts phase 1), peers' state pages
        self._sensor_pages = {m.frame_id: [(sig, spec_.name) for sig, spec_ in m.signals if sig]
                              for m in layout.messages if m.kind == "sensor" and m.ecu == self.index}
        self._last_sensor_id = max(self._sensor_pages)
        self._listens = list(spec.listens)                     # ECU indices (1-based)
        self._state_pages: dict[int, tuple[int, int, list[tuple[str, str]]]] = {}  # id -> (ecu, page, sigs)
        self._pages_of: dict[int, int] = {}
        for m in layout.messages:
            if m.kind == "state" and m.ecu in self._listens:
                self._state_pages[m.frame_id] = (m.ecu, m.page, [(sig, sp.name) for sig, sp in m.signals if sig])
                self._pages_of[m.ecu] = self._pages_of.get(m.ecu, 0) + 1
        self._state_done_ids = {layout.plan.state_done(j): j for j in self._listens}
        # secured layouts: authenticator id -> (ECU, its state page's id); state pages that passed
        # the E2E check wait as candidates (origin, payload) until an authenticator verifies them
        self._auth_of: dict[int, tuple[int, int]] = {}
        if secoc is not None:
            state_id = {(m.ecu, m.page): m.frame_id for m in layout.messages if m.kind == "state"}
            self._auth_of = {m.frame_id: (m.ecu, state_id[(m.ecu, m.page)]) for m in layout.messages
                             if m.kind == "state_auth" and m.ecu in self._listens}
        self._candidates: dict[int, list[tuple[int, bytes]]] = {}
        self._peer_ids = {**self._state_pages, **self._auth_of}  # id -> (ECU index, ...): one lookup per frame
        names = sorted({sig for _, _, sigs in self._state_pages.values() for sig, _ in sigs}
                       | {"speed_mps", "position_m"})
        self._multi_page = {j: c > 1 for j, c in self._pages_of.items()}  # ECU index (1-based) -> bool
        self._listened = [j - 1 for j in self._listens]  # listened ECUs' indices (0-based)
        # listened external ECUs (not canbrake's): their state completes a tick by its pages or its
        # STATE_DONE; in lockstep they are waited for at most external_timeout_s (wall) once every other
        # peer is in, then counted silent (not waited for) until they are on time again
        self._has_ext = any(j in external for j in self._listens)
        # peers' values (an array per signal over the train's ECUs), their newest origins (ticks),
        # the pages of this tick seen and which peers are complete, kept by compiled code
        # (canbrake.bus._codec.PeerTable): a state page is checked (E2E) and decoded straight into
        # the arrays. The table is also this ECU's receive side (feed): a batch of frames is
        # taken in one compiled loop that comes back here only where this node acts
        self._peers = PeerTable(self.n, names, self._listened, self.guard.max_lag,
                                [j - 1 for j in self._listens if j in external])
        for fid, (e, _p, sigs) in self._state_pages.items():
            self._peers.add_page(fid, e - 1, codec.by_id[fid]._c, sigs, self._multi_page[e],
                                 self.guard.counter_ext.get(fid))
        self._peers.route_ecu(
            self.sensors, [(fid, codec.by_id[fid]._c, sigs) for fid, sigs in sorted(self._sensor_pages.items())
                           if fid != self._last_sensor_id] +
            [(self._last_sensor_id, codec.by_id[self._last_sensor_id]._c, self._sensor_pages[self._last_sensor_id])],
            codec.by_id[layout.reference_id]._c, layout.reference_id,
            codec.by_id[layout.reference_pos_id]._c if layout.ref_position else None, layout.reference_pos_id,
            layout.sync_id, [*self._state_done_ids, *self._auth_of], barrier=barrier, lockstep=mode == "lockstep",
            per_frame=rx_path is not None or secoc is not None, final_tick=self.final_tick)
        self.peer_signals: dict[str, np.ndarray] = self._peers.values
        # what the controller sees: read-only views of the table (no copy per period; this ECU
        # writes its own sensor values into its own entry, which no peer page touches)
        self._peer_views: dict[str, np.ndarray] = {}
        for nm, arr in self.peer_signals.items():
            view = arr.view()
            view.flags.writeable = False
            self._peer_views[nm] = view
        self._own_signals = tuple(nm for nm in self.peer_signals if nm in spec.sensors)
        self._ext_timeout = float(external_timeout_s)
        self.time_scale = float(time_scale)
        # frames out: per message (id, codec, keys): the value of each of its fields is the value
        # of that key in the period's values (FieldCodec.encode_from)
        self._cmd_msgs = [(m.frame_id, codec[m.name]._c,
                           codec[m.name]._c.keys_for({"Status": _STATUS, **{sp.name: sig for sig, sp in m.signals if sig}}))
                          for m in layout.messages if m.kind == "cmd" and m.ecu == self.index]
        own = [m for m in layout.messages if m.ecu == self.index]  # (not all pairs of the layout: 106 ECUs)
        auth_id = {sm.frame_id: am.frame_id for sm in own for am in own
                   if sm.kind == "state" and am.kind == "state_auth" and sm.page == am.page}
        #: (id, codec, keys, its authenticator's id or None)
        self._state_msgs = ([(m.frame_id, codec[m.name]._c,
                              codec[m.name]._c.keys_for({sp.name: sig for sig, sp in m.signals if sig}),
                              auth_id.get(m.frame_id))
                             for m in layout.messages if m.kind == "state" and m.ecu == self.index]
                            if spec.listeners else [])
        self._broadcast: dict[str, float] = {}
        #: lockstep: peers' STATE frames that came after the sender's STATE_DONE of this tick, held
        #: until this ECU has decided (see _held_late)
        self._late_rx: list[can.Message] = []
        self._hb_id = layout.plan.heartbeat(self.index)
        self._sdone_id = layout.plan.state_done(self.index)
        self._cdone_id = layout.plan.cmd_done(self.index)
        self._hb_payload = codec.by_id[self._hb_id].encode({"NodeState": 5})  # the same every time
        self._sdone = codec.by_id.get(self._sdone_id)  # None: nobody listens, no state phase to close
        self._cdone = codec.by_id[self._cdone_id]
        self._sync_id = layout.sync_id
        self._deadline: float | None = None
        self._trace: CsvTrace | None = None  # its rows are left pending by self._period (see after_send)
        # realtime: this ECU's own timer (canbrake.bus.clock.EcuClock): phase 1 of tick k starts
        # offset_s(k) after its sensor frames (drift + jitter), not at once; None: on the plant's grid
        self.clock = clock if mode == "realtime" else None
        self._p1_at: float | None = None
        # realtime bus errors injected at this sender (canbrake.bus.rt_errors.RealtimeErrors) or None
        self.rt_errors = rt_errors if mode == "realtime" else None
        #: no timing model, no injected errors, no impairment: _emit appends the frame as it is
        #: (PassThrough.submit returns it alone, its release nothing)
        self._plain_send = bus_timing is None and self.rt_errors is None and type(self.send_path) is PassThrough
        #: ... and no receive links: the phases need no send or release times
        self._fast = self._plain_send and rx_path is None
        self._has_front = self.car > 1                # a coupler ahead (deflection_front_m)
        self._has_rear = not self._last_vehicle()     # a coupler behind (deflection_rear_m)
        self._diag_names: tuple[str, ...] = tuple(controller.diagnostic_names)
        # the period's decision, compiled (see _phase2)
        self._period = EcuPeriod(self._peers, self.sensors, self._own_signals, self.i, self.dt, self._peer_views,
                                 Observation, self._has_front, self._has_rear, self._cmd_msgs,
                                 _STATUS, self._control_pending, self._control_time,
                                 None if secoc is None else functools.partial(sign_protected, secoc),
                                 self._state_msgs, None if secoc is None else functools.partial(state_authenticator, secoc))

    def filters(self) -> list[dict]:
        ids = [self.layout.sync_id, self.layout.reference_id, *self._sensor_pages, *self._state_pages, *self._auth_of]
        if self.layout.ref_position:
            ids.append(self.layout.reference_pos_id)
        if self.barrier:
            ids += list(self._state_done_ids)
        return [exact_filter(i, self.layout.plan.extended and i > 0x7FF) for i in ids]

    def start(self, now: float) -> list[can.Message]:
        self._diag_names = tuple(self.controller.diagnostic_names)
        self._trace = CsvTrace(None if self.out_dir is None else self.out_dir / f"ecu_c{self.car}.csv",
                               ["tick", "brake_cmd_n", *self._diag_names, "max_peer_age_s", "peers_fresh"],
                               self.flush_every)
        self._period.set_trace(self._trace, self._diag_names)
        return []

    # ---------------------------------------------------------------- receive
    def handle(self, msg: can.Message, now: float) -> list[can.Message]:
        return self.handle_batch([msg], now)

    def handle_batch(self, msgs: list[can.Message], now: float) -> list[can.Message]:
        """Frames received together, in bus order: the peer table's compiled loop
        (:meth:`~canbrake.bus._codec.PeerTable.feed`) takes the state pages, the sensor pages and
        the reference, and comes back here for the frames and moments this node acts on."""
        if type(msgs) is not list:
            msgs = list(msgs)
        return take_batch(self, self._peers.feed, msgs, None, False, now)  # (compiled)

    def batch_handler(self) -> BatchTaker:
        """:meth:`handle_batch` over a list as one compiled call (the Router's, in process)."""
        return BatchTaker(self)

    def handle_raw(self, frames: bytes | bytearray, now: float, message: Any) -> list[can.Message]:
        """:meth:`handle_batch` for the memory bus's slot images (``MemoryBus.recv_raw``), taken
        by :meth:`~canbrake.bus._codec.PeerTable.feed_raw` without a ``can.Message`` per frame;
        ``message(frames, i)`` makes one of image i for the frames this node's Python handles."""
        return take_batch(self, self._peers.feed_raw, frames, message, True, now)  # (compiled)

    def _handle_frame(self, msg: can.Message, now: float) -> list[can.Message]:
        """A frame the peer table hands back: SYNC, a barrier frame, or (SecOC, receive links) a
        peer's state frame or authenticator."""
        aid = msg.arbitration_id
        st = self._peer_ids.get(aid)
        if st is not None:
            j = st[0] - 1
            if self.rx_path is not None:
                self._receive_linked(msg, j, now)
                return []
            if self._held_late(j, msg):
                return []
            if self._on_state(j, msg) == 2 and (not self.barrier or self._peers.is_external(j)):
                return self._peer_done(j, now)  # the sender's last page of this tick
            return []
        if aid == self._sync_id and msg.is_extended_id == (aid > 0x7FF):
            verdict = sync_verdict(self.guard, aid, msg.data, self.k, lockstep=self.mode == "lockstep",
                                   tick_complete=self.phase == 2 or self.k < 0, final_tick=self.final_tick)
            if verdict is None:
                return []
            if verdict == "end":
                self.finished = True
                return []
            self._peers.new_tick()
            self._start_period(int.from_bytes(msg.data[:4], "little"))  # SYNC's Tick (bits 0-31, LE)
            return []
        src = self._state_done_ids.get(aid)
        if src is not None:
            tick = self.codec.by_id[aid].decode(msg.data)["Tick"]
            if tick != (self.k & 0xFFFF):
                if not self._peers.is_external(src - 1):  # an external peer late for a period already gone: not a fault
                    self.guard.reject("sync")
            elif self.guard.control(aid, msg.data, self.k):
                return self._peer_done(src - 1, now)
        return []

    def _start_period(self, k_new: int) -> None:
        """SYNC(k_new) accepted (the peer table's new tick begun)."""
        if self._p1_at is not None:  # the drifting timer did not fire within the period: a sample slip
            self.stats.timer_slips += 1
            self._p1_at = None
        if self.mode != "lockstep" and self.k >= 0:
            # periods this ECU never commanded (a pause of its process: it takes the SYNCs it
            # missed in a row): the current one unless done, and any it never saw the start of
            self.stats.skipped_periods += k_new - self.k - 1 + (self.phase != 2)
        self.k = k_new
        self.phase = 0
        if self._candidates:
            self._expire_candidates()

    def frames_wanted(self) -> int:
        """Waiting for peers' state frames (phase 1) with nothing but those frames completing a
        peer (no barrier frames, no receive links, no SecOC, no external peer): one frame at least
        from each listened ECU not complete yet (realtime too: there the compute deadline ends the
        wait for frames that do not come), so the ECU is woken once, not at each peer; else 1."""
        if (self.phase != 1 or self.barrier or self.rx_path is not None
                or self.secoc is not None or self._has_ext):
            return 1
        return max(1, self._peers.not_done())

    def _held_late(self, j: int, msg: can.Message) -> bool:
        """Lockstep: hold a STATE frame of ECU index j+1 that comes after that peer's STATE_DONE of this tick
        until this ECU has decided (True: held). Such a frame is one the sender's send path released
        after the decision point (phase 2: the CAN timing model or an impairment made it late); by the
        lockstep rule it is for the next tick. The sender sends it after its STATE_DONE, so it reaches
        an ECU already past its own barrier only then, but one still waiting for another peer's
        STATE_DONE before it decides: without the hold, which tick used it would depend on the
        processes' speed (the in-process engine always delivers it after every decision). The
        peer table holds the state pages it takes likewise (FEED_HELD)."""
        if self.barrier and self.phase != 2 and self.mode == "lockstep" and self._peers.is_done(j):
            self._late_rx.append(msg)
            return True
        return False

    def _take_held(self, now: float) -> None:
        """The held late STATE frames (see :meth:`_held_late`), once this ECU has decided."""
        held, self._late_rx = self._late_rx, []
        self.handle_batch(held, now)

    def _peer_done(self, j: int, now: float) -> list[can.Message]:
        """ECU index j+1 is complete for this tick: phase 2 once every peer is."""
        self._peers.peer_done(j)
        if self.phase == 1:
            if self._peers.missing == 0:
                return self._phase2(now)
            self._arm_external(now)
        return []

    def _arm_external(self, now: float) -> None:
        """Lockstep, phase 1: once only external peers are missing, wait for them at most external_timeout_s."""
        if self.mode != "lockstep" or not self._has_ext or self._deadline is not None:
            return
        if self._peers.only_external_missing():
            self._deadline = now + self._ext_timeout

    def _receive_linked(self, msg: can.Message, j: int, now: float) -> None:
        """A peer's state frame through this ECU's per-link impairments: frames the link delays
        are taken in a later phase (see :meth:`_release_linked`). Peer frames arrive in phase 0/1."""
        from canbrake.bus.impair import TxFrame

        self.rx_path.submit(TxFrame.from_message(msg, self.layout.by_index[j + 1].name, self._times(now, 1)[0]))
        self._release_linked(now)

    def _release_linked(self, now: float) -> None:
        """Take the peer frames this ECU's receive links release by the phase-1 horizon."""
        if self.rx_path is None:
            return
        for f in self.rx_path.release(self._times(now, 1)[1]):
            m = f.to_message()
            self._on_state((self._state_pages.get(m.arbitration_id) or self._auth_of[m.arbitration_id])[0] - 1, m)

    def _on_state(self, j: int, msg: can.Message) -> int:
        """Take a state frame (or, secured, its authenticator) of ECU index j+1: 0 nothing of
        this tick accepted, 1 a state page of this tick, 2 the sender's last page of this tick."""
        if msg.arbitration_id in self._auth_of:
            return self._on_state_auth(j, msg)
        if self.secoc is None:  # checked and applied in one compiled call
            r = self._peers.take(msg.arbitration_id, msg.data, self.k)
            if r < 0:
                self.guard.reject("crc" if r == REJECT_CRC else "counter")
                self._count_peer_rejection()
                return 0
            return r
        origin = self.guard.origin(msg.arbitration_id, msg.data, self.k, self._peers.origin_of(j),
                                   same_tick_ok=self._multi_page[j + 1])
        if origin is None:
            self._count_peer_rejection()
            return 0
        # secured: applied only once its authenticator verifies it
        cands = self._candidates.setdefault(msg.arbitration_id, [])
        cands.append((origin, bytes(msg.data)))
        if len(cands) > 2 * COUNTER_MODULO:  # a flood of forgeries: keep the newest
            del cands[0]
            self.guard.reject("authentication")
        return 0

    def _count_peer_rejection(self) -> None:
        if self.guard.last_reason == "crc":
            self.stats.peer_corrupted += 1
        else:
            self.stats.peer_stale_or_duplicate += 1

    def _on_state_auth(self, j: int, msg: can.Message) -> int:
        """A STATE_AUTH frame (canbrake.bus.secoc): apply the candidate state page it verifies."""
        from canbrake.bus.e2e import e2e_crc
        from canbrake.bus.secoc import authenticator_tick

        aid, data = msg.arbitration_id, msg.data
        state_id = self._auth_of[aid][1]
        if len(data) != 8 or data[0] != e2e_crc(aid, data):
            self.guard.reject("crc")
            self._count_peer_rejection()
            return 0
        tick, last = authenticator_tick(data), self._peers.origin_of(j)
        if tick > self.k or self.k - tick > self.guard.max_lag or tick < last or (
                tick == last and self._pages_of[j + 1] == 1):
            self.guard.reject("freshness")  # an authenticator of an earlier (or no) period: a replay
            self._count_peer_rejection()
            return 0
        cands = self._candidates.get(state_id, [])
        hit = next((p for o, p in cands if o == tick and self.secoc.verify_state(state_id, p, data)), None)
        if hit is None:
            if any(o == tick for o, _ in cands):
                self.guard.reject("authentication")  # a state of that tick, but not the one authenticated
                self._count_peer_rejection()
            else:
                self.guard.state_auth_orphans += 1  # its state frame was lost (or never sent)
            return 0
        keep = [(o, p) for o, p in cands if o > tick]
        for _ in range(len(cands) - len(keep) - 1):  # the other candidates of that tick or older: forged/replayed
            self.guard.reject("authentication")
        self._candidates[state_id] = keep
        return self._apply_state(j, state_id, hit, tick)

    def _expire_candidates(self) -> None:
        """Candidates too old for the window never got their authenticator: rejected."""
        for sid, cands in self._candidates.items():
            keep = [(o, p) for o, p in cands if self.k - o <= self.guard.max_lag]
            for _ in range(len(cands) - len(keep)):
                self.guard.reject("authentication")
            self._candidates[sid] = keep

    def _apply_state(self, j: int, state_id: int, data: bytes | bytearray, origin: int) -> int:
        """Use an accepted state page of ECU index j+1 sent at tick ``origin`` (as _on_state)."""
        return self._peers.apply(state_id, data, origin, self.k)

    # ---------------------------------------------------------------- send
    def _emit(self, msg: can.Message, t_s: float, out: list[can.Message]) -> None:
        if self._plain_send:  # nothing between this ECU and the bus: the frame goes now
            out.append(msg)
            return
        if self.bus_timing is not None:
            lat = self.bus_timing.latency_s(self.k, self.name, msg.arbitration_id, t_s)
            kind = self.layout.by_id[msg.arbitration_id].kind
            self._latency.setdefault("brake_cmd" if kind == "cmd" else kind, []).append(lat)
            if not math.isfinite(lat):  # starved by higher-priority traffic: never gets on the bus
                self.stats.frames_starved += 1
                return
            out.extend(self.send_path.submit(msg, t_s, delay_s=lat))  # held until it is off the wire
            return
        if self.rt_errors is not None:  # realtime: error frames before it, or nothing when bus-off
            errors, ok = self.rt_errors.attempt(msg, t_s)
            out.extend(errors)
            if not ok:
                return
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
        k = self.k
        if self.crash_at_tick is not None and k >= self.crash_at_tick:
            raise RuntimeError(f"injected crash of {self.name} at tick {k} (ecu.crash in the scenario)")
        plain = self._plain_send
        if not self._fast:
            t, horizon = self._times(now, 1)
            self._release_linked(now)
        out: list[can.Message] = []
        if k % self.heartbeat_every == 0:
            if plain:
                out.append(frame(self._hb_id, self._hb_payload))
            else:
                self._emit(frame(self._hb_id, self._hb_payload), t, out)
        if self._state_msgs:  # (compiled) each with its authenticator after it with SecOC
            if plain:
                out += self._period.state_frames(k, self._broadcast)
            else:
                for m in self._period.state_frames(k, self._broadcast):
                    self._emit(m, t, out)
        if not plain:
            out += self.send_path.release(horizon)
        if self.barrier and self._state_msgs:
            sdone = sign_control(self.secoc, self._sdone_id, self._sdone.encode({"Tick": k & 0xFFFF}), k)
            out.append(frame(self._sdone_id, sdone))
        self.phase = 1
        if self.mode == "realtime":
            self._deadline = now + self.compute_deadline * self.dt / self.time_scale
        if self._peers.missing == 0:
            out += self._phase2(now)
        elif self._has_ext:
            self._arm_external(now)
        return out

    def _phase2(self, now: float) -> list[can.Message]:
        self.phase = 2
        self._deadline = None
        k = self.k
        plain = self._plain_send
        if not self._fast:
            t, horizon = self._times(now, 2)
            self._release_linked(now)
        # compiled: its own values into the peer table, the peers' ages, the Observation, the
        # controller's step (timed), the command frames (canbrake.nodes._ecu.EcuPeriod); it writes
        # the last period's trace row first and leaves this one's pending
        hold = self.peer_hold_periods
        result, cmds, max_age, fresh, dropped = self._period.decide(
            self.controller, k, -1 if hold is None else hold, self._in_fallback)
        if hold is not None:
            self._count_fallback(dropped)
        self.stats.peer_missing += len(self._listened) + 1 - fresh
        self._broadcast = result.broadcast
        diag = result.diagnostics
        if plain:
            out = cmds
        else:
            out = []
            for m in cmds:
                self._emit(m, t, out)
            out += self.send_path.release(horizon)
        if self.barrier:
            cdone = sign_control(self.secoc, self._cdone_id, self._cdone.encode({"Tick": k & 0xFFFF}), k)
            out.append(frame(self._cdone_id, cdone))
        self.stats.ticks += 1
        if self._late_rx:
            self._take_held(now)
        return out

    def after_send(self) -> None:
        """Write the trace row of the period last computed, if pending: in a node process after
        its command frames are on the bus, so the row's text is not made before they leave."""
        self._period.write_row()  # (compiled)

    def _count_fallback(self, dropped: bool) -> None:
        """Listened ECUs whose newest value is older than ``peer_hold_periods`` were dropped this
        tick (NaN: the controller runs on its own sensors for them, see
        :meth:`~canbrake.bus._codec.PeerTable.hold_copy`): count entries and ticks in fallback."""
        if dropped and not self._in_fallback:
            self.stats.fallback_entries += 1
        self.stats.fallback_ticks += int(dropped)
        self._in_fallback = dropped

    def _last_vehicle(self) -> bool:
        return self.car >= getattr(self.layout, "n_vehicles", 10 ** 9)

    # ---------------------------------------------------------------- realtime
    def next_deadline(self) -> float | None:
        if self.phase == 0 and self._p1_at is not None:
            return self._p1_at
        return self._deadline if self.phase == 1 else None

    def on_timer(self, now: float) -> list[can.Message]:
        if self.phase == 0 and self._p1_at is not None:
            if now < self._p1_at:
                return []
            self._p1_at = None
            return self._phase1(now)
        if self.phase != 1:
            return []
        if self.mode == "lockstep":  # external peers late: go on without them (see _arm_external)
            self.stats.external_timeouts += 1
            self._peers.lose_external()
            return self._phase2(now)
        self.stats.deadline_misses += 1
        return self._phase2(now)

    # ---------------------------------------------------------------- trace
    def close(self, status: str = "ok") -> None:
        if self._trace is not None:
            try:
                self.after_send()  # the last period's row (a full disk: the close below trims it)
            finally:
                self._trace.close()
        self.stats.status = "ok" if self.finished else status
        self.stats.peer_frames = self._peers.accepted  # state pages accepted (counted by the peer table)
        self.stats.guard = self.guard.stats()
        self.stats.scheduling = self.scheduling
        if self._control_pending:
            self._control_time.add_many(self._control_pending)
            self._control_pending.clear()
        self.stats.control_step_s = self._control_time.figures()
        if self.rt_errors is not None:
            self.stats.can_errors = self.rt_errors.summary()
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
            write_text_atomic(self.out_dir / f"ecu_c{self.car}_stats.json", json.dumps(self.stats.__dict__, indent=1))
