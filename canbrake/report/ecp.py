"""ECP braking over CAN on the 1+105 heavy-haul train: ``docs/ecp-over-can.md`` from runs.

``generate()`` runs ``scenarios/li2024_ecp_over_can.yaml`` (a brake application at 5 s from 60 km/h;
105 wagon brake ECUs apply the locomotive ECU's broadcast demand; CAN timing model on) at 125, 250
and 500 kbit/s, the same train with the pneumatic brake pipe, and ECP with one wagon ECU silent,
all with the in-process engine (each is a ``canbrake run`` command printed in the document), and
writes the comparison: in-train coupler forces (peak tension and compression and where), speed lost
and distance run after the application (stopping distance when the train stops within the run),
brake application time to the last wagon, bus load and command latency. Every number is computed
from the runs.
"""
from __future__ import annotations

import json
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Callable, Sequence

import numpy as np

from canbrake.report.pool import map_tasks

SCENARIO = "li2024_ecp_over_can.yaml"
REPORT_VERSION = 3
DEFAULT_DURATION_S = 80.0  # the scenario's: long enough for every run with a brake to stop
KMH = 1.0 / 3.6
SILENT = 53  # the silent_wagon profile's vehicle


@dataclass(frozen=True)
class Spec:
    key: str
    profile: str | None
    label: str
    #: ``--set`` overrides (dotted key, value), e.g. the integration step of the step-size check
    sets: tuple[tuple[str, Any], ...] = ()


SPECS = (Spec("ecp-250k", None, "ECP, 250 kbit/s"), Spec("ecp-125k", "kbps125", "ECP, 125 kbit/s"),
         Spec("ecp-500k", "kbps500", "ECP, 500 kbit/s"), Spec("pneumatic-250k", "pneumatic", "pneumatic brake pipe"),
         Spec("ecp-silent-wagon", "silent_wagon", f"ECP, wagon {SILENT}'s ECU silent"),
         Spec("ecp-silent-failsafe", "silent_wagon_failsafe",
              f"ECP, wagon {SILENT}'s ECU silent, with the fail-safe"))
#: the step-size check: these runs again with the plant's integration step halved twice
STEP_BASES = ("ecp-250k", "pneumatic-250k")
STEP_DIVISORS = (2, 4)


def step_specs(base_step_s: float, specs: Sequence[Spec] = SPECS) -> list[Spec]:
    """The runs of the step-size check: each of ``STEP_BASES`` at base_step / 2 and / 4."""
    out = []
    for sp in specs:
        if sp.key in STEP_BASES:
            for d in STEP_DIVISORS:
                h = base_step_s / d
                out.append(Spec(f"{sp.key}-h{1000 * h:g}ms", sp.profile, f"{sp.label}, step {1000 * h:g} ms",
                                sp.sets + (("train.integration_step_s", h),)))
    return out


def scenario_dir() -> Path:
    """The built-in scenarios (package data: the repository's scenarios/ in a checkout, the
    installed package's copy otherwise)."""
    from canbrake.builtin import builtin_dir

    return builtin_dir()


def command(spec: Spec, duration_s: float, runs_dir: str) -> str:
    prof = f" --profile {spec.profile}" if spec.profile else ""
    sets = "".join(f" --set {k}={v:g}" if isinstance(v, float) else f" --set {k}={v}" for k, v in spec.sets)
    return (f"canbrake run scenarios/{SCENARIO}{prof}{sets} --duration {duration_s:g} --bus inprocess "
            f"--out {runs_dir}/{spec.key}")


def _load(spec: Spec, duration_s: float, scen_dir: Path) -> Any:
    from canbrake.scenario import load_scenario
    return load_scenario(scen_dir / SCENARIO, profile=spec.profile, overrides={"duration_s": duration_s, **dict(spec.sets)})


