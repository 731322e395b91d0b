"""Reproduction report of Li, Zeng & Yu 2024 (heavy-haul 1+105, PID / SMC / RBFNN-SMC + NDO).

``generate()`` makes (or reuses) the synthetic driver reference and every closed-loop run of
:func:`run_specs` with :mod:`canbrake.li2024_sim`, then writes ``li2024.md`` and
``figures/li2024_*.png``. Every number in the document is computed from the runs; the paper's own
values (:data:`PAPER`) are the only numbers typed by hand.

Runs are cached as ``runs_dir/<key>.npz`` with a JSON header; a run is reused when its header
(report version, duration, key) matches, unless ``force=True``.
"""
from __future__ import annotations

import time
from concurrent.futures import ProcessPoolExecutor
from dataclasses import dataclass
from pathlib import Path
from typing import Callable, Sequence

import numpy as np

from canbrake.li2024_sim import (
    CRUISE_KMH,
    UNCERTAINTY,
    V0_KMH,
    Reference,
    driver_reference,
    simulate,
)
from canbrake import li2024_sim as hh
from canbrake.report.cache import load_npz, save_npz

REPORT_VERSION = 1
DEFAULT_DURATION_S = 2600.0
STEP_CHECK_S = 1200.0

#: Table 2 of the paper (velocity RMSE, km/h) and the error bands quoted in section 3.2
PAPER = {
    "rmse": {"pid": (0.1402, 0.1436), "smc": (0.0432, 0.0443), "rbfnn-smc+ndo": (0.0314, 0.0315)},
    "band": {"pid": "−0.15 … 0.27", "smc": "±0.2", "rbfnn-smc+ndo": "±0.15"},
}
LABEL = {"pid": "PID", "smc": "SMC", "rbfnn-smc": "RBFNN-SMC (no NDO)", "rbfnn-smc+ndo": "RBFNN-SMC + NDO"}
READING_TEXT = {
    "listed": "ṡ = −ζ0·|s|^α·sgn s − κ·tansig|e|·sgn s (ζ0 = 0.005 on the power term)",
    "adaptive-power": "ṡ = −κ·tansig|e|·|s|^α·sgn s − ζ0·sgn s (ζ0 = 0.005 on the switching term)",
}


@dataclass(frozen=True)
class RunSpec:
    controller: str
    disturbance: bool
    reading: str = "listed"
    airbrake: str = "replay"  # or "rules" (section-1.2 rules on the controlled train)

    @property
    def key(self) -> str:
        rd = "" if self.controller == "pid" else f"-{self.reading}"
        ab = "" if self.airbrake == "replay" else f"-ab{self.airbrake}"
        return f"{self.controller}{rd}{ab}-{'dist' if self.disturbance else 'nodist'}"


def run_specs() -> list[RunSpec]:
    out = []
    for dist in (False, True):
        out.append(RunSpec("pid", dist))
        for rd in ("listed", "adaptive-power"):
            out.append(RunSpec("smc", dist, rd))
            out.append(RunSpec("rbfnn-smc+ndo", dist, rd))
        out.append(RunSpec("rbfnn-smc", dist, "listed"))
    out.append(RunSpec("smc", False, "listed", "rules"))
    return out


# ----------------------------------------------------------------------------------- runs
def _header(kind: str, duration_s: float) -> dict:
    return {"report_version": REPORT_VERSION, "kind": kind, "duration_s": duration_s}


def reference(runs_dir: Path, duration_s: float, force: bool, log) -> tuple[Reference, dict]:
    path = runs_dir / "reference.npz"
    hdr = _header("reference", duration_s)
    d = None if force else load_npz(path, hdr)
    if d is None:
        log(f"  driver reference ({duration_s:.0f} s) ...")
        ref, raw = driver_reference(duration_s=duration_s)
        ev = raw.pop("airbrake_events")  # (time, "apply"/"release")
        d = {"t_s": ref.t_s, "x_m": ref.x_m, "v_mps": ref.v_mps, "a_mps2": ref.a_mps2,
             "raw_x_m": raw["x_m"], "raw_v_mps": raw["v_mps"], "raw_u_n": raw["u_n"],
             "ab_t_s": np.array([t for t, _ in ev]), "ab_apply": np.array([e == "apply" for _, e in ev])}
        save_npz(path, hdr, d)
    events = [(float(t), bool(a)) for t, a in zip(d["ab_t_s"], d["ab_apply"])]
    ref = Reference(d["t_s"], d["x_m"], d["v_mps"], d["a_mps2"], float(d["t_s"][1] - d["t_s"][0]), events)
    return ref, d


