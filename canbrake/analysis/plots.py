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
