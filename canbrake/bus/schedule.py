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


@dataclass(frozen=True)
class Stream:
    """One periodic frame of the nominal schedule: ``sender`` queues ``arbitration_id`` at
    ``t_k + offset_s`` of every tick k with ``k % every_ticks == 0``."""

    sender: str
    arbitration_id: int
    dlc: int
    every_ticks: int = 1
    offset_s: float = 0.0
    is_extended: bool = False
    name: str = ""


def nominal_streams(layout: Any, *, decision_offset_s: float, heartbeat_every: int,
                    plant_io_on_bus: bool = False) -> list[Stream]:
    """The nominal traffic of one control period, in the layout's identifier order: SYNC,
    REFERENCE(_POS) and the plant's heartbeat at t_k; per ECU STATE and heartbeat at t_k and its
    commands at the decision instant t_k + ``decision_offset_s``; sensor frames at t_k if
    ``plant_io_on_bus``. The timing model (:class:`LockstepBusTiming`) and the response-time
    analysis (:func:`message_set`) both read it."""
    hb = max(1, heartbeat_every)
    out: list[Stream] = []
    for msg in layout.messages:
        sender = "plant" if msg.ecu == 0 else layout.by_index[msg.ecu].name
        s = dict(sender=sender, arbitration_id=msg.frame_id, dlc=msg.length, is_extended=msg.extended, name=msg.name)
        if msg.kind in ("sync", "reference", "reference_pos") or (msg.kind == "sensor" and plant_io_on_bus):
            out.append(Stream(**s))
        elif msg.kind == "heartbeat":
            out.append(Stream(**s, every_ticks=hb))
        elif msg.kind in ("state", "state_auth"):
            out.append(Stream(**s))
        elif msg.kind == "cmd":
            out.append(Stream(**s, offset_s=decision_offset_s))
    return out


