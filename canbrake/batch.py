"""The batch engine: many lockstep runs (sweep points) of one scenario family at once, in one process.

What it reuses per point: the controllers (:func:`canbrake.build.build_controller`: the same
``chen2023`` / ``chen2023_compensated`` / ``pi`` classes, brake functions included), the plant
(:func:`canbrake.build.build_plant_model`) and a :class:`~canbrake.nodes.plant.PlantNode` for
its column layout, initial command hold and statistics, the impairment chains
(:func:`canbrake.build.build_send_path`: the same seeded :class:`~canbrake.bus.impair.SendPath`
objects, so every loss draw and delay is the one the node engine makes) and the summary
(:func:`canbrake.analysis.summary.finalize_run`).

Vectorised over the points (issue 13, item 3: one numpy call serves every point, so a tick costs
about the same for 8 points as for 64):

* **frames' fates**: every frame an ECU will send is known before the run (a STATE frame at t_k, a
  command frame at t_k + c·T), so :meth:`~canbrake.bus.impair.SendPath.fates` draws each one's
  release time (or loss) up front, from the same generators in the same order as ``submit``;
  the frames are then handed out per release window as arrays (:meth:`BatchEngine._schedule`).
* **controllers**: where every point runs the same controller on an ECU slot and the controller
  offers a batch form (:meth:`~canbrake.control.chen.ChenConsensusController.step_batch`, the
  same operations in the same order on arrays of shape (points,)), one object steps every point;
  ECU slots whose controllers differ only in car and mass (``group_key``: Chen's) step together,
  one call per tick for every slot and point (:class:`~canbrake.control.chen.ChenBatch`, arrays
  of points x slots); otherwise each point's own controller steps.
* **plant**: plants that qualify (:func:`~canbrake.physics.train.stack_plants`: the same
  resistance tables, traction envelopes, end stops and wheelsets at every point, end stops never
  refining the sub-step) step as one stack with a leading points axis; otherwise each its own.

Every path gives each point the floats its per-point run computes: tests/test_batch_sweep.py
compares them text for text, tests/test_control.py, test_physics.py and test_impair.py the batch
forms against the scalar ones.

What it does instead of the nodes: it moves *values*, not frames. A frame's payload is what the
receiver decodes, :meth:`canbrake.bus.codec.MessageCodec.quantiser` (the DBC scale, offset and
range, vectorised over points and cars); the E2E alive counter is the sender's tick mod 15 and
the receivers date a frame as :meth:`canbrake.bus.guard.FrameGuard.origin` does (ECU: lag window
14 periods, plant: 7, only newer origins accepted; the aliasing of frames 15 or more periods
old included). The lockstep phases are those of :mod:`canbrake.nodes.base`: every ECU's STATE
frames of tick k are submitted at t_k and those released by t_k + c·T (c =
``ecu.lockstep_deadline``) are used in tick k; frames released later in the period reach their
receivers after they computed; commands submitted at t_k + c·T and released by the end of the
period are applied to the step of that tick. Values are exchanged as arrays of shape
(points, ECUs), quantised in one call per signal and tick for every point.

Where it falls back (:func:`unsupported`): anything it does not reproduce exactly — another physics
kernel than ``coupled`` (Chen couplers), controllers other than the three above, realtime mode, the bus timing
model, impairments other than delay/loss/jitter (or per-link, or the scenario's own), SecOC,
fail-safe, peer hold, ECU crashes, external ECUs, a reference position, coupler sensors, multi-page
frames. ``canbrake sweep`` then runs those points one by one and says why.

Not produced (the per-point run has them): ``frames.log``, ``bus_stats.json`` (frames on the bus,
bus load: the sweep rows' ``frames_on_bus``/``bus_load_*`` columns stay empty) and the plant's
E2E sequence counters. tests/test_batch_sweep.py checks signals.csv, the ECU traces, the
metrics and the verdict against the per-point in-process run.
"""
from __future__ import annotations

import math
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Sequence

import numpy as np

from canbrake.bus.e2e import COUNTER_MODULO
from canbrake.scenario import Scenario

#: controllers the batch engine runs (others fall back to per-point runs)
BATCH_CONTROLLERS = ("chen2023", "chen2023_compensated", "pi")
#: impairment types whose effect the batch engine reproduces (through the same SendPath objects)
BATCH_IMPAIRMENTS = ("delay", "loss", "jitter")
#: lag windows of the receivers' counter checks (canbrake.nodes.ecu / plant: FrameGuard max_lag)
ECU_MAX_LAG = COUNTER_MODULO - 1
PLANT_MAX_LAG = 7


