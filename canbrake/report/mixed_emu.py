"""The 8-car EMU on a low-adhesion section: the section "8-car EMU on a low-adhesion section" of
``docs/mixed-trains.md``, from runs (``canbrake report mixed_emu``).

``scenarios/emu8_low_adhesion.yaml`` (Tc-M-M-T-T-M-M-Tc, one chen2023_compensated ECU per car, EP
brake with lag and jerk limit, ED/friction blending, four wheelsets per car with adhesion per axle)
brakes from 100 km/h at 0.83 m/s²; ``generate()`` runs it on dry rail, through the low-adhesion
window without and with wheel-slide protection, reduces each run's ``signals.csv`` with
:func:`reduce_run` and repeats every run at half the control (= integration) step.
"""
from __future__ import annotations

import json
import math
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Callable, Sequence

import numpy as np

from canbrake.report.pool import map_tasks

DEFAULT_OUT = "docs"
DOC = "mixed-trains.md"
SCENARIO = "emu8_low_adhesion.yaml"
BEGIN, END = "<!-- begin: mixed-emu (canbrake/report/mixed_emu.py) -->", "<!-- end: mixed-emu -->"
REPORT_VERSION = 4
#: the integration step check: every run again with the control period (= plant step) divided by this
STEP_DIVISOR = 2
#: standstill: the lead car's speed at or below this (m/s)
STILL_MPS = 0.01


@dataclass(frozen=True)
class Case:
    """One run of the scenario: a profile (None: the scenario as written) and ``--set`` overrides."""

    key: str
    label: str
    profile: str | None
    sets: tuple[tuple[str, Any], ...] = ()


CASES = (Case("dry", "dry rail, no WSP", "dry"),
         Case("low", "low adhesion, no WSP", None),
         Case("low-wsp", "low adhesion, WSP", "wsp"),
         Case("li-env", "low adhesion, WSP, motor cars' ED brake as Li's envelope", "li_envelope"))

HEADS = ("stopping_distance_m", "max_tension_n", "max_compression_n", "max_decel_mps2", "max_jerk_mps3",
         "slide_s")
HEAD_NAMES = {"stopping_distance_m": "stopping distance", "max_tension_n": "peak tension",
              "max_compression_n": "peak compression", "max_decel_mps2": "max deceleration",
              "max_jerk_mps3": "max jerk", "slide_s": "slide time"}


def scenario_path(scen_dir: Path | None = None) -> Path:
    from canbrake.builtin import builtin_dir

    return (scen_dir or builtin_dir()) / SCENARIO


def half_step(c: Case) -> Case:
    """The same run with the plant's integration step halved (``plant.substeps`` x ``STEP_DIVISOR``;
    the ECUs' control period, and so the controllers, unchanged): the numerical convergence check."""
    return Case(f"{c.key}-sub{STEP_DIVISOR}", f"{c.label}, integration step / {STEP_DIVISOR}", c.profile,
                c.sets + (("plant.substeps", STEP_DIVISOR),))


def half_period(c: Case, period_s: float) -> Case:
    """The same run at half the control period (ECUs, bus frames and plant step all twice as often):
    not a pure numerical check, since the sampled controllers and WSP react faster."""
    h = period_s / STEP_DIVISOR
    return Case(f"{c.key}-p{1000 * h:g}ms", f"{c.label}, control period {1000 * h:g} ms", c.profile,
                c.sets + (("control_period_s", h),))


def _load(c: Case, scen_dir: Path | None) -> Any:
    from canbrake.scenario import load_scenario

    return load_scenario(scenario_path(scen_dir), profile=c.profile, overrides=dict(c.sets))


