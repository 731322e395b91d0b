"""Turn a finished (or failed) run directory into signals.csv with ECU columns, summary.json and plots."""
from __future__ import annotations

import contextlib
import csv
import io
import json
import os
from pathlib import Path
from typing import Any, Callable, Iterator

import numpy as np

from canbrake.analysis.metrics import Trace, compute_metrics
from canbrake.atomic import write_text_atomic
from canbrake.scenario import Scenario


def _complete_rows(path: str | Path) -> tuple[list[str], bytes] | None:
    """(header, body) of a CSV whose every complete data row has the header's width, the body
    cut after its last newline (a writer killed mid-row leaves a partial last line: dropped);
    None when some row is damaged otherwise (the careful row-by-row readers handle those)."""
    data = Path(path).read_bytes()
    nl = data.find(b"\n")
    if nl < 0:
        return None
    header = next(csv.reader([data[:nl].decode()]))
    body = data[nl + 1:data.rfind(b"\n") + 1]
    if body.count(b",") != body.count(b"\n") * (len(header) - 1) or b'"' in body:
        return None  # a short or long row (or quoting) somewhere: row by row
    return header, body


def read_signals(path: str | Path, keep: Callable[[str], bool] | None = None,
                 content: tuple[list[str], bytes] | None = None) -> dict[str, np.ndarray]:
    """signals.csv as a dict of float columns (only those whose name ``keep`` accepts, if given).
    pandas' C parser reads a file of complete rows (exactly the floats Python's ``float`` gives:
    tests/test_run.py); a damaged file is read row by row, dropping rows cut short and stopping at
    the first cell that is not a number. ``content``: the file's (header, rows) as
    :func:`merge_ecu_columns` returns them, complete rows, not read again."""
    import pandas as pd

    ok = content if content is not None else _complete_rows(path)
    if ok is not None:
        header, body = ok
        use = [j for j, name in enumerate(header) if keep is None or keep(name)]
        try:
            df = pd.read_csv(io.BytesIO(body), header=None, names=range(len(header)), usecols=use, dtype=float,
                             keep_default_na=False, na_values=["", "nan"], engine="c")
        except (ValueError, pd.errors.ParserError):
            pass
        else:
            # column by column (a copy each: no 2-D interleave of every column first)
            return {header[j]: df[j].to_numpy(dtype=float, copy=True) for j in use}
    cols = _read_signals_rows(path)
    return cols if keep is None else {name: a for name, a in cols.items() if keep(name)}


def _read_signals_rows(path: str | Path) -> dict[str, np.ndarray]:
    """:func:`read_signals`, row by row (damaged files)."""
    with open(path, newline="") as f:
        rows = list(csv.reader(f))
    if len(rows) < 2:
        return {name: np.zeros(0) for name in (rows[0] if rows else [])}
    header, body = rows[0], rows[1:]
    width = len(header)
    # a row cut short by a killed writer (or a full disk) is dropped, not half-read
    body = [r for r in body if len(r) == width]
    arr = np.full((len(body), width), np.nan)
    for i, r in enumerate(body):
        try:
            arr[i] = [float(x) if x not in ("", "nan") else np.nan for x in r]
        except ValueError:
            arr = arr[:i]
            break
    return {name: arr[:, j] for j, name in enumerate(header)}


def trace_from_columns(cols: dict[str, np.ndarray], n: int) -> Trace:
    """Build a :class:`Trace` from signals.csv columns."""
    rows = len(cols["t_s"])

    def stack(prefix: str, count: int) -> np.ndarray:
        # a column a node never wrote (killed before its first row) is NaN, never a KeyError
        if count == 0:
            return np.zeros((rows, 0))
        return np.column_stack([cols.get(f"{prefix}{c}", np.full(rows, np.nan)) for c in range(1, count + 1)])

    obs = None
    if any(f"observer_accel_mps2_c{c}" in cols for c in range(1, n + 1)):
        obs = stack("observer_accel_mps2_c", n)
    return Trace(t_s=cols["t_s"], ref_speed_mps=cols["ref_speed_mps"], position_m=stack("position_m_c", n),
                 speed_mps=stack("speed_mps_c", n), accel_mps2=stack("accel_mps2_c", n),
                 brake_cmd_n=stack("brake_cmd_n_c", n), brake_applied_n=stack("brake_applied_n_c", n),
                 deflection_m=stack("deflection_m_k", n - 1), coupler_force_n=stack("coupler_force_n_k", n - 1),
                 observer_accel_mps2=obs, ref_position_m=cols.get("ref_position_m"))