class LockstepBusTiming:
    """Replicated deterministic bus timing for lockstep runs (simulated seconds).

    Optional: ``faults`` (:class:`canbrake.bus.faults.FaultConfinement`: error frames,
    retransmissions, bus-off — a dropped frame's latency is ``math.inf``), ``tx_buffers``
    (per-node transmit buffers, :mod:`canbrake.bus.txbuffer`), ``clocks`` (node name ->
    :class:`canbrake.bus.clock.EcuClock`: the node's frames of tick k are queued at its drifting
    timer instant), ``record_history`` (latency statistics, for ``canbrake analyze``).
    """

    def __init__(self, layout: Any, dt_s: float, bitrate_bps: float, *, decision_offset_s: float,
                 heartbeat_every: int, plant_io_on_bus: bool = False, coupler_sensors: bool = False,
                 babblers: list[BabbleSource] | None = None, max_wait_ticks: int = 2_000,
                 record_history: bool = False, faults: Any = None, tx_buffers: Any = None,
                 clocks: dict[str, Any] | None = None) -> None:
        if isinstance(layout, int):  # a number of cars: Chen's default placement
            layout = dbc.BusLayout(dbc.default_ecus(layout, coupler_sensors=coupler_sensors))
        self.layout = layout
        self.n = len(layout.ecus)
        self.dt = dt_s
        self.c = decision_offset_s
        self.hb_every = max(1, heartbeat_every)
        self.plant_io = plant_io_on_bus
        self.coupler_sensors = coupler_sensors
        self.streams = nominal_streams(layout, decision_offset_s=decision_offset_s, heartbeat_every=heartbeat_every,
                                       plant_io_on_bus=plant_io_on_bus)
        self.babblers = list(babblers or [])
        self.max_wait_ticks = max_wait_ticks
        self.model = BusTimingModel(bitrate_bps, stuffing="worst", record_history=record_history, faults=faults,
                                    tx_buffers=tx_buffers)
        self.faults = faults
        self.clocks = dict(clocks or {})  # node -> canbrake.bus.clock.EcuClock
        self._next_tick = 0
        self._done: dict[tuple[int, str, int], float] = {}
        self._babble_next = [0] * len(self.babblers)
        self._query_tick = 0  # latest tick asked about; deliveries older than it are forgotten
        #: the run's number of ticks (None: unbounded). A frame still queued when the run ends is
        #: starved for this run: ``latency_s`` never simulates the bus past it (a starved frame
        #: otherwise costs ``max_wait_ticks`` periods of look-ahead in every process that asks)
        self.horizon_ticks: int | None = None
        #: when a list, every frame the model carries is appended as (t_end_s, arbitration_id,
        #: is_extended) in bus order (the recorder's stamps: canbrake.nodes.recorder)
        self.delivery_log: list[tuple[float, int, bool]] | None = None
        self._columns: tuple[list, ...] | None = None  # the streams column-wise (_submit_streams)

    def _submit_tick(self, k: int) -> None:
        t = k * self.dt
        sub = self._queue
        drift = {node: c.offset_s(k) for node, c in self.clocks.items()}
        self._submit_streams(k, t, drift)
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

    def _submit_streams(self, k: int, t: float, drift: dict[str, float]) -> None:
        """Queue the nominal streams' frames of tick ``k`` (starting at ``t``, s; ``drift``: clock
        offsets by node), tagged ``(k, sender, arbitration_id)``: in the compiled core."""
        if self._columns is None:
            st = self.streams
            self._columns = ([s.sender for s in st], [s.arbitration_id for s in st], [s.is_extended for s in st],
                             [s.dlc for s in st], [s.offset_s for s in st], [s.every_ticks for s in st])
        self.model.submit_streams(k, t, *self._columns, drift)

    def _queue(self, node: str, msg_id: int, is_extended: bool, dlc: int, data: Any, t_s: float, *, tag: Any) -> None:
        self.model.submit(node, msg_id, is_extended, dlc, data, t_s, tag=tag)

    def simulate_through(self, t_s: float) -> None:
        """Simulate every tick that starts before ``t_s`` (keeps the latencies for ``latency_s``)."""
        self._query_tick = max(self._query_tick, int(t_s / self.dt) - 1)  # older latencies can go
        while self._next_tick * self.dt < t_s - 1e-12:
            self._step()

    def run_ticks(self, n_ticks: int) -> None:
        """Simulate the nominal traffic of ticks 0..n_ticks-1 (for statistics; needs
        ``record_history=True`` to keep latencies)."""
        while self._next_tick < n_ticks:
            self._step()
            self._done.clear()

    def _step(self) -> None:
        k = self._next_tick
        self._submit_tick(k)
        # end times into _done by tag (inf: dropped), the bus order into delivery_log: compiled
        self.model.advance_into((k + 1) * self.dt, self._done, self.delivery_log)
        self._next_tick = k + 1
        if k % 256 == 0:  # forget deliveries nobody will ask for (other nodes' frames of past ticks)
            old = self._query_tick - 2
            self._done = {key: v for key, v in self._done.items() if key[0] >= old}

    def latency_s(self, k: int, node: str, msg_id: int, t_queue_s: float) -> float:
        """Bus latency (queueing + transmission, s) of ``node``'s frame ``msg_id`` of tick ``k``;
        ``math.inf`` if it would wait more than ``max_wait_ticks`` periods (starved), is still queued
        when the run ends (``horizon_ticks``: it never arrives within the run), or never
        reaches the bus (its node is bus-off, its transmit buffer was full)."""
        key = (k, node, msg_id)
        self._query_tick = max(self._query_tick, k)
        end = k + self.max_wait_ticks if self.horizon_ticks is None else min(k + self.max_wait_ticks,
                                                                            self.horizon_ticks - 1)
        while key not in self._done:
            if self._next_tick > end:
                return math.inf
            self._step()
        return self._done.pop(key) - t_queue_s


