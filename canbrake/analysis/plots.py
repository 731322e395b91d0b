"""Plots of one run (matplotlib, Agg backend: no display needed). km/h only here, at the edge."""
from __future__ import annotations

from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402

from canbrake.analysis.metrics import KMH, Trace  # noqa: E402


def plot_run(tr: Trace, out_dir: Path, title: str = "", band_kmh: float = 0.5, bound_m: float = 0.01) -> list[str]:
    """Write speeds.png, errors.png, deflections.png (and forces.png); returns the file names."""
    out_dir.mkdir(parents=True, exist_ok=True)
    t = tr.t_s
    files = []

    fig, ax = plt.subplots(figsize=(8, 4.5))
    ax.plot(t, tr.ref_speed_mps * KMH, "k--", lw=2, label="v* (reference)")
    for i in range(tr.n_cars):
        ax.plot(t, tr.speed_mps[:, i] * KMH, lw=1, label=f"car {i + 1}")
    ax.set(xlabel="time (s)", ylabel="speed (km/h)", title=f"{title}: speeds")
    ax.grid(alpha=0.3)
    ax.legend(ncol=2, fontsize=8)
    files.append(_save(fig, out_dir / "speeds.png"))

    fig, ax = plt.subplots(figsize=(8, 4.5))
    err = (tr.speed_mps - tr.ref_speed_mps[:, None]) * KMH
    for i in range(tr.n_cars):
        ax.plot(t, err[:, i], lw=1, label=f"car {i + 1}")
    ax.axhspan(-band_kmh, band_kmh, color="g", alpha=0.1, label=f"±{band_kmh} km/h")
    ax.set(xlabel="time (s)", ylabel="v - v* (km/h)", title=f"{title}: tracking error")
    ax.grid(alpha=0.3)
    ax.legend(ncol=2, fontsize=8)
    files.append(_save(fig, out_dir / "errors.png"))

    if tr.deflection_m.shape[1]:
        fig, ax = plt.subplots(figsize=(8, 4.5))
        for j in range(tr.deflection_m.shape[1]):
            ax.plot(t, tr.deflection_m[:, j] * 100, lw=1, label=f"coupler {j + 1}-{j + 2}")
        ax.axhline(bound_m * 100, color="r", ls=":", lw=1)
        ax.axhline(-bound_m * 100, color="r", ls=":", lw=1, label=f"±{bound_m * 100:g} cm")
        ax.set(xlabel="time (s)", ylabel="deflection (cm)", title=f"{title}: coupler deflections")
        ax.grid(alpha=0.3)
        ax.legend(ncol=2, fontsize=8)
        files.append(_save(fig, out_dir / "deflections.png"))

    fig, ax = plt.subplots(figsize=(8, 4.5))
    for i in range(tr.n_cars):
        ax.plot(t, tr.brake_applied_n[:, i] / 1000, lw=1, label=f"car {i + 1}")
    ax.set(xlabel="time (s)", ylabel="applied brake force (kN)", title=f"{title}: brake forces")
    ax.grid(alpha=0.3)
    ax.legend(ncol=2, fontsize=8)
    files.append(_save(fig, out_dir / "forces.png"))
    return files


def _save(fig: plt.Figure, path: Path) -> str:
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)
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
    fig, axes = plt.subplots(n_panels, 1, figsize=(9, 3.0 * n_panels), squeeze=False)
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
