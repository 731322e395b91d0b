"""Bus segments joined by gateways: a train network that is not one bus (pure; no processes).

A real train's network is several buses: one per carriage, joined through gateways to a train
backbone (IEC 61375 consist and train networks; CiA 421 for CANopen in rail vehicles). Here:

* ``bus.segments``: each segment has a name (used as the candump interface name in the logs), a
  bit rate and the nodes on it (ECU names, ``plant``). The plant (time base, reference and every
  car's brake unit and sensors) is one node of the run; its SYNC/REFERENCE frames start on its own
  segment (the first segment unless one lists ``plant``); a car's SENSOR frames and the brake unit
  that takes its ECU's commands sit on that ECU's segment.
* ``bus.gateways``: each joins two segments, forwards a frame after ``delay_s`` (store and
  forward: the frame is complete on the input segment, then processed) and queues it on the
  output segment in its own transmit queue (node = the gateway's name; ``bus.tx_buffers`` can
  make it a FIFO of a given depth). The forwarding tables are derived from the placement: a
  gateway forwards a frame towards every segment where some node receives it (STATE frames to
  the segments of the ECUs that listen to the sender; SYNC/REFERENCE to every segment with an
  ECU; commands, heartbeats and sensor frames stay on their own segment), along the shortest
  path between segments (:meth:`Topology.tree`).

The segmentation is *modelled*: every node of a run still shares one transport channel (the
in-memory bus, vcan0, ...), and :class:`SegmentedNetwork` — one
:class:`~canbrake.bus.timing.BusTimingModel` per segment, co-simulated with the gateways'
forwarding — decides when each frame ends on each segment it crosses. The in-loop timing model
(:class:`canbrake.bus.schedule.SegmentedBusTiming`) holds a frame until it has reached the last
segment it is addressed to (its farthest receiver), the recorder writes each segment's frames
with the network's times to ``frames_<segment>.log`` and all of them, channel = segment name, to
``frames.log``; ``canbrake analyze`` analyses every segment (the forwarded copies queued by
their gateway with the upstream response time as release jitter, iterated to a fixed point —
holistic analysis) and bounds each message end to end.

Co-simulation: the segments are advanced together in steps no longer than the shortest
gateway delay, so a frame a gateway forwards during a step is queued on the far segment no
earlier than the step's end (conservative synchronisation; idle stretches are skipped).
"""
from __future__ import annotations

import math
from collections import deque
from dataclasses import dataclass, field
from typing import Any, Iterable

from pydantic import BaseModel, ConfigDict, Field, model_validator

from canbrake.bus.timing import BusTimingModel, Delivery, Stuffing

__all__ = ["SegmentConfig", "GatewayConfig", "Topology", "SegmentedNetwork", "topology_of", "message_routes"]

_NAME = r"^[A-Za-z][A-Za-z0-9_]{0,14}$"  # a network interface name (IFNAMSIZ 16), usable as a file suffix


class SegmentConfig(BaseModel):
    """Scenario entry ``bus.segments[i]``: one bus segment."""

    model_config = ConfigDict(extra="forbid", frozen=True)

    name: str = Field(..., pattern=_NAME, description="segment name: the interface column of the logs (car1, backbone)")
    bitrate_bps: int | None = Field(None, gt=0, le=1_000_000, description="bit rate (default: bus.bitrate_bps)")
    nodes: list[str] = Field(default_factory=list, description="nodes on this segment: ECU names, plant")


class GatewayConfig(BaseModel):
    """Scenario entry ``bus.gateways[i]``: a gateway joining two segments."""

    model_config = ConfigDict(extra="forbid", frozen=True)

    name: str = Field(..., pattern=_NAME, description="gateway node name (its transmit queues, bus.tx_buffers)")
    segments: tuple[str, str] = Field(..., description="the two segments it joins")
    delay_s: float = Field(2e-4, ge=1e-5, le=0.1, description="forwarding delay: end of the frame on one "
                                                              "segment to queued on the other (s)")

    @model_validator(mode="after")
    def _check(self) -> "GatewayConfig":
        if self.segments[0] == self.segments[1]:
            raise ValueError(f"gateway {self.name} joins segment {self.segments[0]} to itself")
        return self