def merge_ecu_columns(run_dir: Path, n: int) -> tuple[list[str], bytes] | None:
    """Add each ECU's diagnostics (e.g. observer estimate) to signals.csv, joined on tick.

    Written to a temporary file and renamed, so signals.csv is never left half-written. Returns
    signals.csv's content as it now is, (header, the rows' bytes), when the files were complete
    (every row of the header's width: :func:`read_signals` can parse it as it is); else None.
    """
    sig = run_dir / "signals.csv"
    if not sig.exists():
        return None
    done = _merge_ecu_columns_fast(run_dir, n)
    if done:
        return done
    with open(sig, newline="") as f:
        rows = list(csv.reader(f))
    if not rows:
        return None
    header, body = rows[0], [r for r in rows[1:] if len(r) == len(rows[0])]
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
            if len(r) != len(erows[0]) or not r[col].isdigit():
                continue  # a row cut short by a killed ECU
            k = int(r[col])
            vals = [v for j, v in enumerate(r) if j != col]
            extra.setdefault(k, []).extend([""] * (start - len(extra.get(k, []))))
            extra[k][start:start + len(names)] = vals
    if not extra_header or set(extra_header) & set(header):
        return None  # nothing to add, or already merged (never duplicate columns)
    total = sum(widths)
    with _rewrite(sig) as f:
        w = csv.writer(f)
        w.writerow(header + extra_header)
        for r in body:
            e = extra.get(int(float(r[0])), [])
            w.writerow(r + e + [""] * (total - len(e)))
    return None


def _merge_ecu_columns_fast(run_dir: Path, n: int) -> tuple[list[str], bytes] | None:
    """:func:`merge_ecu_columns` on the lines' bytes (no CSV parsing: no cell of ours is quoted),
    ~5x faster for long runs; False when a file is damaged (short rows, a tick that is not a
    number, quoting, text that is not ASCII) and the row-by-row merge must do it. Same bytes out
    (tests/test_run.py). Else signals.csv's content as it now is, (header, rows). Where an ECU wrote ticks 0, 1, 2, ... one per row, as the nodes do, and
    signals.csv holds ticks 0, 1, 2, ..., its rows pair up in order without a lookup by tick."""
    sig = run_dir / "signals.csv"
    ok = _complete_rows(sig)
    if ok is None:
        return None
    header, body = ok
    if not body.isascii():
        return None
    lines = body.splitlines()
    sig_ticks: list[int] | None = None  # signals.csv's ticks, read only if an ECU's rows do not pair up
    in_order: bool | None = None  # signals.csv's ticks are 0, 1, 2, ...
    extra_header: list[str] = []
    columns: list[list[bytes]] = []  # per ECU, its cells' text for each row of signals.csv
    for c in range(1, n + 1):
        p = run_dir / f"ecu_c{c}.csv"
        if not p.exists() or p.stat().st_size == 0:
            continue
        got = _complete_rows(p)
        if got is None:
            return None
        eh, eb = got
        if eh[0] != "tick" or not eb.isascii():
            return None
        names = eh[1:]
        extra_header += [f"ecu_{h}_c{c}" if f"{h}_c{c}" in header else f"{h}_c{c}" for h in names]
        empty = b"," * (len(names) - 1)
        rows = [line.partition(b",") for line in eb.splitlines()]
        ticks = [t for t, _s, _r in rows]
        if in_order is None:
            in_order = [line.partition(b",")[0] for line in lines] == [b"%d" % k for k in range(len(lines))]
        if in_order and ticks == [b"%d" % k for k in range(len(ticks))]:
            cells = [r for _t, _s, r in rows[:len(lines)]]
            columns.append(cells + [empty] * (len(lines) - len(cells)))
            continue
        by_tick: dict[int, bytes] = {}
        for t, _s, rest in rows:
            if not t.isdigit():
                return None
            by_tick[int(t)] = rest  # a tick written twice: the last one
        if sig_ticks is None:
            sig_ticks = [int(float(line[:line.index(b",")] if b"," in line else line)) for line in lines]
        columns.append([by_tick.get(k, empty) for k in sig_ticks])
    if not extra_header or set(extra_header) & set(header):
        return ok  # nothing to add, or already merged (never duplicate columns)
    head = io.StringIO()
    csv.writer(head).writerow(header + extra_header)
    merged = b"".join([b",".join(cells) + b"\r\n" for cells in zip(lines, *columns)])
    with _rewrite(sig) as f:
        f.write(head.getvalue())
        f.flush()
        f.buffer.write(merged)
    return header + extra_header, merged


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
    with _rewrite(sig) as f:
        w = csv.writer(f)
        w.writerow(rows[0] + names)
        for r in rows[1:]:
            w.writerow(r + by_tick.get(int(float(r[0])), [""] * len(names)))


