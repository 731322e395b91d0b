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
    mass_kg: np.ndarray | None = None  # (n,) car masses, if known (observer error, brake decel)
    ref_position_m: np.ndarray | None = None  # (T,) reference position x*, if the run has one

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
    diverged_src = tr
    finite = np.all(np.isfinite(tr.speed_mps), axis=1) & np.all(np.isfinite(tr.position_m), axis=1)
    if not finite.all():  # a diverged run: judge the part that was still a number
        keep = np.nonzero(finite)[0]
        last = int(keep[-1]) + 1 if keep.size else 1
        tr = Trace(*(getattr(tr, f)[:last] if getattr(tr, f) is not None else None
                     for f in ("t_s", "ref_speed_mps", "position_m", "speed_mps", "accel_mps2", "brake_cmd_n",
                               "brake_applied_n", "deflection_m", "coupler_force_n", "observer_accel_mps2")),
                   ref_position_m=None if tr.ref_position_m is None else tr.ref_position_m[:last])
    t = tr.t_s
    err_kmh = (tr.speed_mps - tr.ref_speed_mps[:, None]) * KMH
    tc = convergence_time_s(t, err_kmh, band_kmh)
    after = t >= tc if tc is not None else np.zeros_like(t, dtype=bool)
    rmse = np.sqrt(np.mean(err_kmh ** 2, axis=0))
    rmse_after = np.sqrt(np.mean(err_kmh[after] ** 2, axis=0)) if after.any() else np.full(tr.n_cars, np.nan)
    defl = np.abs(tr.deflection_m) if tr.deflection_m.size else np.zeros((len(t), 1))
    cforce = np.abs(tr.coupler_force_n) if tr.coupler_force_n.size else np.zeros((len(t), 1))
    decel = -tr.accel_mps2
    jerk = jerk_mps3(t, tr.accel_mps2)
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
        "diverged_at_s": diverged_at_s(diverged_src),
        "max_brake_cmd_n": float(np.nanmax(tr.brake_cmd_n)) if np.isfinite(tr.brake_cmd_n).any() else None,
        "distance_m": float(np.mean(np.abs(tr.position_m[-1] - tr.position_m[0]))),
        "final_speed_kmh": [float(x) for x in tr.speed_mps[-1] * KMH],
        "stopped": bool(np.all(tr.speed_mps[-1] < 0.01)),
    }
    out["lead_vehicle"] = lead_vehicle_metrics(tr, rmse)
    if tr.observer_accel_mps2 is not None and np.isfinite(tr.observer_accel_mps2).any():
        out["observer_max_abs_estimate_mps2"] = float(np.nanmax(np.abs(tr.observer_accel_mps2)))
    out.update(distance_metrics(tr))
    if tr.mass_kg is not None:
        out.update(brake_effort_metrics(tr))
        if tr.observer_accel_mps2 is not None and np.isfinite(tr.observer_accel_mps2).any():
            out.update(observer_metrics(tr))
    return out


def lead_vehicle_metrics(tr: Trace, speed_rmse_kmh: np.ndarray) -> dict:
    """The lead vehicle's (vehicle 1: the locomotive of Li 2024's and Cai 2014's trains) figures, the
    ones those papers report: its speed RMSE (km/h; Li 2024 Table 2) and, when the run has a reference
    position x*, its position error x_1 − x* (:func:`position_error_m`) as mean and max |e| (m) over
    the run (Cai 2014 Fig. 7's window: the whole run; :func:`position_error_metrics`)."""
    out: dict = {"vehicle": 1, "speed_rmse_kmh": float(speed_rmse_kmh[0])}
    if tr.ref_position_m is not None and np.isfinite(tr.ref_position_m).any():
        e = position_error_metrics(tr.t_s, position_error_m(tr.position_m[:, 0], tr.ref_position_m))
        out.update({"position_error_mean_abs_m": e["mean_abs_m"], "position_error_max_abs_m": e["max_abs_m"],
                    "position_error_window_s": [float(tr.t_s[0]), float(tr.t_s[-1])]})
    return out


# ----------------------------------------------------------------------------- additional metrics
#: tolerance (m/s²) within which an observer estimate counts as converged to the actual value
OBSERVER_TOL_MPS2 = 0.01