def reduce_run(run_dir: Path, brake_at_s: float) -> dict[str, Any]:
    """Numbers and traces of one run (signals.csv + summary.json)."""
    import pandas as pd

    df = pd.read_csv(run_dir / "signals.csv", usecols=lambda c: c in ("t_s", "speed_mps_c1", "position_m_c1")
                     or c.startswith("coupler_force_n_k") or c.startswith("brake_cylinder_pressure_pa_c"))
    t, v, x = df["t_s"].to_numpy(), df["speed_mps_c1"].to_numpy(), df["position_m_c1"].to_numpy()
    nk = sum(1 for c in df.columns if c.startswith("coupler_force_n_k"))
    nv = nk + 1
    fc = np.column_stack([df[f"coupler_force_n_k{j}"].to_numpy() for j in range(1, nk + 1)])
    pc = np.column_stack([df[f"brake_cylinder_pressure_pa_c{i}"].to_numpy() for i in range(1, nv + 1)])
    summary = json.loads((run_dir / "summary.json").read_text())
    after = t >= brake_at_s - 1e-9
    i0 = int(np.argmax(after))
    fc = fc[after]  # in-train forces from the demand on (before it: the steady running tensions)
    t_fc = t[after]
    stop = np.flatnonzero((v <= 0.01) & after)
    last = pc[:, -1]
    pfull = float(pc.max())

    def first(cond: np.ndarray) -> float:
        k = np.flatnonzero(cond & after)
        return float(t[k[0]] - brake_at_s) if k.size else float("nan")

    return {
        "t_s": t, "v_mps": v, "cyl_pa": pc[:, [1, SILENT - 2, SILENT - 1, SILENT, nv - 1]],
        "cyl_vehicles": [2, SILENT - 1, SILENT, SILENT + 1, nv],
        "peak_tension_n": fc.max(axis=0), "peak_compression_n": fc.min(axis=0),
        "max_tension_n": float(fc.max()), "max_tension_at": int(np.argmax(fc.max(axis=0))) + 1,
        "max_tension_t_s": float(t_fc[int(np.argmax(fc.max(axis=1)))]),
        "max_compression_n": float(fc.min()), "max_compression_at": int(np.argmin(fc.min(axis=0))) + 1,
        "max_compression_t_s": float(t_fc[int(np.argmin(fc.min(axis=1)))]),
        "last_wagon_first_s": first(last > 0.0), "last_wagon_half_s": first(last >= 0.5 * pfull),
        "speed_lost_kmh": float((v[i0] - v[-1]) / KMH), "distance_after_m": float(x[-1] - x[i0]),
        "stopped_at_s": float(t[stop[0]]) if stop.size else float("nan"),
        "stopping_distance_m": float(x[stop[0]] - x[i0]) if stop.size else float("nan"),
        "silent_cyl_max_pa": float(pc[:, SILENT - 1].max()), "cyl_full_pa": pfull,
        "bus_load": summary.get("bus_load", {}), "latency": summary.get("bus_latency_in_loop", {}),
        "status": summary.get("status"),
    }


def execute(spec: Spec, duration_s: float, runs_dir: str, force: bool, scen_dir: str) -> tuple[str, bool, float]:
    from canbrake.run import run_scenario

    t0 = time.time()
    scn = _load(spec, duration_s, Path(scen_dir))
    run_dir = Path(runs_dir) / spec.key
    out = run_dir / "report.json"
    try:
        if not force and (run_dir / "scenario.yaml").read_text() == scn.to_yaml() and \
                json.loads(out.read_text()).get("version") == REPORT_VERSION:
            return spec.key, True, time.time() - t0
    except (OSError, ValueError):
        pass
    try:  # the run is there, only its reduction is older: reduce again
        same = (run_dir / "scenario.yaml").read_text() == scn.to_yaml() and (run_dir / "signals.csv").exists() \
            and json.loads((run_dir / "summary.json").read_text()).get("status") == "ok"
    except (OSError, ValueError):
        same = False
    s = {"status": "ok"} if same and not force else run_scenario(scn, run_dir, backend="inprocess", plots=False)
    if s.get("status") != "ok":
        raise RuntimeError(f"{spec.key}: run ended with status {s.get('status')!r} ({run_dir})")
    brake_at = float(scn.ecus[0].controller.params.get("brake_at_s", 5.0))
    r = reduce_run(run_dir, brake_at)
    r = {k: (v.tolist() if isinstance(v, np.ndarray) else v) for k, v in r.items()}
    out.write_text(json.dumps({"version": REPORT_VERSION, "brake_at_s": brake_at, **r}))
    (run_dir / "frames.log").unlink(missing_ok=True)
    return spec.key, False, time.time() - t0


def _star(a: tuple) -> tuple[str, bool, float]:
    return execute(*a)