@dataclass
class Topology:
    """Segments, gateways and node placement of a scenario, with shortest-path routing."""

    names: list[str]
    bitrate: dict[str, float]
    segment_of: dict[str, str]                 # node -> segment
    delay: dict[str, float]                    # gateway -> forwarding delay (s)
    adj: dict[str, list[tuple[str, str]]]      # segment -> [(gateway, neighbour segment)]
    _trees: dict[Any, dict[str, list[tuple[str, str]]]] = field(default_factory=dict)

    @property
    def plant_segment(self) -> str:
        return self.segment_of["plant"]

    def parents(self, src: str) -> dict[str, tuple[str, str] | None]:
        """BFS from ``src``: segment -> (gateway, previous segment) on a shortest path."""
        par: dict[str, tuple[str, str] | None] = {src: None}
        q = deque([src])
        while q:
            s = q.popleft()
            for gw, nb in self.adj[s]:
                if nb not in par:
                    par[nb] = (gw, s)
                    q.append(nb)
        return par

    def path(self, src: str, dst: str) -> list[tuple[str, str, str]]:
        """Hops ``(from segment, gateway, to segment)`` from ``src`` to ``dst`` (shortest path)."""
        par = self.parents(src)
        hops: list[tuple[str, str, str]] = []
        s = dst
        while par[s] is not None:
            gw, prev = par[s]  # type: ignore[misc]
            hops.append((prev, gw, s))
            s = prev
        return hops[::-1]

    def tree(self, src: str, dests: Iterable[str]) -> dict[str, list[tuple[str, str]]]:
        """Forwarding of a frame that starts on ``src`` and must reach ``dests``: segment ->
        [(gateway, next segment)]; every segment the frame crosses is a key (src included)."""
        key = (src, frozenset(dests))
        t = self._trees.get(key)
        if t is None:
            t = {src: []}
            for d in sorted(key[1]):
                for a, gw, b in self.path(src, d):
                    t.setdefault(a, [])
                    if (gw, b) not in t[a]:
                        t[a].append((gw, b))
                    t.setdefault(b, [])
            self._trees[key] = t
        return t


def topology_of(scn: Any, layout: Any) -> Topology | None:
    """The scenario's :class:`Topology` (None without ``bus.segments``) on its bus ``layout``
    (:func:`canbrake.build.bus_layout`). Raises :class:`canbrake.errors.ScenarioError` naming the
    field on an inconsistent network."""
    from canbrake.errors import ScenarioError

    segs = list(getattr(scn.bus, "segments", None) or [])
    gws = list(getattr(scn.bus, "gateways", None) or [])
    if not segs:
        if gws:
            raise ScenarioError("bus.gateways: gateways need bus.segments")
        return None
    names = [s.name for s in segs]
    dup = sorted({n for n in names if names.count(n) > 1})
    if dup:
        raise ScenarioError(f"bus.segments: segment name(s) used twice: {', '.join(dup)}")
    ecus = [e.name for e in layout.ecus]
    known = set(ecus) | {"plant"}
    segment_of: dict[str, str] = {}
    for i, s in enumerate(segs):
        for node in s.nodes:
            if node not in known:
                raise ScenarioError(f"bus.segments.{i}.nodes: {node!r} is not a node of this train "
                                    f"(plant, {', '.join(ecus[:4])}{', ...' if len(ecus) > 4 else ''})")
            if node in segment_of:
                raise ScenarioError(f"bus.segments.{i}.nodes: {node} is already on segment {segment_of[node]}")
            segment_of[node] = s.name
    missing = [e for e in ecus if e not in segment_of]
    if missing:
        raise ScenarioError(f"bus.segments: ECU(s) {', '.join(missing[:6])} on no segment (list each ECU in the "
                            "nodes of one segment)")
    segment_of.setdefault("plant", names[0])
    gw_names = [g.name for g in gws]
    clash = sorted({n for n in gw_names if gw_names.count(n) > 1} | (set(gw_names) & known))
    if clash:
        raise ScenarioError(f"bus.gateways: name(s) {', '.join(clash)} used twice or by another node")
    adj: dict[str, list[tuple[str, str]]] = {n: [] for n in names}
    for i, g in enumerate(gws):
        for s in g.segments:
            if s not in adj:
                raise ScenarioError(f"bus.gateways.{i}.segments: no segment named {s!r} (segments: {', '.join(names)})")
        a, b = g.segments
        adj[a].append((g.name, b))
        adj[b].append((g.name, a))
    bitrate = {s.name: float(s.bitrate_bps or scn.bus.bitrate_bps) for s in segs}
    topo = Topology(names, bitrate, segment_of, {g.name: g.delay_s for g in gws}, adj)
    reach = topo.parents(names[0])
    cut = [n for n in names if n not in reach]
    if cut:
        raise ScenarioError(f"bus.gateways: segment(s) {', '.join(cut)} are not joined to {names[0]} by any gateway")
    return topo