@contextlib.contextmanager
def _rewrite(path: Path) -> Iterator[Any]:
    """A text file to write ``path``'s new content into, renamed over ``path`` when the block
    ends: a failure (a full disk) leaves the old file and no temporary file behind."""
    tmp = path.with_suffix(".csv.tmp")
    try:
        with open(tmp, "w", newline="") as f:
            yield f
        os.replace(tmp, path)
    except BaseException:
        with contextlib.suppress(OSError):
            tmp.unlink()
        raise


def _load_json(p: Path) -> dict[str, Any]:
    try:
        return json.loads(p.read_text())
    except (OSError, ValueError):
        return {}


def write_json_atomic(path: Path, data: Any) -> None:
    """Write ``data`` as JSON to a temporary file next to ``path``, fsync it and rename it over
    ``path``: a reader sees the old file or the new one, never a partial one (a full disk raises
    OSError and leaves the old file)."""
    write_text_atomic(path, json.dumps(data, indent=1, allow_nan=False, default=_json_default),
                      fsync=True)


def _json_default(o: Any) -> Any:
    if isinstance(o, (np.integer,)):
        return int(o)
    if isinstance(o, (np.floating,)):
        return float(o)
    raise TypeError(f"not JSON serialisable: {type(o).__name__}")


def _finite_json(x: Any) -> Any:
    """Non-finite floats as strings ("inf", "nan"): summary.json stays strict JSON."""
    if isinstance(x, float) and not np.isfinite(x):
        return "nan" if np.isnan(x) else ("inf" if x > 0 else "-inf")
    if isinstance(x, dict):
        return {k: _finite_json(v) for k, v in x.items()}
    if isinstance(x, (list, tuple)):
        return [_finite_json(v) for v in x]
    return x


def _base_summary(scn: Scenario, bus: str, outcome: dict[str, Any]) -> dict[str, Any]:
    return {
        "scenario": scn.name,
        "profile": scn.profile,
        "seed": scn.seed,
        "bus": bus,
        "mode": scn.mode,
        "controller": scn.controller.name,
        "n_cars": scn.n_cars,
        "duration_s": scn.duration_s,
        "control_period_s": scn.control_period_s,
        "status": outcome.get("status", "failed"),
        "message": outcome.get("message", ""),
        "verdict": None,
        "wall_time_s": outcome.get("wall_time_s"),
        "ticks": outcome.get("ticks", 0),
    }


def finalize_run(scn: Scenario, run_dir: Path, bus: str, outcome: dict[str, Any], *, plots: bool = True) -> dict[str, Any]:
    """Write summary.json (and plots) for ``run_dir``; returns the summary.

    ``outcome``: ``status`` (ok / failed / interrupted: how the run executed), ``message``,
    ``wall_time_s`` and optionally ``ticks`` (the last progress the orchestrator saw) and
    ``live_nodes`` (node processes that could not be stopped: their files are not touched).
    summary.json is always written (atomically), also when the traces are damaged or a second
    Ctrl-C arrives here: then it holds what is known and ``finalize_error`` says what is missing.
    """
    import warnings

    try:
        with np.errstate(all="ignore"), warnings.catch_warnings():
            warnings.simplefilter("ignore", RuntimeWarning)
            summary = _summarise(scn, run_dir, bus, outcome, plots=plots)
    except KeyboardInterrupt:
        summary = _base_summary(scn, bus, {**outcome, "status": "interrupted",
                                           "message": outcome.get("message") or "interrupted while writing the summary"})
        summary["finalize_error"] = "interrupted while the summary was being computed: metrics and plots are missing"
        summary["verdict"] = "unknown"
    except Exception as e:  # noqa: BLE001 - a damaged trace must not cost the run its summary
        summary = _base_summary(scn, bus, outcome)
        summary["finalize_error"] = f"{type(e).__name__}: {e}"
        summary["verdict"] = "unknown"
    try:
        write_json_atomic(run_dir / "summary.json", _finite_json(summary))
    except OSError as e:  # a full disk: say which file (the CLI prints it as one line, exit 1)
        raise OSError(e.errno, f"cannot write it: {e.strerror or e}"
                      + (f" (the run: {summary['status']}: {summary['message']})" if summary.get("message") else ""),
                      str(run_dir / "summary.json")) from None
    return summary