def settling_time_s(t: np.ndarray, err: np.ndarray, tol: float, t_from: float = 0.0,
                    t_to: float = np.inf) -> float | None:
    """First time ``t_s >= t_from`` after which every column of ``|err|`` stays ``<= tol`` up to ``t_to``.

    ``err`` is (T,) or (T, k); NaN rows are ignored. Returns None if the window ends outside the band
    (or is empty).
    """
    e = np.abs(err.reshape(len(t), -1))
    win = (t >= t_from - 1e-12) & (t < t_to - 1e-12)
    idx = np.nonzero(win)[0]
    if idx.size == 0:
        return None
    with np.errstate(invalid="ignore"):
        outside = np.any(e[idx] > tol, axis=1)
    if not outside.any():
        return float(t[idx[0]])
    last = int(np.nonzero(outside)[0][-1])
    if last + 1 >= idx.size:
        return None
    return float(t[idx[last + 1]])


def convergence_time_in_window_s(tr: Trace, t_from: float, t_to: float = np.inf,
                                 band_kmh: float = DEFAULT_BAND_KMH) -> float | None:
    """Like :func:`convergence_time_s`, restricted to ``t_from <= t < t_to`` (absolute time, s)."""
    err_kmh = (tr.speed_mps - tr.ref_speed_mps[:, None]) * KMH
    return settling_time_s(tr.t_s, err_kmh, band_kmh, t_from, t_to)


def lumped_disturbance_mps2(tr: Trace) -> np.ndarray:
    """The actual lumped disturbance φ_i/m_i (couplers, resistance, grade, external forces; m/s²),
    (T, n), from the plant's trace: m_i a_i = −F_rail,i + φ_i, so φ_i/m_i = a_i + F_rail,i/m_i
    (cars moving forwards). Row k uses the acceleration and rail force of the period ending at
    tick k — the same period the observer's estimate at tick k describes. Row 0 is NaN."""
    if tr.mass_kg is None:
        raise ValueError("lumped_disturbance_mps2 needs Trace.mass_kg")
    phi = tr.accel_mps2 + tr.brake_applied_n / np.asarray(tr.mass_kg, dtype=float)[None, :]
    phi = phi.astype(float, copy=True)
    phi[0] = np.nan
    return phi


def observer_metrics(tr: Trace, tol_mps2: float = OBSERVER_TOL_MPS2, settle_s: float = 0.02) -> dict:
    """Estimation error of the ECUs' disturbance observers against :func:`lumped_disturbance_mps2`."""
    phi = lumped_disturbance_mps2(tr)
    assert tr.observer_accel_mps2 is not None
    err = tr.observer_accel_mps2 - phi
    t = tr.t_s
    after = t >= settle_s - 1e-12
    import warnings

    with np.errstate(invalid="ignore"), warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)  # all-NaN columns (no observer) give NaN, reported as None
        rms = np.sqrt(np.nanmean(err[1:] ** 2, axis=0))
        mx = np.nanmax(np.abs(err[after]), axis=0) if after.any() else np.full(tr.n_cars, np.nan)
    per_car_settle = [settling_time_s(t, err[:, i], tol_mps2, 0.0, _first_quiet_end(t, err[:, i], tol_mps2))
                      for i in range(tr.n_cars)]
    return {
        "observer_tol_mps2": tol_mps2,
        "observer_error_rms_mps2": [None if np.isnan(x) else float(x) for x in rms],
        f"observer_error_max_after_{int(round(settle_s * 1000))}ms_mps2":
            [None if np.isnan(x) else float(x) for x in mx],
        "observer_settling_time_s": per_car_settle,
    }


def _first_quiet_end(t: np.ndarray, err: np.ndarray, tol: float, hold_s: float = 0.5) -> float:
    """End of the first stretch of ``hold_s`` seconds inside the band (the initial convergence, before
    any later event drives the estimate out again); inf if the run has none."""
    with np.errstate(invalid="ignore"):
        inside = np.abs(err) <= tol
    inside[np.isnan(err)] = True
    start = None
    for k in range(len(t)):
        if inside[k]:
            if start is None:
                start = k
            if t[k] - t[start] >= hold_s:
                return float(t[k])
        else:
            start = None
    return float(np.inf)


def brake_effort_metrics(tr: Trace) -> dict:
    """Braking effort per unit mass: what the actuator was asked for and what reached the rail."""
    m = np.asarray(tr.mass_kg, dtype=float)[None, :]
    cmd = tr.brake_cmd_n / m
    app = tr.brake_applied_n / m
    return {
        "peak_brake_cmd_decel_mps2": float(np.nanmax(cmd)) if np.isfinite(cmd).any() else None,
        "peak_brake_applied_decel_mps2": float(np.nanmax(app)) if np.isfinite(app).any() else None,
        "peak_traction_cmd_accel_mps2": float(max(0.0, -np.nanmin(cmd))) if np.isfinite(cmd).any() else None,
    }


