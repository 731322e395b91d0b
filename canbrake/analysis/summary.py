"""Turn a finished (or failed) run directory into signals.csv with ECU columns, summary.json and plots."""
from __future__ import annotations

import csv
import json
import os
from pathlib import Path
from typing import Any

import numpy as np

from canbrake.analysis.metrics import Trace, compute_metrics
from canbrake.scenario import Scenario


def read_signals(path: str | Path) -> dict[str, np.ndarray]:
    """signals.csv as a dict of float columns."""
    with open(path, newline="") as f:
        rows = list(csv.reader(f))
    if len(rows) < 2:
        return {name: np.zeros(0) for name in (rows[0] if rows else [])}
    header, body = rows[0], rows[1:]
    arr = np.array([[float(x) if x not in ("", "nan") else np.nan for x in r] for r in body], dtype=float)
    return {name: arr[:, j] for j, name in enumerate(header)}


def trace_from_columns(cols: dict[str, np.ndarray], n: int) -> Trace:
    """Build a :class:`Trace` from signals.csv columns."""
    def stack(prefix: str, count: int) -> np.ndarray:
        if count == 0:
            return np.zeros((len(cols["t_s"]), 0))
        return np.column_stack([cols[f"{prefix}{c}"] for c in range(1, count + 1)])

    obs = None
    if "observer_accel_mps2_c1" in cols:
        obs = stack("observer_accel_mps2_c", n)
    return Trace(t_s=cols["t_s"], ref_speed_mps=cols["ref_speed_mps"], position_m=stack("position_m_c", n),
                 speed_mps=stack("speed_mps_c", n), accel_mps2=stack("accel_mps2_c", n),
                 brake_cmd_n=stack("brake_cmd_n_c", n), brake_applied_n=stack("brake_applied_n_c", n),
                 deflection_m=stack("deflection_m_k", n - 1), coupler_force_n=stack("coupler_force_n_k", n - 1),
                 observer_accel_mps2=obs)


def merge_ecu_columns(run_dir: Path, n: int) -> None:
    """Add each ECU's diagnostics (e.g. observer estimate) to signals.csv, joined on tick.

    Written to a temporary file and renamed, so signals.csv is never left half-written.
    """
    sig = run_dir / "signals.csv"
    if not sig.exists():
        return
    with open(sig, newline="") as f:
        rows = list(csv.reader(f))
    if not rows:
        return
    header, body = rows[0], rows[1:]
    extra_header: list[str] = []
    extra: dict[int, list[str]] = {}
    widths: list[int] = []
    for c in range(1, n + 1):
        p = run_dir / f"ecu_c{c}.csv"
        if not p.exists():
            continue
        with open(p, newline="") as f:
            erows = list(csv.reader(f))
        if not erows:
            continue
        names = [h for h in erows[0] if h != "tick"]
        # an ECU column named like a plant column (brake_cmd_n: what the ECU sent vs what the
        # plant used) is prefixed ecu_
        extra_header += [f"ecu_{h}_c{c}" if f"{h}_c{c}" in header else f"{h}_c{c}" for h in names]
        col = erows[0].index("tick")
        start = sum(widths)
        widths.append(len(names))
        for r in erows[1:]:
            k = int(r[col])
            vals = [v for j, v in enumerate(r) if j != col]
            extra.setdefault(k, []).extend([""] * (start - len(extra.get(k, []))))
            extra[k][start:start + len(names)] = vals
    if not extra_header:
        return
    total = sum(widths)
    tmp = sig.with_suffix(".csv.tmp")
    with open(tmp, "w", newline="") as f:
        w = csv.writer(f)
        w.writerow(header + extra_header)
        for r in body:
            e = extra.get(int(float(r[0])), [])
            w.writerow(r + e + [""] * (total - len(e)))
    os.replace(tmp, sig)


def merge_tick_file(run_dir: Path, name: str) -> None:
    """Append the columns of ``run_dir/name`` (a CSV with a ``tick`` column, e.g. the recorder's
    can_errors.csv) to signals.csv, joined on tick; atomic like :func:`merge_ecu_columns`."""
    sig, extra_p = run_dir / "signals.csv", run_dir / name
    if not sig.exists() or not extra_p.exists():
        return
    with open(sig, newline="") as f:
        rows = list(csv.reader(f))
    with open(extra_p, newline="") as f:
        erows = list(csv.reader(f))
    if not rows or not erows:
        return
    col = erows[0].index("tick")
    names = [h for j, h in enumerate(erows[0]) if j != col]
    if set(names) & set(rows[0]):
        return  # already merged
    by_tick = {int(r[col]): [v for j, v in enumerate(r) if j != col] for r in erows[1:]}
    tmp = sig.with_suffix(".csv.tmp")
    with open(tmp, "w", newline="") as f:
        w = csv.writer(f)
        w.writerow(rows[0] + names)
        for r in rows[1:]:
            w.writerow(r + by_tick.get(int(float(r[0])), [""] * len(names)))
    os.replace(tmp, sig)