def message_routes(layout: Any, topo: Topology, plant_io_on_bus: bool = False) -> dict[int, tuple[str, str, frozenset]]:
    """Per frame id of the layout: (sending node on its first segment, first segment, segments
    that must receive it) — the forwarding tables' input. Barrier frames (*_DONE) are not listed."""
    ecu_seg = {e.index: topo.segment_of[e.name] for e in layout.ecus}
    with_ecus = frozenset(ecu_seg.values())
    out: dict[int, tuple[str, str, frozenset]] = {}
    for m in layout.messages:
        if m.kind in ("state_done", "cmd_done"):
            continue
        if m.ecu == 0:  # plant: time base and reference to every ECU; its heartbeat stays home
            src = topo.plant_segment
            dests = frozenset({src}) if m.kind == "heartbeat" else with_ecus | {src}
            out[m.frame_id] = ("plant", src, dests)
            continue
        e = layout.by_index[m.ecu]
        src = ecu_seg[m.ecu]
        if m.kind == "sensor":  # the car's own sensors, on its segment
            out[m.frame_id] = (e.name, src, frozenset({src}))
        elif m.kind == "state":
            out[m.frame_id] = (e.name, src, frozenset({src} | {ecu_seg[j] for j in e.listeners}))
        else:  # commands (the car's brake unit is on the ECU's segment), heartbeats
            out[m.frame_id] = (e.name, src, frozenset({src}))
    return out


def forwarding_tables(layout: Any, topo: Topology) -> dict[str, dict[str, list[str]]]:
    """Per gateway: ``"from->to"`` -> names of the messages it forwards that way."""
    names = {m.frame_id: m.name for m in layout.messages}
    out: dict[str, dict[str, list[str]]] = {g: {} for g in sorted(topo.delay)}
    for fid, (_node, src, dests) in sorted(message_routes(layout, topo).items()):
        for a, hops in topo.tree(src, dests).items():
            for gw, b in hops:
                out[gw].setdefault(f"{a}->{b}", []).append(names[fid])
    return out


class _Route:
    """A frame in flight through the network: its tag, forwarding tree, segments still to reach."""

    __slots__ = ("tag", "tree", "left", "t_end", "t_queue", "lost", "node")

    def __init__(self, tag: Any, tree: dict[str, list[tuple[str, str]]], t_queue: float, node: str) -> None:
        self.tag = tag
        self.tree = tree
        self.left = len(tree)
        self.t_end = -math.inf
        self.t_queue = t_queue
        self.lost = False
        self.node = node


