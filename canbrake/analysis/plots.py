"""Plots of one run, made to be read at a glance (matplotlib's object API: no display, no pyplot
state, so they work in scripts, notebooks and node-free servers alike). km/h only here, at the edge.

Every figure's title names the scenario, profile, controller, bus and mode. Files in ``plots/``:
``overview.png`` (the run on one page) and ``speeds``, ``errors``, ``decel`` (deceleration and
jerk against comfort and emergency limits), ``deflections`` (with the bound, and coupler force),
``forces`` (brake force, symmetric-log axis when the first instants dwarf service braking) and
``stopping`` (stopping distance against v²/2a*).
"""
from __future__ import annotations

import textwrap
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Callable

import numpy as np
from matplotlib.axes import Axes
from matplotlib.figure import Figure

from canbrake.analysis.metrics import KMH, Trace

#: passenger-comfort limits drawn on the deceleration and jerk plots: a metro's service brake
#: (≈1.0 m/s²), its emergency brake (1.5 m/s², the rating of canbrake's realistic actuator) and a
#: comfortable jerk (1 m/s³, the realistic actuator's default jerk limit)
COMFORT_DECEL_MPS2 = 1.0
EMERGENCY_DECEL_MPS2 = 1.5
COMFORT_JERK_MPS3 = 1.0
#: the coupler deflection bound (m) of the papers' safety requirement
DEFLECTION_BOUND_M = 0.01


@dataclass
class PlotMeta:
    """What the titles and limit lines need to know about a run."""

    scenario: str = ""
    profile: str | None = None
    controller: str = ""
    bus: str = ""
    mode: str = ""
    ref_decel_mps2: float | None = None      # a* (m/s², > 0 decelerates)
    band_kmh: float = 0.5
    bound_m: float | None = DEFLECTION_BOUND_M   # None: the scenario has no deflection bound, none drawn
    emergency_decel_mps2: float = EMERGENCY_DECEL_MPS2
    comfort_decel_mps2: float = COMFORT_DECEL_MPS2
    jerk_limit_mps3: float = COMFORT_JERK_MPS3

    def title(self) -> str:
        parts = [self.scenario or "run"]
        if self.profile:
            parts.append(f"profile {self.profile}")
        if self.controller:
            parts.append(f"controller {self.controller}")
        if self.bus:
            parts.append(f"bus {self.bus}")
        if self.mode:
            parts.append(self.mode)
        return " · ".join(parts)


def plot_meta(scn: Any, bus: str = "") -> PlotMeta:
    """A :class:`PlotMeta` from a :class:`canbrake.scenario.Scenario` and the bus description."""
    act = scn.actuator

    def largest(v: Any) -> float | None:  # one value, or the largest of the vehicles' (None: none given)
        vals = [x for x in (v if isinstance(v, list) else [v]) if x is not None]
        return float(max(vals)) if vals else None
    emergency = EMERGENCY_DECEL_MPS2
    if getattr(act, "model", "") == "realistic" and largest(getattr(act, "max_brake_decel_mps2", None)):
        emergency = largest(act.max_brake_decel_mps2)  # type: ignore[assignment]
    jerk = COMFORT_JERK_MPS3
    if getattr(act, "model", "") == "realistic" and largest(getattr(act, "jerk_limit_mps3", None)):
        jerk = largest(act.jerk_limit_mps3)  # type: ignore[assignment]
    ctrl = " + ".join(dict.fromkeys(p.controller.name for p in scn.placement()))  # every ECU's, in order
    from canbrake.analysis.verdict import deflection_bound_m

    return PlotMeta(scenario=scn.name, profile=scn.profile, controller=ctrl,
                    bus=_short_bus(bus), mode=scn.mode, ref_decel_mps2=float(scn.reference.decel_mps2),
                    bound_m=deflection_bound_m(scn),  # the verdict's bound, whatever the controller
                    emergency_decel_mps2=emergency, jerk_limit_mps3=jerk)


def _short_bus(bus: str) -> str:
    """``canbrake:cb1234-abcdef`` -> ``memory``; ``socketcan:vcan0`` stays."""
    if bus.startswith("canbrake:"):
        return "memory"
    if bus.startswith("None:virtual"):
        return "inprocess/virtual"
    return bus