def _fmt_s(x: float) -> str:
    return "—" if not np.isfinite(x) else f"{x:.2f} s"


#: the headline numbers of the step-size check (keys of a run's report.json)
STEP_HEADS = ("stopping_distance_m", "max_compression_n", "max_tension_n", "last_wagon_half_s")


def step_table(res: dict[str, dict[str, Any]], h0: float,
               specs: Sequence[Spec] = SPECS) -> tuple[list[str], bool, float | None]:
    """The step-size table's Markdown lines and whether the scenario's step ``h0`` (s) is converged,
    from the runs ``res`` (key -> report.json) of ``STEP_BASES`` at h0, h0/2, h0/4. The changes are
    those of :func:`canbrake.analysis.metrics.step_convergence` (one definition for every report);
    a number that is "never" (not finite: the train did not stop, the cylinder did not fill) on two
    neighbouring steps counts as unchanged, on one of them as changed. Converged: halving h0
    changes every headline number of every base run by less than ``metrics.STEP_TOL``; the third
    value is the largest relative change of that first halving (None: finite at one step, "never"
    at the other)."""
    from canbrake.analysis import metrics as M

    lines = ["| run | step | stopping distance (m) | peak compression (kN) | peak tension (kN) | "
             "last wagon half pressure | largest change to the next finer step |",
             "|---|---|---|---|---|---|---|"]
    converged = True
    worst: float | None = 0.0
    for base in STEP_BASES:
        if base not in res:
            continue
        chain = [(h0, res[base])] + [(h0 / d, res[f"{base}-h{1000 * h0 / d:g}ms"]) for d in STEP_DIVISORS]
        tab = M.step_convergence([(h, {k: (float(r[k]) if np.isfinite(r[k]) else None) for k in STEP_HEADS})
                                  for h, r in chain])
        converged = converged and M.first_converged_step(tab) == h0
        first = list(tab[1]["change"].values()) if len(tab) > 1 else []
        worst = None if (worst is None or None in first) else max([worst, *first])
        label = next(sp.label for sp in specs if sp.key == base)
        for i, (h, r) in enumerate(chain):
            if i + 1 < len(chain):
                ch = list(tab[i + 1]["change"].values())
                chs = ("changed (a number is finite at one step and \"never\" at the other)" if None in ch
                       else f"{100 * max(ch):.2f} %")
            else:
                chs = "—"
            sd_m = "—" if not np.isfinite(r["stopping_distance_m"]) else f"{r['stopping_distance_m']:.1f}"
            lines.append(f"| {label} | {1000 * h:g} ms | {sd_m} | {-r['max_compression_n'] / 1e3:.1f} | "
                         f"{r['max_tension_n'] / 1e3:.1f} | {_fmt_s(r['last_wagon_half_s'])} | {chs} |")
    return lines, converged, worst


DEFAULT_OUT = "docs"  # `canbrake report ecp` writes docs/ecp-over-can.md


