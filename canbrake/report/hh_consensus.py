"""The 1 + 105 heavy-haul train over ECP with Chen's consensus controller in every ECU: the section
"1 + 105 over ECP: consensus in every wagon" of ``docs/mixed-trains.md``, from runs
(``canbrake report hh_consensus``).

``scenarios/hh106_ecp_consensus.yaml`` (Li 2024's HXD1 + 105 C80, ECP brakes, the CAN timing model
at 500 kbit/s, 50 ms period) brakes from 60 km/h two ways: every vehicle's ECU runs ``chen2023``
(speed and draft-gear consensus with the two coupled vehicles, tracking a 1 km/h/s braking curve;
a wagon's ECU turns its force into a cylinder demand, :class:`canbrake.control.ecp.EcpUnit`), and
the locomotive-only application (profile ``loco_only``: one full-service demand for the whole
train at t = 0). ``generate()`` runs both, reduces each run's ``signals.csv`` and ``summary.json``
with :func:`reduce_run`, and repeats every run with the plant's integration step halved and at half
the control period.
"""
from __future__ import annotations

import json
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Callable, Sequence

import numpy as np

from canbrake.report.pool import map_tasks

DEFAULT_OUT = "docs"
DOC = "mixed-trains.md"
SCENARIO = "hh106_ecp_consensus.yaml"
BEGIN, END = "<!-- begin: hh-consensus (canbrake/report/hh_consensus.py) -->", "<!-- end: hh-consensus -->"
REPORT_VERSION = 5
STEP_DIVISOR = 2
#: standstill: the locomotive's speed at or below this (m/s)
STILL_MPS = 0.01
#: coupler peaks are taken from this time on: before the brake demand the locomotive hauls the train
#: at 60 km/h and coupler 1 carries the train's running resistance (~170 kN), which takes ~2 s to
#: decay once traction stops; it is reported apart as the initial tension
SETTLE_S = 3.0
#: frames of the train's own traffic (what a real train would carry); the rest of the recorder's
#: count is the emulation's (the plant's sensor frames, the lockstep barrier frames, SYNC)
TRAIN_KINDS = ("state", "brake_cmd", "heartbeat")


@dataclass(frozen=True)
class Case:
    """One run of the scenario: a profile (None: as written) and ``--set`` overrides."""

    key: str
    label: str
    profile: str | None
    sets: tuple[tuple[str, Any], ...] = ()


#: the slower bus of the load cases (bit/s)
SLOW_BPS = 500_000
CASES = (Case("loco-only", "locomotive-only ECP full service", "loco_only"),
         Case("consensus", "Chen consensus in all 106 ECUs", None),
         Case("consensus-observer", "the same with Chen's disturbance observer", "observer"),
         Case("consensus-500k", "Chen consensus, 500 kbit/s", None, (("bus.bitrate_bps", SLOW_BPS),)),
         Case("consensus-observer-500k", "with the observer, 500 kbit/s", "observer", (("bus.bitrate_bps", SLOW_BPS),)))

HEADS = ("stopping_distance_m", "max_tension_n", "max_compression_n", "max_abs_deflection_m",
         "max_adjacent_dv_mps", "lead_rmse_kmh")
HEAD_NAMES = {"stopping_distance_m": "stopping distance", "max_tension_n": "peak tension",
              "max_compression_n": "peak compression", "max_abs_deflection_m": "largest draft-gear deflection",
              "max_adjacent_dv_mps": "largest speed difference of coupled vehicles",
              "lead_rmse_kmh": "locomotive speed RMSE"}


def scenario_path(scen_dir: Path | None = None) -> Path:
    from canbrake.builtin import builtin_dir

    return (scen_dir or builtin_dir()) / SCENARIO


def half_step(c: Case, step_s: float) -> Case:
    """The same run with the plant's integration step halved (the numerical check)."""
    h = step_s / STEP_DIVISOR
    return Case(f"{c.key}-h{1e3 * h:g}ms", f"{c.label}, integration step {1e3 * h:g} ms", c.profile,
                c.sets + (("train.integration_step_s", h),))


def _load(c: Case, scen_dir: Path | None) -> Any:
    from canbrake.scenario import load_scenario

    return load_scenario(scenario_path(scen_dir), profile=c.profile, overrides=dict(c.sets))


