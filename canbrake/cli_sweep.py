"""``canbrake sweep``: run a scenario over a grid of impairments (and any scenario field) × seeds,
write results.csv and heatmaps. The work is done by :mod:`canbrake.sweep`."""
from __future__ import annotations

import argparse
import os
import sys
from pathlib import Path
from typing import Any

DEFAULT_GRID = ("delay=0:50ms:11", "loss=0:0.5:11")

EPILOG = """\
grid axes (NAME=START:STOP[UNIT]:COUNT or NAME=V1,V2,...):
  delay, loss, jitter        on every ECU's STATE (0x141..) and BRAKE_CMD (0x081..) frames
  state_delay/_loss/_jitter  STATE frames only;  cmd_delay/_loss/_jitter  BRAKE_CMD frames only
  bitrate (bps, kbps), period (control period; s, ms, us), set:DOTTED.PATH (any scenario field)
  units: s, ms, us, % (loss), kbps; e.g. --grid delay=0:50ms:11 --grid loss=0:50%:11
         --grid set:controller.name=chen2023,chen2023_compensated   (a third axis: maps side by side)

writes DIR/results.csv (one row per point and seed), DIR/heatmap_{deflection,speed_rmse,convergence,safety}.png,
DIR/thresholds.md, DIR/sweep.json and DIR/points/<id>/summary.json. Rerunning the same command resumes: finished points
are skipped (use a new DIR after changing canbrake's code). Classification: docs/delay-robustness.md.
"""


def _cmd_sweep(a: argparse.Namespace) -> int:
    from canbrake.cli import EXIT_INTERRUPTED, EXIT_OK, InputError, _parse_set
    from canbrake.scenario import load_scenario
    from canbrake.sweep import GridError, check_axes, parse_grid, run_sweep

    try:
        axes = [parse_grid(g) for g in (a.grid or DEFAULT_GRID)]
        check_axes(axes)
    except GridError as e:
        raise InputError(str(e)) from None
    sets = _parse_set(a.set or [])
    if a.workers is not None and a.workers < 0:
        raise InputError(f"--workers must be >= 0, got {a.workers}")
    if a.seeds < 1:
        raise InputError(f"--seeds must be >= 1, got {a.seeds}")
    if a.duration is not None and not a.duration > 0:
        raise InputError(f"--duration must be > 0, got {a.duration:g}")
    scheduler = a.scheduler
    if scheduler is not None and scheduler.lower() == "none":
        scheduler = "none"
    workers = a.workers if a.workers is not None else min(os.cpu_count() or 1, 8)
    if a.out:
        out = Path(a.out)
    else:
        base = load_scenario(a.scenario, profile=a.profile, overrides=sets)
        out = Path("runs") / (f"sweep-{base.name}" + (f"-{a.profile}" if a.profile else ""))
    where = ("serially in this process" if scheduler == "none" or (scheduler is None and workers == 0)
             else f"on the Dask scheduler {scheduler}" if scheduler else f"on {workers} local Dask worker(s)")
    print(f"canbrake: sweep of {a.scenario} over " + " x ".join(f"{ax.name}[{len(ax.values)}]" for ax in axes)
          + f", {where}", file=sys.stderr)

    def log(msg: str) -> None:
        print(f"canbrake: {msg}", file=sys.stderr)

    try:
        res = run_sweep(a.scenario, axes, out, profile=a.profile, sets=sets, duration_s=a.duration, seeds=a.seeds,
                        workers=workers, scheduler=scheduler, keep=a.keep, plots=not a.no_plots,
                        progress=not a.quiet, log=log, engine=a.engine)
    except GridError as e:
        raise InputError(str(e)) from None
    done = len(res.rows)
    if res.interrupted:
        print(f"canbrake: interrupted; {done} run(s) in {res.results_csv}. Run the same command again to resume.",
              file=sys.stderr)
        return EXIT_INTERRUPTED
    _print_table(res.rows)
    th = res.out / "thresholds.md"
    if th.exists():
        print("first grid value (worst seed) at which the run ...\n" + th.read_text().rstrip())
    print(f"ran {res.ran}, reused {res.skipped}; written: {res.results_csv}"
          + (", " + ", ".join(p.name for p in res.heatmaps) if res.heatmaps else ""))
    if res.errors:
        print(f"canbrake: {res.errors} run(s) ended in an error (status 'error' in results.csv); "
              f"rerun to retry them", file=sys.stderr)
        return 1
    return EXIT_OK


def _print_table(rows: list[dict[str, Any]]) -> None:
    from collections import Counter

    c = Counter(r.get("safety") or r.get("status") for r in rows)
    parts = [f"{k}: {c[k]}" for k in ("ok", "degraded", "violation", "unstable", "invalid", "error") if c.get(k)]
    print("runs by outcome — " + ", ".join(parts))


def register(sub: Any) -> None:
    """Add the ``sweep`` subcommand to the ``canbrake`` parser."""
    s = sub.add_parser("sweep", help="run a scenario over a grid of impairments, write results.csv and heatmaps",
                       description="Run SCENARIO over a grid (delay x loss by default) with the in-process lockstep "
                                   "engine, several seeds where randomness is involved, on Dask workers.",
                       epilog=EPILOG, formatter_class=argparse.RawDescriptionHelpFormatter)
    s.add_argument("scenario", help="scenario YAML file, or the name of a built-in scenario (canbrake scenarios)")
    s.add_argument("--grid", action="append", metavar="NAME=SPEC",
                   help=f"a grid axis (repeatable); default: {' '.join(DEFAULT_GRID)}")
    s.add_argument("--profile", help="a profile of the scenario (e.g. paper, realistic)")
    s.add_argument("--set", action="append", metavar="KEY=VALUE", help="override a scenario field (repeatable)")
    s.add_argument("--duration", type=float, metavar="S",
                   help="simulated seconds per run (default: 1000 control periods, at most the scenario's duration)")
    s.add_argument("--seeds", type=int, default=3, help="seeds per point where loss/jitter is involved (default 3)")
    s.add_argument("--workers", type=int, help="local Dask worker processes (default: CPU count; 0 = serial, "
                                               "in this process)")
    s.add_argument("--scheduler", metavar="ADDRESS",
                   help="address of an existing Dask scheduler (tcp://host:8786), or 'none' to run serially")
    s.add_argument("--out", help="output directory (default runs/sweep-<scenario>[-<profile>])")
    s.add_argument("--keep", choices=["summary", "all"], default="summary",
                   help="what to keep of each run: summary.json and stats (default) or all traces")
    s.add_argument("--engine", choices=["auto", "batch", "points"], default="auto",
                   help="auto: run the points the batch engine supports many at once in one process "
                        "(canbrake.batch; the others one by one, with a line saying why); batch: only the batch "
                        "engine (exit 2 if a point needs the per-point engine); points: every point by itself "
                        "with the in-process node engine (default auto)")
    s.add_argument("--no-plots", action="store_true", help="do not draw the heatmaps")
    s.add_argument("-q", "--quiet", action="store_true", help="no progress bar")
    s.set_defaults(func=_cmd_sweep)