def _run(args) -> tuple[str, dict]:
    spec, ref = args
    r = simulate(spec.controller, ref, disturbance=spec.disturbance, reading=spec.reading, airbrake=spec.airbrake)
    return spec.key, r


def run_all(specs: Sequence[RunSpec], ref: Reference, runs_dir: Path, duration_s: float, force: bool,
            jobs: int, log) -> dict[str, dict]:
    res: dict[str, dict] = {}
    todo = []
    for sp in specs:
        hdr = {**_header("run", duration_s), "key": sp.key}
        d = None if force else load_npz(runs_dir / f"{sp.key}.npz", hdr)
        if d is None:
            todo.append(sp)
        else:
            res[sp.key] = d
    if todo:
        log(f"  {len(todo)} run(s) to make, {len(specs) - len(todo)} reused ({jobs} worker(s))")
        t0 = time.time()
        if jobs > 1:
            with ProcessPoolExecutor(max_workers=jobs) as ex:
                outs = list(ex.map(_run, [(sp, ref) for sp in todo]))
        else:
            outs = [_run((sp, ref)) for sp in todo]
        for key, r in outs:
            save_npz(runs_dir / f"{key}.npz", {**_header("run", duration_s), "key": key}, r)
            res[key] = {k: np.asarray(v) for k, v in r.items()}
        log(f"  runs done in {time.time() - t0:.0f} s")
    return res


def step_check(runs_dir: Path, duration_s: float, force: bool, log) -> dict:
    """SMC (listed, no disturbance) with the 10 ms and a 5 ms step, each with its own driver reference."""
    out = {}
    for dt in (0.01, 0.005):
        path = runs_dir / f"stepcheck-{int(round(dt * 1e4))}.npz"
        hdr = {**_header("stepcheck", duration_s), "dt": dt}
        d = None if force else load_npz(path, hdr)
        if d is None:
            log(f"  step check dt = {dt} s ({duration_s:.0f} s) ...")
            ref, _ = driver_reference(duration_s=duration_s, dt_s=dt)
            r = simulate("smc", ref)
            d = {k: np.asarray(r[k]) for k in ("rmse_kmh", "max_tension_n", "max_compression_n", "err_min_kmh",
                                               "err_max_kmh")}
            d["ref_v_end_kmh"] = np.asarray(ref.v_mps[-1] / hh.KMH)
            save_npz(path, hdr, d)
        out[dt] = d
    return out