def realtime_figures(plant: dict[str, Any], ecus: list[dict[str, Any]], busst: dict[str, Any]) -> dict[str, Any]:
    """A realtime run's timing as measured (canbrake.nodes.plant): plant deadline misses as a share
    of the periods that ended, command latency (SYNC sent -> last command of the period in, s;
    null when the percentile falls on a missed period), late periods and the wall time (s) the
    grid moved on after them, and the scheduling every process obtained (SCHED_FIFO or the
    fallback, and its CPUs; canbrake.nodes.rt)."""
    ex = plant.get("extra") or {}
    periods = int(ex.get("cmd_latency_periods") or plant.get("ticks") or 0)
    misses = int(plant.get("deadline_misses", 0))
    sched = {"plant": ex.get("scheduling"), "recorder": busst.get("scheduling")}
    sched.update({f"ecu_c{c}": e.get("scheduling") for c, e in enumerate(ecus, 1)})
    return {"periods": periods, "plant_deadline_misses": misses,
            "plant_deadline_miss_pct": round(100.0 * misses / periods, 4) if periods else None,
            **{k: ex.get(k) for k in ("cmd_latency_p50_s", "cmd_latency_p99_s", "cmd_latency_max_s",
                                      "cmd_latency_missing", "sync_delay_p50_s", "sync_delay_p99_s",
                                      "sync_delay_max_s")},
            "late_periods": plant.get("late_periods", 0), "max_lateness_s": plant.get("max_lateness_s", 0.0),
            "slipped_s": plant.get("slipped_s", 0.0),
            # periods an ECU never commanded because the next one began first (its process paused)
            "ecu_skipped_periods": sum(int(e.get("skipped_periods", 0)) for e in ecus), "scheduling": sched}


#: signals.csv's columns the summary reads (trace_from_columns), by prefix
_SUMMARY_PREFIXES = ("position_m_c", "speed_mps_c", "accel_mps2_c", "brake_cmd_n_c", "brake_applied_n_c",
                     "deflection_m_k", "coupler_force_n_k", "observer_accel_mps2_c")


def _summary_column(name: str, brakes: bool) -> bool:
    """Whether the summary reads signals.csv's column ``name`` (the trace; with brake equipment
    also the axles' slips and the dump valves, :func:`canbrake.analysis.braking.braking_summary`)."""
    return (name in ("tick", "t_s", "ref_speed_mps", "ref_position_m") or name.startswith(_SUMMARY_PREFIXES)
            or (brakes and ((name.startswith("axle") and "_slip_c" in name) or name.startswith("wsp_valve_c"))))