def unsupported(scn: Scenario, base_impairments: int = 0) -> str | None:
    """Why the batch engine cannot run ``scn`` exactly as the node engine does, or None.

    ``base_impairments``: how many of ``scn.bus.impairments`` come from the scenario itself (the
    sweep appends its axes' after them); those are not reproduced."""
    from canbrake.build import bus_layout, external_ecus

    train = scn.train.kernel_name
    if train != "coupled":
        return f"not for {train} trains"
    if getattr(scn.consist, "mixed", False):
        return "not for trains with draft gears or air brakes on the coupled kernel"
    if getattr(scn.consist, "rigid", False):
        return "not for rigidly coupled trains with driven axles"
    if scn.mode != "lockstep":
        return f"not in {scn.mode} mode"
    if scn.bus.timing != "ideal":
        return "not with the bus timing model (bus.timing: model)"
    if getattr(scn, "security", None) is not None:
        return "not with SecOC (security)"
    if scn.safety.command_timeout_s is not None:
        return "not with the fail-safe (safety.command_timeout_s)"
    if scn.safety.peer_hold_periods is not None:
        return "not with safety.peer_hold_periods"
    if scn.ecu.crash is not None:
        return "not with an injected ECU crash"
    if external_ecus(scn):
        return "not with external ECUs"
    if getattr(scn.plant, "coupler_sensors", False):
        return "not with coupler sensors"
    if getattr(scn.bus, "segments", None):
        return "not with bus segments"
    names = {p.controller.name for p in scn.placement()}
    other = sorted(names - set(BATCH_CONTROLLERS))
    if other:
        return f"not for the controller(s) {', '.join(other)}"
    for i, spec in enumerate(scn.bus.impairments):
        if i < base_impairments:
            return "not with the scenario's own bus.impairments"
        kind = getattr(spec, "type", None)
        if kind not in BATCH_IMPAIRMENTS:
            return f"not with {kind} impairments"
        if getattr(spec, "receivers", None):
            return "not with per-link (receivers) impairments"
    layout = bus_layout(scn)
    if layout.ref_position:
        return "not with a reference position"
    if layout.counter_ext():
        return "not with extended alive counters"
    for e in layout.ecus:
        if len(layout.ids("state", e.index)) > 1 or len(layout.ids("cmd", e.index)) > 1:
            return "not with multi-page STATE/command frames"
    return None


def batch_key(scn: Scenario) -> tuple:
    """Points that share this key run in one batch: same cars, ECUs, signals, number of ticks and
    controllers."""
    from canbrake.build import bus_layout

    lay = bus_layout(scn)
    return (scn.n_cars, scn.n_ticks, scn.control_period_s, scn.ecu.lockstep_deadline, scn.plant.trace_every,
            tuple((m.kind, m.ecu, m.frame_id, tuple((sig, sp.name, sp.scale, sp.offset, sp.length, sp.signed)
                                                    for sig, sp in m.signals)) for m in lay.messages),
            tuple((e.sensors, e.commands, e.broadcast, e.listens, e.listeners) for e in lay.ecus),
            # the same controllers (and vehicle masses): each ECU slot steps all points in one batch call
            tuple(_ctrl_key(scn, s) for s in range(len(lay.ecus))))


def point_bytes(scn: Scenario) -> int:
    """Memory (bytes, estimate) a point takes in a batch: its signals.csv rows and ECU traces (held
    until the point ends, floats) and its frames' schedule (two kinds, four int32 per frame)."""
    n, m, ticks = scn.n_cars, len(scn.placement()), scn.n_ticks
    cols = 4 + 7 * n + m * (4 + 12)  # per-car and coupler columns; per ECU up to 12 diagnostics
    return ticks * (8 * cols + 2 * m * 16)


def batch_groups(scns: Sequence[Scenario]) -> list[list[int]]:
    """Indices of ``scns`` grouped into batches that can run together (same layout and length)."""
    groups: dict[tuple, list[int]] = {}
    for i, s in enumerate(scns):
        groups.setdefault(batch_key(s), []).append(i)
    return list(groups.values())


@dataclass
class _Point:
    """One sweep point: its scenario, run directory, plant node (its statistics, command layout and
    per-point plant), controllers (used where a slot has no batch form) and send paths."""

    scn: Scenario
    run_dir: Path | None
    plant: Any                                  # canbrake.nodes.plant.PlantNode (holds the model)
    ctrls: list[Any]
    paths: list[Any] | None                     # per ECU: canbrake.bus.impair.SendPath, or None (no impairment)


@dataclass
class _Deliveries:
    """Every frame of one kind (STATE or command) that reaches its receivers, sorted by the window
    it is released in, then point, sender, release time and origin (the order a SendPath hands them
    out). Window w is tick w // 2, phase 1 (w even: released by t_k + c·T) or 2 (w odd: by the end
    of the period). ``rank``: the frame's place among those of the same point and sender in its
    window (0 for the first); ``bounds[w]:bounds[w + 1]`` are window w's frames."""

    point: np.ndarray
    sender: np.ndarray
    origin: np.ndarray
    rank: np.ndarray
    bounds: np.ndarray
    max_rank: np.ndarray                        # per window


