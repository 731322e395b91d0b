"""The verdict of a run: does the result mean anything? (``status`` says only whether it ran.)

One place judges the physics and the bus of a finished run, from its trace and statistics:

========================  ==========================================================================
verdict (worst first)     when
========================  ==========================================================================
``diverged``              the plant state became non-finite, a coupler left its physical range
                          (past the force peak of a softening coupler, |Δl| = 1/sqrt(3|ε|), or
                          compressed by more than the car spacing) or a car's speed became
                          impossible for the scenario (|v| > 1.5 x the highest initial/reference
                          speed + 20 km/h). ``diverged_at_s`` says when. Exit status 1.
``unsafe``                a safety bound of the scenario was exceeded: |Δl| beyond
                          ``safety.max_abs_deflection_m`` (default: the controller's
                          ``theta_lower_m``/``theta_upper_m`` if it has them) or a speed above
                          ``safety.max_speed_kmh``.
``overloaded``            under ``bus.timing: ideal``, the traffic needs more than the bus can carry
                          (mean load > 100 %): the results assume a bus that cannot exist.
``late``                  realtime: periods in which a command or a peer's state came too late
                          (deadline misses; a stopped or starved node shows here).
``ok``                    none of the above.
``unknown``               no trace to judge (the run failed before its first ticks).
========================  ==========================================================================

Every finding is listed in ``findings`` (kind, message, figures), so a run can be both unsafe
and overloaded; ``verdict`` is the worst one.
"""
from __future__ import annotations

import math
import warnings
from typing import Any

import numpy as np

from canbrake.analysis.metrics import Trace

#: verdicts, worst first
VERDICTS = ("diverged", "unsafe", "overloaded", "late", "ok", "unknown")

KMH = 3.6  # km/h per m/s

#: a speed above this multiple of the scenario's highest initial/reference speed (+ the margin
#: below) cannot come out of a braking scenario: the loop has diverged
SPEED_FACTOR = 1.5
SPEED_MARGIN_KMH = 20.0


def fmt_quantity(x: float | None, unit: str = "", digits: int = 3) -> str:
    """A magnitude for people: 3 significant digits, scientific beyond 1e5 or below 1e-3, ``inf``
    and ``nan`` as such (never a 220-digit number)."""
    if x is None:
        return "n/a"
    x = float(x)
    if not math.isfinite(x):
        s = "nan" if math.isnan(x) else ("inf" if x > 0 else "-inf")
    elif x != 0 and (abs(x) >= 1e5 or abs(x) < 1e-3):
        s = f"{x:.{digits - 1}e}"
    elif abs(x) >= 10 ** digits:
        s = f"{x:.0f}"
    else:
        s = f"{x:.{digits}g}"
    return f"{s} {unit}".rstrip()


def coupler_limits_m(scn: Any) -> np.ndarray:
    """Physical |Δl| range of each coupler (m), shape (n-1,): the car spacing (cars would overlap)
    and, for a softening coupler (ε < 0), the deflection of its force peak 1/sqrt(3|ε|) (beyond it
    the model's stiffness is negative: no coupler behaves so)."""
    n = scn.n_cars
    if n < 2:
        return np.zeros(0)
    from canbrake.arrays import per_car

    c = getattr(scn.consist, "coupler", None)
    if c is None or not hasattr(c, "epsilon_per_m2") or getattr(scn.consist, "rigid", False):
        # another train model (or rigid couplers, never deflected): its plant judges its couplers
        return np.full(n - 1, np.inf)
    x0 = scn.initial_position_m()
    spacing = np.abs(per_car(c.spacing_m, n - 1, "spacing") if c.spacing_m is not None else x0[:-1] - x0[1:])
    eps = per_car(c.epsilon_per_m2, n - 1, "epsilon")
    with np.errstate(divide="ignore"):
        peak = np.where(eps < 0, 1.0 / np.sqrt(3.0 * np.abs(eps)), np.inf)
    lim = np.minimum(np.where(spacing > 0, spacing, np.inf), peak)
    return lim


def plausible_speed_mps(scn: Any, ref_speed_mps: np.ndarray | None = None) -> float:
    """Highest |v| (m/s) a car can reach in this scenario without the loop having diverged:
    1.5 × the highest of the initial speeds and the reference v* (+ 20 km/h). ``ref_speed_mps``:
    the run's v* trace (m/s, shape (T,)), which covers accelerating ramps and table references;
    without it, the ramp's start and end speeds."""
    v0 = float(np.max(np.abs(scn.initial_speed_mps()))) if scn.n_cars else 0.0
    r = scn.reference
    vref = max(r.speed_mps, float(getattr(r, "target_kmh", 0.0) or 0.0) / KMH)
    if ref_speed_mps is not None and np.size(ref_speed_mps):
        with np.errstate(all="ignore"):
            finite = np.asarray(ref_speed_mps, dtype=float)
            finite = finite[np.isfinite(finite)]
        if finite.size:
            vref = max(vref, float(np.max(np.abs(finite))))
    return SPEED_FACTOR * max(v0, vref) + SPEED_MARGIN_KMH / KMH


