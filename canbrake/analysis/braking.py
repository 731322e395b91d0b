"""Metrics of a stop: the jerk a passenger feels as the train comes to rest, the deceleration left
at standstill, the wheel slip. Arrays in, floats out (SI).

Stop jerk. A step in acceleration is an infinite jerk at any sampling rate, and a train always ends
its stop with one: the running resistance's constant term (Davis c0, ~0.03 m/s² for a metro car)
and any brake force left act until the car stands and then vanish. Ride-comfort evaluations
therefore take the jerk of a low-pass filtered acceleration. We use a moving mean over
``window_s`` = 0.1 s (our choice, first zero at 10 Hz: above the car body's longitudinal modes,
below the 100 Hz of a 10 ms trace) and report the largest |d/dt| of it over the final approach, from
the last time the car was faster than ``approach_mps`` until ``after_s`` after it stood still.
"""
from __future__ import annotations

import numpy as np

#: comfort limit for the stop jerk (m/s³): 1–1.5 m/s³ is the usual range for metro service braking
STOP_JERK_LIMIT_MPS3 = 1.5


def smoothed_accel(t_s: np.ndarray, accel: np.ndarray, window_s: float = 0.1) -> tuple[np.ndarray, np.ndarray]:
    """Moving mean of ``accel`` (T,) or (T, n) over ``window_s``; returns (times of the window
    centres, smoothed acceleration). A uniform time step is assumed."""
    a = np.asarray(accel, dtype=float)
    a2 = a.reshape(a.shape[0], -1)
    dt = float(np.median(np.diff(t_s)))
    w = max(1, int(round(window_s / dt)))
    c = np.cumsum(np.vstack([np.zeros((1, a2.shape[1])), a2]), axis=0)
    mean = (c[w:] - c[:-w]) / w
    tc = np.asarray(t_s, dtype=float)[: mean.shape[0]] + 0.5 * (w - 1) * dt
    return tc, mean.reshape((mean.shape[0],) + a.shape[1:])


def stop_jerk_mps3(t_s: np.ndarray, speed_mps: np.ndarray, accel_mps2: np.ndarray, *, window_s: float = 0.1,
                   approach_mps: float = 3.0, after_s: float = 1.0) -> float:
    """Largest |jerk| (m/s³) of the smoothed acceleration of any car over its final approach to
    standstill (see the module docstring); NaN when no car stops. Arrays (T,) or (T, n)."""
    t = np.asarray(t_s, dtype=float)
    v = np.abs(np.asarray(speed_mps, dtype=float)).reshape(t.size, -1)
    tc, am = smoothed_accel(t, np.asarray(accel_mps2, dtype=float).reshape(t.size, -1), window_s)
    jerk = np.diff(am, axis=0) / np.diff(tc)[:, None]
    tj = 0.5 * (tc[1:] + tc[:-1])
    worst = float("nan")
    for i in range(v.shape[1]):
        still = np.flatnonzero(v[:, i] <= 1e-6)
        if still.size == 0:
            continue
        t_stop = t[still[0]]
        fast = np.flatnonzero((v[:, i] > approach_mps) & (t < t_stop))
        t_from = t[fast[-1]] if fast.size else t[0]
        sel = (tj >= t_from) & (tj <= t_stop + after_s)
        if sel.any():
            j = float(np.max(np.abs(jerk[sel, i])))
            worst = j if not worst == worst else max(worst, j)
    return worst


def decel_at_standstill_mps2(t_s: np.ndarray, speed_mps: np.ndarray, accel_mps2: np.ndarray) -> float:
    """Largest deceleration (m/s²) any car had in the sample before it stood still; NaN if none stops."""
    v = np.abs(np.asarray(speed_mps, dtype=float)).reshape(len(t_s), -1)
    a = np.asarray(accel_mps2, dtype=float).reshape(len(t_s), -1)
    out = float("nan")
    for i in range(v.shape[1]):
        still = np.flatnonzero(v[:, i] <= 1e-6)
        if still.size and still[0] >= 2:
            d = float(-a[still[0] - 1, i])
            out = d if not out == out else max(out, d)
    return out


def braking_summary(t_s: np.ndarray, speed_mps: np.ndarray, accel_mps2: np.ndarray,
                    columns: dict[str, np.ndarray]) -> dict[str, object]:
    """The ``braking`` section of a run's summary (coupled trains with brake equipment: blending, easing, wheels, WSP): stop jerk (m/s³,
    against :data:`STOP_JERK_LIMIT_MPS3`), deceleration left at standstill (m/s²), and per car, when
    the trace has wheels (``axle<j>_slip_c<i>``), the worst slip (λ < 0 braking), the time any axle
    slid past |λ| = 0.5 (s) and the time its dump valves were open more than half (s)."""
    def clean(x: float) -> float | None:
        return None if not x == x else float(x)

    sj = stop_jerk_mps3(t_s, speed_mps, accel_mps2)
    out: dict[str, object] = {"stop_jerk_mps3": clean(sj), "stop_jerk_limit_mps3": STOP_JERK_LIMIT_MPS3,
                              "stop_jerk_within_limit": None if not sj == sj else bool(sj <= STOP_JERK_LIMIT_MPS3),
                              "decel_at_standstill_mps2": clean(decel_at_standstill_mps2(t_s, speed_mps, accel_mps2))}
    n = speed_mps.shape[1] if np.ndim(speed_mps) == 2 else 1
    dt = float(np.median(np.diff(t_s))) if len(t_s) > 1 else 0.0
    slips = []
    for i in range(1, n + 1):
        cols = [np.asarray(v, dtype=float) for k, v in columns.items()
                if k.startswith("axle") and k.endswith(f"_slip_c{i}")]
        if not cols:
            continue
        lam = np.vstack(cols)
        valve = np.asarray(columns.get(f"wsp_valve_c{i}", np.zeros(lam.shape[1])), dtype=float)
        slips.append({"car": i, "min_slip": float(np.nanmin(lam)),
                      "sliding_s": float(np.sum(np.nanmax(np.abs(lam), axis=0) > 0.5) * dt),
                      "wsp_venting_s": float(np.sum(valve > 0.5) * dt)})
    if slips:
        out["wheels"] = slips
    return out