# ----------------------------------------------------------------------------- panels
#: more per-vehicle series than this: the legend names only the first and the last vehicle
LEGEND_MAX_SERIES = 12


def _legend(ax: Axes, n: int) -> None:
    ax.grid(alpha=0.3)
    if n <= LEGEND_MAX_SERIES:
        ax.legend(ncol=2 if n > 3 else 1, fontsize=7, loc="best")
        return
    # a long train (106 vehicles): a legend entry per vehicle would leave no room for the axes
    handles, labels = ax.get_legend_handles_labels()
    series = [i for i, lb in enumerate(labels) if lb.split(" ")[0] in ("car", "coupler", "vehicle")]
    keep = [i for i in range(len(labels)) if i not in series] + series[:1] + series[-1:]
    ax.legend([handles[i] for i in keep], [labels[i] for i in keep], fontsize=7, loc="best",
              title=f"{n} series, first and last named", title_fontsize=7)


def _symlog_if_extreme(ax: Axes, values: np.ndarray, unit_scale: float = 1.0, limit: float | None = None) -> bool:
    """Use a symmetric-log y axis when the largest |value| is over 20 times the 90th percentile (a
    few extreme instants would flatten the rest). ``values`` in SI, plotted times ``unit_scale``.
    Linear up to the power of ten at or below 1.5 × the 90th percentile (a decade, so that no decade
    tick crowds into the linear part, and the bulk of the values shows in the first log decade), or up
    to the decade of ``limit`` (a band drawn at ±limit, in plotted units) when that is smaller, so that
    the band stays visible. True if set."""
    v = np.abs(values[np.isfinite(values)]) * unit_scale
    if v.size == 0:
        return False
    p90 = float(np.percentile(v, 90))
    if p90 > 0 and v.max() > 20 * p90:
        lin = 10.0 ** np.floor(np.log10(max(p90 * 1.5, 1e-12)))
        if limit is not None and limit > 0:
            lin = min(lin, 10.0 ** np.ceil(np.log10(limit)))
        ax.set_yscale("symlog", linthresh=float(lin))
        return True
    return False


def _speeds(ax: Axes, tr: Trace, meta: PlotMeta) -> None:
    ax.plot(tr.t_s, tr.ref_speed_mps * KMH, "k--", lw=2, label="v* (reference)")
    for i in range(tr.n_cars):
        ax.plot(tr.t_s, tr.speed_mps[:, i] * KMH, lw=1, label=f"car {i + 1}")
    ax.set(xlabel="time (s)", ylabel="speed (km/h)", title="speed against the reference v*")
    _legend(ax, tr.n_cars)


def _errors(ax: Axes, tr: Trace, meta: PlotMeta) -> None:
    err = (tr.speed_mps - tr.ref_speed_mps[:, None]) * KMH
    for i in range(tr.n_cars):
        ax.plot(tr.t_s, err[:, i], lw=1, label=f"car {i + 1}")
    ax.axhspan(-meta.band_kmh, meta.band_kmh, color="g", alpha=0.1, label=f"±{meta.band_kmh:g} km/h band")
    ax.set(xlabel="time (s)", ylabel="v − v* (km/h)", title="speed tracking error")
    _symlog_if_extreme(ax, err, limit=meta.band_kmh)
    _legend(ax, tr.n_cars)


def _decel(ax: Axes, tr: Trace, meta: PlotMeta) -> None:
    decel = -tr.accel_mps2
    for i in range(tr.n_cars):
        ax.plot(tr.t_s, decel[:, i], lw=1, label=f"car {i + 1}")
    if meta.ref_decel_mps2 is not None:
        ax.axhline(meta.ref_decel_mps2, color="k", ls="--", lw=1.2, label=f"a* = {meta.ref_decel_mps2:.3g} m/s²")
    ax.axhline(meta.comfort_decel_mps2, color="tab:orange", ls=":", lw=1.2,
               label=f"comfort (service) {meta.comfort_decel_mps2:g} m/s²")
    ax.axhline(meta.emergency_decel_mps2, color="r", ls=":", lw=1.2,
               label=f"emergency {meta.emergency_decel_mps2:g} m/s²")
    ax.set(xlabel="time (s)", ylabel="deceleration (m/s², + brakes)", title="deceleration against comfort and "
                                                                          "emergency limits")
    _symlog_if_extreme(ax, decel)
    _legend(ax, tr.n_cars)