def reduce_run(run_dir: Path) -> dict[str, Any]:
    """Numbers of one run from its ``signals.csv`` (SI): stopping distance and time of the lead car
    from the brake demand (t = 0: the reference decelerates from the start) to standstill; the
    largest coupler tension (> 0) and compression (reported > 0); the largest deceleration and
    |jerk| of any car, both of the acceleration smoothed over 0.1 s (the stop-jerk filter of
    :mod:`canbrake.analysis.braking`: a raw 10 ms difference sees every step of the running
    resistance at standstill); wheel-slide episodes per car (:func:`canbrake.analysis.metrics.slide_episodes`)."""
    import pandas as pd

    from canbrake.analysis.braking import smoothed_accel
    from canbrake.analysis.metrics import SLIDE_SLIP, slide_episodes

    df = pd.read_csv(run_dir / "signals.csv")
    t = df["t_s"].to_numpy()
    n = sum(1 for c in df.columns if c.startswith("speed_mps_c"))
    v1, x1 = df["speed_mps_c1"].to_numpy(), df["position_m_c1"].to_numpy()
    fc = df[[f"coupler_force_n_k{j}" for j in range(1, n)]].to_numpy()
    acc = df[[f"accel_mps2_c{i}" for i in range(1, n + 1)]].to_numpy()
    tc, am = smoothed_accel(t[1:], acc[1:])  # row 0 is the initial state (acceleration 0 by construction)
    jerk = np.diff(am, axis=0) / np.diff(tc)[:, None]
    still = np.flatnonzero(v1 <= STILL_MPS)
    cars = []
    for i in range(1, n + 1):
        cols = [c for c in df.columns if c.startswith("axle") and c.endswith(f"_slip_c{i}")]
        s = slide_episodes(t, df[cols].to_numpy()) if cols else {"episodes": 0, "duration_s": 0.0, "longest_s": 0.0}
        valve = df.get(f"wsp_valve_c{i}")
        s["min_slip"] = float(df[cols].to_numpy().min()) if cols else 0.0
        s["wsp_venting_s"] = float(np.sum(valve.to_numpy() > 0.5) * np.median(np.diff(t))) if valve is not None else 0.0
        cars.append(s)
    summary = json.loads((run_dir / "summary.json").read_text())
    return {
        "stopping_distance_m": float(x1[still[0]] - x1[0]) if still.size else float("nan"),
        "stopping_time_s": float(t[still[0]] - t[0]) if still.size else float("nan"),
        "v0_mps": float(v1[0]),
        "max_tension_n": float(max(fc.max(), 0.0)), "max_compression_n": float(max(-fc.min(), 0.0)),
        "max_compression_at": int(np.unravel_index(np.argmin(fc), fc.shape)[1]) + 1,
        "max_compression_t_s": float(t[np.unravel_index(np.argmin(fc), fc.shape)[0]]),
        "max_decel_mps2": float(-am.min()), "max_jerk_mps3": float(np.abs(jerk).max()),
        "max_decel_car": int(np.unravel_index(np.argmin(am), am.shape)[1]) + 1,
        "max_decel_t_s": float(tc[np.unravel_index(np.argmin(am), am.shape)[0]]),
        "slide_episodes": int(sum(c["episodes"] for c in cars)),
        "slide_s": float(sum(c["duration_s"] for c in cars)),
        "slide_longest_s": float(max(c["longest_s"] for c in cars)),
        "cars_sliding": [i + 1 for i, c in enumerate(cars) if c["episodes"]],
        "worst_slip": float(min(c["min_slip"] for c in cars)),
        "wsp_venting_s": float(sum(c["wsp_venting_s"] for c in cars)),
        "slide_threshold": SLIDE_SLIP, "status": summary.get("status"),
        "verdict": summary.get("verdict"),
    }


def execute(c: Case, runs_dir: str, force: bool, scen_dir: str | None) -> tuple[str, bool, float]:
    """Run (or reuse: same resolved scenario, status ok, same report version) one case; writes report.json."""
    from canbrake.run import run_scenario

    t0 = time.time()
    scn = _load(c, Path(scen_dir) if scen_dir else None)
    run_dir = Path(runs_dir) / c.key
    out = run_dir / "report.json"
    try:
        if not force and (run_dir / "scenario.yaml").read_text() == scn.to_yaml() and \
                json.loads(out.read_text()).get("version") == REPORT_VERSION:
            return c.key, True, time.time() - t0
    except (OSError, ValueError):
        pass
    s = run_scenario(scn, run_dir, backend="inprocess", plots=False)
    if s.get("status") != "ok":
        raise RuntimeError(f"{c.key}: run ended with status {s.get('status')!r} ({run_dir})")
    out.write_text(json.dumps({"version": REPORT_VERSION, **reduce_run(run_dir)}))
    (run_dir / "frames.log").unlink(missing_ok=True)
    return c.key, False, time.time() - t0