def distance_metrics(tr: Trace) -> dict:
    """Distance run against the reference's over the same window, and the stopping distance."""
    t = tr.t_s
    ref = float(np.sum(0.5 * (tr.ref_speed_mps[1:] + tr.ref_speed_mps[:-1]) * np.diff(t))) if len(t) > 1 else 0.0
    d = np.abs(tr.position_m - tr.position_m[0])
    dist = float(np.mean(d[-1]))
    stopped = np.all(tr.speed_mps < 0.01, axis=1)
    stop = None
    if stopped.any():
        k = int(np.argmax(stopped))
        stop = float(np.mean(d[k]))
    return {
        "reference_distance_m": ref,
        "distance_excess_m": dist - ref,
        "stopping_distance_m": stop,
        "stopping_time_s": float(t[int(np.argmax(stopped))]) if stopped.any() else None,
    }


def within_bound(tr: Trace, bound_m: float) -> bool:
    """True if every coupler deflection stayed within ±``bound_m`` throughout."""
    return bool(np.all(np.abs(tr.deflection_m) <= bound_m))


# ----------------------------------------------------------------------------- derivatives, divergence
#: a state beyond these is a diverged integration, not a train (m/s; m of coupler deflection)
DIVERGED_SPEED_MPS = 1e3
DIVERGED_DEFLECTION_M = 1e2


def jerk_mps3(t_s: np.ndarray, accel_mps2: np.ndarray) -> np.ndarray:
    """Jerk (m/s³) between consecutive trace rows, (T-2, n) for (T, n) accelerations.

    Row 0 of a plant trace is the initial state, recorded before any period was integrated, so its
    acceleration is 0 by construction (not a measurement); differencing it against row 1 would report
    a(t_1)/dt of jerk that no car ever had. The jerk therefore starts between rows 1 and 2.
    """
    a = np.asarray(accel_mps2, dtype=float)
    a = a.reshape(len(t_s), -1)
    if len(t_s) < 3:
        return np.zeros((0, a.shape[1]))
    return np.diff(a[1:], axis=0) / np.diff(np.asarray(t_s, dtype=float)[1:])[:, None]


def diverged_at_s(tr: Trace) -> float | None:
    """Time of the first trace row whose state is not finite or beyond any train (|v| >
    :data:`DIVERGED_SPEED_MPS`, |Δl| > :data:`DIVERGED_DEFLECTION_M`); None if the run never diverged."""
    with np.errstate(invalid="ignore"):
        bad = ~(np.all(np.abs(tr.speed_mps) <= DIVERGED_SPEED_MPS, axis=1)
                & np.all(np.isfinite(tr.position_m), axis=1))
        if tr.deflection_m.size:
            bad |= ~np.all(np.abs(tr.deflection_m) <= DIVERGED_DEFLECTION_M, axis=1)
    k = np.nonzero(bad)[0]
    return float(tr.t_s[k[0]]) if k.size else None


# ----------------------------------------------------------------------------- plausibility
#: a metro's brake (EN 13452-1 / typical metro specifications): service brake up to 1.0–1.2 m/s²,
#: emergency brake 1.3–1.5 m/s² (MODELS.md section 1); jerk 1–1.5 m/s³ for passenger comfort in
#: service braking (emergency braking is not jerk-limited). The upper ends are the limits judged.
METRO_SERVICE_DECEL_MPS2 = 1.2
METRO_EMERGENCY_DECEL_MPS2 = 1.5
METRO_SERVICE_JERK_MPS3 = 1.5
#: a metro's traction: up to about 1.0–1.3 m/s²
METRO_TRACTION_ACCEL_MPS2 = 1.3