def _load_json(p: Path) -> dict[str, Any]:
    try:
        return json.loads(p.read_text())
    except (OSError, ValueError):
        return {}


def finalize_run(scn: Scenario, run_dir: Path, bus: str, outcome: dict[str, Any], *, plots: bool = True) -> dict[str, Any]:
    """Write summary.json (and plots) for ``run_dir``; returns the summary."""
    n = scn.n_cars
    merge_ecu_columns(run_dir, n)
    merge_tick_file(run_dir, "can_errors.csv")
    plant = _load_json(run_dir / "plant_stats.json")
    busst = _load_json(run_dir / "bus_stats.json")
    ecus = [_load_json(run_dir / f"ecu_c{c}_stats.json") for c in range(1, n + 1)]
    if outcome.get("status") == "ok" and plant.get("status") == "diverged":
        outcome = {**outcome, "status": "diverged",
                   "message": f"the closed loop diverged at t = {plant['extra'].get('diverged_at_s', 0):.3f} s: "
                              f"{plant['extra'].get('message', '')}"}
    summary: dict[str, Any] = {
        "scenario": scn.name,
        "profile": scn.profile,
        "seed": scn.seed,
        "bus": bus,
        "mode": scn.mode,
        "controller": scn.controller.name,
        "n_cars": n,
        "duration_s": scn.duration_s,
        "control_period_s": scn.control_period_s,
        "status": outcome.get("status", "failed"),
        "message": outcome.get("message", ""),
        "wall_time_s": outcome.get("wall_time_s"),
        "ticks": plant.get("ticks", 0),
    }
    if summary["ticks"] and plant.get("wall_time_s"):
        # simulated seconds per wall second of the plant's loop (start-up of the processes excluded)
        summary["real_time_factor"] = summary["ticks"] * scn.control_period_s / plant["wall_time_s"]
    sig = run_dir / "signals.csv"
    if sig.exists():
        cols = read_signals(sig)
        if cols.get("t_s") is not None and len(cols["t_s"]) > 1:
            tr = trace_from_columns(cols, n)
            tr.mass_kg = scn.vehicle_masses_kg()
            summary["metrics"] = compute_metrics(tr)
            if plots:
                from canbrake.analysis.plots import plot_meta, plot_run

                try:
                    summary["plots"] = plot_run(tr, run_dir / "plots", title=scn.name, meta=plot_meta(scn, bus))
                    from canbrake.analysis.plots import plot_bus

                    summary["plots"] += plot_bus(run_dir, run_dir / "plots", title=scn.name)
                except Exception as e:  # noqa: BLE001 - a plotting problem must not lose the run's results
                    summary["plots_error"] = str(e)
    summary["frames"] = {
        "on_bus": busst.get("frames"),
        "by_kind": busst.get("frames_by_kind"),
        "commands_received": plant.get("commands_received"),
        "commands_missed": plant.get("commands_missed"),
        "commands_corrupted": plant.get("commands_corrupted"),
        "peer_frames_received": sum(e.get("peer_frames", 0) for e in ecus),
        "peer_frames_corrupted": sum(e.get("peer_corrupted", 0) for e in ecus),
        "peer_frames_stale_or_duplicate": sum(e.get("peer_stale_or_duplicate", 0) for e in ecus),
        "peer_values_missing": sum(e.get("peer_missing", 0) for e in ecus),
    }
    summary["bus_load"] = {k: busst.get(k) for k in ("bitrate_bps", "bus_load_mean", "bus_load_peak",
                                                      "bus_load_peak_window", "bus_load_window_s",
                                                      "error_frames_per_s", "frames_per_s_by_sender",
                                                      "latency_p50_s", "latency_p99_s", "latency_max_s",
                                                      "latency_model")}
    lat: dict[str, Any] = {}
    for e in ecus:
        for kind, st in (e.get("bus_latency") or {}).items():
            agg = lat.setdefault(kind, {"n": 0, "starved": 0, "late_frames": 0, "p99_s": 0.0, "max_s": 0.0})
            agg["n"] += st["n"]
            agg["starved"] += st["starved"]
            agg["late_frames"] += st["late_frames"]
            agg["p99_s"] = max(agg["p99_s"], st["p99_s"] or 0.0)
            agg["max_s"] = max(agg["max_s"], st["max_s"] or 0.0)
    if lat:
        summary["bus_latency_in_loop"] = {"model": scn.bus.timing, **lat}
    if busst.get("errors"):
        summary["can_errors"] = busst["errors"]
    if scn.safety.command_timeout_s is not None:
        summary["failsafe"] = {"command_timeout_s": scn.safety.command_timeout_s,
                               "activations": plant.get("failsafe_activations", 0),
                               "car_ticks": plant.get("failsafe_ticks", 0),
                               "first_activation_s": plant.get("failsafe_first_s", {})}
    summary["safety"] = safety_counters(scn, plant, ecus, busst)
    summary["deadline_misses"] = {"plant": plant.get("deadline_misses", 0),
                                  "ecus": sum(e.get("deadline_misses", 0) for e in ecus),
                                  "late_periods": plant.get("late_periods", 0),
                                  "max_lateness_s": plant.get("max_lateness_s", 0.0)}
    (run_dir / "summary.json").write_text(json.dumps(summary, indent=1))
    return summary