def generate(out_dir: str | Path = "docs", runs_dir: str | Path = "runs/report-ecp", force: bool = False,
             jobs: int = 2, log: Callable[[str], None] = print, duration_s: float = DEFAULT_DURATION_S,
             specs: Sequence[Spec] = SPECS, scen_dir: str | Path | None = None, step_check: bool = True) -> Path:
    """Run (or reuse) the runs and write ``out_dir/ecp-over-can.md`` with ``figures/ecp_*.png``;
    ``step_check``: also the runs of ``STEP_BASES`` with the plant step halved twice (step table)."""
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    t0 = time.time()
    out_dir, runs_dir = Path(out_dir), Path(runs_dir)
    sd = Path(scen_dir) if scen_dir else scenario_dir()
    runs_dir.mkdir(parents=True, exist_ok=True)
    h0 = float(_load(specs[0], duration_s, sd).consist.max_substep_s)
    checks = step_specs(h0, specs) if step_check else []
    tasks = [(sp, duration_s, str(runs_dir), force, str(sd)) for sp in (*specs, *checks)]
    outs = map_tasks(_star, tasks, jobs)
    for key, reused, wall in outs:
        log(f"  {key}: {'reused' if reused else f'ran in {wall:.0f} s'}")
    res = {sp.key: json.loads((runs_dir / sp.key / "report.json").read_text()) for sp in (*specs, *checks)}

    fig_dir = out_dir / "figures"
    fig_dir.mkdir(parents=True, exist_ok=True)
    fig, ax = plt.subplots(3, 1, figsize=(9, 9))
    for sp in specs:
        r = res[sp.key]
        ax[0].plot(r["t_s"], np.asarray(r["v_mps"]) / KMH, lw=0.8, label=sp.label)
        ax[2].plot(np.arange(1, len(r["peak_tension_n"]) + 1), np.asarray(r["peak_tension_n"]) / 1e3, lw=0.8,
                   label=f"{sp.label}: tension")
        ax[2].plot(np.arange(1, len(r["peak_compression_n"]) + 1), np.asarray(r["peak_compression_n"]) / 1e3,
                   lw=0.8, ls="--")
    for sp in specs:
        if sp.key in ("ecp-250k", "pneumatic-250k"):
            r = res[sp.key]
            cyl = np.asarray(r["cyl_pa"])
            for j, veh in enumerate(r["cyl_vehicles"]):
                if veh in (2, r["cyl_vehicles"][-1]):
                    ax[1].plot(r["t_s"], cyl[:, j] / 1e3, lw=0.8, label=f"{sp.label}, vehicle {veh}")
    ax[0].set_ylabel("locomotive speed (km/h)")
    ax[1].set_ylabel("cylinder pressure (kPa)")
    ax[2].set_ylabel("peak coupler force (kN)\n(solid tension, dashed compression)")
    ax[2].set_xlabel("coupler j (behind vehicle j)")
    for a in ax:
        a.grid(alpha=0.3)
        a.legend(fontsize=7)
    ax[1].set_xlabel("time (s)")
    fig.tight_layout()
    fig.savefig(fig_dir / "ecp_over_can.png", dpi=110)
    plt.close(fig)

    base = res[specs[0].key]
    L: list[str] = []
    w = L.append
    w("# ECP braking over CAN on the 1+105 heavy-haul train")
    w("")
    w("<!-- generated by canbrake/report/ecp.py (generate()); do not edit by hand -->")
    w("")
    w(f"Li 2024's train (HXD1 + 105 C80, `scenarios/li2024_ecp_over_can.yaml`) runs at 60 km/h on level track; "
      f"at {base['brake_at_s']:.0f} s the locomotive ECU demands a full service application. With **ECP** each of the "
      "105 wagons has a brake ECU on the bus: it receives the demand in the locomotive ECU's STATE frame and "
      "commands its own cylinder (first-order fill, τ as in the pneumatic model); with the **pneumatic** brake the "
      "signal runs along the brake pipe at 200 m/s. The CAN timing model is on (`bus.timing: model`): frames that "
      "do not fit the bus queue and arrive late. Control period 50 ms (a 10 ms cycle of 105 command frames "
      f"does not fit even 500 kbit/s). Each run lasts {duration_s:g} s; every number below comes from the runs.")
    w("")
    w("| run | last wagon's cylinder starts / reaches half pressure after the demand | speed lost (km/h) | "
      "distance after the demand (m) | stop | peak tension (kN) at coupler | peak compression (kN) at coupler | "
      "bus load mean / peak | command frames late | command latency p99 |")
    w("|---|---|---|---|---|---|---|---|---|---|")
    for sp in specs:
        r = res[sp.key]
        bl, lat = r["bus_load"], r["latency"].get("brake_cmd", {})
        stop = "—" if not np.isfinite(r["stopping_distance_m"]) else f"{r['stopping_distance_m']:.0f} m at {r['stopped_at_s']:.1f} s"
        w(f"| {sp.label} | {_fmt_s(r['last_wagon_first_s'])} / {_fmt_s(r['last_wagon_half_s'])} | "
          f"{r['speed_lost_kmh']:.2f} | {r['distance_after_m']:.0f} | {stop} | "
          f"{r['max_tension_n'] / 1e3:.0f} at {r['max_tension_at']} ({r['max_tension_t_s']:.1f} s) | "
          f"{-r['max_compression_n'] / 1e3:.0f} at {r['max_compression_at']} ({r['max_compression_t_s']:.1f} s) | "
          f"{100 * bl.get('bus_load_mean', float('nan')):.0f} % / {100 * bl.get('bus_load_peak', float('nan')):.0f} % | "
          f"{lat.get('late_frames', '—')} of {lat.get('n', '—')} | "
          f"{1000 * lat.get('p99_s', float('nan')):.1f} ms |")
    w("")
    w("—: not within the run (stop: the train did not stop; cylinder: the last wagon's brake did not start). "
      "Coupler forces are the peaks from the demand on (+ tension); coupler j is behind vehicle j. The wagon "
      "ECUs send their command frames in the pneumatic run too (the plant ignores ECP demands there), so its "
      "bus columns equal ECP's at the same bit rate.")
    w("")
    # the silent wagon's settings as the scenario's profiles give them (not restated here)
    fs_cfg = _load(Spec("", "silent_wagon_failsafe", ""), duration_s, sd).safety
    silent_at = _load(Spec("", "silent_wagon", ""), duration_s, sd).bus.impairments[0].start_s
    sil = res.get("ecp-silent-wagon")
    if sil is not None:
        w(f"**A silent wagon ECU.** Wagon {SILENT}'s ECU stops sending at {silent_at:g} s, before the demand. The plant holds the "
          f"last command it received (zero-order hold: the papers' assumption, no fail-safe configured), which was "
          f"\"released\": its cylinder stays at {sil['silent_cyl_max_pa'] / 1e3:.1f} kPa while its neighbours reach "
          f"{max(np.asarray(sil['cyl_pa'])[:, 1].max(), np.asarray(sil['cyl_pa'])[:, 3].max()) / 1e3:.0f} kPa. "
          "The train loses one wagon's brake in 105; `safety.command_timeout_s` would make its brake unit brake on "
          "its own instead.")
        w("")
    fsr = res.get("ecp-silent-failsafe")
    if fsr is not None:
        fs_cmds = ", ".join(f"{k}: {v:g}" for k, v in (fs_cfg.failsafe_commands or {}).items())
        w(f"**The same with a fail-safe.** With `safety: {{command_timeout_s: {fs_cfg.command_timeout_s:g}, "
          f"failsafe_commands: {{{fs_cmds}}}}}` (profile `silent_wagon_failsafe`) wagon {SILENT}'s brake unit "
          f"applies on its own after {fs_cfg.command_timeout_s:g} s "
          f"without a command: its cylinder reaches {fsr['silent_cyl_max_pa'] / 1e3:.0f} kPa, before the demand at "
          f"{fsr['brake_at_s']:.0f} s, so the train runs with one wagon braking until the demand "
          + (f"and stops in {fsr['stopping_distance_m']:.0f} m" if np.isfinite(fsr["stopping_distance_m"]) else "")
          + f" (peak tension {fsr['max_tension_n'] / 1e3:.0f} kN, compression {-fsr['max_compression_n'] / 1e3:.0f} kN).")
        w("")
    if checks:
        w("## Integration step")
        w("")
        w(f"The plant integrates with a fixed step h = {1000 * h0:g} ms (semi-implicit Euler, "
          f"{int(round(_load(specs[0], duration_s, sd).control_period_s / h0))} sub-steps per control period). "
          "The same runs with h / 2 and h / 4 (change: relative to the next finer step):")
        w("")
        table, converged, worst = step_table(res, h0, specs)
        L.extend(table)
        w("")
        by = "between finite and \"never\"" if worst is None else f"by {100 * worst:.1f} %"
        verdict = ("converged: every headline number changes by less than 1 % when the step is halved"
                   if converged else
                   f"**not converged to 1 %**: halving the step changes a headline number {by}; "
                   "read the table's finest-step row")
        w(f"At the scenario's step the numbers above are {verdict}.")
        w("")
    w("Bus load counts every frame the recorder sees, including the plant's sensor frames (the plant's "
      "\"local wiring\" in the emulation) and the lockstep barrier frames; the timing model queues the "
      "ECUs' state, command and heartbeat frames by priority.")
    w("")
    w("![ECP over CAN](figures/ecp_over_can.png)")
    w("")
    w("## Runs")
    w("")
    w("```sh")
    for sp in (*specs, *checks):
        w(command(sp, duration_s, str(runs_dir)))
    w("```")
    w("")
    w(f"*Generated in {time.time() - t0:.0f} s by `canbrake.report.ecp.generate()`.*")
    md = out_dir / "ecp-over-can.md"
    md.write_text("\n".join(L) + "\n", encoding="utf-8")
    log(f"wrote {md}")
    return md