def plausibility(tr: Trace, t_from_s: float = 0.0) -> dict:
    """What the cars actually did (their accelerations in the trace: brake, traction, couplers,
    resistance, disturbances together) against a metro's limits, from ``t_from_s`` on.

    Returns the peak deceleration, acceleration and |jerk| over every car (jerk per
    :func:`jerk_mps3`), the car and time of each, and ``verdict``: ``"service"`` (decel ≤
    :data:`METRO_SERVICE_DECEL_MPS2`, jerk ≤ :data:`METRO_SERVICE_JERK_MPS3`, accel ≤
    :data:`METRO_TRACTION_ACCEL_MPS2`), ``"emergency"`` (decel ≤ :data:`METRO_EMERGENCY_DECEL_MPS2`
    and accel within traction, jerk unlimited) or ``"beyond"`` (no metro brake does this).
    """
    t = np.asarray(tr.t_s, dtype=float)
    a = np.asarray(tr.accel_mps2, dtype=float)
    rows = np.arange(len(t)) >= 1  # row 0: no period integrated yet (see jerk_mps3)
    rows &= t >= t_from_s - 1e-12
    rows &= np.all(np.isfinite(a), axis=1)
    if not rows.any():
        return {"verdict": None}
    aw = np.where(rows[:, None], a, np.nan)
    kd = np.unravel_index(int(np.nanargmin(aw)), aw.shape)
    ka = np.unravel_index(int(np.nanargmax(aw)), aw.shape)
    j = jerk_mps3(t, a)
    jt = t[2:]
    jw = np.where((rows[2:] & rows[1:-1])[:, None], np.abs(j), np.nan) if j.size else j
    if j.size and np.isfinite(jw).any():
        kj = np.unravel_index(int(np.nanargmax(jw)), jw.shape)
        jerk, jerk_car, jerk_t = float(jw[kj]), int(kj[1]) + 1, float(jt[kj[0]])
    else:
        jerk, jerk_car, jerk_t = 0.0, None, None
    decel, accel = float(max(0.0, -aw[kd])), float(max(0.0, aw[ka]))
    if decel <= METRO_SERVICE_DECEL_MPS2 and jerk <= METRO_SERVICE_JERK_MPS3 and accel <= METRO_TRACTION_ACCEL_MPS2:
        verdict = "service"
    elif decel <= METRO_EMERGENCY_DECEL_MPS2 and accel <= METRO_TRACTION_ACCEL_MPS2:
        verdict = "emergency"
    else:
        verdict = "beyond"
    return {"peak_decel_mps2": decel, "peak_decel_car": int(kd[1]) + 1, "peak_decel_t_s": float(t[kd[0]]),
            "peak_accel_mps2": accel, "peak_accel_car": int(ka[1]) + 1, "peak_accel_t_s": float(t[ka[0]]),
            "peak_abs_jerk_mps3": jerk, "peak_jerk_car": jerk_car, "peak_jerk_t_s": jerk_t, "verdict": verdict}


# ----------------------------------------------------------------------------- tracking errors
def rmse(err: np.ndarray) -> float:
    """Root mean square of ``err`` (any unit; NaN ignored)."""
    e = np.asarray(err, dtype=float)
    return float(np.sqrt(np.nanmean(e * e)))


def error_band(err: np.ndarray) -> tuple[float, float]:
    """(min, max) of a signed error (NaN ignored)."""
    e = np.asarray(err, dtype=float)
    return float(np.nanmin(e)), float(np.nanmax(e))


def within_band(err: np.ndarray, lo: float, hi: float) -> bool:
    """True if every value of ``err`` lies in [lo, hi]."""
    e = np.asarray(err, dtype=float)
    return bool(np.all((e >= lo) & (e <= hi)))


def position_error_m(position_m: np.ndarray, ref_position_m: np.ndarray) -> np.ndarray:
    """The position error e = x − x* (m, + ahead of the reference), shape of ``position_m``: the
    tracking error Cai 2014 plots in Fig. 7 (the train's position against the reference's)."""
    return np.asarray(position_m, dtype=float) - np.asarray(ref_position_m, dtype=float)


def position_error_metrics(t_s: np.ndarray, pos_err_m: np.ndarray, t0_s: float = 0.0,
                           t1_s: float = np.inf) -> dict:
    """Mean and max |e| (m) of a position error (T,) over ``t0_s`` ≤ t ≤ ``t1_s`` (s)."""
    t = np.asarray(t_s)
    e = np.abs(np.asarray(pos_err_m, dtype=float)[(t >= t0_s) & (t <= t1_s)])
    return {"mean_abs_m": float(np.mean(e)), "max_abs_m": float(np.max(e))}


def tracking_errors(t_s: np.ndarray, pos_err_m: np.ndarray, speed_err_mps: np.ndarray, t0_s: float = 0.0) -> dict:
    """Mean and max |position error| (m; :func:`position_error_metrics`), mean and max |speed error|
    (m/s) and the position error's RMS for t ≥ ``t0_s``."""
    sel = np.asarray(t_s) >= t0_s
    e, de = np.abs(np.asarray(pos_err_m)[sel]), np.abs(np.asarray(speed_err_mps)[sel])
    pe = position_error_metrics(t_s, pos_err_m, t0_s)
    return {"mean_abs_pos_err_m": pe["mean_abs_m"], "max_abs_pos_err_m": pe["max_abs_m"],
            "mean_abs_speed_err_mps": float(np.mean(de)), "max_abs_speed_err_mps": float(np.max(de)),
            "rms_pos_err_m": rmse(e)}