class SegmentedNetwork:
    """One :class:`BusTimingModel` per segment, co-simulated with gateway forwarding.

    :meth:`submit` queues a frame on its first segment; :meth:`advance` returns
    ``(segment, Delivery)`` for every end of frame on any segment by ``until_s`` (in time order),
    and collects each frame that has reached every segment of its tree (:meth:`pop_completed`:
    ``(tag, t_end_s)`` with the latest end, ``math.inf`` if a queue dropped it on the way).
    """

    def __init__(self, topo: Topology, *, stuffing: Stuffing = "worst", record_history: bool = False,
                 tx_buffers: Any = None) -> None:
        self.topo = topo
        self.models = {s: BusTimingModel(topo.bitrate[s], stuffing=stuffing, record_history=record_history,
                                         tx_buffers=tx_buffers) for s in topo.names}
        self.h = min(topo.delay.values(), default=math.inf)
        self.record_history = record_history
        self._now = 0.0
        self._completed: list[tuple[Any, float]] = []
        self.e2e: dict[tuple[int, bool], list[float]] = {}  # record_history: queued -> last segment (s)
        self.forwarded: dict[str, int] = {}                 # gateway -> frames it queued

    @property
    def now_s(self) -> float:
        return self._now

    def submit(self, node: str, msg_id: int, is_extended: bool, dlc: int, data: bytes | None, t_queue_s: float, *,
               src: str, dests: Iterable[str], tag: Any = None) -> None:
        """Queue a frame of ``node`` on segment ``src`` at ``t_queue_s``, addressed to ``dests``."""
        r = _Route(tag, self.topo.tree(src, dests), t_queue_s, node)
        self.models[src].submit(node, msg_id, is_extended, dlc, data, t_queue_s, tag=r)

    def advance(self, until_s: float) -> list[tuple[str, Delivery]]:
        out: list[tuple[str, Delivery]] = []
        models = self.models
        while self._now < until_s - 1e-12:
            ev = [(m.next_event_s(), seg, m) for seg, m in models.items()]
            nxt = min(e[0] for e in ev)
            # nothing happens before nxt: jump there; else one step no longer than a gateway delay
            u = min(until_s, nxt if nxt > self._now + self.h else self._now + self.h)
            for t_ev, seg, m in ev:
                if t_ev > u:  # nothing due on this segment: it stays where it is (submissions stay legal)
                    continue
                for d in m.advance(u):
                    out.append((seg, d))
                    self._delivered(seg, d)
                for d in m.pop_dropped():
                    self._lost(d.tag)
            self._now = u
        out.sort(key=lambda sd: sd[1].t_end_s)
        return out

    def _delivered(self, seg: str, d: Delivery) -> None:
        r: _Route = d.tag
        for gw, nb in r.tree[seg]:
            self.forwarded[gw] = self.forwarded.get(gw, 0) + 1
            self.models[nb].submit(gw, d.arbitration_id, d.is_extended, d.dlc, d.data,
                                   d.t_end_s + self.topo.delay[gw], is_remote=d.is_remote, tag=r)
        r.t_end = max(r.t_end, d.t_end_s)
        r.left -= 1
        if r.left == 0 and not r.lost:
            self._completed.append((r.tag, r.t_end))
            if self.record_history:
                self.e2e.setdefault((d.arbitration_id, d.is_extended), []).append(r.t_end - r.t_queue)

    def _lost(self, r: _Route) -> None:
        if not r.lost:
            r.lost = True
            self._completed.append((r.tag, math.inf))

    def pop_completed(self) -> list[tuple[Any, float]]:
        out, self._completed = self._completed, []
        return out

    def pending(self) -> bool:
        """True while any frame is queued or on the wire on some segment."""
        return any(math.isfinite(m.next_event_s()) for m in self.models.values())


# --------------------------------------------------------------------------------------------
# response-time analysis per segment and end to end (holistic)


@dataclass(frozen=True)
class Hop:
    """One segment of a message's path in the analysis (times in s)."""

    segment: str
    gateway: str | None      # the gateway that queued it here (None on the first segment)
    delay_s: float           # that gateway's forwarding delay (0 on the first segment)
    jitter_s: float          # release jitter on this segment (upstream response time - best case)
    response_s: float        # Davis 2007 R on this segment, jitter included (inf: unbounded)

    @property
    def bound_s(self) -> float:
        """Queued on this segment -> end of frame, worst case (R - J)."""
        return self.response_s - self.jitter_s if math.isfinite(self.response_s) else math.inf


@dataclass(frozen=True)
class EndToEnd:
    """Worst-case response time of a message from its release to the end of its frame on the
    farthest segment it must reach: R on the first segment + Σ (gateway delay + R − J on the next)."""

    name: str
    arbitration_id: int
    sender: str
    hops: list[Hop]
    response_s: float
    deadline_s: float

    @property
    def schedulable(self) -> bool:
        return self.response_s <= self.deadline_s * (1 + 1e-12)

    def as_dict(self) -> dict:
        def f(x: float) -> float | None:
            return x if math.isfinite(x) else None

        return {"name": self.name, "id": self.arbitration_id, "id_hex": f"0x{self.arbitration_id:X}",
                "sender": self.sender, "path": [h.segment for h in self.hops],
                "hops": [{"segment": h.segment, "gateway": h.gateway, "delay_s": h.delay_s, "jitter_s": h.jitter_s,
                          "response_s": f(h.response_s), "bound_s": f(h.bound_s)} for h in self.hops],
                "gateway_delay_s": sum(h.delay_s for h in self.hops), "response_s": f(self.response_s),
                "deadline_s": self.deadline_s, "schedulable": self.schedulable}