# ----------------------------------------------------------------------------------- figures
def make_figures(res: dict, refd: dict, fig_dir: Path) -> dict[str, str]:
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig_dir.mkdir(parents=True, exist_ok=True)
    figs = {}
    route = hh.li2024_route()
    main = [("pid", "pid"), ("smc", "smc-listed"), ("rbfnn-smc+ndo", "rbfnn-smc+ndo-listed")]

    # route and reference
    fig, ax = plt.subplots(2, 1, figsize=(9, 5.5), sharex=True)
    xs = np.linspace(0, route.length_m, 2000)
    ax[0].plot(xs / 1000, route.grade_at(xs), "k")
    ax[0].set_ylabel("grade (‰, + up)")
    ax[0].grid(alpha=0.3)
    ax[1].plot(refd["raw_x_m"][::50] / 1000, refd["raw_v_mps"][::50] / hh.KMH, color="0.6", lw=0.8, label="driver run (raw)")
    ax[1].plot(refd["x_m"][::50] / 1000, refd["v_mps"][::50] / hh.KMH, "b", lw=1.2, label="reference (5 s smoothed)")
    for t, ap in zip(refd["ab_t_s"], refd["ab_apply"]):
        k = min(int(round(t / (refd["t_s"][1] - refd["t_s"][0]))), refd["x_m"].size - 1)
        ax[1].axvline(refd["raw_x_m"][k] / 1000, color="r" if ap else "g", lw=0.6, ls="--")
    ax[1].set_ylabel("speed (km/h)")
    ax[1].set_xlabel("position (km)  — red: air brake applied, green: released")
    ax[1].legend(fontsize=8)
    ax[1].grid(alpha=0.3)
    fig.tight_layout()
    figs["route"] = "figures/li2024_route.png"
    fig.savefig(fig_dir / "li2024_route.png", dpi=110)
    plt.close(fig)

    # tracking errors
    fig, ax = plt.subplots(2, 1, figsize=(9, 6), sharex=True)
    for i, suffix in enumerate(("nodist", "dist")):
        for ctl, key in main:
            r = res.get(f"{key}-{suffix}")
            if r is None:
                continue
            ax[i].plot(r["t_s"], (r["v_mps"] - r["v_ref_mps"]) / hh.KMH, lw=0.7, label=LABEL[ctl])
        ax[i].set_ylabel("v − v_ref (km/h)")
        ax[i].set_title("without disturbance" if suffix == "nodist" else "with the disturbance of eq. (40)", fontsize=9)
        ax[i].grid(alpha=0.3)
        ax[i].legend(fontsize=8)
    ax[1].set_xlabel("time (s)")
    fig.tight_layout()
    figs["errors"] = "figures/li2024_errors.png"
    fig.savefig(fig_dir / "li2024_errors.png", dpi=110)
    plt.close(fig)

    # control force
    fig, ax = plt.subplots(figsize=(9, 4))
    for ctl, key in main:
        r = res.get(f"{key}-nodist")
        if r is not None:
            ax.plot(r["t_s"], r["u_n"] / 1000, lw=0.7, label=LABEL[ctl])
    r = res.get("pid-nodist")
    if r is not None:
        ax.plot(r["t_s"], hh.traction_envelope_kn(r["v_mps"] / hh.KMH), "k:", lw=0.8, label="F_T envelope")
        ax.plot(r["t_s"], -hh.electric_brake_envelope_kn(r["v_mps"] / hh.KMH), "k--", lw=0.8, label="−F_B envelope")
    ax.set_ylabel("locomotive force (kN)")
    ax.set_xlabel("time (s)")
    ax.grid(alpha=0.3)
    ax.legend(fontsize=8)
    fig.tight_layout()
    figs["force"] = "figures/li2024_force.png"
    fig.savefig(fig_dir / "li2024_force.png", dpi=110)
    plt.close(fig)

    # couplers
    r = res.get("rbfnn-smc+ndo-listed-nodist")
    if r is not None:
        fig, ax = plt.subplots(figsize=(9, 4))
        for j, cpl in enumerate(r["recorded_couplers"]):
            ax.plot(r["t_s"], r["coupler_n"][:, j] / 1000, lw=0.7, label=f"coupler {int(cpl)} (behind vehicle {int(cpl)})")
        ax.set_ylabel("coupler force (kN, + tension)")
        ax.set_xlabel("time (s)")
        ax.grid(alpha=0.3)
        ax.legend(fontsize=8)
        ax.set_title("RBFNN-SMC + NDO, no disturbance", fontsize=9)
        fig.tight_layout()
        figs["couplers"] = "figures/li2024_couplers.png"
        fig.savefig(fig_dir / "li2024_couplers.png", dpi=110)
        plt.close(fig)
    # sliding variable and estimates
    keys = ["smc-listed-nodist", "rbfnn-smc-listed-nodist", "rbfnn-smc+ndo-listed-nodist"]
    if all(k in res for k in keys):
        fig, ax = plt.subplots(3, 1, figsize=(9, 7), sharex=True)
        for k, lab in zip(keys, ("SMC", "RBFNN-SMC (no NDO)", "RBFNN-SMC + NDO")):
            r = res[k]
            ax[0].plot(r["t_s"], r["s"], lw=0.7, label=lab)
        ax[0].set_ylabel("s (m/s)")
        ax[0].legend(fontsize=8)
        for k, lab in zip(keys[1:], ("RBFNN-SMC (no NDO)", "RBFNN-SMC + NDO")):
            ax[1].plot(res[k]["t_s"], res[k]["delta_hat"], lw=0.7, label=lab)
        ax[1].set_ylabel("δ̂ = Ŵᵀh (m/s²)")
        ax[1].legend(fontsize=8)
        r = res[keys[2]]
        ax[2].plot(r["t_s"], r["d_hat"], lw=0.7, color="g", label="NDO d̂ (RBFNN-SMC + NDO)")
        ax[2].set_ylabel("d̂ (m/s²)")
        ax[2].set_xlabel("time (s)")
        ax[2].legend(fontsize=8)
        for a in ax:
            a.grid(alpha=0.3)
        fig.tight_layout()
        figs["sliding"] = "figures/li2024_sliding.png"
        fig.savefig(fig_dir / "li2024_sliding.png", dpi=110)
        plt.close(fig)
    return figs