def _jerk(ax: Axes, tr: Trace, meta: PlotMeta) -> None:
    if len(tr.t_s) < 2:
        return
    jerk = np.diff(tr.accel_mps2, axis=0) / np.diff(tr.t_s)[:, None]
    t = tr.t_s[1:]
    for i in range(tr.n_cars):
        ax.plot(t, jerk[:, i], lw=0.8, label=f"car {i + 1}")
    ax.axhspan(-meta.jerk_limit_mps3, meta.jerk_limit_mps3, color="g", alpha=0.1,
               label=f"comfort ±{meta.jerk_limit_mps3:g} m/s³")
    ax.set(xlabel="time (s)", ylabel="jerk da/dt (m/s³)", title="jerk against the comfort limit")
    _symlog_if_extreme(ax, jerk, limit=meta.jerk_limit_mps3)
    _legend(ax, tr.n_cars)


def _deflections(ax: Axes, tr: Trace, meta: PlotMeta) -> None:
    for j in range(tr.deflection_m.shape[1]):
        ax.plot(tr.t_s, tr.deflection_m[:, j] * 100, lw=1, label=f"coupler {j + 1}–{j + 2}")
    if meta.bound_m is None:  # no bound in the scenario: nothing to draw (and the verdict judges none)
        ax.set(xlabel="time (s)", ylabel="deflection Δl (cm, + stretched)",
               title="coupler deflection (no bound set: safety.max_abs_deflection_m)")
        _symlog_if_extreme(ax, tr.deflection_m, 100)
        _legend(ax, tr.deflection_m.shape[1])
        return
    b = meta.bound_m * 100
    ax.axhline(b, color="r", ls=":", lw=1.2)
    ax.axhline(-b, color="r", ls=":", lw=1.2, label=f"bound ±{b:g} cm")
    ax.set(xlabel="time (s)", ylabel="deflection Δl (cm, + stretched)", title="coupler deflection against its bound")
    _symlog_if_extreme(ax, tr.deflection_m, 100, limit=b)
    _legend(ax, tr.deflection_m.shape[1])


def _coupler_forces(ax: Axes, tr: Trace, meta: PlotMeta) -> None:
    for j in range(tr.coupler_force_n.shape[1]):
        ax.plot(tr.t_s, tr.coupler_force_n[:, j] / 1000, lw=1, label=f"coupler {j + 1}–{j + 2}")
    ax.set(xlabel="time (s)", ylabel="coupler force (kN)", title="coupler force")
    _symlog_if_extreme(ax, tr.coupler_force_n, 1e-3)  # plotted in kN
    _legend(ax, tr.coupler_force_n.shape[1])


def _forces(ax: Axes, tr: Trace, meta: PlotMeta) -> None:
    f = tr.brake_applied_n / 1000
    for i in range(tr.n_cars):
        ax.plot(tr.t_s, f[:, i], lw=1, label=f"car {i + 1}")
    ax.axhline(0, color="k", lw=0.6)
    log = _symlog_if_extreme(ax, f)
    ax.set(xlabel="time (s)", ylabel="applied force (kN; + brakes, − traction)",
           title="brake force" + (" (symmetric-log axis: linear near 0)" if log else ""))
    _legend(ax, tr.n_cars)


def _stopping(ax: Axes, tr: Trace, meta: PlotMeta) -> None:
    """Predicted stopping distance s(t) = (x(t) − x(0)) + v(t)²/(2a*): where each car would stop if
    it braked at a* from now on, against the reference's v0*²/(2a*)."""
    a = meta.ref_decel_mps2
    if not a or a <= 0:
        ax.text(0.5, 0.5, "no decelerating reference: no stopping distance", ha="center", transform=ax.transAxes)
        ax.set_axis_off()
        return
    travelled = tr.position_m - tr.position_m[0]
    pred = travelled + tr.speed_mps ** 2 / (2 * a)
    for i in range(tr.n_cars):
        ax.plot(tr.t_s, pred[:, i], lw=1, label=f"car {i + 1}")
    v0 = float(tr.ref_speed_mps[0])
    ref = v0 ** 2 / (2 * a)
    ax.axhline(ref, color="k", ls="--", lw=1.2, label=f"v0*²/2a* = {ref:.1f} m")
    ax.set(xlabel="time (s)", ylabel="travelled + v²/2a* (m)", title="stopping distance (braking at a* from now)")
    _legend(ax, tr.n_cars)