class SegmentedBusTiming(LockstepBusTiming):
    """:class:`LockstepBusTiming` over several segments joined by gateways
    (:class:`canbrake.bus.segments.SegmentedNetwork`): each frame of the nominal schedule is
    queued on its sender's segment, forwarded by the gateways towards every segment where it has
    a receiver, and its latency is the time until it has ended on the last of them (the farthest
    receiver). ``self.net.models`` are the per-segment bus models. Bus errors are not modelled
    across segments (refused by :func:`check_faults`)."""

    def __init__(self, layout: Any, topo: Any, dt_s: float, *, record_history: bool = False,
                 tx_buffers: Any = None, **kw: Any) -> None:
        from canbrake.bus.segments import SegmentedNetwork, message_routes

        super().__init__(layout, dt_s, max(topo.bitrate.values()), record_history=False, tx_buffers=tx_buffers, **kw)
        self.topo = topo
        self.net = SegmentedNetwork(topo, record_history=record_history, tx_buffers=tx_buffers)
        self.routes = message_routes(self.layout, topo, self.plant_io)
        self._babble_seg = topo.plant_segment

    def _submit_streams(self, k: int, t: float, drift: dict[str, float]) -> None:
        for s in self.streams:  # routed through the gateways, frame by frame
            if k % s.every_ticks == 0:
                self._queue(s.sender, s.arbitration_id, s.is_extended, s.dlc, None,
                            t + s.offset_s + drift.get(s.sender, 0.0), tag=(k, s.sender, s.arbitration_id))

    def _queue(self, node: str, msg_id: int, is_extended: bool, dlc: int, data: Any, t_s: float, *, tag: Any) -> None:
        r = self.routes.get(msg_id)
        if r is None or tag[2] < 0:  # a babbler: on the plant's segment, nobody forwards it
            src, dests = self._babble_seg, (self._babble_seg,)
        else:
            src, dests = r[1], r[2]
        self.net.submit(node, msg_id, is_extended, dlc, data, t_s, src=src, dests=dests, tag=tag)

    def _step(self) -> None:
        k = self._next_tick
        self._submit_tick(k)
        self.net.advance((k + 1) * self.dt)
        for tag, t_end in self.net.pop_completed():
            if tag[2] >= 0:
                self._done[tag] = t_end
        self._next_tick = k + 1
        if k % 256 == 0:
            old = self._query_tick - 2
            self._done = {key: v for key, v in self._done.items() if key[0] >= old}


def _babblers_of(scn: Any) -> list[BabbleSource]:
    from canbrake.bus.impair import BabbleSpec

    return [BabbleSource(s.sender, s.arbitration_id, s.rate_hz, s.dlc, s.is_extended, s.start_s,
                         math.inf if getattr(s, "stop_s", None) is None else s.stop_s)
            for s in scn.bus.impairments if isinstance(s, BabbleSpec)]


def faults_of(scn: Any) -> Any:
    """The :class:`~canbrake.bus.faults.FaultConfinement` of ``scn``'s ``bit_error_rate`` and
    ``faulty_transceiver`` impairments (None if it has none). Seeded from the run seed with a
    stable hash, so every process of a run draws the same errors."""
    from canbrake.bus.faults import BitErrorSource, FaultConfinement, FaultyTransceiver
    from canbrake.bus.impair import BitErrorRateSpec, FaultyTransceiverSpec, derive_seed

    specs = [s for s in scn.bus.impairments if isinstance(s, (BitErrorRateSpec, FaultyTransceiverSpec))]
    if not specs:
        return None
    stop = [math.inf if s.stop_s is None else s.stop_s for s in specs]
    seed = int(derive_seed(scn.seed, "bus_errors").generate_state(1)[0])
    return FaultConfinement(
        bit_errors=[BitErrorSource(s.ber, s.start_s, e) for s, e in zip(specs, stop) if isinstance(s, BitErrorRateSpec)],
        faulty=[FaultyTransceiver(s.node, s.probability, s.start_s, e) for s, e in zip(specs, stop)
                if isinstance(s, FaultyTransceiverSpec)],
        seed=seed, auto_recovery=all(s.auto_recovery for s in specs), bitrate_bps=float(scn.bus.bitrate_bps),
        recovery_delay_s=max(s.recovery_delay_s for s in specs))