def analyze_network(messages: list[Any], topo: Topology, routes: dict[int, tuple[str, str, frozenset]], *,
                    method: str = "davis2007", fifo_nodes: Any = None,
                    max_iter: int = 100) -> tuple[dict[str, Any], list[EndToEnd]]:
    """Davis 2007 on every segment and end-to-end bounds through the gateways.

    ``messages``: :class:`canbrake.bus.rta.CanMessage` with their senders and release jitter;
    ``routes``: :func:`message_routes` (a message not in it, a babbler, stays on the plant's
    segment). On a segment a message reaches through gateway g it is sent by g, with release
    jitter J = R(previous segment) − C_best(previous segment) (best case: no stuff bits), since
    it arrives at the gateway between C_best and R after its release; the segments are analysed
    again until no jitter changes (holistic analysis, Tindell & Clark 1994). ``fifo_nodes(seg,
    msgs)`` names the nodes of a segment analysed as FIFO queues. Returns the per-segment
    :class:`canbrake.bus.rta.Analysis` and one :class:`EndToEnd` per message (worst destination)."""
    from dataclasses import replace

    from canbrake.bus.rta import analyze
    from canbrake.bus.timing import frame_bits

    plant = topo.plant_segment
    src: dict[str, str] = {}
    tree: dict[str, dict[str, list[tuple[str, str]]]] = {}
    dests: dict[str, frozenset] = {}
    parent: dict[tuple[str, str], tuple[str, str]] = {}
    for m in messages:
        r = routes.get(m.arbitration_id) if not m.name.startswith("BABBLE_") else None
        src[m.name], dests[m.name] = (r[1], r[2]) if r is not None else (plant, frozenset({plant}))
        tree[m.name] = topo.tree(src[m.name], dests[m.name])
        for a, hops in tree[m.name].items():
            for gw, b in hops:
                parent[(m.name, b)] = (a, gw)
    jit = {(m.name, seg): (m.jitter_s if seg == src[m.name] else 0.0) for m in messages for seg in tree[m.name]}
    res: dict[str, Any] = {}
    for _ in range(max_iter):
        res = {}
        for seg in topo.names:
            on = [replace(m, sender=m.sender if seg == src[m.name] else parent[(m.name, seg)][1],
                          jitter_s=jit[(m.name, seg)]) for m in messages if seg in tree[m.name]]
            if on:
                res[seg] = analyze(on, topo.bitrate[seg], method=method,  # type: ignore[arg-type]
                                   fifo_nodes=fifo_nodes(seg, on) if fifo_nodes else ())
        by = {seg: a.by_name() for seg, a in res.items()}
        new = dict(jit)
        for (name, seg), (prev, _gw) in parent.items():
            r = by[prev][name]
            m = r.message
            c_best = frame_bits(m.arbitration_id, m.is_extended, m.dlc, stuffing="none") / topo.bitrate[prev]
            # an unbounded upstream response: a jitter of 1000 periods (the segment's R is then unbounded too)
            new[(name, seg)] = r.response_s - c_best if math.isfinite(r.response_s) else 1000.0 * m.period_s
        if all(abs(new[k] - jit[k]) <= 1e-12 for k in jit):
            break
        jit = new
    by = {seg: a.by_name() for seg, a in res.items()}
    e2e: list[EndToEnd] = []
    for m in messages:
        s0 = src[m.name]
        first = Hop(s0, None, 0.0, jit[(m.name, s0)], by[s0][m.name].response_s)
        worst: EndToEnd | None = None
        for d in sorted(dests[m.name]):
            hops = [first]
            total = first.response_s
            for _a, gw, b in topo.path(s0, d):
                h = Hop(b, gw, topo.delay[gw], jit[(m.name, b)], by[b][m.name].response_s)
                hops.append(h)
                total += h.delay_s + h.bound_s
            cand = EndToEnd(m.name, m.arbitration_id, m.sender, hops, total, m.deadline)
            if worst is None or cand.response_s > worst.response_s or (
                    cand.response_s == worst.response_s and len(hops) > len(worst.hops)):
                worst = cand
        assert worst is not None
        e2e.append(worst)
    return res, e2e