# ----------------------------------------------------------------------------------- markdown
def _f(x: float, n: int = 4) -> str:
    return f"{float(x):.{n}f}"


def ordering(res: dict, reading: str, suffix: str) -> list[str]:
    """Controllers sorted by measured RMSE (best first) for one reading / disturbance case."""
    keys = {"pid": "pid", "smc": f"smc-{reading}", "rbfnn-smc+ndo": f"rbfnn-smc+ndo-{reading}"}
    have = {c: float(res[f"{k}-{suffix}"]["rmse_kmh"]) for c, k in keys.items() if f"{k}-{suffix}" in res}
    return sorted(have, key=have.get)


def _rms_s(r: dict) -> str:
    sv = np.asarray(r["s"], dtype=float)
    return "—" if not np.any(np.isfinite(sv)) else f"{float(np.sqrt(np.nanmean(sv ** 2))):.3g}"


def _rules_sentence(res: dict) -> str:
    r = res.get("smc-listed-abrules-nodist")
    if r is None:
        return ""
    return (f"Measured (SMC, listed reading, no disturbance, rules on the controlled train): RMSE "
            f"{_f(r['rmse_kmh'])} km/h, error {_f(r['err_min_kmh'], 2)} … {_f(r['err_max_kmh'], 2)} km/h, command "
            f"saturated in {100 * float(r['u_sat_fraction']):.1f} % of the steps, "
            f"{int(r['n_airbrake_applications'])} air-brake applications (driver run: see above).")