def reduce_run(run_dir: Path) -> dict[str, Any]:
    """Numbers of one run (SI): the locomotive's stopping distance and time from t = 0 (the brake
    demand and the reference's start) to standstill; the largest coupler tension (> 0) and
    compression (reported > 0) with coupler and time; the largest |draft-gear deflection|; the
    largest speed difference of two coupled vehicles; the locomotive's speed RMSE against the
    reference (``summary.json``); the recorder's bus load and the train's own frames per second."""
    import pandas as pd

    df = pd.read_csv(run_dir / "signals.csv")
    t = df["t_s"].to_numpy()
    n = sum(1 for c in df.columns if c.startswith("speed_mps_c"))
    v = df[[f"speed_mps_c{i}" for i in range(1, n + 1)]].to_numpy()
    x1 = df["position_m_c1"].to_numpy()
    fc = df[[f"coupler_force_n_k{j}" for j in range(1, n)]].to_numpy()
    dl = df[[f"deflection_m_k{j}" for j in range(1, n)]].to_numpy()
    still = np.flatnonzero(v[:, 0] <= STILL_MPS)
    k0 = int(np.searchsorted(t, SETTLE_S))
    it, jt = np.unravel_index(np.argmax(fc[k0:]), fc[k0:].shape)
    ic, jc = np.unravel_index(np.argmin(fc[k0:]), fc[k0:].shape)
    it, ic = it + k0, ic + k0
    dv = np.abs(np.diff(v, axis=1))
    ages = []  # the oldest neighbour state an ECU decided on, per ECU (s; its trace's max_peer_age_s)
    for f in sorted(run_dir.glob("ecu_c*.csv")):
        a = pd.read_csv(f, usecols=["max_peer_age_s"])["max_peer_age_s"].to_numpy()
        a = a[np.isfinite(a)]
        ages.append(float(a.max()) if a.size else 0.0)
    s = json.loads((run_dir / "summary.json").read_text())
    dur = float(s.get("duration_s") or t[-1])
    kinds = s.get("frames", {}).get("by_kind", {})
    rmse = s.get("metrics", {}).get("speed_rmse_kmh") or [float("nan")]
    return {
        "v0_mps": float(v[0, 0]),
        "stopping_distance_m": float(x1[still[0]] - x1[0]) if still.size else float("nan"),
        "stopping_time_s": float(t[still[0]] - t[0]) if still.size else float("nan"),
        "initial_tension_n": float(fc[0].max()),
        "max_tension_n": float(max(fc[it, jt], 0.0)), "tension_at": int(jt) + 1, "tension_t_s": float(t[it]),
        "max_compression_n": float(max(-fc[ic, jc], 0.0)), "compression_at": int(jc) + 1,
        "compression_t_s": float(t[ic]),
        "max_abs_deflection_m": float(np.abs(dl).max()),
        "max_adjacent_dv_mps": float(dv.max()),
        "lead_rmse_kmh": float(rmse[0]), "worst_rmse_kmh": float(np.nanmax(rmse)),
        "bus_load_mean": float(s.get("bus_load", {}).get("bus_load_mean", float("nan"))),
        "bus_load_peak": float(s.get("bus_load", {}).get("bus_load_peak", float("nan"))),
        "bitrate_bps": float(s.get("bus_load", {}).get("bitrate_bps", float("nan"))),
        "train_frames_per_s": float(sum(kinds.get(k, 0) for k in TRAIN_KINDS) / dur),
        "frames_per_s": float(sum(kinds.values()) / dur),
        "commands_missed": int(s.get("frames", {}).get("commands_missed", 0)),
        "max_peer_age_s": max(ages, default=0.0),
        # the timing model's in-loop figures: STATE frames off the wire after a peer's decision point,
        # heartbeats (the lowest priority) that never got onto the bus
        "state_late_share": _share(s, "state", "late_frames"),
        "heartbeat_starved_share": _share(s, "heartbeat", "starved"),
        "status": s.get("status"), "verdict": s.get("verdict"),
    }


def _share(summary: dict[str, Any], kind: str, what: str) -> float:
    """``what`` / ``n`` of frame ``kind`` in the summary's ``bus_latency_in_loop`` (0 when absent)."""
    d = (summary.get("bus_latency_in_loop") or {}).get(kind) or {}
    return float(d.get(what, 0)) / float(d["n"]) if d.get("n") else 0.0


