"""Run metrics computed from traces (SI arrays in, plain floats out).

All functions take arrays shaped (T,) for time and (T, n) per car / (T, n-1) per coupler.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

KMH = 3.6  # km/h per m/s

#: speed band (km/h) that counts as "converged" to the reference
DEFAULT_BAND_KMH = 0.5


@dataclass
class Trace:
    """The plant's trace of one run."""

    t_s: np.ndarray            # (T,)
    ref_speed_mps: np.ndarray  # (T,)
    position_m: np.ndarray     # (T, n)
    speed_mps: np.ndarray      # (T, n)
    accel_mps2: np.ndarray     # (T, n)
    brake_cmd_n: np.ndarray    # (T, n)
    brake_applied_n: np.ndarray  # (T, n)
    deflection_m: np.ndarray   # (T, n-1)
    coupler_force_n: np.ndarray  # (T, n-1)
    observer_accel_mps2: np.ndarray | None = None  # (T, n) ECU estimates, if reported

    @property
    def n_cars(self) -> int:
        return self.speed_mps.shape[1]


def convergence_time_s(t: np.ndarray, err_kmh: np.ndarray, band_kmh: float = DEFAULT_BAND_KMH) -> float | None:
    """First time after which every car stays within ``band_kmh`` of the reference (None: never)."""
    outside = np.any(np.abs(err_kmh) > band_kmh, axis=1)
    if not outside.any():
        return float(t[0])
    last = int(np.nonzero(outside)[0][-1])
    if last + 1 >= len(t):
        return None
    return float(t[last + 1])


def compute_metrics(tr: Trace, band_kmh: float = DEFAULT_BAND_KMH) -> dict:
    """Tracking, coupler, comfort and braking metrics of one trace."""
    finite = np.all(np.isfinite(tr.speed_mps), axis=1) & np.all(np.isfinite(tr.position_m), axis=1)
    if not finite.all():  # a diverged run: judge the part that was still a number
        keep = np.nonzero(finite)[0]
        last = int(keep[-1]) + 1 if keep.size else 1
        tr = Trace(*(getattr(tr, f)[:last] if getattr(tr, f) is not None else None
                     for f in ("t_s", "ref_speed_mps", "position_m", "speed_mps", "accel_mps2", "brake_cmd_n",
                               "brake_applied_n", "deflection_m", "coupler_force_n", "observer_accel_mps2")))
    t = tr.t_s
    err_kmh = (tr.speed_mps - tr.ref_speed_mps[:, None]) * KMH
    tc = convergence_time_s(t, err_kmh, band_kmh)
    after = t >= tc if tc is not None else np.zeros_like(t, dtype=bool)
    rmse = np.sqrt(np.mean(err_kmh ** 2, axis=0))
    rmse_after = np.sqrt(np.mean(err_kmh[after] ** 2, axis=0)) if after.any() else np.full(tr.n_cars, np.nan)
    defl = np.abs(tr.deflection_m) if tr.deflection_m.size else np.zeros((len(t), 1))
    cforce = np.abs(tr.coupler_force_n) if tr.coupler_force_n.size else np.zeros((len(t), 1))
    dt = np.diff(t)
    decel = -tr.accel_mps2
    jerk = np.diff(tr.accel_mps2, axis=0) / dt[:, None] if len(t) > 1 else np.zeros((1, tr.n_cars))
    out = {
        "band_kmh": band_kmh,
        "convergence_time_s": tc,
        "speed_rmse_kmh": [float(x) for x in rmse],
        "speed_rmse_after_convergence_kmh": [None if np.isnan(x) else float(x) for x in rmse_after],
        "speed_max_abs_error_kmh": [float(x) for x in np.max(np.abs(err_kmh), axis=0)],
        "speed_max_abs_error_after_convergence_kmh":
            float(np.max(np.abs(err_kmh[after]))) if after.any() else None,
        "final_speed_error_kmh": [float(x) for x in err_kmh[-1]],
        "max_abs_deflection_m": float(defl.max()),
        "max_abs_deflection_per_coupler_m": [float(x) for x in defl.max(axis=0)],
        "max_abs_coupler_force_n": float(cforce.max()),
        "peak_decel_mps2": float(decel.max()),
        "peak_accel_mps2": float(tr.accel_mps2.max()),
        "peak_abs_jerk_mps3": float(np.abs(jerk).max()) if jerk.size else 0.0,
        "max_brake_cmd_n": float(np.nanmax(tr.brake_cmd_n)) if np.isfinite(tr.brake_cmd_n).any() else None,
        "distance_m": float(np.mean(np.abs(tr.position_m[-1] - tr.position_m[0]))),
        "final_speed_kmh": [float(x) for x in tr.speed_mps[-1] * KMH],
        "stopped": bool(np.all(tr.speed_mps[-1] < 0.01)),
    }
    if tr.observer_accel_mps2 is not None and np.isfinite(tr.observer_accel_mps2).any():
        out["observer_max_abs_estimate_mps2"] = float(np.nanmax(np.abs(tr.observer_accel_mps2)))
    return out


def within_bound(tr: Trace, bound_m: float) -> bool:
    """True if every coupler deflection stayed within ±``bound_m`` throughout."""
    return bool(np.all(np.abs(tr.deflection_m) <= bound_m))