def check_faults(scn: Any, layout: Any) -> None:
    """Bus errors and ECU clock drift are modelled in simulated time only: refuse them elsewhere,
    and refuse clocks of cars the train does not have (one clear message, exit 2). ``layout``:
    the run's :class:`~canbrake.bus.dbc.BusLayout` (:func:`canbrake.build.bus_layout`)."""
    from canbrake.bus.segments import topology_of
    from canbrake.errors import ScenarioError as InputError

    if topology_of(scn, layout) is not None:
        if scn.mode != "lockstep":
            raise InputError("bus.segments: segments and gateways are modelled in simulated time and need mode: "
                             f"lockstep (got mode: {scn.mode}); realtime runs share one bus")
        if faults_of(scn) is not None:
            raise InputError("bus.impairments: bit_error_rate / faulty_transceiver are modelled on a single bus, "
                             "not across bus.segments (remove one or the other)")
    clocks = getattr(scn.ecu, "clocks", []) or []
    for c in clocks:
        if c.car not in layout.by_index:
            raise InputError(f"ecu.clocks: car {c.car} has no ECU (ECU indices 1..{len(layout.ecus)})")
    if clocks and scn.mode == "lockstep" and scn.bus.timing != "model":
        raise InputError("ecu.clocks: in lockstep, clock drift acts in the CAN timing model and needs "
                         f"bus.timing: model (got bus.timing: {scn.bus.timing}); realtime runs apply it to the "
                         "ECUs' timers")
    if faults_of(scn) is None:
        return
    if scn.mode == "lockstep" and scn.bus.timing != "model":
        raise InputError("bus.impairments: in lockstep, bit_error_rate / faulty_transceiver act in the CAN timing "
                         f"model and need bus.timing: model (got bus.timing: {scn.bus.timing}); realtime runs inject "
                         "them at each ECU")
    if scn.mode == "realtime":
        for s in scn.bus.impairments:
            if getattr(s, "type", None) == "faulty_transceiver" and s.node not in {e.name for e in layout.ecus}:
                raise InputError(f"bus.impairments: faulty_transceiver node {s.node!r}: in realtime only ECUs inject "
                                 "errors (canbrake.bus.rt_errors); the plant's frames stand in for the time base")
    names = {"plant"} | {e.name for e in layout.ecus} | {b.sender for b in _babblers_of(scn)}
    for s in scn.bus.impairments:
        if getattr(s, "type", None) == "faulty_transceiver" and s.node not in names:
            raise InputError(f"bus.impairments: faulty_transceiver node {s.node!r} is not a node of this train "
                             f"(plant, {', '.join(e.name for e in layout.ecus[:3])}, ...)")


def timing_of(scn: Any, layout: Any, *, record_history: bool = False) -> LockstepBusTiming:
    """The nominal-traffic timing model of ``scn`` with its bus ``layout``
    (:func:`canbrake.build.bus_layout`), whatever its mode and ``bus.timing``."""
    from canbrake.bus.segments import topology_of

    dt = scn.control_period_s
    topo = topology_of(scn, layout)
    if topo is not None:
        return SegmentedBusTiming(layout, topo, dt, decision_offset_s=scn.ecu.lockstep_deadline * dt,
                                  heartbeat_every=int(round(scn.ecu.heartbeat_period_s / dt)),
                                  plant_io_on_bus=scn.bus.plant_io_on_bus, coupler_sensors=scn.plant.coupler_sensors,
                                  babblers=_babblers_of(scn), record_history=record_history,
                                  tx_buffers=getattr(scn.bus, "tx_buffers", None), clocks=clocks_of(scn, layout))
    return LockstepBusTiming(layout, dt, scn.bus.bitrate_bps, decision_offset_s=scn.ecu.lockstep_deadline * dt,
                             heartbeat_every=int(round(scn.ecu.heartbeat_period_s / dt)),
                             plant_io_on_bus=scn.bus.plant_io_on_bus, coupler_sensors=scn.plant.coupler_sensors,
                             babblers=_babblers_of(scn), record_history=record_history, faults=faults_of(scn),
                             tx_buffers=getattr(scn.bus, "tx_buffers", None), clocks=clocks_of(scn, layout))