def relative_estimation_error(estimate: np.ndarray, actual: np.ndarray) -> float:
    """RMS(estimate − actual) / RMS(actual): an observer's error relative to what it estimates."""
    est, act = np.asarray(estimate, dtype=float), np.asarray(actual, dtype=float)
    return rmse(est - act) / rmse(act)


def relative_spread(values: np.ndarray) -> np.ndarray:
    """Per row of (T, k) ``values``: (max − min) / max(|mean|, 1) — e.g. how unequal axle forces are."""
    v = np.asarray(values, dtype=float)
    return (v.max(axis=1) - v.min(axis=1)) / np.maximum(np.abs(v.mean(axis=1)), 1.0)


# ----------------------------------------------------------------------------- step-size convergence
#: a metric counts as converged when halving the step changes it by less than this (relative)
STEP_TOL = 0.01


def step_convergence(rows: list[tuple[float, dict]], tol: float = STEP_TOL) -> list[dict]:
    """Step-size table: ``rows`` = [(step_s, {metric: value}), ...] from the coarsest step down,
    each step half (or a fraction) of the one before. Returns one dict per row with the values, the
    relative change of each metric against the previous (coarser) row and ``converged`` (every
    metric changed by < ``tol``; None on the first row). A metric that is None (e.g. "never") on both
    rows counts as unchanged, on one of them as changed."""
    out: list[dict] = []
    prev: dict | None = None
    for step, vals in rows:
        ch: dict[str, float | None] = {}
        ok: bool | None = None
        if prev is not None:
            ok = True
            for k, v in vals.items():
                p = prev.get(k)
                if v is None and p is None:
                    ch[k] = 0.0
                elif v is None or p is None or not (np.isfinite(v) and np.isfinite(p)):
                    ch[k], ok = None, False
                else:
                    c = abs(v - p) / max(abs(v), abs(p), 1e-300) if (v or p) else 0.0
                    ch[k] = c
                    ok = ok and c < tol
        out.append({"step_s": step, "values": dict(vals), "change": ch, "converged": ok})
        prev = vals
    return out


def first_converged_step(table: list[dict]) -> float | None:
    """The coarsest step of a :func:`step_convergence` table whose halving changed no metric by the
    tolerance (the step before the first converged row); None if no row converged."""
    for i, row in enumerate(table):
        if row["converged"]:
            return table[i - 1]["step_s"]
    return None


# ----------------------------------------------------------------------------- wheel slide
#: a car's wheels slide while any of its axles' slip |λ| exceeds this: far past the slip curve's peak
#: (|λ| ≈ 0.16 for Cai's curve), where the wheel runs away towards locking (the ``braking`` summary's
#: "sliding" uses the same 0.5)
SLIDE_SLIP = 0.5


def slide_episodes(t_s: np.ndarray, slip: np.ndarray, threshold: float = SLIDE_SLIP) -> dict:
    """Wheel-slide episodes of one car. ``slip`` (T, n_axles) or (T,): the axles' slip λ (< 0 braking);
    the car slides in a sample when any axle has |λ| > ``threshold``; an episode is a maximal run of
    such samples. Each sample stands for the time to the next (the last for the median step).
    Returns ``episodes`` (count), ``duration_s`` (total) and ``longest_s``."""
    t = np.asarray(t_s, dtype=float)
    lam = np.abs(np.asarray(slip, dtype=float).reshape(t.size, -1))
    on = np.nanmax(lam, axis=1) > threshold if t.size else np.zeros(0, bool)
    if not on.any():
        return {"episodes": 0, "duration_s": 0.0, "longest_s": 0.0}
    dt = np.diff(t, append=t[-1] + (float(np.median(np.diff(t))) if t.size > 1 else 0.0))
    edges = np.diff(np.concatenate(([0], on.astype(np.int8), [0])))
    starts, ends = np.flatnonzero(edges == 1), np.flatnonzero(edges == -1)
    dur = np.array([dt[a:b].sum() for a, b in zip(starts, ends)])
    return {"episodes": int(starts.size), "duration_s": float(dur.sum()), "longest_s": float(dur.max())}