PANELS: dict[str, list[Callable[[Axes, Trace, PlotMeta], None]]] = {
    "speeds": [_speeds],
    "errors": [_errors],
    "decel": [_decel, _jerk],
    "deflections": [_deflections, _coupler_forces],
    "forces": [_forces],
    "stopping": [_stopping],
}
_OVERVIEW = [_speeds, _errors, _decel, _jerk, _deflections, _coupler_forces, _forces, _stopping]


def _suptitle(fig: Figure, text: str, width_in: float, fontsize: float = 10) -> None:
    """A title wrapped to the figure's width (≈ 0.6 em per character)."""
    chars = max(20, int(width_in * 72 / (fontsize * 0.6)))
    fig.suptitle(textwrap.fill(text, chars), fontsize=fontsize)


def figures(tr: Trace, meta: PlotMeta, only: str | None = None) -> dict[str, Figure]:
    """The run's figures by name (``overview`` and the names of :data:`PANELS`); ``only``: just one."""
    figs: dict[str, Figure] = {}
    has_couplers = tr.deflection_m.shape[1] > 0
    for name, panels in PANELS.items():
        if only not in (None, name) or (name == "deflections" and not has_couplers):
            continue
        fig = Figure(figsize=(8, 3.6 * len(panels) + 0.6), layout="constrained")
        for k, draw in enumerate(panels):
            draw(fig.add_subplot(len(panels), 1, k + 1), tr, meta)
        _suptitle(fig, meta.title(), 8)
        figs[name] = fig
    if only in (None, "overview"):
        panels = [p for p in _OVERVIEW if has_couplers or p not in (_deflections, _coupler_forces)]
        rows = (len(panels) + 1) // 2
        fig = Figure(figsize=(15, 3.4 * rows + 0.8), layout="constrained")
        for k, draw in enumerate(panels):
            draw(fig.add_subplot(rows, 2, k + 1), tr, meta)
        _suptitle(fig, meta.title(), 15, 12)
        figs["overview"] = fig
    return figs


def plot_run(tr: Trace, out_dir: Path, title: str = "", band_kmh: float | None = None,
             bound_m: float | None = None, meta: PlotMeta | None = None) -> list[str]:
    """Write overview.png and one PNG per entry of :data:`PANELS` into ``out_dir``; returns the file names.
    ``band_kmh``/``bound_m``: instead of ``meta``'s (the scenario's bound, :func:`plot_meta`)."""
    out_dir.mkdir(parents=True, exist_ok=True)
    meta = meta or PlotMeta(scenario=title)
    if band_kmh is not None:
        meta.band_kmh = band_kmh
    if bound_m is not None:
        meta.bound_m = bound_m
    files = []
    for name, fig in figures(tr, meta).items():
        fig.savefig(out_dir / f"{name}.png", dpi=80 if name == "overview" else 100)
        files.append(f"{name}.png")
    return files


def run_figures(run_dir: str | Path, only: str | None = None) -> dict[str, Figure]:
    """The figures of a finished run directory (reads scenario.yaml, signals.csv, summary.json)."""
    import json

    from canbrake.analysis.summary import read_signals, trace_from_columns
    from canbrake.scenario import load_scenario

    d = Path(run_dir)
    scn = load_scenario(d / "scenario.yaml")
    try:
        bus = json.loads((d / "summary.json").read_text()).get("bus", "")
    except (OSError, ValueError):
        bus = ""
    tr = trace_from_columns(read_signals(d / "signals.csv"), scn.n_cars)
    return figures(tr, plot_meta(scn, bus), only)


def _save(fig: Figure, path: Path) -> str:
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    return path.name


