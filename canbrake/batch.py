"""The batch engine: many lockstep runs (sweep points) of one scenario family at once, in one process.

What it reuses, unchanged, per point: the controllers (:func:`canbrake.build.build_controller`,
so the same ``chen2023`` / ``chen2023_compensated`` / ``pi`` objects, brake functions included),
the plant (:func:`canbrake.build.build_plant_model`) held by a real
:class:`~canbrake.nodes.plant.PlantNode` (its command hold, fail-safe-free applied commands,
column layout and statistics), the impairment chains (:func:`canbrake.build.build_send_path`:
the same seeded :class:`~canbrake.bus.impair.SendPath` objects, so every loss draw and delay is
the one the node engine makes) and the summary (:func:`canbrake.analysis.summary.finalize_run`).

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

Where it falls back (:func:`unsupported`): anything it does not reproduce exactly — another train
family than ``coupled``, controllers other than the three above, realtime mode, the bus timing
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
from dataclasses import dataclass, field
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

    train = getattr(scn.train, "model", "coupled")
    if train != "coupled":
        return f"not for {train} trains"
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
    """Points that share this key run in one batch: same cars, ECUs, signals and number of ticks."""
    from canbrake.build import bus_layout

    lay = bus_layout(scn)
    return (scn.n_cars, scn.n_ticks, scn.control_period_s, scn.ecu.lockstep_deadline, scn.plant.trace_every,
            tuple((m.kind, m.ecu, m.frame_id, tuple((sig, sp.name, sp.scale, sp.offset, sp.length, sp.signed)
                                                    for sig, sp in m.signals)) for m in lay.messages),
            tuple((e.sensors, e.commands, e.broadcast, e.listens, e.listeners) for e in lay.ecus))


def batch_groups(scns: Sequence[Scenario]) -> list[list[int]]:
    """Indices of ``scns`` grouped into batches that can run together (same layout and length)."""
    groups: dict[tuple, list[int]] = {}
    for i, s in enumerate(scns):
        groups.setdefault(batch_key(s), []).append(i)
    return list(groups.values())


@dataclass
class _Point:
    """One sweep point: its scenario, plant node, controllers, send paths and receiver state."""

    scn: Scenario
    run_dir: Path | None
    plant: Any                                  # canbrake.nodes.plant.PlantNode (holds the model)
    ctrls: list[Any]
    paths: list[Any] | None                     # per ECU: canbrake.bus.impair.SendPath, or None (no impairment)
    reference: Any
    rows: np.ndarray                            # signals.csv rows
    n_rows: int = 0
    ecu_rows: list[list[list[Any]]] = field(default_factory=list)  # per ECU: its trace rows (ecu_c<v>.csv)
    n_ecu_rows: int = 0
    alive: bool = True
    broadcast: list[dict[str, float]] = field(default_factory=list)
    plant_origin: np.ndarray | None = None      # per ECU: newest accepted command tick
    late: list[tuple[int, int, Any]] = field(default_factory=list)  # (sender, origin, values) after phase 2
    peer_frames: np.ndarray | None = None
    peer_stale: np.ndarray | None = None
    peer_missing: np.ndarray | None = None


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
        self.listeners = [np.flatnonzero(self.listen[:, j]) for j in range(m)]
        self.peer_names = sorted({sig for _, sig, _ in self.state_q} | {"speed_mps", "position_m"})
        self.state_ids = {mm.frame_id for mm in lay.messages if mm.kind == "state"}
        self.n_listened = self.listen.sum(axis=1)
        self.state_id = [(lay.ids("state", e.index) or [0])[0] for e in self.ecus]
        self.cmd_id = [lay.ids("cmd", e.index)[0] for e in self.ecus]
        self.names = [e.name for e in self.ecus]
        self.points: list[_Point] = []
        for scn, rd in zip(scns, run_dirs):
            run_dir = prepare_run_dir(scn, rd) if rd is not None else None
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
            n_rows = self.n_ticks // self.trace_every + 2
            ctrls = [build_controller(scn, i) for i in range(1, m + 1)]
            pt = _Point(scn, run_dir, plant, ctrls, paths,
                        reference_fn(scn), np.full((n_rows, len(plant.columns())), np.nan),
                        ecu_rows=[[] for _ in ctrls],
                        broadcast=[{} for _ in range(m)],
                        plant_origin=np.full(m, -1, dtype=np.int64),
                        peer_frames=np.zeros(m, dtype=np.int64), peer_stale=np.zeros(m, dtype=np.int64),
                        peer_missing=np.zeros(m, dtype=np.int64))
            self.points.append(pt)
        P = len(self.points)
        # what every receiver holds of its peers (the ECU node's peer_signals / peer_origin)
        self.peer = {nm: np.full((P, m, m), np.nan) for nm in self.peer_names}
        self.origin = np.full((P, m, m), -(10 ** 12), dtype=np.int64)
        self.cols = self.points[0].plant.columns()
        self._nan_n = np.full(self.points[0].plant.n, np.nan)

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

    # ------------------------------------------------------------------ run
    def run(self) -> list[dict[str, Any]]:
        """Run every point to its end; write each run directory; returns the outcomes (as
        :func:`canbrake.run.run_in_process` does: status, message, wall_time_s per point)."""
        import warnings

        t0 = time.time()
        with warnings.catch_warnings(), np.errstate(all="ignore"):
            warnings.simplefilter("ignore", RuntimeWarning)
            for k in range(self.n_ticks):
                if not any(p.alive for p in self.points):
                    break
                self._tick(k)
            for p in self.points:
                if p.alive:
                    self._finish(p)
        wall = (time.time() - t0) / len(self.points)
        return [{"status": "ok", "message": "", "wall_time_s": wall} for _ in self.points]

    def _tick(self, k: int) -> None:
        from canbrake.bus.impair import TxFrame

        dt, m = self.dt, self.n_ecus
        t = k * dt
        pts = self.points
        P = len(pts)
        # phase 0 (plant): measurements and reference, as the ECUs decode them
        meas = [p.plant.model.measurements() if p.alive else None for p in pts]
        refs = [p.reference(t) if p.alive else (0.0, 0.0) for p in pts]
        v_ref = self.q_ref_v(np.array([r[0] for r in refs]))
        a_ref = self.q_ref_a(np.array([r[1] for r in refs]))
        sensors: dict[str, np.ndarray] = {}
        raw: dict[str, np.ndarray] = {}
        for sig, slots, q in self.sensor_g:
            if sig not in raw:
                raw[sig] = np.stack([mm[sig] if mm is not None else self._nan_n for mm in meas])[:, self.veh]
                sensors[sig] = np.full((P, m), np.nan)
            sensors[sig][:, slots] = q(raw[sig][:, slots])
        # phase 1: STATE frames (sensor values as measured, else the controller's broadcast of tick k-1)
        state: dict[str, np.ndarray] = {}
        for sig, slots, q in self.state_g:
            if sig in sensors:
                v = sensors[sig][:, slots]
            else:
                v = np.array([[p.broadcast[s].get(sig, math.nan) for s in slots] for p in pts], dtype=float)
            state.setdefault(sig, np.full((P, m), np.nan))[:, slots] = q(v)
        horizon1 = t + self.c * dt
        plain = [i for i, p in enumerate(pts) if p.alive and p.paths is None]
        if plain:
            idx = np.asarray(plain)
            for sig, arr in state.items():
                blk = self.peer[sig][idx]
                self.peer[sig][idx] = np.where(self.listen[None, :, :], arr[idx][:, None, :], blk)
            org = self.origin[idx]
            self.origin[idx] = np.where(self.listen[None, :, :], k, org)
            for i in plain:
                pts[i].peer_frames += self.n_listened
        for i, p in enumerate(pts):
            if not p.alive or p.paths is None:
                continue
            p.late = []
            for j in range(m):
                path = p.paths[j]
                vals = {sig: float(state[sig][i, j]) for sig in state} if self.has_state[j] else None
                if path is None:
                    if vals is not None:
                        self._state_in(i, j, k, vals, k)
                    continue
                if vals is not None:
                    path.submit(TxFrame(self.state_id[j], False, b"", 8, self.names[j], t, t, origin=(k, vals)))
                # release(t) then release(horizon1), as the ECU node does, hands out the same frames in
                # the same order as release(horizon1) alone: frames by (release time, submission)
                for f in path.release(horizon1):
                    self._deliver(i, j, f, k, phase2=False)
        # phase 2: every ECU computes
        cmds: dict[str, np.ndarray] = {sig: np.full((P, m), np.nan) for _, sig, _ in self.cmd_q}
        views = self._views(k, sensors)
        for i, p in enumerate(pts):
            if p.alive:
                self._compute(i, p, k, sensors, float(v_ref[i]), float(a_ref[i]), cmds, views)
        qcmd: dict[str, np.ndarray] = {}
        for sig, slots, q in self.cmd_g:
            qcmd.setdefault(sig, np.full((P, m), np.nan))[:, slots] = q(cmds[sig][:, slots])
        t2, horizon2 = t + self.c * dt, t + dt * (1 - 1e-9)
        for i, p in enumerate(pts):
            if not p.alive:
                continue
            plant = p.plant
            if p.paths is None:  # every command arrives in its tick
                for sig, arr in qcmd.items():
                    plant.commands[sig][self.veh] = arr[i]
                plant._fresh[:] = True
                plant.stats.commands_received += m
                p.plant_origin[:] = k
            else:
                for j in range(m):
                    path = p.paths[j]
                    vals = {sig: float(qcmd[sig][i, j]) for sig in qcmd}
                    if path is None:
                        self._cmd_in(p, j, k, vals, k)
                        continue
                    path.submit(TxFrame(self.cmd_id[j], False, b"", 8, self.names[j], t2, t2, origin=(k, vals)))
                    for f in path.release(horizon2):
                        self._deliver(i, j, f, k, phase2=True)
                for j, origin, vals in p.late:  # state frames released after the receivers computed
                    self._state_in(i, j, origin, vals, k)
            self._advance(p, k, meas[i], refs[i])

    def _deliver(self, i: int, j: int, f: Any, k: int, *, phase2: bool) -> None:
        origin, vals = f.origin
        if f.arbitration_id in self.state_ids:
            if phase2:
                self.points[i].late.append((j, origin, vals))
            else:
                self._state_in(i, j, origin, vals, k)
        else:
            self._cmd_in(self.points[i], j, origin, vals, k)

    def _state_in(self, i: int, j: int, sent: int, vals: dict[str, float], k: int) -> None:
        """ECU j's STATE frame sent at tick ``sent`` reaches its listeners at their tick ``k``."""
        p = self.points[i]
        lag = (k - sent) % COUNTER_MODULO  # the receiver knows only the alive counter
        origin = k - lag
        for r in self.listeners[j]:
            last = int(self.origin[i, r, j])
            if lag > ECU_MAX_LAG or origin <= last:
                p.peer_stale[r] += 1
                continue
            for sig, v in vals.items():
                self.peer[sig][i, r, j] = v
            self.origin[i, r, j] = origin
            p.peer_frames[r] += 1

    def _cmd_in(self, p: _Point, j: int, sent: int, vals: dict[str, float], k: int) -> None:
        """ECU j's command frame sent at tick ``sent`` reaches the brake unit at the plant's tick ``k``."""
        lag = (k - sent) % COUNTER_MODULO
        origin = k - lag
        plant = p.plant
        if lag > PLANT_MAX_LAG or origin <= p.plant_origin[j]:
            plant.guard.reject("counter")
            return
        p.plant_origin[j] = origin
        v = self.veh[j]
        for sig, x in vals.items():
            plant.commands[sig][v] = x
        plant.stats.commands_received += 1
        if origin == k:
            plant._fresh[j] = True

    def _views(self, k: int, sensors: dict[str, np.ndarray]) -> tuple[dict[str, np.ndarray], np.ndarray, np.ndarray,
                                                                        np.ndarray, np.ndarray]:
        """What every ECU of every point knows at phase 2 of tick k, as the ECU node builds it:
        peer values with its own sensors in its own entry, ages (s; inf if never received),
        fresh values (peers of this tick + itself), the oldest finite age. Shapes (P, m, m) / (P, m)."""
        m = self.n_ecus
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
        return peers, age, fresh, max_age, self.n_listened + 1 - fresh

    def _compute(self, i: int, p: _Point, k: int, sensors: dict[str, np.ndarray], v_ref: float,
                 a_ref: float, cmds: dict[str, np.ndarray], views: tuple) -> None:
        """Phase 2 of every ECU of point ``i``: the Observation the ECU node builds, the controller step."""
        from canbrake.control.base import Observation

        peers, age, fresh, max_age, missing = views
        p.peer_missing += missing[i]
        t = k * self.dt
        sp, ps = peers["speed_mps"][i], peers["position_m"][i]
        rows = {nm: arr[i].tolist() for nm, arr in sensors.items()}  # Python floats, as decoded
        max_age_i, fresh_i = max_age[i].tolist(), fresh[i].tolist()
        for s, e in enumerate(self.ecus):
            sens = {nm: rows[nm][s] for nm in e.sensors}
            obs = Observation(tick=k, time_s=t, speed_mps=sens.get("speed_mps", math.nan),
                              position_m=sens.get("position_m", math.nan), ref_speed_mps=v_ref,
                              ref_decel_mps2=a_ref, peer_speed_mps=sp[s], peer_position_m=ps[s],
                              peer_age_s=age[i, s], deflection_front_m=None, deflection_rear_m=None,
                              ref_position_m=math.nan, sensors=sens,
                              peer_signals={nm: arr[i, s] for nm, arr in peers.items()})
            ctrl = p.ctrls[s]
            res = ctrl.step(obs)
            p.broadcast[s] = res.broadcast
            if res.commands:
                values = {"brake_force_n": res.brake_force_n, **res.commands}
                for sig in cmds:
                    cmds[sig][i, s] = float(values.get(sig, math.nan))
            else:
                cmds["brake_force_n"][i, s] = float(res.brake_force_n)
            diag = res.diagnostics
            p.ecu_rows[s].append([k, res.brake_force_n, *[diag.get(n, np.nan) for n in ctrl.diagnostic_names],
                                  max_age_i[s], fresh_i[s]])
        p.n_ecu_rows += 1

    # ------------------------------------------------------------------ plant
    def _record(self, p: _Point, final: bool = False, mm: Any = None, ref: Any = None) -> None:
        """One signals.csv row (the layout of PlantNode.columns / _record); ``mm``, ``ref``: the
        measurements and reference of this tick if already taken."""
        plant = p.plant
        mm = plant.model.measurements() if mm is None else mm
        t = plant.k * self.dt
        v_ref, a_ref = p.reference(t) if ref is None else ref
        n = plant.n
        row = p.rows[p.n_rows]
        row[0], row[1], row[2], row[3] = plant.k, t, v_ref, a_ref
        per_car = row[4:4 + 5 * n]
        per_car[0::5] = mm["position_m"]
        per_car[1::5] = mm["speed_mps"]
        per_car[2::5] = mm["accel_mps2"]
        per_car[3::5] = np.nan if final else plant.cmd_n
        per_car[4::5] = mm["applied_brake_n"]
        cpl = row[4 + 5 * n:4 + 5 * n + 2 * (n - 1)]
        cpl[0::2] = mm["deflection_m"]
        cpl[1::2] = mm["coupler_force_n"]
        col = 4 + 5 * n + 2 * (n - 1)
        for name in plant.command_names:
            if name != "brake_force_n":
                for e in self.ecus:
                    if name in e.commands:
                        row[col] = np.nan if final else float(plant.commands[name][e.vehicle - 1])
                        col += 1
        for name in plant._extra_measurements():
            row[col:col + n] = mm[name]
            col += n
        p.n_rows += 1

    def _advance(self, p: _Point, k: int, mm: Any = None, ref: Any = None) -> None:
        """The plant's end of tick k (PlantNode._advance without frames)."""
        plant = p.plant
        fresh = plant._fresh
        plant.stats.commands_missed += int((~fresh).sum())
        for s in np.flatnonzero(~fresh):
            plant.stats.commands_missed_per_car[s] += 1
        applied = plant._applied_commands()
        if plant.k % plant.trace_every == 0:
            self._record(p, mm=mm, ref=ref)
        try:
            plant.model.step(self.dt, applied)
        except FloatingPointError as e:  # diverged: the run's result (PlantNode does the same)
            plant.finished = True
            plant.stats.status = "diverged"
            plant.stats.extra["diverged_at_s"] = plant.k * self.dt
            plant.stats.extra["message"] = str(e)
            self._close(p)
            return
        plant.k += 1
        plant.stats.ticks = plant.k
        fresh[:] = False
        if plant.k >= plant.n_ticks:
            self._finish(p)

    def _finish(self, p: _Point) -> None:
        self._record(p, final=True)
        p.plant.finished = True
        p.plant.stats.status = "ok"
        self._close(p)

    def _close(self, p: _Point) -> None:
        """Write the run directory of a point that has ended (signals.csv, ECU traces, statistics)."""
        import json

        p.alive = False
        rd = p.run_dir
        if rd is None:
            return
        _write_csv(rd / "signals.csv", self.cols, p.rows[:p.n_rows])
        for s, e in enumerate(self.ecus):
            ctrl = p.ctrls[s]
            header = ["tick", "brake_cmd_n", *ctrl.diagnostic_names, "max_peer_age_s", "peers_fresh"]
            _write_csv(rd / f"ecu_c{e.vehicle}.csv", header, np.array(p.ecu_rows[s], dtype=float).reshape(
                -1, len(header)), last_int=True)
            stats = {"ticks": p.n_ecu_rows, "peer_frames": int(p.peer_frames[s]),
                     "peer_corrupted": 0, "peer_stale_or_duplicate": int(p.peer_stale[s]),
                     "peer_missing": int(p.peer_missing[s]), "deadline_misses": 0, "status": "ok",
                     "engine": "batch"}
            (rd / f"ecu_c{e.vehicle}_stats.json").write_text(json.dumps(stats, indent=1))
        p.plant.close("ok")  # plant_stats.json (its trace was never opened)
        p.ecu_rows = []
        p.rows = p.rows[:0]


def _write_csv(path: Path, header: list[str], rows: np.ndarray, last_int: bool = False) -> None:
    """Rows written as canbrake.nodes.base.CsvTrace writes them: the tick (first column; with
    ``last_int`` also the last) as an integer, floats with 9 significant digits."""
    import csv

    with open(path, "w", newline="") as f:
        csv.writer(f).writerow(header)
        cells = ["%d"] + ["%.9g"] * (len(header) - 1)
        if last_int:
            cells[-1] = "%d"
        fmt = ",".join(cells) + "\r\n"
        f.write("".join([fmt % tuple(r) for r in rows.tolist()]))


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