def _star(a: tuple) -> tuple[str, bool, float]:
    return execute(*a)


def command(c: Case, runs_dir: str) -> str:
    prof = f" --profile {c.profile}" if c.profile else ""
    sets = "".join(f" --set {k}={v:g}" if isinstance(v, float) else f" --set {k}={v}" for k, v in c.sets)
    return f"canbrake run scenarios/{SCENARIO}{prof}{sets} --bus inprocess --out {runs_dir}/{c.key}"


def _f(x: float, nd: int = 1) -> str:
    return "—" if not np.isfinite(x) else f"{x:.{nd}f}"


def generate(out_dir: str | Path = "docs", runs_dir: str | Path = "runs/report-mixed_emu", force: bool = False,
             jobs: int = 1, log: Callable[[str], None] = print, cases: Sequence[Case] = CASES,
             scen_dir: str | Path | None = None, step_check: bool = True) -> Path:
    """Run (or reuse) every case (and, with ``step_check``, each at half the step) and write the section
    between ``BEGIN`` and ``END`` of ``out_dir/mixed-trains.md`` (the rest of the file is kept)."""
    from canbrake.analysis import metrics as M

    t0 = time.time()
    out_dir, runs_dir = Path(out_dir), Path(runs_dir)
    sd = Path(scen_dir) if scen_dir else None
    runs_dir.mkdir(parents=True, exist_ok=True)
    base = _load(cases[0], sd)
    h0 = float(base.control_period_s)
    fine = {c.key: half_step(c) for c in cases} if step_check else {}
    per_ = {c.key: half_period(c, h0) for c in cases} if step_check else {}
    extra = (*fine.values(), *per_.values())
    tasks = [(c, str(runs_dir), force, str(sd) if sd else None) for c in (*cases, *extra)]
    for key, reused, wall in map_tasks(_star, tasks, jobs):
        log(f"  {key}: {'reused' if reused else f'ran in {wall:.0f} s'}")
    res = {c.key: json.loads((runs_dir / c.key / "report.json").read_text()) for c in (*cases, *extra)}

    a_ref = float(base.reference.decel_kmh_per_s) / 3.6
    ev = [e for e in _load(Case("as-written", "", None), sd).events if getattr(e, "type", "") == "rail"]
    L: list[str] = []
    w = L.append
    w(BEGIN)
    w("## 8-car EMU on a low-adhesion section")
    w("")
    w("<!-- generated by canbrake/report/mixed_emu.py (generate()); do not edit by hand -->")
    w("")
    w(f"`scenarios/{SCENARIO}`: an 8-car EMU (Tc-M-M-T-T-M-M-Tc, 46 t motor and 40 t trailer cars, as "
      "`emu8_example`), one `chen2023_compensated` ECU per car at a 10 ms cycle, an electro-pneumatic brake "
      "(lag 0.3 s, jerk limit 1 m/s³), ED/friction blending, easing before standstill, four wheelsets per car "
      "with Cai's slip curve per axle (peak μ 0.25 on dry rail), service braking from "
      f"{3.6 * res[cases[0].key]['v0_mps']:.0f} km/h at {a_ref:.2f} m/s² (the reference, from t = 0)."
      + (f" Low adhesion: a section of μ = {min(float(np.min(e.adhesion_mu)) for e in ev):g} (leaves / wet rail, "
         "assumed) that each car enters and leaves in turn; the coupled family's rail events are per car over "
         "time, so the scenario gives each car's time in the section from the reference's motion "
         f"(cars in it from {min(e.start_s for e in ev):.1f} s to {max(e.stop_s for e in ev):.1f} s)."
         if ev else "")
      + " Blending is local to each car: a motor car's ED brake (1.0 m/s² of its own mass, fading from 10 to "
      "3 km/h) takes its demand first and its friction brake tops up with a 0.2 s lag; the trailers have no ED "
      "brake (`ed_brake: {model: none}`) and brake by friction alone. The last case gives the motor cars Li "
      "2024's electric-brake envelope (eq. 2) instead, sized for a 46 t motor car with 800 kW at the wheel "
      "(our assumption: 46 kN from 10 km/h up to 62.6 km/h, 28.8 kN at 100 km/h, a linear ramp below "
      "10 km/h): a vehicle with Chen's coupler, Li's ED-brake envelope and Cai's slip curve.")
    w("")
    w(f"**Stopping distance**: the lead car's travel from the brake demand (t = 0) to standstill "
      f"(speed ≤ {STILL_MPS} m/s); the reference's v₀²/(2a) is "
      f"{res[cases[0].key]['v0_mps'] ** 2 / (2 * a_ref):.1f} m. **Slide**: a car slides while any of its "
      f"axles has |λ| > {M.SLIDE_SLIP:g} (far past the curve's peak at |λ| ≈ 0.16); an episode is one "
      "uninterrupted slide of one car (`canbrake.analysis.metrics.slide_episodes`); episodes and seconds are "
      "summed over the cars. **Forces**: the largest coupler tension and compression over all couplers and "
      "the whole run. **Deceleration, jerk**: the largest of any car, of its acceleration smoothed over "
      "0.1 s (a raw 10 ms difference reports the step at standstill); a car's acceleration includes its "
      "coupler forces. **Verdict**: the run's own (`summary.json`, `canbrake.analysis.verdict`): it judges "
      "divergence and the coupler deflection against the scenario's bound "
      f"({base.safety.max_abs_deflection_m} m, the draft gear's travel); it has no criterion for wheel slides or "
      "the stopping distance, which are the table's own columns: an `ok` verdict does not say a slide is "
      "acceptable.")
    w("")
    w("| case | stop (m) | stop time (s) | slide episodes | slide (s, longest) | cars sliding | worst slip | "
      "WSP venting (s) | peak tension (kN) | peak compression (kN) | max decel (m/s², car at s) | max jerk (m/s³) | "
      "verdict |")
    w("|---|---|---|---|---|---|---|---|---|---|---|---|---|")
    for c in cases:
        r = res[c.key]
        vd = r.get("verdict")
        vtxt = (vd.get("verdict") or vd.get("status") or str(vd)) if isinstance(vd, dict) else str(vd)
        w(f"| {c.label} | {_f(r['stopping_distance_m'])} | {_f(r['stopping_time_s'], 2)} | {r['slide_episodes']} | "
          f"{r['slide_s']:.2f} ({r['slide_longest_s']:.2f}) | {', '.join(map(str, r['cars_sliding'])) or 'none'} | "
          f"{r['worst_slip']:.2f} | {r['wsp_venting_s']:.2f} | {r['max_tension_n'] / 1e3:.1f} | "
          f"{r['max_compression_n'] / 1e3:.1f} | {r['max_decel_mps2']:.2f} (car {r['max_decel_car']} at "
          f"{r['max_decel_t_s']:.1f} s) | {r['max_jerk_mps3']:.2f} | {vtxt} |")
    w("")
    keys = [c.key for c in cases]
    if {"dry", "low", "low-wsp"} <= set(keys):
        d, lo, ws = res["dry"], res["low"], res["low-wsp"]
        w(f"Through the low-adhesion section the stop changes by {lo['stopping_distance_m'] - d['stopping_distance_m']:+.1f} m "
          f"against dry rail without WSP and by {ws['stopping_distance_m'] - d['stopping_distance_m']:+.1f} m with "
          f"WSP (WSP against none: {ws['stopping_distance_m'] - lo['stopping_distance_m']:+.1f} m). Without WSP "
          f"{len(lo['cars_sliding'])} of 8 cars slide ({lo['slide_episodes']} episodes, {lo['slide_s']:.1f} s summed, "
          f"the longest {lo['slide_longest_s']:.1f} s; worst slip {lo['worst_slip']:.2f}"
          + (", i.e. locked wheels" if lo["worst_slip"] <= -0.99 else "") + f"); with WSP {ws['slide_episodes']} "
          f"episodes, {ws['slide_s']:.1f} s (worst slip {ws['worst_slip']:.2f}, dump valves open "
          f"{ws['wsp_venting_s']:.1f} s summed over cars). The cost in distance is small because the controllers "
          "track the reference's speed and position: while the cars are faster than it, in and after the section, "
          f"the ECUs command up to the brake rating ({base.actuator.max_brake_decel_mps2:g} m/s²). "
          f"On dry rail the couplers carry little ({d['max_tension_n'] / 1e3:.1f} kN, at {d['max_compression_t_s']:.1f} s: "
          "as the brake applies, the trailers' friction brakes follow the demand with their lag while the motor "
          "cars' ED brakes act at once); the formation Tc-M-M-T-T-M-M-Tc and its braking are symmetric, so the "
          "peak tension of one coupler "
          "is the peak compression of its mirror image. In the section the cars "
          "that slide brake less than those that do not: the couplers carry "
          f"{max(lo['max_tension_n'], lo['max_compression_n']) / 1e3:.0f} kN without WSP and "
          f"{max(ws['max_tension_n'], ws['max_compression_n']) / 1e3:.0f} kN with it. The service brake's jerk limit is "
          f"{base.actuator.jerk_limit_mps3:g} m/s³; the cars' smoothed jerk (which also has the couplers and the "
          f"running resistance in it) is {d['max_jerk_mps3']:.2f} m/s³ on dry rail, while slides and the dump valves "
          f"(which bypass the limit) give {lo['max_jerk_mps3']:.0f} m/s³ without and {ws['max_jerk_mps3']:.0f} m/s³ "
          "with WSP.")
        if "li-env" in keys:
            le = res["li-env"]
            w("")
            w(f"With Li's envelope on the motor cars (last row) the stop is {le['stopping_distance_m']:.1f} m "
              f"({le['stopping_distance_m'] - ws['stopping_distance_m']:+.1f} m against the per-mass ED brake, "
              f"both with WSP): above 62.6 km/h the envelope's power limit leaves part of the demand to the "
              f"friction brake, which follows it with its lag; slides {le['slide_episodes']} episodes, "
              f"{le['slide_s']:.1f} s; couplers {le['max_tension_n'] / 1e3:.1f} kN tension, "
              f"{le['max_compression_n'] / 1e3:.1f} kN compression (per-mass: {ws['max_tension_n'] / 1e3:.1f} / "
              f"{ws['max_compression_n'] / 1e3:.1f} kN).")
        if ev:
            def left_s(car: int) -> float:  # when ``car`` (1-based) leaves the section
                return max((e.stop_s for e in ev if np.asarray(e.adhesion_mu, float).reshape(-1)[
                    min(car - 1, np.size(e.adhesion_mu) - 1)] < float(np.min(base.actuator.adhesion_mu))), default=math.nan)
            after = [(c.label, res[c.key]["max_decel_t_s"] - left_s(res[c.key]["max_decel_car"])) for c in cases
                     if c.key != "dry"]
            w("")
            w(" ".join(f"In the run \"{lab}\" the largest deceleration comes {dt:.1f} s after its car left the section."
                       for lab, dt in after if np.isfinite(dt))
              + " The section's ends are steps in μ: a wheel still slipping meets the dry rail's creep force at once, "
              "a short, strong deceleration of its car (a real contamination has no sharp edge).")
        w("")
    w("### Integration step")
    w("")
    if fine:
        for title, other, what in (
                ("integration step", fine, f"with the plant's integration step halved ({1000 * h0:g} ms → "
                 f"{1000 * h0 / STEP_DIVISOR:g} ms, `plant.substeps: {STEP_DIVISOR}`; the ECUs still run every "
                 f"{1000 * h0:g} ms): the numerical check."),
                ("control period", per_, f"at half the control period ({1000 * h0:g} ms → "
                 f"{1000 * h0 / STEP_DIVISOR:g} ms: ECUs, frames and plant step twice as often). This is not a "
                 "pure numerical check: the sampled controllers and the wheel-slide protection react one period "
                 "sooner, so a change here is partly a change of the control system.")):
            worst, at = 0.0, ""
            per = {m: (0.0, "") for m in HEADS}  # the largest change of each number, and where
            for c in cases:
                a, b = res[c.key], res[other[c.key].key]
                ch = M.step_convergence([(h0, {m: a[m] for m in HEADS}), (h0 / 2, {m: b[m] for m in HEADS})])[1]
                for m, x in ch["change"].items():
                    x = float("inf") if x is None else x
                    if x > worst:
                        worst, at = x, f"{c.key}, {m}"
                    if x > per[m][0]:
                        per[m] = (x, c.key)
            ok = worst < M.STEP_TOL
            w(f"**{title.capitalize()}.** Every run again {what} "
              + (f"Every number changes by less than {100 * M.STEP_TOL:g} % (largest: {100 * worst:.2f} %, {at})."
                 if ok else f"**Not every number is converged to {100 * M.STEP_TOL:g} %**: largest relative change "
                 f"{100 * worst:.1f} % ({at}); the table gives both values.")
              + " Largest change of each: " + ", ".join(f"{HEAD_NAMES[m]} {100 * per[m][0]:.2f} %"
                                                        + (f" ({per[m][1]})" if per[m][1] else "") for m in HEADS)
              + " (a slide time of 0 at both steps counts as unchanged).")
            if not ok:
                w("")
                w("Where: peak compression at h / h/2 " + "; ".join(
                    f"{c.label}: coupler {res[c.key]['max_compression_at']} at {res[c.key]['max_compression_t_s']:.1f} s / "
                    f"coupler {res[other[c.key].key]['max_compression_at']} at "
                    f"{res[other[c.key].key]['max_compression_t_s']:.1f} s" for c in cases)
                  + ". Peaks that come from switching (the dump valves open and close on slip thresholds, wheels "
                  "lock and release) move by a step when the step changes and are not a smooth function of it; the "
                  "stopping distance and the slide time integrate over the stop. The peaks in the results table are "
                  "uncertain by about the difference between the two columns here.")
            w("")
            w("| case | stop h / h/2 (m) | slide h / h/2 (s) | slide episodes h / h/2 | peak tension h / h/2 (kN) | "
              "peak compression h / h/2 (kN) | max decel h / h/2 (m/s²) | max jerk h / h/2 (m/s³) |")
            w("|---|---|---|---|---|---|---|---|")
            for c in cases:
                a, b = res[c.key], res[other[c.key].key]
                w(f"| {c.label} | {_f(a['stopping_distance_m'], 2)} / {_f(b['stopping_distance_m'], 2)} | "
                  f"{a['slide_s']:.2f} / {b['slide_s']:.2f} | {a['slide_episodes']} / {b['slide_episodes']} | "
                  f"{a['max_tension_n'] / 1e3:.2f} / {b['max_tension_n'] / 1e3:.2f} | "
                  f"{a['max_compression_n'] / 1e3:.2f} / {b['max_compression_n'] / 1e3:.2f} | "
                  f"{a['max_decel_mps2']:.3f} / {b['max_decel_mps2']:.3f} | {a['max_jerk_mps3']:.2f} / "
                  f"{b['max_jerk_mps3']:.2f} |")
            w("")
    else:
        w("Not checked in this generation (step_check=False).")
        w("")
    w("### Runs")
    w("")
    w("In process (`--bus inprocess`); in lockstep mode the memory bus with one process per ECU (`canbrake run "
      f"scenarios/{SCENARIO}`, its default) gives the same `signals.csv` (compared for the three cases when this "
      "report was written).")
    w("")
    w("```sh")
    for c in (*cases, *extra):
        w(command(c, str(runs_dir)))
    w("```")
    w("")
    w(f"*Generated in {time.time() - t0:.0f} s by `canbrake.report.mixed_emu.generate()` "
      "(`canbrake report mixed_emu`).*")
    w(END)
    md = out_dir / DOC
    out_dir.mkdir(parents=True, exist_ok=True)
    old = md.read_text(encoding="utf-8") if md.exists() else (
        "# Mixed trains\n\nGenerated sections; each names the module that writes it.\n\n")
    section = "\n".join(L)
    if BEGIN in old and END in old:
        new = old[:old.index(BEGIN)] + section + old[old.index(END) + len(END):]
    else:
        new = old.rstrip("\n") + "\n\n" + section + "\n"
    md.write_text(new, encoding="utf-8")
    log(f"wrote {md}")
    return md