def _summarise(scn: Scenario, run_dir: Path, bus: str, outcome: dict[str, Any], *, plots: bool) -> dict[str, Any]:
    from canbrake.analysis.verdict import judge

    n = scn.n_cars
    live = outcome.get("live_nodes") or []
    content = None  # signals.csv's (header, rows) once merged, when complete: not read again
    if not live:  # never rewrite signals.csv while a node may still write it
        content = merge_ecu_columns(run_dir, n)
        if (run_dir / "can_errors.csv").exists():
            content = None
            merge_tick_file(run_dir, "can_errors.csv")
    plant = _load_json(run_dir / "plant_stats.json")
    busst = _load_json(run_dir / "bus_stats.json")
    ecus = [_load_json(run_dir / f"ecu_c{c}_stats.json") for c in range(1, n + 1)]
    summary = _base_summary(scn, bus, outcome)
    if live:
        summary["live_nodes"] = live
    summary["ticks"] = plant.get("ticks") or outcome.get("ticks") or 0
    if summary["ticks"] and plant.get("wall_time_s"):
        # simulated seconds per wall second of the plant's loop (start-up of the processes excluded)
        summary["real_time_factor"] = summary["ticks"] * scn.control_period_s / plant["wall_time_s"]
    sig = run_dir / "signals.csv"
    tr = None
    if sig.exists():
        brakes = getattr(scn.consist, "brakes", None) is not None
        cols = read_signals(sig, keep=lambda name: _summary_column(name, brakes), content=content)
        if cols.get("t_s") is not None and len(cols["t_s"]) > 0:
            tr = trace_from_columns(cols, n)
            tr.mass_kg = scn.vehicle_masses_kg()
            if not plant.get("ticks"):  # the plant died before writing its statistics
                summary["ticks"] = max(int(summary["ticks"]), int(cols["tick"][-1]) if "tick" in cols else 0)
        if tr is not None and len(tr.t_s) > 1:
            summary["metrics"] = compute_metrics(tr)
            if brakes:  # brake equipment: the stop and the wheels
                from canbrake.analysis.braking import braking_summary

                summary["braking"] = braking_summary(tr.t_s, tr.speed_mps, tr.accel_mps2, cols)
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
                                                      "bus_load_peak_window", "bus_load_window_s",
                                                      "error_frames_per_s", "frames_per_s_by_sender",
                                                      "latency_model", "segments", "gateways")}
    if summary["bus_load"].get("segments") is None:  # one bus
        summary["bus_load"].pop("segments")
        summary["bus_load"].pop("gateways")
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
    rt_errors = {f"ecu_c{c}": e["can_errors"] for c, e in enumerate(ecus, 1) if e.get("can_errors")}
    if rt_errors:  # realtime: injected at each ECU (canbrake.bus.rt_errors)
        summary["can_errors"] = {"model": "realtime: injected at each sending ECU", "nodes": rt_errors,
                                 "error_frames_logged": busst.get("error_frames_received")}
    if scn.safety.command_timeout_s is not None:
        summary["failsafe"] = {"command_timeout_s": scn.safety.command_timeout_s,
                               "activations": plant.get("failsafe_activations", 0),
                               "car_ticks": plant.get("failsafe_ticks", 0),
                               "first_activation_s": plant.get("failsafe_first_s", {})}
    summary["safety"] = safety_counters(scn, plant, ecus, busst)
    summary["deadline_misses"] = {"plant": plant.get("deadline_misses", 0),
                                  "ecus": sum(e.get("deadline_misses", 0) for e in ecus),
                                  "ecus_per_car": [e.get("deadline_misses", 0) for e in ecus],
                                  "missed_commands_per_car": plant.get("commands_missed_per_car"),
                                  "late_periods": plant.get("late_periods", 0),
                                  "max_lateness_s": plant.get("max_lateness_s", 0.0)}
    if scn.mode != "realtime":
        summary["deadline_misses"]["missed_commands_per_car"] = None  # lockstep: missing = lost, not late
    else:
        summary["realtime"] = realtime_figures(plant, ecus, busst)
    summary["clock"] = clock_figures(scn, plant, int(summary["ticks"] or 0))
    # the loop's wall time: the plant's (start-up excluded); in process the engine's loop (outcome)
    comp = compute_figures(plant, ecus, int(summary["ticks"] or 0),
                           plant.get("wall_time_s") or summary.get("wall_time_s") or 0.0)
    procs = process_figures(run_dir, int(summary["ticks"] or 0))
    if comp is not None:
        summary["compute"] = comp
        if procs is not None:
            comp["processes"] = procs
    if plant.get("response_s"):
        summary["ecu_response_s"] = plant["response_s"]
    from canbrake.external import external_finding, external_summary

    ext = external_summary(scn, plant)
    if ext is not None:
        summary["external_ecus"] = ext
    v = judge(scn, summary, tr, plant)
    late = external_finding(scn, ext, int(summary["ticks"] or 0))
    if late is not None:
        from canbrake.analysis.verdict import VERDICTS

        v["findings"].append(late)
        if VERDICTS.index("late") < VERDICTS.index(v["verdict"]):
            v["verdict"] = "late"
    summary["verdict"] = v["verdict"]
    summary["findings"] = v["findings"]
    summary["diverged_at_s"] = v["diverged_at_s"]
    return summary