def deflection_bound_m(scn: Any) -> float | None:
    """The scenario's coupler deflection bound (m), whatever controller runs: ``safety.max_abs_deflection_m``,
    else the tightest barrier bounds ``theta_lower_m``/``theta_upper_m`` among the controllers'
    parameters (top level and per ECU), else None. (A controller switched by name leaves its
    predecessor's bounds in ``safety.max_abs_deflection_m``: :func:`canbrake.scenario.resolve`.)
    The verdict judges against it and the deflection plot draws it."""
    b = getattr(scn.safety, "max_abs_deflection_m", None)
    if b is not None:
        return float(b)
    bounds = []
    for c in [scn.controller, *(e.controller for e in getattr(scn, "ecus", []) if e.controller is not None)]:
        lo, hi = c.params.get("theta_lower_m"), c.params.get("theta_upper_m")
        if isinstance(lo, (int, float)) and isinstance(hi, (int, float)):
            bounds.append(float(min(abs(lo), abs(hi))))
    return min(bounds) if bounds else None


def _first_bad_row(tr: Trace, coupler_lim: np.ndarray, vmax: float) -> tuple[int | None, str]:
    """Index of the first row whose state is non-finite or out of range, and why."""
    with np.errstate(all="ignore"), warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)
        checks: list[tuple[np.ndarray, str]] = []
        state = [tr.speed_mps, tr.position_m]
        if tr.deflection_m.size:
            state += [tr.deflection_m, tr.coupler_force_n]
        nonfinite = np.zeros(len(tr.t_s), dtype=bool)
        for a in state:
            nonfinite |= ~np.all(np.isfinite(a), axis=1)
        checks.append((nonfinite, "the train state is not finite"))
        if tr.deflection_m.size and coupler_lim.size:
            over = np.abs(tr.deflection_m) > coupler_lim[None, :]
            checks.append((np.any(over, axis=1), "a coupler left its physical range"))
        checks.append((np.any(np.abs(tr.speed_mps) > vmax, axis=1), "a car's speed is impossible for the scenario"))
    best: tuple[int | None, str] = (None, "")
    for mask, why in checks:
        idx = np.flatnonzero(mask)
        if idx.size and (best[0] is None or idx[0] < best[0]):
            best = (int(idx[0]), why)
    return best