def clocks_of(scn: Any, layout: Any) -> dict[str, Any]:
    """``ecu.clocks`` as :class:`~canbrake.bus.clock.EcuClock` per ECU node name (``car`` is the
    ECU's index in the placement), seeded from the run seed."""
    from canbrake.bus.clock import EcuClock
    from canbrake.bus.impair import derive_seed

    out = {}
    for c in getattr(scn.ecu, "clocks", []) or []:
        if c.car not in layout.by_index:
            continue  # refused by check_faults before a run
        node = layout.by_index[c.car].name
        out[node] = EcuClock(c, scn.control_period_s, int(derive_seed(scn.seed, "clock", node).generate_state(1)[0]))
    return out


def build_bus_timing(scn: Any, layout: Any) -> LockstepBusTiming | None:
    """The in-loop timing model of ``scn`` (None unless lockstep with ``bus.timing: model``)."""
    if scn.mode != "lockstep" or scn.bus.timing != "model":
        return None
    t = timing_of(scn, layout)
    t.horizon_ticks = scn.n_ticks
    return t


def message_set(scn: Any, layout: Any) -> list[Any]:
    """The periodic messages of ``scn``'s nominal schedule as :class:`canbrake.bus.rta.CanMessage`
    (names from the scenario's DBC; period = ``every_ticks`` control periods, deadline = period;
    a babbler is a message with period 1/rate_hz). Lockstep barrier frames take no bus time and
    are not listed. An ECU with a clock (``ecu.clocks``) gets release jitter: its timer jitter
    plus its phase, or a whole period if it drifts (the send instant slides over the period)."""
    from canbrake.bus.rta import CanMessage

    t = timing_of(scn, layout)
    dt = scn.control_period_s
    jitter: dict[str, float] = {}
    for node, clk in t.clocks.items():  # drift slides the send instant over a whole period
        c = clk.cfg
        jitter[node] = (dt if c.ppm else c.phase_s) + c.jitter_s
    out = [CanMessage(s.name or f"0x{s.arbitration_id:X}", s.arbitration_id, s.dlc,
                      s.every_ticks * dt, is_extended=s.is_extended, sender=s.sender,
                      jitter_s=jitter.get(s.sender, 0.0)) for s in t.streams]
    out += [CanMessage(f"BABBLE_{b.sender}_0x{b.arbitration_id:X}", b.arbitration_id, b.dlc, 1.0 / b.rate_hz,
                       is_extended=b.is_extended, sender=b.sender) for b in t.babblers]
    return out


def fifo_like_nodes(scn: Any, messages: list[Any]) -> list[str]:
    """Senders whose transmit buffer (``bus.tx_buffers``) can invert priorities: the analysis
    treats their messages at the node's lowest priority (:func:`canbrake.bus.rta.analyze`)."""
    from canbrake.bus.txbuffer import inverting_nodes

    per_node: dict[str, int] = {}
    for m in messages:
        per_node[m.sender] = per_node.get(m.sender, 0) + 1
    return inverting_nodes(list(getattr(scn.bus, "tx_buffers", []) or []), per_node)


def dbc_cycle_times_s(layout: Any) -> dict[int, float]:
    """Cycle times (s) the bus ``layout``'s DBC declares (``GenMsgCycleTime``), by frame id."""
    return {m.frame_id: m.cycle_ms / 1000.0 for m in layout.messages if m.cycle_ms}