def safety_counters(scn: Scenario, plant: dict[str, Any], ecus: list[dict[str, Any]],
                    busst: dict[str, Any]) -> dict[str, Any]:
    """Detections and reactions of a run (``summary.json`` ``safety``): frames rejected by reason
    (:mod:`canbrake.bus.guard`) in total and per node, frames of unknown senders by identifier,
    fallbacks entered (ECU: peers lost; brake unit: fail-safe) and time in fallback, and a verdict:
    ``clean`` (nothing rejected, no fallback), ``attack or fault detected`` (frames rejected,
    braking as commanded), ``detected, fail-safe engaged`` (a brake unit reacted)."""
    from canbrake.bus.guard import REASONS

    nodes = {"plant": plant.get("guard") or {}, "recorder": busst.get("guard") or {}}
    for c, e in enumerate(ecus, start=1):
        nodes[f"ecu{c}"] = e.get("guard") or {}
    total = {r: sum((g.get("rejected") or {}).get(r, 0) for g in nodes.values()) for r in REASONS}
    unknown: dict[str, int] = {}
    for g in nodes.values():
        for k, v in (g.get("unknown_ids") or {}).items():
            unknown[k] = unknown.get(k, 0) + v
    dt = scn.control_period_s
    fb_ticks = sum(e.get("fallback_ticks", 0) for e in ecus)
    fs_ticks = plant.get("failsafe_ticks", 0)
    fallbacks = {"ecu_peer_loss_entries": sum(e.get("fallback_entries", 0) for e in ecus),
                 "ecu_peer_loss_time_s": round(fb_ticks * dt, 9),
                 "failsafe_entries": plant.get("failsafe_activations", 0),
                 "failsafe_time_s": round(fs_ticks * dt, 9)}
    if fallbacks["failsafe_entries"]:
        verdict = "detected, fail-safe engaged"
    elif sum(total.values()) or fallbacks["ecu_peer_loss_entries"]:
        verdict = "attack or fault detected"
    else:
        verdict = "clean"
    flood = {"frames_on_unknown_ids": busst.get("frames_by_unknown_id") or {},
             "rx_frames_lost": {n: g.get("rx_frames_lost", 0) for n, g in nodes.items() if g.get("rx_frames_lost")}}
    # unauthenticated END frames before the last tick: the plant's own after a divergence (one per
    # listening node) or forged ones
    end_ignored = sum(g.get("end_ignored", 0) for g in nodes.values())
    own_end = len(nodes) - 1 if plant.get("status") == "diverged" else 0
    if verdict == "clean" and (flood["frames_on_unknown_ids"] or flood["rx_frames_lost"] or end_ignored > own_end):
        verdict = "attack or fault detected"
    return {"authenticated": scn.security is not None, "verdict": verdict, "rejected": total, "flood": flood,
            "end_frames_ignored": end_ignored,
            "rejected_by_node": {n: g.get("rejected", {}) for n, g in nodes.items() if sum((g.get("rejected") or {}).values())},
            "unknown_senders": unknown, "fallbacks": fallbacks}