def plot_bus(run_dir: Path, out_dir: Path, title: str = "") -> list[str]:
    """plots/bus.png: bus load per control period and per 100 ms window, frames per second by
    sender, and — with bus errors — error frames and each node's error state and TEC over time
    (what CANoe's statistics window shows). Reads the recorder's bus_load.csv, bus_stats.json and
    can_errors.csv; returns the file names ([] if the run has no bus_load.csv)."""
    import csv
    import json

    import numpy as np

    load_p = run_dir / "bus_load.csv"
    if not load_p.exists():
        return []
    with open(load_p, newline="") as f:
        rows = list(csv.DictReader(f))
    if not rows:
        return []
    out_dir.mkdir(parents=True, exist_ok=True)
    t = np.array([float(r["t_s"]) for r in rows])
    load = np.array([float(r["bus_load"]) for r in rows])
    errs = np.array([float(r["error_frames"] or 0) for r in rows])
    stats = json.loads((run_dir / "bus_stats.json").read_text()) if (run_dir / "bus_stats.json").exists() else {}
    err_p = run_dir / "can_errors.csv"
    states: dict[str, np.ndarray] = {}
    tec: dict[str, np.ndarray] = {}
    t_err = np.zeros(0)
    if err_p.exists():
        with open(err_p, newline="") as f:
            erows = list(csv.DictReader(f))
        if erows:
            dt = t[1] - t[0] if len(t) > 1 else 1.0
            t_err = np.array([int(r["tick"]) * dt for r in erows])
            for key in erows[0]:
                if key.startswith("can_state_"):
                    node = key[len("can_state_"):]
                    states[node] = np.array([int(r[key]) for r in erows])
                    tec[node] = np.array([int(r[f"tec_{node}"]) for r in erows])
    n_panels = 2 + (1 if states else 0)
    fig = Figure(figsize=(9, 3.0 * n_panels))
    axes = fig.subplots(n_panels, 1, squeeze=False)
    ax = axes[0, 0]
    ax.plot(t, load * 100, lw=0.7, color="0.6", label="per control period")
    win = stats.get("bus_load_windows") or []
    w = stats.get("bus_load_window_s", 0.1)
    if win:
        ax.step(np.arange(len(win)) * w, np.asarray(win) * 100, where="post", color="C0", lw=1.5,
                label=f"mean per {w * 1000:g} ms window")
    ax.axhline(100, color="r", lw=0.8, ls="--")
    if errs.any():
        ax2 = ax.twinx()
        ax2.bar(t, errs, width=(t[1] - t[0]) if len(t) > 1 else 1e-3, color="C3", alpha=0.5, label="error frames")
        ax2.set_ylabel("error frames / period", color="C3")
    ax.set(xlabel="time (s)", ylabel="bus load (%)",
           title=f"{title}: bus load (mean {stats.get('bus_load_mean', float('nan')) * 100:.1f} %, "
                 f"peak period {stats.get('bus_load_peak', float('nan')) * 100:.1f} %)")
    ax.grid(alpha=0.3)
    ax.legend(fontsize=8, loc="upper left")
    ax = axes[1, 0]
    fps = stats.get("frames_per_s_by_sender") or {}
    if fps:
        names = list(fps)
        ax.bar(names, [fps[n] for n in names], color="C0")
    ax.set(ylabel="frames/s", title=f"frames per second by sender ({stats.get('error_frames_per_s', 0):.1f} error frames/s)")
    ax.grid(alpha=0.3, axis="y")
    if states:
        ax = axes[2, 0]
        for i, (node, tc) in enumerate(sorted(tec.items())):
            if tc.any() or states[node].any():
                ax.step(t_err, tc, where="post", lw=1, label=f"TEC {node}", color=f"C{i % 10}")
                off = np.where(states[node] == 2)[0]
                if off.size:
                    ax.plot(t_err[off], np.full(off.size, 270), "|", color=f"C{i % 10}", ms=8)
        ax.axhline(128, color="orange", lw=0.8, ls="--", label="error-passive (128)")
        ax.axhline(255, color="r", lw=0.8, ls="--", label="bus-off (> 255)")
        ax.set(xlabel="time (s)", ylabel="TEC", title="transmit error counters (ticks at 270: bus-off)")
        ax.grid(alpha=0.3)
        ax.legend(fontsize=8, ncol=3)
    fig.tight_layout()
    out_dir.mkdir(parents=True, exist_ok=True)
    return [_save(fig, out_dir / "bus.png")]