def judge(scn: Any, summary: dict[str, Any], trace: Trace | None,
          plant_stats: dict[str, Any] | None = None) -> dict[str, Any]:
    """The verdict of a run: ``{"verdict": one of VERDICTS, "findings": [...], "diverged_at_s": ...}``.

    ``summary``: the run's summary so far (``bus_load``, ``deadline_misses``, ``ticks``);
    ``trace``: the plant's trace (None if there is none); ``plant_stats``: plant_stats.json.
    """
    findings: list[dict[str, Any]] = []
    plant_stats = plant_stats or {}
    diverged_at: float | None = None
    if trace is not None and len(trace.t_s):
        lim = coupler_limits_m(scn)
        vmax = plausible_speed_mps(scn, trace.ref_speed_mps)
        k, why = _first_bad_row(trace, lim, vmax)
        if k is not None:
            diverged_at = float(trace.t_s[k])
            with np.errstate(all="ignore"):
                d = np.abs(trace.deflection_m[: k + 1])
                dmax = float(np.nanmax(d)) if d.size and np.isfinite(d).any() else None
                vpk = np.abs(trace.speed_mps[: k + 1])
                vpeak = float(np.nanmax(vpk)) if np.isfinite(vpk).any() else None
            findings.append({"kind": "diverged", "at_s": diverged_at, "reason": why,
                             "max_abs_deflection_m": dmax, "coupler_limit_m": float(lim.min()) if lim.size else None,
                             "max_abs_speed_kmh": None if vpeak is None else vpeak * KMH,
                             "plausible_speed_kmh": vmax * KMH,
                             "message": f"at t = {fmt_quantity(diverged_at, 's')}: {why} "
                                        f"(max |deflection| {fmt_quantity(None if dmax is None else dmax * 100, 'cm')}, "
                                        f"physical limit {fmt_quantity(float(lim.min()) * 100 if lim.size else None, 'cm')}; "
                                        f"max |speed| {fmt_quantity(None if vpeak is None else vpeak * KMH, 'km/h')})"})
    if diverged_at is None and plant_stats.get("status") == "diverged":
        extra = plant_stats.get("extra") or {}
        diverged_at = float(extra.get("diverged_at_s", 0.0))
        findings.append({"kind": "diverged", "at_s": diverged_at, "reason": str(extra.get("message", "")),
                         "message": f"at t = {fmt_quantity(diverged_at, 's')}: the plant stopped: "
                                    f"{str(extra.get('message', '')).splitlines()[0] if extra.get('message') else ''}"})
    if trace is not None and len(trace.t_s):
        end = len(trace.t_s)
        if diverged_at is not None:
            end = int(np.searchsorted(trace.t_s, diverged_at))  # judge safety on the part before
        bound = deflection_bound_m(scn)
        if bound is not None and trace.deflection_m.size and end > 0:
            with np.errstate(all="ignore"):
                d = np.abs(trace.deflection_m[:end])
                dmax = float(np.nanmax(d)) if np.isfinite(d).any() else 0.0
            if dmax > bound:
                k = int(np.argmax(np.any(d > bound, axis=1)))
                findings.append({"kind": "unsafe", "quantity": "deflection", "bound_m": bound, "max_abs_deflection_m": dmax,
                                 "first_s": float(trace.t_s[k]),
                                 "message": f"coupler deflection {fmt_quantity(dmax * 100, 'cm')} exceeds the bound "
                                            f"±{fmt_quantity(bound * 100, 'cm')} (first at t = {fmt_quantity(float(trace.t_s[k]), 's')})"})
        vlim = getattr(scn.safety, "max_speed_kmh", None)
        if vlim is not None and end > 0:
            with np.errstate(all="ignore"):
                v = np.abs(trace.speed_mps[:end]) * KMH
                vpk = float(np.nanmax(v)) if np.isfinite(v).any() else 0.0
            if vpk > vlim:
                k = int(np.argmax(np.any(v > vlim, axis=1)))
                findings.append({"kind": "unsafe", "quantity": "speed", "bound_kmh": float(vlim), "max_speed_kmh": vpk,
                                 "first_s": float(trace.t_s[k]),
                                 "message": f"speed {fmt_quantity(vpk, 'km/h')} exceeds safety.max_speed_kmh "
                                            f"{fmt_quantity(float(vlim), 'km/h')} (first at t = {fmt_quantity(float(trace.t_s[k]), 's')})"})
    bl = summary.get("bus_load") or {}
    mean = bl.get("bus_load_mean")
    if scn.bus.timing == "ideal" and mean is not None and mean > 1.0:
        findings.append({"kind": "overloaded", "bus_load_mean": mean, "bus_load_peak": bl.get("bus_load_peak"),
                         "bitrate_bps": bl.get("bitrate_bps"),
                         "message": f"bus overloaded: mean load {fmt_quantity(mean * 100, '%')} at "
                                    f"{fmt_quantity((bl.get('bitrate_bps') or 0) / 1000, 'kbit/s')} under ideal timing "
                                    f"(the results assume a bus that cannot exist; try bus.timing=model, a longer "
                                    f"control period or a higher bit rate)"})
    dm = summary.get("deadline_misses") or {}
    ticks = int(summary.get("ticks") or 0)
    plant_miss, ecu_miss = int(dm.get("plant") or 0), int(dm.get("ecus") or 0)
    if plant_miss or ecu_miss:
        rate = plant_miss / ticks if ticks else None
        cars = dm.get("missed_commands_per_car")
        worst = ""
        if isinstance(cars, list) and cars and max(cars) > 0:
            c = int(np.argmax(cars)) + 1
            worst = f"; most missed commands: car {c} ({cars[c - 1]} of {ticks} periods)"
        findings.append({"kind": "late", "plant_deadline_misses": plant_miss, "ecu_deadline_misses": ecu_miss,
                         "plant_miss_rate": rate,
                         "message": f"deadline misses: plant {plant_miss}"
                                    + (f" of {ticks} periods ({fmt_quantity(rate * 100, '%')})" if rate is not None else "")
                                    + f", ECUs {ecu_miss}{worst}"})
    kinds = {f["kind"] for f in findings}
    verdict = next((v for v in VERDICTS if v in kinds), "ok")
    if verdict == "ok" and (trace is None or len(trace.t_s) < 2):
        verdict = "unknown"  # nothing was simulated that could be judged
    return {"verdict": verdict, "findings": findings, "diverged_at_s": diverged_at}