def execute(c: Case, runs_dir: str, force: bool, scen_dir: str | None) -> tuple[str, bool, float]:
    """Run (or reuse: same resolved scenario, same report version) one case; writes report.json."""
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


def _verdict(r: dict[str, Any]) -> str:
    vd = r.get("verdict")
    return (vd.get("verdict") or vd.get("status") or str(vd)) if isinstance(vd, dict) else str(vd)


def generate(out_dir: str | Path = "docs", runs_dir: str | Path = "runs/report-hh_consensus", force: bool = False,
             jobs: int = 1, log: Callable[[str], None] = print, cases: Sequence[Case] = CASES,
             scen_dir: str | Path | None = None, step_check: bool = True) -> Path:
    """Run (or reuse) every case (with ``step_check`` also at half the integration step and half the
    control period) and write the section between ``BEGIN`` and ``END`` of ``out_dir/mixed-trains.md``."""
    from canbrake.analysis import metrics as M

    t0 = time.time()
    out_dir, runs_dir = Path(out_dir), Path(runs_dir)
    sd = Path(scen_dir) if scen_dir else None
    runs_dir.mkdir(parents=True, exist_ok=True)
    base = _load(Case("as-written", "", None), sd)
    h0, p0 = float(base.consist.max_substep_s), float(base.control_period_s)
    fine = {c.key: half_step(c, h0) for c in cases} if step_check else {}
    # The control period is not halved here: twice the frames would need twice the bit rate, beyond
    # classic CAN's 1 Mbit/s, and at this rate the bus would be at ~90 % load (see the section's text).
    per_: dict[str, Case] = {}
    extra = (*fine.values(), *per_.values())
    tasks = [(c, str(runs_dir), force, str(sd) if sd else None) for c in (*cases, *extra)]
    for key, reused, wall in map_tasks(_star, tasks, jobs):
        log(f"  {key}: {'reused' if reused else f'ran in {wall:.0f} s'}")
    res = {c.key: json.loads((runs_dir / c.key / "report.json").read_text()) for c in (*cases, *extra)}

    a_ref = float(base.reference.decel_kmh_per_s) / 3.6
    v0 = res[cases[0].key]["v0_mps"]
    chen = base.controller.params
    L: list[str] = []
    w = L.append
    w(BEGIN)
    w("## 1 + 105 over ECP: consensus in every wagon")
    w("")
    w("<!-- generated by canbrake/report/hh_consensus.py (generate()); do not edit by hand -->")
    w("")
    w(f"`scenarios/{SCENARIO}`: Li 2024's heavy-haul train (an HXD1 locomotive and 105 C80 wagons, their "
      "draft gears with slack, the air brake of `li2024_ecp_over_can` in ECP mode: each cylinder follows its "
      f"ECU's demand with a {base.consist.air_brake.cylinder_tau_s:g} s lag, full service β_c = "
      f"{base.consist.air_brake.service_factor:g}) braking from {3.6 * v0:.0f} km/h on level track, one ECU per "
      f"vehicle on a CAN bus of {base.bus.bitrate_bps / 1e3:g} kbit/s with the timing model, a "
      f"{1e3 * p0:g} ms control period. Two ways of braking it:")
    w("")
    w("- **locomotive-only** (profile `loco_only`, as `li2024_ecp_over_can` and ECP trains run today): the "
      "locomotive's ECU demands one full-service application for the whole train at t = 0; every wagon's ECU "
      "applies that demand to its own cylinder. Open loop: the train's deceleration is what full service gives.")
    w(f"- **consensus** (the scenario as written): every ECU runs Chen 2023's controller (`chen2023`: α1 = "
      f"{chen.get('alpha1')} 1/s speed consensus and α2 = {chen.get('alpha2')} 1/s² draft-gear deflection consensus "
      f"with the two coupled vehicles, mass-scaled; k = {chen.get('k')} 1/s tracking of the braking curve "
      f"{3.6 * v0:.0f} km/h → 0 at {a_ref:.3f} m/s²; no barrier potential: "
      "Chen's is made for a 1 cm coupler gap) and listens to the STATE frames of the ECUs of its two coupled "
      "vehicles (`listens: neighbours`). A wagon has no traction and takes only a cylinder demand, so its ECU "
      "turns the force its controller asks for into the demand by inverting the wagon's brake force law at its "
      "measured speed (eqs. 10-12, `canbrake.control.ecp.EcpUnit`): negative (traction) demands release the "
      "brake, demands beyond full service are capped at it. The locomotive's ECU brakes with its electric brake "
      "(its traction envelope) and leaves its own air brake released. The gains are ours, chosen for the "
      "2 s cylinder lag (the emulator's metro gains, α1 = 120 as in Chen's paper, are for an ideal actuator). "
      "Chen's disturbance observer is off here.")
    w("- **consensus with the observer** (profile `observer`): the same with Chen's sliding-mode disturbance "
      "observer and its cancellation term m·φ̂ (the paper's design).")
    w("")
    w(f"**Stopping distance**: the locomotive's travel from t = 0 to standstill (speed ≤ {STILL_MPS} m/s); the "
      f"consensus case's braking curve alone gives v₀²/(2a) = {v0 ** 2 / (2 * a_ref):.1f} m. **Forces**: the "
      f"largest draft-gear tension and compression over the 105 couplers from t = {SETTLE_S:g} s on (coupler j is "
      "behind vehicle j); before the brake demand the locomotive hauls the train and coupler 1 carries its running "
      f"resistance, {res[cases[0].key]['initial_tension_n'] / 1e3:.0f} kN at t = 0, which takes about 2 s to decay. **Δv**: the largest speed difference of two coupled vehicles. **Bus load**: the recorder's, "
      "over every frame it sees (also the plant's sensor frames and the lockstep barrier frames of the "
      "emulation); **train frames/s** counts only what the train itself sends (STATE, commands, heartbeats).")
    w("")
    w("| case | stop (m) | stop time (s) | peak tension (kN, coupler at s) | peak compression (kN, coupler at s) | "
      "max |deflection| (mm) | max Δv (km/h) | loco speed RMSE (km/h) | bus load mean / peak | train frames/s | "
      "commands missed | verdict |")
    w("|---|---|---|---|---|---|---|---|---|---|---|---|")
    for c in cases:
        r = res[c.key]
        w(f"| {c.label} | {r['stopping_distance_m']:.1f} | {r['stopping_time_s']:.1f} | "
          f"{r['max_tension_n'] / 1e3:.0f} ({r['tension_at']} at {r['tension_t_s']:.1f}) | "
          f"{r['max_compression_n'] / 1e3:.0f} ({r['compression_at']} at {r['compression_t_s']:.1f}) | "
          f"{1e3 * r['max_abs_deflection_m']:.1f} | {3.6 * r['max_adjacent_dv_mps']:.2f} | {r['lead_rmse_kmh']:.2f} | "
          f"{100 * r['bus_load_mean']:.0f} % / {100 * r['bus_load_peak']:.0f} % | {r['train_frames_per_s']:.0f} | "
          f"{r['commands_missed']} | {_verdict(r)} |")
    w("")
    keys = [c.key for c in cases]
    if {"loco-only", "consensus"} <= set(keys):
        lo, co = res["loco-only"], res["consensus"]
        d = co["stopping_distance_m"] - lo["stopping_distance_m"]
        w(f"The consensus train stops in {co['stopping_distance_m']:.0f} m, {d:+.0f} m "
          f"({100 * d / lo['stopping_distance_m']:+.0f} %) against the locomotive-only full-service stop: it follows "
          f"its braking curve ({a_ref:.2f} m/s², {v0 ** 2 / (2 * a_ref):.0f} m), which is gentler than full service "
          "on purpose, so that every ECU has brake in reserve to correct with; a stop as short as full service would "
          "need a curve at full service, with no reserve left for the consensus terms. "
          f"The in-train forces: peak tension {lo['max_tension_n'] / 1e3:.0f} kN → {co['max_tension_n'] / 1e3:.0f} kN, "
          f"peak compression {lo['max_compression_n'] / 1e3:.0f} kN → {co['max_compression_n'] / 1e3:.0f} kN, the "
          f"largest draft-gear deflection {1e3 * lo['max_abs_deflection_m']:.1f} mm → "
          f"{1e3 * co['max_abs_deflection_m']:.1f} mm, the largest speed difference of coupled vehicles "
          f"{3.6 * lo['max_adjacent_dv_mps']:.2f} → {3.6 * co['max_adjacent_dv_mps']:.2f} km/h: ECP already applies "
          "every wagon's brake at the same moment, so the locomotive-only train has small in-train forces, and "
          "closing the loop in every wagon is about following a braking curve (the locomotive-only stop follows "
          "none: its speed RMSE is against the consensus case's curve, for reference), not about lower forces. "
          f"The price is on the bus: every ECU now sends a STATE frame each period as well as its command, "
          f"{lo['train_frames_per_s']:.0f} → {co['train_frames_per_s']:.0f} train frames/s, and the recorder's bus "
          f"load at {base.bus.bitrate_bps / 1e3:g} kbit/s goes from {100 * lo['bus_load_mean']:.0f} % to "
          f"{100 * co['bus_load_mean']:.0f} %; scaled to the 250 kbit/s of `li2024_ecp_over_can` that would be "
          f"{100 * co['bus_load_mean'] * co['bitrate_bps'] / 250e3:.0f} %, more than the bus can carry.")
        if "consensus-observer" in keys:
            ob = res["consensus-observer"]
            w("")
            w(f"With Chen's disturbance observer (and its cancellation m·φ̂) the stop is {ob['stopping_distance_m']:.0f} m, "
              f"the locomotive's speed RMSE {ob['lead_rmse_kmh']:.2f} km/h, the peak tension "
              f"{ob['max_tension_n'] / 1e3:.0f} kN (coupler {ob['tension_at']} at {ob['tension_t_s']:.0f} s) and the peak "
              f"compression {ob['max_compression_n'] / 1e3:.0f} kN (coupler {ob['compression_at']} at "
              f"{ob['compression_t_s']:.0f} s).")
        w("")
    if {"consensus-500k", "consensus-observer-500k"} <= set(keys):
        c5, o5, co = res["consensus-500k"], res["consensus-observer-500k"], res["consensus"]
        w(f"**The same frames on a slower bus.** At {SLOW_BPS / 1e3:g} kbit/s the consensus traffic loads the bus "
          f"to {100 * c5['bus_load_mean']:.0f} % (peak {100 * c5['bus_load_peak']:.0f} %). On the modelled bus the "
          "lower-priority frames then wait for the bus: "
          f"{100 * c5['state_late_share']:.0f} % of the STATE frames are off the wire only after a peer's decision "
          f"point (at {base.bus.bitrate_bps / 1e3:g} kbit/s: {100 * co['state_late_share']:.0f} %) and are used a "
          f"period later, and {100 * c5['heartbeat_starved_share']:.0f} % of the heartbeats, the lowest-priority "
          "frames, never get onto the bus (hence fewer train frames per second). The oldest neighbour state an ECU "
          f"decided on is {c5['max_peer_age_s']:.2f} s against {co['max_peer_age_s']:.2f} s at "
          f"{base.bus.bitrate_bps / 1e3:g} kbit/s. Chen's controller takes a "
          "neighbour's position as it was sent (`stale_policy: hold`), so a state one period old makes the draft gear "
          f"between them look {v0 * p0:.2f} m longer or shorter at {3.6 * v0:.0f} km/h. Without the observer the "
          f"stop is {c5['stopping_distance_m']:.0f} m, the peak tension {c5['max_tension_n'] / 1e3:.0f} kN and the "
          f"peak compression {c5['max_compression_n'] / 1e3:.0f} kN (at {base.bus.bitrate_bps / 1e3:g} kbit/s: "
          f"{co['max_tension_n'] / 1e3:.0f} and {co['max_compression_n'] / 1e3:.0f} kN); with the observer the stop "
          f"is {o5['stopping_distance_m']:.0f} m, the peak tension {o5['max_tension_n'] / 1e3:.0f} kN and the peak "
          f"compression {o5['max_compression_n'] / 1e3:.0f} kN (coupler {o5['compression_at']} at "
          f"{o5['compression_t_s']:.0f} s), the largest draft-gear deflection {1e3 * o5['max_abs_deflection_m']:.1f} mm. "
          "The controllers' gains are unchanged; what changed is only how late their neighbours' states arrive "
          "(`stale_policy: extrapolate`, or `chen2023_compensated`, which predicts a late state forward, are the "
          "remedies the emulator offers; not run here).")
        w("")
    w("### Integration step")
    w("")
    if fine:
        for title, other, what in (
                ("integration step", fine, f"with the plant's integration step halved ({1e3 * h0:g} ms → "
                 f"{1e3 * h0 / STEP_DIVISOR:g} ms; ECUs unchanged): the numerical check."),
        ):
            worst, at = 0.0, ""
            per = {m: (0.0, "") for m in HEADS}
            for c in cases:
                a, b = res[c.key], res[other[c.key].key]
                ch = M.step_convergence([(h0, {m: a[m] for m in HEADS}), (h0 / 2, {m: b[m] for m in HEADS})])[1]
                for m, x in ch["change"].items():
                    x = float("inf") if x is None else x
                    if x > worst:
                        worst, at = x, f"{c.key}, {HEAD_NAMES[m]}"
                    if x > per[m][0]:
                        per[m] = (x, c.key)
            ok = worst < M.STEP_TOL
            w(f"**{title.capitalize()}.** Every run again {what} "
              + (f"Every number changes by less than {100 * M.STEP_TOL:g} % (largest: {100 * worst:.2f} %, {at})."
                 if ok else f"**Not every number is converged to {100 * M.STEP_TOL:g} %**: largest relative change "
                 f"{100 * worst:.1f} % ({at}); the table gives both values.")
              + " Largest change of each: " + ", ".join(f"{HEAD_NAMES[m]} {100 * per[m][0]:.2f} %"
                                                        + (f" ({per[m][1]})" if per[m][1] else "") for m in HEADS)
              + ".")
            if not ok:
                w("")
                w("Where the peaks are at each step: " + "; ".join(
                    f"{c.label}: tension coupler {res[c.key]['tension_at']} at {res[c.key]['tension_t_s']:.1f} s / "
                    f"{res[other[c.key].key]['tension_at']} at {res[other[c.key].key]['tension_t_s']:.1f} s, compression "
                    f"coupler {res[c.key]['compression_at']} at {res[c.key]['compression_t_s']:.1f} s / "
                    f"{res[other[c.key].key]['compression_at']} at {res[other[c.key].key]['compression_t_s']:.1f} s"
                    for c in cases)
                  + f". The locomotive stops at about {res[cases[-1].key]['stopping_time_s']:.0f} s in the consensus "
                  "runs: peaks at that time come from the stop itself and depend on when the sampled controllers "
                  "see the standstill; the results table's peaks carry the uncertainty shown here.")
            w("")
            w("| case | stop (m) | peak tension (kN) | peak compression (kN) | max |deflection| (mm) | max Δv (km/h) | "
              "loco RMSE (km/h) | bus load mean |")
            w("|---|---|---|---|---|---|---|---|")
            for c in cases:
                a, b = res[c.key], res[other[c.key].key]
                w(f"| {c.label} | {a['stopping_distance_m']:.2f} / {b['stopping_distance_m']:.2f} | "
                  f"{a['max_tension_n'] / 1e3:.1f} / {b['max_tension_n'] / 1e3:.1f} | "
                  f"{a['max_compression_n'] / 1e3:.1f} / {b['max_compression_n'] / 1e3:.1f} | "
                  f"{1e3 * a['max_abs_deflection_m']:.2f} / {1e3 * b['max_abs_deflection_m']:.2f} | "
                  f"{3.6 * a['max_adjacent_dv_mps']:.3f} / {3.6 * b['max_adjacent_dv_mps']:.3f} | "
                  f"{a['lead_rmse_kmh']:.3f} / {b['lead_rmse_kmh']:.3f} | {100 * a['bus_load_mean']:.0f} % / "
                  f"{100 * b['bus_load_mean']:.0f} % |")
            w("")
    else:
        w("Not checked in this generation (step_check=False).")
        w("")
    w("### Runs")
    w("")
    w("In process (`--bus inprocess`); the scenario's default, the memory bus with 8 ECUs hosted per process, "
      "and `--set ecu.per_process=1` (one process per ECU, 108 processes) run the same lockstep exchange.")
    w("")
    w("```sh")
    for c in (*cases, *extra):
        w(command(c, str(runs_dir)))
    w("```")
    w("")
    w(f"*Generated in {time.time() - t0:.0f} s by `canbrake.report.hh_consensus.generate()` "
      "(`canbrake report hh_consensus`).*")
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