def compute_figures(plant: dict[str, Any], ecus: list[dict[str, Any]], ticks: int,
                    loop_wall_s: float) -> dict[str, Any] | None:
    """``summary.json``'s ``compute``: the wall time (s) of the plant model's step and of every
    controller's step on this host (preemption included), from the nodes' statistics; None when
    no node measured any (a run that never stepped).

    ``model_step_s`` and ``control_step_s`` each hold n, mean, p99 and max (for the controllers:
    every ECU's steps together, p99 the worst ECU's and ``worst_p99_ecu`` which); ``per_period_s``
    is the physics and control work of one period (the model's mean step plus every ECU's mean
    step), ``loop_per_period_s`` the run loop's wall time per period (``loop_wall_s``): in process their
    ratio is the share of the run spent in the train's own formulas, the rest is the bus and the
    nodes; with one process per ECU the ECUs' steps run beside each other."""
    model = plant.get("model_step_s") or {}
    steps = [(f"ecu_c{c}", e["control_step_s"]) for c, e in enumerate(ecus, 1)
             if (e.get("control_step_s") or {}).get("n")]
    if not model.get("n") and not steps:
        return None
    n = sum(st["n"] for _, st in steps)
    total = sum(st["total_s"] for _, st in steps)
    worst = max(steps, key=lambda x: x[1]["p99_s"]) if steps else None
    control = {"n": n, "mean_s": total / n if n else None,
               "p99_s": worst[1]["p99_s"] if worst else None, "worst_p99_ecu": worst[0] if worst else None,
               "max_s": max(st["max_s"] for _, st in steps) if steps else None, "ecus": len(steps)}
    per_period = (model.get("mean_s") or 0.0) + sum(st["mean_s"] for _, st in steps)
    return {"model_step_s": {k: model.get(k) for k in ("n", "mean_s", "p99_s", "max_s")},
            "control_step_s": control, "per_period_s": per_period,
            "loop_per_period_s": loop_wall_s / ticks if loop_wall_s and ticks else None}


def process_figures(run_dir: Path, ticks: int) -> dict[str, Any] | None:
    """``summary.json``'s ``compute.processes`` (one process per node: ``processes/*.json``, see
    :func:`canbrake.run._write_process_stats`): each node process's CPU time per period (s, user +
    system) and, on the memory bus, wake-ups per period; ``cpu_per_period_s`` their sum, and
    ``cpu_bound_periods_per_s`` = CPUs / that sum, the rate no run on this machine can exceed
    however the processes are scheduled (every period needs that much CPU). None in process."""
    files = sorted((run_dir / "processes").glob("*.json")) if ticks else []
    nodes: dict[str, dict[str, Any]] = {}
    for f in files:
        try:
            rec = json.loads(f.read_text())
        except (OSError, ValueError):
            continue
        nodes[rec["name"]] = {"role": rec.get("role"), "cpu_per_period_s": rec["cpu_s"] / ticks,
                              "wakeups_per_period": (rec["wakeups"] / ticks if rec.get("wakeups") is not None
                                                     else None)}
    if not nodes:
        return None
    total = sum(v["cpu_per_period_s"] for v in nodes.values())
    cpus = os.cpu_count() or 1
    wk = [v["wakeups_per_period"] for v in nodes.values() if v["wakeups_per_period"] is not None]
    return {"nodes": nodes, "cpu_per_period_s": total, "cpus": cpus,
            "cpu_bound_periods_per_s": cpus / total if total > 0 else None,
            "wakeups_per_period": sum(wk) if wk else None}


def clock_figures(scn: Scenario, plant: dict[str, Any], ticks: int) -> dict[str, Any]:
    """``summary.json``'s ``clock``: how simulated time related to the wall clock. ``time_scale``
    (realtime: simulated s per wall s asked for), ``wall_period_s`` (the plant's period on the wall
    clock), ``achieved_time_scale`` (simulated s per wall s of the plant's loop, start-up excluded),
    realtime ``late_periods`` (a period started more than one period late) and ``max_lateness_s``."""
    dt = scn.control_period_s
    wall = plant.get("wall_time_s") or 0.0
    out: dict[str, Any] = {"mode": scn.mode, "time_scale": scn.time_scale if scn.mode == "realtime" else None,
                           "control_period_s": dt,
                           "wall_period_s": dt / scn.time_scale if scn.mode == "realtime" else None,
                           "simulated_s": round(ticks * dt, 9), "plant_wall_s": wall,
                           "achieved_time_scale": (ticks * dt / wall) if wall else None}
    if scn.mode == "realtime":
        out["late_periods"] = plant.get("late_periods", 0)
        out["max_lateness_s"] = plant.get("max_lateness_s", 0.0)
    return out


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
            # secured runs: STATE_AUTH frames whose state frame never came (a lost state frame)
            "state_auth_orphans": sum(g.get("state_auth_orphans", 0) for g in nodes.values()),
            "rejected_by_node": {n: g.get("rejected", {}) for n, g in nodes.items() if sum((g.get("rejected") or {}).values())},
            "unknown_senders": unknown, "fallbacks": fallbacks}
