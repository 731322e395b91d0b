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
    bound_m: float = DEFLECTION_BOUND_M
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
    emergency = EMERGENCY_DECEL_MPS2
    if getattr(act, "model", "") == "realistic" and getattr(act, "max_brake_decel_mps2", None):
        emergency = float(act.max_brake_decel_mps2)
    jerk = COMFORT_JERK_MPS3
    if getattr(act, "model", "") == "realistic" and getattr(act, "jerk_limit_mps3", None):
        jerk = float(act.jerk_limit_mps3)
    return PlotMeta(scenario=scn.name, profile=scn.profile, controller=scn.controller.name,
                    bus=_short_bus(bus), mode=scn.mode, ref_decel_mps2=float(scn.reference.decel_mps2),
                    emergency_decel_mps2=emergency, jerk_limit_mps3=jerk)


def _short_bus(bus: str) -> str:
    """``canbrake:cb1234-abcdef`` -> ``memory``; ``socketcan:vcan0`` stays."""
    if bus.startswith("canbrake:"):
        return "memory"
    if bus.startswith("None:virtual"):
        return "inprocess/virtual"
    return bus


# ----------------------------------------------------------------------------- panels
def _legend(ax: Axes, n: int) -> None:
    ax.grid(alpha=0.3)
    ax.legend(ncol=2 if n > 3 else 1, fontsize=7, loc="best")


def _symlog_if_extreme(ax: Axes, values: np.ndarray, unit_scale: float = 1.0) -> bool:
    """Use a symmetric-log y axis when the largest |value| is over 20 times the 90th percentile (a
    few extreme instants would flatten the rest); linear below the 90th percentile. True if set."""
    v = np.abs(values[np.isfinite(values)]) * unit_scale
    if v.size == 0:
        return False
    p90 = float(np.percentile(v, 90))
    if p90 > 0 and v.max() > 20 * p90:
        ax.set_yscale("symlog", linthresh=max(p90 * 1.5, 1e-9))
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
    _symlog_if_extreme(ax, err)
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
    _symlog_if_extreme(ax, jerk)
    _legend(ax, tr.n_cars)


def _deflections(ax: Axes, tr: Trace, meta: PlotMeta) -> None:
    for j in range(tr.deflection_m.shape[1]):
        ax.plot(tr.t_s, tr.deflection_m[:, j] * 100, lw=1, label=f"coupler {j + 1}–{j + 2}")
    b = meta.bound_m * 100
    ax.axhline(b, color="r", ls=":", lw=1.2)
    ax.axhline(-b, color="r", ls=":", lw=1.2, label=f"bound ±{b:g} cm")
    ax.set(xlabel="time (s)", ylabel="deflection Δl (cm, + stretched)", title="coupler deflection against its bound")
    _symlog_if_extreme(ax, tr.deflection_m, 100)
    _legend(ax, tr.deflection_m.shape[1])


def _coupler_forces(ax: Axes, tr: Trace, meta: PlotMeta) -> None:
    for j in range(tr.coupler_force_n.shape[1]):
        ax.plot(tr.t_s, tr.coupler_force_n[:, j] / 1000, lw=1, label=f"coupler {j + 1}–{j + 2}")
    ax.set(xlabel="time (s)", ylabel="coupler force (kN)", title="coupler force")
    _symlog_if_extreme(ax, tr.coupler_force_n)
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


def plot_run(tr: Trace, out_dir: Path, title: str = "", band_kmh: float = 0.5, bound_m: float = DEFLECTION_BOUND_M,
             meta: PlotMeta | None = None) -> list[str]:
    """Write overview.png and one PNG per entry of :data:`PANELS` into ``out_dir``; returns the file names."""
    out_dir.mkdir(parents=True, exist_ok=True)
    meta = meta or PlotMeta(scenario=title)
    meta.band_kmh, meta.bound_m = band_kmh, bound_m
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