class BatchEngine:
    """Run the lockstep loop of several points of one layout at once (see the module docstring).

    ``scns``: the resolved scenarios (all in one :func:`batch_groups` group, each supported);
    ``run_dirs``: their run directories (prepared here as ``run_scenario`` does) or None."""

    def __init__(self, scns: Sequence[Scenario], run_dirs: Sequence[str | Path | None]) -> None:
        from canbrake.build import (build_controller, build_plant_model, build_send_path, bus_layout,
                                    reference_fn)
        from canbrake.bus.codec import FrameCodec
        from canbrake.nodes.base import PassThrough
        from canbrake.nodes.plant import PlantNode
        from canbrake.run import prepare_run_dir

        if not scns:
            raise ValueError("no points")
        s0 = scns[0]
        self.layout = lay = bus_layout(s0)
        self.codec = codec = FrameCodec(lay.database())
        self.dt = s0.control_period_s
        self.n_ticks = s0.n_ticks
        self.c = s0.ecu.lockstep_deadline
        self.trace_every = max(1, int(s0.plant.trace_every))
        self.ecus = list(lay.ecus)
        m = self.n_ecus = len(self.ecus)
        self.veh = np.asarray([e.vehicle - 1 for e in self.ecus], dtype=np.int64)
        # signals: sensors (plant -> ECU), state (ECU -> ECUs), commands (ECU -> plant)
        self.sensor_q = self._quantisers("sensor")
        self.state_q = self._quantisers("state")
        self.cmd_q = self._quantisers("cmd")
        # one quantiser call per signal for every ECU whose frame has the same format
        self.sensor_g, self.state_g, self.cmd_g = (self._groups(x) for x in (self.sensor_q, self.state_q, self.cmd_q))
        ref = codec["REFERENCE"]
        self.q_ref_v, self.q_ref_a = ref.quantiser("RefSpeed"), ref.quantiser("RefDecel")
        self.has_state = np.asarray([bool(e.listeners) for e in self.ecus])
        # listen[i, j]: ECU i receives ECU j's STATE frames
        self.listen = np.zeros((m, m), dtype=bool)
        for i, e in enumerate(self.ecus):
            for j in e.listens:
                self.listen[i, j - 1] = True
        self.peer_names = sorted({sig for _, sig, _ in self.state_q} | {"speed_mps", "position_m"})
        self.state_sigs = sorted({sig for _, sig, _ in self.state_q})
        self.cmd_sigs = sorted({sig for _, sig, _ in self.cmd_q})
        self.n_listened = self.listen.sum(axis=1)
        self.state_id = [(lay.ids("state", e.index) or [0])[0] for e in self.ecus]
        self.cmd_id = [lay.ids("cmd", e.index)[0] for e in self.ecus]
        self.points: list[_Point] = []
        dbc_text = lay.database().as_dbc_string()  # every point's (batch_key: the same layout)
        for scn, rd in zip(scns, run_dirs):
            run_dir = prepare_run_dir(scn, rd, dbc_text=dbc_text) if rd is not None else None
            plant = PlantNode(build_plant_model(scn), codec, layout=lay, dt_s=scn.control_period_s,
                              n_ticks=scn.n_ticks, reference=reference_fn(scn), mode=scn.mode,
                              heartbeat_period_s=scn.ecu.heartbeat_period_s, out_dir=run_dir, barrier=True,
                              trace_every=scn.plant.trace_every)
            paths = None
            if scn.bus.impairments:
                paths = []
                for e in self.ecus:
                    sp = build_send_path(scn, e.name)
                    paths.append(None if isinstance(sp, PassThrough) else sp.path.path)  # the impair.SendPath
            ctrls = [build_controller(scn, i) for i in range(1, m + 1)]
            self.points.append(_Point(scn, run_dir, plant, ctrls, paths))
        P = self.P = len(self.points)
        pn0 = self.points[0].plant
        self.n = pn0.n
        self.cols = pn0.columns()
        self.command_names = list(pn0.command_names)
        self.extra_meas = list(pn0._extra_measurements())
        self.alive = np.ones(P, dtype=bool)
        # what every receiver holds of its peers (the ECU node's peer_signals / _origin_of)
        self.peer = {nm: np.full((P, m, m), np.nan) for nm in self.peer_names}
        self.origin = np.full((P, m, m), -(10 ** 12), dtype=np.int64)
        self.peer_frames = np.zeros((P, m), dtype=np.int64)
        self.peer_stale = np.zeros((P, m), dtype=np.int64)
        self.peer_missing = np.zeros((P, m), dtype=np.int64)
        # the brake units: newest command per vehicle (PlantNode.commands), its origin per ECU
        self.hold = {c: np.stack([p.plant.commands[c] for p in self.points]) for c in self.command_names}
        self.plant_origin = np.full((P, m), -1, dtype=np.int64)
        self.fresh = np.zeros((P, m), dtype=bool)
        self.received = np.zeros(P, dtype=np.int64)
        self.rejected = np.zeros(P, dtype=np.int64)
        self.missed = np.zeros((P, m), dtype=np.int64)
        self.k_plant = np.zeros(P, dtype=np.int64)
        self.bcast = {sig: np.full((P, m), np.nan) for sig in self.state_sigs}
        # the controllers: one batch object per ECU slot where every point runs the same one
        self.batch_ctrl: list[Any] = []
        # (the first point's, stepped in its batch form; the other points' are then never stepped)
        for s in range(m):
            c0, key = self.points[0].ctrls[s], _ctrl_key(scns[0], s)
            same = all(_ctrl_key(p.scn, s) == key for p in self.points[1:])
            ok = same and callable(getattr(c0, "batchable", None)) and c0.batchable()
            self.batch_ctrl.append(c0 if ok else None)
        # slots whose batch controllers step as one (ChenConsensusController.group_key: the same
        # class and parameters but the car): one call per tick for all of them and every point
        by_key: dict[tuple, list[int]] = {}
        for s, bc in enumerate(self.batch_ctrl):
            gk = getattr(type(bc), "group_key", None)
            key = gk(bc) if bc is not None and gk is not None else None
            if key is not None:
                by_key.setdefault((type(bc), key), []).append(s)
        self.slot_groups = [(np.asarray(slots), type(self.batch_ctrl[slots[0]]).batch_group(
            [self.batch_ctrl[s] for s in slots], P)) for slots in by_key.values()]
        self.grouped = {s for slots in by_key.values() for s in slots}
        # the plant: one stacked plant for every point where they qualify, else each its own
        from canbrake.build import CoupledPlant
        from canbrake.physics.train import stack_plants

        models = [p.plant.model for p in self.points]
        self.stack = None
        if all(type(mo) is CoupledPlant for mo in models):
            self.stack = stack_plants([mo.plant for mo in models])
        # traces: signals.csv rows and the ECU traces, per point (filled while the point is alive;
        # np.empty: a point's rows [0, n_rows) / [0, n_ecu_rows) are all written before they are
        # read, every cell _close reads of them included, and filling ~1 GB with NaN first cost ~5 %
        # of a sweep's CPU)
        self.n_rows = np.zeros(P, dtype=np.int64)
        self.rows = np.empty((self.n_ticks // self.trace_every + 2, P, len(self.cols)))
        self.n_ecu_rows = np.zeros(P, dtype=np.int64)
        # per slot: [tick, command, diagnostics (as many as the point's controller has; the others
        # unused), oldest peer age, fresh peers]; each point's trace has its own controller's columns
        n_diag = [max(len(p.ctrls[s].diagnostic_names) for p in self.points) for s in range(m)]
        self.ecu_rows = [np.empty((self.n_ticks, P, nd + 4)) for nd in n_diag]
        self._schedule()

    @staticmethod
    def _groups(qs: list[tuple[int, str, Any]]) -> list[tuple[str, np.ndarray, Any]]:
        """(signal, ECU slots, quantiser): the slots whose frames carry the signal in the same format."""
        groups: dict[tuple, tuple[str, list[int], Any]] = {}
        for slot, sig, q in qs:
            key = (sig, q.scale, q.offset, q.lo, q.hi)
            if key not in groups:
                groups[key] = (sig, [], q)
            groups[key][1].append(slot)
        return [(sig, np.asarray(slots), q) for sig, slots, q in groups.values()]

    def _quantisers(self, kind: str) -> list[tuple[int, str, Any]]:
        """(ECU slot, signal name, quantiser) of every signal of the ``kind`` frames, in frame order."""
        out = []
        for mm in self.layout.messages:
            if mm.kind == kind:
                q = self.codec[mm.name]
                out += [(mm.ecu - 1, sig, q.quantiser(sp.name)) for sig, sp in mm.signals if sig]
        return out

    # ------------------------------------------------------------------ the frames' fates
    def _schedule(self) -> None:
        """Every frame every ECU will send is known before the run (one STATE frame at t_k, one
        command frame at t_k + c·T per tick), so its fate is drawn up front: each send path's
        :meth:`~canbrake.bus.impair.SendPath.fates` gives the release times its ``submit`` would,
        from the same generators in the same order. A frame is handed out in the first release
        window (t_k + c·T, then t_k + T(1 − 1e-9), as the ECU node releases) at or after its
        release time and not before it was submitted."""
        n, m, dt = self.n_ticks, self.n_ecus, self.dt
        t = np.arange(n) * dt
        t2 = t + self.c * dt
        win = np.empty(2 * n)
        win[0::2] = t + self.c * dt
        win[1::2] = t + dt * (1 - 1e-9)
        ks = np.arange(n)
        per_kind: dict[str, list[tuple[np.ndarray, ...]]] = {"state": [], "cmd": []}
        hmax = 1
        for i, p in enumerate(self.points):
            for j in range(m):
                path = p.paths[j] if p.paths is not None else None
                st = bool(self.has_state[j])
                if st:
                    t_sub = np.empty(2 * n)
                    t_sub[0::2], t_sub[1::2] = t, t2
                    ids = np.empty(2 * n, dtype=np.int64)
                    ids[0::2], ids[1::2] = self.state_id[j], self.cmd_id[j]
                else:
                    t_sub, ids = t2.copy(), np.full(n, self.cmd_id[j], dtype=np.int64)
                rel = t_sub if path is None else path.fates(t_sub, ids)
                parts = (("state", rel[0::2], 0), ("cmd", rel[1::2], 1)) if st else (("cmd", rel, 1),)
                for kind, r, phase in parts:
                    w = np.maximum(np.searchsorted(win, r, side="left"), 2 * ks + phase)
                    got = w < 2 * n
                    if got.any():
                        hmax = max(hmax, int((w[got] // 2 - ks[got]).max()) + 1)
                    per_kind[kind].append((w[got], np.full(int(got.sum()), i), np.full(int(got.sum()), j),
                                           ks[got], r[got]))
        self.H = hmax
        self.deliveries = {kind: self._sorted(parts, 2 * n) for kind, parts in per_kind.items()}
        P = self.P
        self.state_hist = {sig: np.full((hmax, P, m), np.nan) for sig in self.state_sigs}
        self.cmd_hist = {sig: np.full((hmax, P, m), np.nan) for sig in self.cmd_sigs}

    @staticmethod
    def _sorted(parts: list[tuple[np.ndarray, ...]], n_win: int) -> _Deliveries:
        if parts:
            w, i, j, k, r = (np.concatenate(a) for a in zip(*parts))
        else:
            w = i = j = k = np.zeros(0, dtype=np.int64)
            r = np.zeros(0)
        # by window, point, sender, release time, origin: the parts come point by point, sender by
        # sender, origin by origin, so a stable sort by release time and then a stable sort by
        # (window, point, sender) as one integer give lexsort((k, r, j, i, w))'s order (two keys
        # sorted instead of five)
        order = np.argsort(r, kind="stable")
        n_pt, n_snd = (int(i.max()) + 1, int(j.max()) + 1) if w.size else (1, 1)
        key = (w[order].astype(np.int64) * n_pt + i[order]) * n_snd + j[order]
        order = order[np.argsort(key, kind="stable")]
        w, i, j, k = w[order], i[order], j[order], k[order]
        new = np.ones(w.size, dtype=bool)
        new[1:] = (w[1:] != w[:-1]) | (i[1:] != i[:-1]) | (j[1:] != j[:-1])
        idx = np.arange(w.size)
        rank = idx - np.maximum.accumulate(np.where(new, idx, 0))
        max_rank = np.full(n_win, -1, dtype=np.int64)
        np.maximum.at(max_rank, w, rank)
        return _Deliveries(i.astype(np.int32), j.astype(np.int32), k.astype(np.int32), rank.astype(np.int32),
                           np.searchsorted(w, np.arange(n_win + 1)), max_rank)

    def _window(self, kind: str, w: int) -> list[tuple[np.ndarray, np.ndarray, np.ndarray]]:
        """Window w's frames of ``kind`` of the points still running, as rounds (point, sender,
        origin) in which each point and sender appears at most once, in release order."""
        d = self.deliveries[kind]
        a, b = d.bounds[w], d.bounds[w + 1]
        if a == b:
            return []
        pt, snd, org = d.point[a:b], d.sender[a:b], d.origin[a:b]
        live = self.alive[pt]
        if d.max_rank[w] == 0:
            return [(pt[live], snd[live], org[live])]
        rank = d.rank[a:b]
        return [(pt[sel], snd[sel], org[sel]) for r in range(int(d.max_rank[w]) + 1)
                for sel in [live & (rank == r)]]

    def _state_in(self, w: int, k: int) -> None:
        """STATE frames released in window w reach their listeners at their tick k; each listener
        dates a frame by its alive counter and keeps only newer ones (canbrake.nodes.ecu)."""
        m = self.n_ecus
        recv = np.arange(m)
        for pt, snd, org in self._window("state", w):
            if pt.size == 0:
                continue
            lag = (k - org) % COUNTER_MODULO  # the receiver knows only the alive counter
            origin = k - lag
            listens = self.listen[:, snd].T                                   # (F, m): frame, receiver
            last = self.origin[pt[:, None], recv[None, :], snd[:, None]]
            ok = listens & (lag <= ECU_MAX_LAG)[:, None] & (origin[:, None] > last)
            np.add.at(self.peer_stale, (pt[:, None].repeat(m, 1), recv[None, :].repeat(pt.size, 0)),
                      listens & ~ok)
            f, r = np.nonzero(ok)
            if f.size == 0:
                continue
            pi, si, oi = pt[f], snd[f], org[f]
            self.origin[pi, r, si] = origin[f]
            slot = oi % self.H
            for sig in self.state_sigs:
                self.peer[sig][pi, r, si] = self.state_hist[sig][slot, pi, si]
            np.add.at(self.peer_frames, (pi, r), 1)

    def _cmd_in(self, w: int, k: int) -> None:
        """Command frames released in window w reach the brake units at the plant's tick k, which
        date them by the alive counter (lag window PLANT_MAX_LAG) and keep only newer ones."""
        for pt, snd, org in self._window("cmd", w):
            if pt.size == 0:
                continue
            lag = (k - org) % COUNTER_MODULO
            origin = k - lag
            ok = (lag <= PLANT_MAX_LAG) & (origin > self.plant_origin[pt, snd])
            np.add.at(self.rejected, pt[~ok], 1)
            pt, snd, org, origin = pt[ok], snd[ok], org[ok], origin[ok]
            self.plant_origin[pt, snd] = origin
            veh = self.veh[snd]
            slot = org % self.H
            for sig in self.cmd_sigs:
                self.hold[sig][pt, veh] = self.cmd_hist[sig][slot, pt, snd]
            np.add.at(self.received, pt, 1)
            now = origin == k
            self.fresh[pt[now], snd[now]] = True

    # ------------------------------------------------------------------ run
    def run(self) -> list[dict[str, Any]]:
        """Run every point to its end; write each run directory; returns the outcomes (as
        :func:`canbrake.run.run_in_process` does: status, message, wall_time_s per point)."""
        import warnings

        t0 = time.time()
        with warnings.catch_warnings(), np.errstate(all="ignore"):
            warnings.simplefilter("ignore", RuntimeWarning)
            for k in range(self.n_ticks):
                if not self.alive.any():
                    break
                self._tick(k)  # every point is closed by its last tick (_advance) or its divergence
        wall = (time.time() - t0) / self.P
        return [{"status": "ok", "message": "", "wall_time_s": wall} for _ in self.points]

    def _measurements(self) -> dict[str, np.ndarray]:
        """Every point's plant measurements, arrays (P, n) / (P, n - 1) (NaN rows: ended points)."""
        st = self.stack
        if st is not None:  # what CoupledPlant.measurements gives, for every point at once
            return {"position_m": st.position_m, "speed_mps": st.speed_mps, "accel_mps2": st.accel_mps2,
                    "applied_brake_n": st.applied_force_n, "deflection_m": st.deflection_m,
                    "coupler_force_n": st.coupler_force_n, **st.equipment_measurements()}
        mms = [p.plant.model.measurements() if a else None for p, a in zip(self.points, self.alive)]
        first = next(mm for mm in mms if mm is not None)
        return {nm: np.stack([np.full(np.shape(v), np.nan) if mm is None else np.asarray(mm[nm], dtype=float)
                              for mm in mms]) for nm, v in first.items()}

    def _tick(self, k: int) -> None:
        dt, m, P = self.dt, self.n_ecus, self.P
        t = k * dt
        pts = self.points
        # phase 0 (plant): measurements and reference, as the ECUs decode them
        meas = self._measurements()
        refs = np.array([p.plant.reference(t) if a else (0.0, 0.0) for p, a in zip(pts, self.alive)], dtype=float)
        v_ref, a_ref = self.q_ref_v(refs[:, 0]), self.q_ref_a(refs[:, 1])
        sensors: dict[str, np.ndarray] = {}
        for sig, slots, q in self.sensor_g:
            if sig not in sensors:
                sensors[sig] = np.full((P, m), np.nan)
            sensors[sig][:, slots] = q(meas[sig][:, self.veh[slots]])
        # phase 1: STATE frames (sensor values as measured, else the controller's broadcast of tick k-1)
        h = k % self.H
        for sig, slots, q in self.state_g:
            v = sensors[sig][:, slots] if sig in sensors else self.bcast[sig][:, slots]
            self.state_hist[sig][h][:, slots] = q(v)
        self._state_in(2 * k, k)
        # phase 2: every ECU computes
        cmds = {sig: np.full((P, m), np.nan) for sig in self.cmd_sigs}
        self._compute(k, sensors, v_ref, a_ref, cmds)
        for sig, slots, q in self.cmd_g:
            self.cmd_hist[sig][h][:, slots] = q(cmds[sig][:, slots])
        self._cmd_in(2 * k, k)      # command frames released by t_k + c·T (sent in earlier ticks)
        self._cmd_in(2 * k + 1, k)  # ... and by the end of the period
        self._state_in(2 * k + 1, k)  # STATE frames released after the receivers computed
        self._advance(k, meas, refs)

    def _compute(self, k: int, sensors: dict[str, np.ndarray], v_ref: np.ndarray, a_ref: np.ndarray,
                 cmds: dict[str, np.ndarray]) -> None:
        """Phase 2 of every ECU of every point: the Observation the ECU node builds (peer values
        with its own sensors in its own entry, ages in s, inf if never received), the controller
        step (the slot's batch form for every point at once, else each point's own controller)."""
        from canbrake.control.base import Observation

        m, t = self.n_ecus, k * self.dt
        diag = np.arange(m)
        peers = {}
        for nm in self.peer_names:
            arr = self.peer[nm].copy()
            if nm in sensors:
                arr[:, diag, diag] = sensors[nm]
            peers[nm] = arr
        origin = self.origin.copy()
        origin[:, diag, diag] = k
        age = np.where(np.isnan(peers["speed_mps"]) & (origin < 0), np.inf, (k - origin) * self.dt)
        fresh = ((origin == k) & self.listen[None]).sum(axis=2) + 1
        finite = np.isfinite(age)
        max_age = np.where(finite.any(axis=2), np.where(finite, age, -np.inf).max(axis=2), np.inf)
        live = self.alive
        self.peer_missing[live] += (self.n_listened + 1 - fresh)[live]
        nan = math.nan
        P = self.P
        for slots, grp in self.slot_groups:
            S = len(slots)
            N = P * S
            obs = Observation(tick=k, time_s=t, speed_mps=sensors["speed_mps"][:, slots].reshape(N),
                              position_m=sensors["position_m"][:, slots].reshape(N),
                              ref_speed_mps=np.repeat(v_ref, S), ref_decel_mps2=np.repeat(a_ref, S),
                              peer_speed_mps=peers["speed_mps"][:, slots].reshape(N, m),
                              peer_position_m=peers["position_m"][:, slots].reshape(N, m),
                              peer_age_s=age[:, slots].reshape(N, m), deflection_front_m=None,
                              deflection_rear_m=None, ref_position_m=nan, sensors={}, peer_signals={})
            res = grp.step(obs)
            force = np.broadcast_to(res.brake_force_n, (N,)).reshape(P, S)
            for sig in cmds:
                cmds[sig][:, slots] = force if sig == "brake_force_n" else nan
            diag = [np.broadcast_to(res.diagnostics.get(name, nan), (N,)).reshape(P, S)
                    for name in grp.diagnostic_names]
            for si, s in enumerate(slots.tolist()):
                rows = self.ecu_rows[s][k]
                rows[:, 1] = force[:, si]
                for c, d in enumerate(diag):
                    rows[:, 2 + c] = d[:, si]
        for s, e in enumerate(self.ecus):
            rows = self.ecu_rows[s][k]
            rows[:, 0] = k
            rows[:, -2] = max_age[:, s]
            rows[:, -1] = fresh[:, s]
            if s in self.grouped:
                continue
            bc = self.batch_ctrl[s]
            if bc is not None:
                sens = {nm: sensors[nm][:, s] for nm in e.sensors}
                obs = Observation(tick=k, time_s=t, speed_mps=sens["speed_mps"], position_m=sens["position_m"],
                                  ref_speed_mps=v_ref, ref_decel_mps2=a_ref,
                                  peer_speed_mps=peers["speed_mps"][:, s], peer_position_m=peers["position_m"][:, s],
                                  peer_age_s=age[:, s], deflection_front_m=None, deflection_rear_m=None,
                                  ref_position_m=nan, sensors=sens,
                                  peer_signals={nm: arr[:, s] for nm, arr in peers.items()})
                res = bc.step_batch(obs)
                force = np.broadcast_to(res.brake_force_n, (self.P,))
                for sig in cmds:
                    val = force if sig == "brake_force_n" else res.commands.get(sig, nan)
                    cmds[sig][:, s] = val
                for sig, val in res.broadcast.items():
                    if sig in self.bcast:
                        self.bcast[sig][:, s] = val
                rows[:, 1] = force
                for c, name in enumerate(bc.diagnostic_names):
                    rows[:, 2 + c] = res.diagnostics.get(name, nan)
            else:
                sv = {nm: sensors[nm][:, s].tolist() for nm in e.sensors}
                vr, ar = v_ref.tolist(), a_ref.tolist()
                for i in np.flatnonzero(live).tolist():
                    p = self.points[i]
                    sens = {nm: sv[nm][i] for nm in e.sensors}
                    obs = Observation(tick=k, time_s=t, speed_mps=sens.get("speed_mps", nan),
                                      position_m=sens.get("position_m", nan), ref_speed_mps=vr[i],
                                      ref_decel_mps2=ar[i], peer_speed_mps=peers["speed_mps"][i, s],
                                      peer_position_m=peers["position_m"][i, s], peer_age_s=age[i, s],
                                      deflection_front_m=None, deflection_rear_m=None, ref_position_m=nan,
                                      sensors=sens, peer_signals={nm: arr[i, s] for nm, arr in peers.items()})
                    ctrl = p.ctrls[s]
                    res = ctrl.step(obs)
                    if res.commands:
                        values = {"brake_force_n": res.brake_force_n, **res.commands}
                        for sig in cmds:
                            cmds[sig][i, s] = float(values.get(sig, nan))
                    else:
                        cmds["brake_force_n"][i, s] = float(res.brake_force_n)
                    for sig, val in res.broadcast.items():
                        if sig in self.bcast:
                            self.bcast[sig][i, s] = val
                    rows[i, 1] = res.brake_force_n
                    d = res.diagnostics
                    rows[i, 2:2 + len(ctrl.diagnostic_names)] = [d.get(nm, np.nan) for nm in ctrl.diagnostic_names]
        self.n_ecu_rows[live] += 1

    # ------------------------------------------------------------------ plant
    def _record(self, k: int, meas: dict[str, np.ndarray], refs: np.ndarray, final: bool = False,
                which: np.ndarray | None = None) -> None:
        """One signals.csv row for every point in ``which`` (default: those running), in the
        layout of PlantNode.columns / _record; ``meas``, ``refs``: this tick's measurements and
        reference (v*, a*) per point."""
        which = self.alive if which is None else which
        r = int(self.n_rows[which].max()) if which.any() else 0
        n = self.n
        row = np.full((self.P, len(self.cols)), np.nan)
        row[:, 0], row[:, 1], row[:, 2], row[:, 3] = k, k * self.dt, refs[:, 0], refs[:, 1]
        per_car = row[:, 4:4 + 5 * n]
        per_car[:, 0::5] = meas["position_m"]
        per_car[:, 1::5] = meas["speed_mps"]
        per_car[:, 2::5] = meas["accel_mps2"]
        per_car[:, 3::5] = np.nan if final else self.hold["brake_force_n"]
        per_car[:, 4::5] = meas["applied_brake_n"]
        cpl = row[:, 4 + 5 * n:4 + 5 * n + 2 * (n - 1)]
        cpl[:, 0::2] = meas["deflection_m"]
        cpl[:, 1::2] = meas["coupler_force_n"]
        col = 4 + 5 * n + 2 * (n - 1)
        for name in self.command_names:
            if name != "brake_force_n":
                for e in self.ecus:
                    if name in e.commands:
                        row[:, col] = np.nan if final else self.hold[name][:, e.vehicle - 1]
                        col += 1
        for name in self.extra_meas:
            row[:, col:col + n] = meas[name]
            col += n
        self.rows[r][which] = row[which]
        self.n_rows[which] = r + 1

    def _advance(self, k: int, meas: dict[str, np.ndarray], refs: np.ndarray) -> None:
        """The plants' end of tick k (PlantNode._advance without frames), for every point running."""
        live = self.alive.copy()
        self.missed[live] += ~self.fresh[live]
        if k % self.trace_every == 0:
            self._record(k, meas, refs)
        st = self.stack
        if st is not None:
            f = self.hold["brake_force_n"]  # as CoupledPlant.step takes the commands
            wsp = self.hold.get("wsp_release")
            if wsp is None:
                st.step(self.dt, np.where(np.isnan(f), 0.0, f))
            else:
                st.step(self.dt, np.where(np.isnan(f), 0.0, f), wsp_release=wsp)
            gone = st.diverged_rows & live
            for i in np.flatnonzero(gone).tolist():
                self._diverged(i, k, st.diverged_text(float(st.diverged_dl_m[i])))
        else:
            for i in np.flatnonzero(live).tolist():
                p = self.points[i]
                applied = {c: a[i].copy() for c, a in self.hold.items()}
                try:
                    p.plant.model.step(self.dt, applied)
                except FloatingPointError as e:  # diverged: the run's result (PlantNode does the same)
                    self._diverged(i, k, str(e))
        self.k_plant[self.alive] = k + 1
        self.fresh[:] = False
        if k + 1 >= self.n_ticks:
            done = self.alive.copy()
            if done.any():
                self._record(k + 1, self._measurements(),
                             np.array([p.plant.reference((k + 1) * self.dt) for p in self.points], dtype=float),
                             final=True, which=done)
                for i in np.flatnonzero(done).tolist():
                    self.points[i].plant.stats.status = "ok"
                    self._close(i)

    def _diverged(self, i: int, k: int, message: str) -> None:
        stats = self.points[i].plant.stats
        stats.status = "diverged"
        stats.extra["diverged_at_s"] = k * self.dt
        stats.extra["message"] = message
        self.k_plant[i] = k
        self._close(i)

    def _close(self, i: int) -> None:
        """Write the run directory of point ``i``, which has ended (signals.csv, ECU traces,
        statistics)."""
        import json

        self.alive[i] = False
        p = self.points[i]
        plant = p.plant
        plant.finished = True
        plant.k = int(self.k_plant[i])
        plant.stats.ticks = plant.k
        plant.stats.commands_received = int(self.received[i])
        plant.stats.commands_missed = int(self.missed[i].sum())
        plant.stats.commands_missed_per_car = [int(x) for x in self.missed[i]]
        if self.rejected[i]:  # as many guard.reject("counter") calls
            plant.guard.rejected["counter"] += int(self.rejected[i])
            plant.guard.last_reason = "counter"
        rd = p.run_dir
        if rd is None:
            return
        _write_csv(rd / "signals.csv", self.cols, self.rows[:self.n_rows[i], i])
        for s, e in enumerate(self.ecus):
            names = p.ctrls[s].diagnostic_names
            cols = [0, 1, *range(2, 2 + len(names)), -2, -1]
            _write_csv(rd / f"ecu_c{e.vehicle}.csv", ["tick", "brake_cmd_n", *names, "max_peer_age_s", "peers_fresh"],
                       self.ecu_rows[s][:self.n_ecu_rows[i], i][:, cols], last_int=True)
            stats = {"ticks": int(self.n_ecu_rows[i]), "peer_frames": int(self.peer_frames[i, s]),
                     "peer_corrupted": 0, "peer_stale_or_duplicate": int(self.peer_stale[i, s]),
                     "peer_missing": int(self.peer_missing[i, s]), "deadline_misses": 0, "status": "ok",
                     "engine": "batch"}
            (rd / f"ecu_c{e.vehicle}_stats.json").write_text(json.dumps(stats, indent=1))
        plant.close(plant.stats.status)  # plant_stats.json (its trace was never opened)


def _ctrl_key(scn: Scenario, slot: int) -> tuple:
    """What makes ECU ``slot``'s controller (0-based): its spec and its vehicle's mass."""
    pl = scn.placement()[slot]
    return (pl.controller.model_dump_json(), float(scn.vehicle_masses_kg()[pl.vehicle - 1]))


def _write_csv(path: Path, header: list[str], rows: np.ndarray, last_int: bool = False) -> None:
    """Rows written as canbrake.nodes.base.CsvTrace writes them: the tick (first column; with
    ``last_int`` also the last) as an integer, floats with 9 significant digits."""
    import csv
    import io

    from canbrake._batch import csv_bytes

    head = io.StringIO(newline="")
    csv.writer(head).writerow(header)
    with open(path, "wb") as f:
        f.write(head.getvalue().encode())
        f.write(csv_bytes(np.ascontiguousarray(rows, dtype=float), last_int))


def run_batch(scns: Sequence[Scenario], run_dirs: Sequence[str | Path | None]) -> list[dict[str, Any]]:
    """Run supported points (one :func:`batch_groups` group) and write each run directory with its
    summary.json (:func:`canbrake.analysis.summary.finalize_run`, as ``run_scenario`` does).
    Returns the summaries in order."""
    from canbrake.analysis.summary import finalize_run
    from canbrake.run import choose_bus

    eng = BatchEngine(scns, run_dirs)
    outcomes = eng.run()
    out = []
    for p, oc in zip(eng.points, outcomes):
        if p.run_dir is None:
            out.append({"status": oc["status"]})
            continue
        out.append(finalize_run(p.scn, p.run_dir, choose_bus(p.scn, "inprocess").describe(), oc, plots=False))
    return out