def write_markdown(res: dict, refd: dict, out_dir: Path, figs: dict, duration_s: float, elapsed_s: float,
                   steps: dict | None = None) -> Path:
    c = hh.li2024_consist()
    ab = hh._RuleAirBrake(c)
    route = hh.li2024_route()
    L = []
    w = L.append
    w("# Li, Zeng & Yu 2024 reproduced in canbrake")
    w("")
    w("<!-- generated by canbrake/report/li2024.py (generate()); do not edit by hand -->")
    w("")
    w("Li Z., Zeng X., Yu J., *Modeling and RBFNN sliding mode control for the operation process of heavy haul "
      "trains*, J. East China Jiaotong University 41(5) (2024) 94–104. A 1+105 heavy-haul train (HXD1 + C80) "
      "follows a recorded driver's speed on the Daqin line; the locomotive force comes from PID, SMC or an RBF "
      "neural-network SMC with a nonlinear disturbance observer (NDO). Table 2 compares the speed RMSE.")
    w("")
    w("Regenerate with `canbrake report li2024` (runs cached in `runs/report-li2024/`; about 11 minutes on two "
      "cores from scratch). Code: `canbrake/physics/heavy_haul.py` (plant), `canbrake/control/li2024.py` "
      "(controllers), `canbrake/li2024_sim.py` (driver reference and closed-loop runs), `canbrake/report/li2024.py`.")
    w("")
    # headline
    pr = {s: ordering(res, "listed", s) for s in ("nodist", "dist")}
    pa = {s: ordering(res, "adaptive-power", s) for s in ("nodist", "dist")}
    w("**In short.** " + (
        f"With eq. (21) read as listed ({READING_TEXT['listed']}) the measured order, best first, is "
        f"{' < '.join(LABEL[x] for x in pr['nodist'])} without and {' < '.join(LABEL[x] for x in pr['dist'])} with "
        f"the disturbance; with the other reading ({READING_TEXT['adaptive-power']}) it is "
        f"{' < '.join(LABEL[x] for x in pa['nodist'])} / {' < '.join(LABEL[x] for x in pa['dist'])}. "
        "The paper's order is RBFNN-SMC + NDO < SMC < PID in both cases. The route and the driver's speed are "
        "synthesised (the paper's are unpublished), so only ordering and rough size are comparable."))
    w("")
    w("## Measured RMSE against Table 2")
    w("")
    w(f"Velocity RMSE of the locomotive (eq. 41) over every 10 ms step of the {duration_s:.0f} s run, km/h; "
      "error band = min … max of v − v_ref.")
    w("")
    w("| controller | eq. (21) reading | paper RMSE before / after | ours before | ours after | ours band before (km/h) | ours band after | paper band (before) | saturated steps (before) | RMS of s (before, m/s) |")
    w("|---|---|---|---|---|---|---|---|---|---|")
    rows = [("pid", "pid", "—"), ("smc", "smc-listed", "listed"), ("rbfnn-smc+ndo", "rbfnn-smc+ndo-listed", "listed"),
            ("rbfnn-smc", "rbfnn-smc-listed", "listed"), ("smc", "smc-adaptive-power", "adaptive-power"),
            ("rbfnn-smc+ndo", "rbfnn-smc+ndo-adaptive-power", "adaptive-power")]
    for ctl, key, rd in rows:
        a, b = res.get(f"{key}-nodist"), res.get(f"{key}-dist")
        if a is None or b is None:
            continue
        p = PAPER["rmse"].get(ctl)
        ptxt = f"{p[0]} / {p[1]}" if p else "(not in Table 2)"
        w(f"| {LABEL[ctl]} | {rd} | {ptxt} | {_f(a['rmse_kmh'])} | {_f(b['rmse_kmh'])} | "
          f"{_f(a['err_min_kmh'], 3)} … {_f(a['err_max_kmh'], 3)} | {_f(b['err_min_kmh'], 3)} … {_f(b['err_max_kmh'], 3)} | "
          f"{PAPER['band'].get(ctl, '—')} | {100 * float(a['u_sat_fraction']):.2f} % | {_rms_s(a)} |")
    w("")
    # relative improvement
    try:
        for rd in ("listed", "adaptive-power"):
            s0 = float(res[f"smc-{rd}-nodist"]["rmse_kmh"])
            s1 = float(res[f"smc-{rd}-dist"]["rmse_kmh"])
            r0 = float(res[f"rbfnn-smc+ndo-{rd}-nodist"]["rmse_kmh"])
            r1 = float(res[f"rbfnn-smc+ndo-{rd}-dist"]["rmse_kmh"])
            w(f"- Reading *{rd}*: RBFNN-SMC + NDO vs SMC: {100 * (s0 - r0) / s0:+.1f} % before, "
              f"{100 * (s1 - r1) / s1:+.1f} % after the disturbance (paper: +27.3 % / +28.9 %; + = better).")
    except KeyError:
        pass
    try:
        rs, rr, rn = (float(res[f"{k}-listed-nodist"]["rmse_kmh"]) for k in ("smc", "rbfnn-smc", "rbfnn-smc+ndo"))
        sm_s, sm_r = (_rms_s(res[f"{k}-listed-nodist"]) for k in ("smc", "rbfnn-smc"))
        w(f"- Contributions (listed reading, no disturbance): the RBF network alone makes SMC "
          f"{'worse' if rr > rs else 'better'} ({_f(rr)} vs {_f(rs)} km/h; RMS of s {sm_r} vs {sm_s} m/s: with "
          f"ζ0 = 0.005 on |s|^5 the reaching law is weak and s stays of order 1 m/s, carried by the integral term "
          f"while e and ė are small, so the adaptation Ŵ̇ = γ s h never sees s ≈ 0); adding the NDO brings it to {_f(rn)} km/h, because the NDO estimates the model uncertainty "
          "Δf and the disturbance together from the measured acceleration every step.")
        dn = [float(res[f"{k}-dist"]["rmse_kmh"]) - float(res[f"{k}-nodist"]["rmse_kmh"])
              for k in ("pid", "smc-listed", "rbfnn-smc+ndo-listed")]
        w(f"- The disturbance of eq. (40) changes the RMSE by {', '.join(f'{d:+.4f}' for d in dn)} km/h "
          "(PID, SMC, RBFNN-SMC + NDO): σ_i/m_i is at most ≈ 0.005 m/s² and acts on 11 of 106 vehicles, small against "
          "grade and air-brake changes (the paper's changes are also small: +0.0034, +0.0011, +0.0001).")
        sat = [100 * float(res[f"{k}-nodist"]["u_sat_fraction"]) for k in ("pid", "smc-listed", "rbfnn-smc+ndo-listed")]
        near = []
        for k in ("pid", "smc-listed", "rbfnn-smc+ndo-listed"):
            r = res[f"{k}-nodist"]
            i = int(np.argmax(np.abs(r["v_mps"] - r["v_ref_mps"])))
            near.append(float(np.min(np.abs(refd["ab_t_s"] - r["t_s"][i]))) if refd["ab_t_s"].size else float("nan"))
        w(f"- The locomotive envelope binds in {', '.join(f'{x:.2f} %' for x in sat)} of the steps (same order). "
          f"The largest |error| of each run comes {', '.join(f'{x:.0f} s' for x in near)} from the nearest air-brake "
          "command (the release wave needs 35 s to reach the last wagon): the bands are set by air-brake transitions.")
    except KeyError:
        pass
    w("")
    for k in ("errors", "force", "sliding"):
        if k in figs:
            w(f"![{k}]({figs[k]})")
            w("")
    w("## Coupler forces")
    w("")
    w("| run | max tension (kN) | max compression (kN) |")
    w("|---|---|---|")
    for key in sorted(res):
        r = res[key]
        w(f"| {key} | {float(r['max_tension_n']) / 1000:.0f} | {-float(r['max_compression_n']) / 1000:.0f} |")
    w("")
    w(f"The draft-gear capacity at full stroke is {hh.MT2.curve_n[-1] / 1e3:.0f} kN (MT-2, our approximated curve) "
      f"and {hh.QKX100.curve_n[-1] / 1e3:.0f} kN (QKX100). The paper's Fig. 10 shows forces \"within the safe range\" "
      "without numbers.")
    w("")
    if "couplers" in figs:
        w(f"![couplers]({figs['couplers']})")
        w("")
    w("## Model and parameters")
    w("")
    w(f"- Consist: HXD1 {hh.LOCO_MASS_KG / 1e3:.0f} t, {hh.LOCO_LENGTH_M} m + {hh.N_WAGONS} × C80 {hh.WAGON_MASS_KG / 1e3:.0f} t, "
      f"{hh.WAGON_LENGTH_M:.0f} m; total {c.total_mass_kg / 1e3:.0f} t, {c.train_length_m:.0f} m. One mass per vehicle "
      "(eq. 16), force only on the locomotive.")
    w("- Envelopes eqs. (1)–(2) (kN, km/h), applied as a saturation of every controller's command: "
      + ", ".join(f"F_T({v}) = {float(hh.traction_envelope_kn(v)):.1f}" for v in (5, 65, 100)) + "; "
      + ", ".join(f"F_B({v}) = {float(hh.electric_brake_envelope_kn(v)):.1f}" for v in (2, 5, 75, 100)) + " kN.")
    w(f"- Basic resistance eq. (3), N/kN: HXD1 {hh.DAVIS_HXD1}, C80 {hh.DAVIS_C80} (A, B, C with v in km/h); "
      f"e.g. one C80 at 60 km/h: {float(hh.basic_resistance_n(c, np.full(c.n, 60 * hh.KMH))[1]):.0f} N. Grade i ‰ → i N/kN, "
      "curve 600/R N/kN, each vehicle at its own position.")
    w("- Couplers (eqs. 7–9): hysteretic spring with slack ±5 mm; loading curve f_l piecewise linear "
      f"(MT-2 points {list(zip([round(1000 * x) for x in hh.MT2.curve_m], [round(f / 1e3) for f in hh.MT2.curve_n]))} mm/kN, "
      f"unloading f_u = {hh.MT2.unloading_ratio}·f_l; QKX100 {list(zip([round(1000 * x) for x in hh.QKX100.curve_m], [round(f / 1e3) for f in hh.QKX100.curve_n]))}, "
      f"f_u = {hh.QKX100.unloading_ratio}·f_l), eq. (8) stiffness k = {hh.MT2.k_elastic_n_per_m:.0e} N/m, "
      f"gear solid beyond the stroke at {hh.MT2.k_solid_n_per_m:.0e} N/m, damping {hh.MT2.damping_n_s_per_m:.0e} N·s/m while engaged. "
      "**Approximation:** Fig. 2's measured curves are not given as numbers, and the velocity-switch form (6) "
      "of QKX100 is replaced by the same displacement-hysteresis scheme with QKX100's curve.")
    w(f"- Air brake (eqs. 10–15, Table 1): per C80 shoe K = {hh.c80_shoe_force_kn():.2f} kN (eq. 15, 8 shoes), "
      f"HXD1 K = {hh.hxd1_pad_force_kn():.2f} kN per cylinder (eqs. 13–14, 16 cylinders), φ from eqs. (11)–(12); "
      f"β_c = {hh.BETA_C} (**assumed**: the paper does not give it). Full-service force of one C80 at 60 km/h: "
      f"{1e-3 * float(hh.BETA_C * 8 * hh.friction_coefficient(hh.c80_shoe_force_kn(), 60, 0.481) * hh.c80_shoe_force_kn() * 1000):.2f} kN. "
      f"Signal along the brake pipe at {ab.apply_wave:.0f} m/s (apply) / {ab.release_wave:.0f} m/s (release): "
      f"it reaches the last wagon {ab.dist[-1] / ab.apply_wave:.1f} s / {ab.dist[-1] / ab.release_wave:.1f} s after "
      f"the locomotive (paper: about 6 s and 36.1 s); then a first-order cylinder fill, τ = {ab.tau} s (assumed). "
      "Rules (section 1.2): apply above 60 km/h when a downgrade steeper than 8 ‰ and at least 500 m long lies "
      "under the train or within 2.5 km ahead, at least 160 s after the previous application; release 10 km/h "
      "below the applying speed, never below 35 km/h. The paper's \"4 such downgrades within 2.5 km\" is read as "
      "\"a downgrade\" (our route, like most, has no four of them within 2.5 km).")
    w(f"- Model uncertainty: ΔF_i = {UNCERTAINTY:.0%} of each vehicle's non-control force F_i (the paper: δ = 1 % "
      "of f(x)); the controllers use the nominal f(x) with the measured front coupler force.")
    w("- Disturbance eq. (40) in newtons (σ_i/m_i in m/s², ∛v with v in m/s) on the locomotive and wagons "
      "10, 20, …, 100.")
    w(f"- Integration: semi-implicit Euler, fixed 10 ms step for plant and controllers (the paper gives no "
      "control period).")
    if steps:
        a, b = steps[0.01], steps[0.005]
        w(f"- Step check (SMC, listed, no disturbance, first {STEP_CHECK_S if duration_s > STEP_CHECK_S else duration_s:.0f} s, "
          "driver reference and run both remade at each step): "
          f"10 ms → RMSE {_f(a['rmse_kmh'])} km/h, max tension {float(a['max_tension_n']) / 1e3:.0f} kN, max compression "
          f"{-float(a['max_compression_n']) / 1e3:.0f} kN, reference end speed {float(a['ref_v_end_kmh']):.2f} km/h; "
          f"5 ms → {_f(b['rmse_kmh'])} km/h, {float(b['max_tension_n']) / 1e3:.0f} kN, "
          f"{-float(b['max_compression_n']) / 1e3:.0f} kN, {float(b['ref_v_end_kmh']):.2f} km/h.")
    w("")
    w("## The synthesised route and reference")
    w("")
    w(f"The Datong South – Dongjingji grade profile (Fig. 3) and the driver's speed (Fig. 4) are not published. "
      f"We use a {route.length_m / 1e3:.0f} km route, level before 0 km (the paper's assumption 3), with long "
      "downgrades of 10–11 ‰ at 18–23.5 km, 31–36 km and 37.5–41.5 km (near the paper's 20, 34 and 39 km) and "
      "three curves. The reference is made by a *driver run* of the same 1+105 plant: P speed control towards "
      f"{CRUISE_KMH:.0f} km/h from {V0_KMH:.0f} km/h with at most 70 % of the locomotive envelope and a 100 kN/s "
      "rate limit, cyclic air braking by the rules above (aiming 12 km/h below the applying speed while it is on); "
      "the locomotive's speed, smoothed over 5 s, is the reference v_ref, its integral x_ref and its derivative "
      f"a_ref. The driver run applied the air brake {int(np.sum(refd['ab_apply']))} times; the reference spans "
      f"{float(refd['v_mps'].min()) / hh.KMH:.1f}–{float(refd['v_mps'].max()) / hh.KMH:.1f} km/h (the commonly quoted Daqin limit for "
      "these trains is 80 km/h; our synthetic driver slightly overshoots it on the first long downgrade). In the controller runs "
      "the driver's air-brake commands are **replayed** at the same times (the driver works the air brake, the "
      "controller only the locomotive force u_0, as in the paper). Letting the rules act on the controlled train "
      "instead is fragile on a synthetic profile: the reference speed hovers at the 60 km/h threshold, a few "
      "hundredths of a km/h of tracking error delay an application, and the locomotive alone (461 kN electric "
      "brake) cannot hold the train on a 10 ‰ downgrade. " + _rules_sentence(res))
    w("")
    if "route" in figs:
        w(f"![route]({figs['route']})")
        w("")
    w("## Readings of ambiguous equations")
    w("")
    w("- **Units.** The paper mixes kN, km, km/h and m/s² in eqs. (16)–(35); the control laws multiply by m0 in kg. "
      "We run everything in SI (N, m, m/s); the gains are used as printed on SI errors. We did not run a kN reading; "
      "MODELS.md records that an independent reference simulation found the train runs away with it.")
    w("- **Eq. (21).** ζ is given both as a constant (0.005) and as the adaptive gain κ·tansig|e| (κ = 0.05), and "
      "it appears twice. We run both assignments: *listed* = " + READING_TEXT["listed"] + "; *adaptive-power* = "
      + READING_TEXT["adaptive-power"] + ". tansig(x) = (1 − e^−x)/(1 + e^−x) as printed.")
    w("- **PID.** Gains 10⁷, 1, 1 read as N per m/s of speed error, N per m, N per m/s² (P, I, D on the speed error).")
    w("- **RBF network.** χ = [e, ė] in m and m/s; centres c = 0.01·[−1, −0.5, 0, 0.5, 1] for both inputs, "
      "b = 0.005, γ = 0.01, Ŵ(0) = 0; δ̂ = Ŵᵀh added inside the bracket of eq. (29).")
    w("- **NDO.** p(x) = ωv, ω = 1000 s⁻¹, so l(x)H = ω. At our 10 ms step explicit Euler of eq. (30) would be "
      "unstable (ω·dt = 10); we integrate its error dynamics exactly over a step with zero-order hold "
      "(d̂ converges to the last step's residual acceleration). The NDO sees d + Δf together, so it also absorbs "
      "the model uncertainty.")
    w("")
    w("## What could not be reproduced, and why")
    w("")
    w("- The route, the recorded speed and the paper's simulation step are unpublished: absolute RMSE values are "
      "not comparable; the table compares ordering and size only.")
    w("- Fig. 2's draft-gear curves, β_c and the cylinder fill dynamics are not given: our values are approximations "
      "or assumptions (above), which change coupler forces and air-brake force.")
    w("- Eq. (21) is ambiguous; the ordering of SMC and RBFNN-SMC + NDO is reported for both readings above.")
    w("- The RBF estimate of δ (Figs. 7–8) and the zoomed control-force comparison of Fig. 9 are not reproduced "
      "as figures; the RMS of the sliding variable s is in the table.")
    w("")
    w(f"*Generated in {elapsed_s:.0f} s by `canbrake.report.li2024.generate()`; runs cached as npz files.*")
    md = out_dir / "li2024.md"
    md.write_text("\n".join(L) + "\n", encoding="utf-8")
    return md


def generate(out_dir: str | Path = "docs/reproduction", runs_dir: str | Path = "runs/report-li2024", force: bool = False,
             jobs: int = 2, log: Callable[[str], None] = print, duration_s: float = DEFAULT_DURATION_S,
             specs: Sequence[RunSpec] | None = None) -> Path:
    """Make (or reuse) the reference and the runs, then write ``out_dir/li2024.md`` and its figures."""
    t0 = time.time()
    out_dir, runs_dir = Path(out_dir), Path(runs_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    specs = list(specs or run_specs())
    log(f"canbrake report li2024: {len(specs)} runs of {duration_s:.0f} s in {runs_dir}")
    ref, refd = reference(runs_dir, duration_s, force, log)
    res = run_all(specs, ref, runs_dir, duration_s, force, jobs, log)
    steps = step_check(runs_dir, min(STEP_CHECK_S, duration_s), force, log)
    figs = make_figures(res, refd, out_dir / "figures")
    md = write_markdown(res, refd, out_dir, figs, duration_s, time.time() - t0, steps)
    log(f"wrote {md} in {time.time() - t0:.0f} s")
    return md
