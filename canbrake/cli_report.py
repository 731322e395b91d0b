"""``canbrake report NAME``: regenerate a reproduction report (runs, figures, Markdown)."""
from __future__ import annotations

import argparse
import os
import sys
from typing import Any


def register(sub: Any) -> None:
    from canbrake.report import REPORTS

    p = sub.add_parser("report", help="regenerate a reproduction report (e.g. chen2023)",
                       description="Run (or reuse) the runs of a reproduction report and write it with its "
                                   "figures. A run is reused when its resolved scenario is unchanged and it "
                                   "finished ok; --force reruns everything.")
    p.add_argument("name", choices=sorted(REPORTS), help="which report")
    p.add_argument("--out", default=None, help="where the report and figures/ go "
                                               "(default docs/reproduction; docs for safety, ecp, delay)")
    p.add_argument("--runs", default=None, help="run directories (default runs/report-NAME)")
    p.add_argument("--force", action="store_true", help="rerun every run instead of reusing")
    p.add_argument("--jobs", type=int, default=min(2, os.cpu_count() or 1),
                   help="worker processes (default: min(2, CPUs))")
    p.set_defaults(func=_cmd_report)


def _cmd_report(a: argparse.Namespace) -> int:
    import importlib

    from canbrake.cli import InputError
    from canbrake.report import REPORTS

    if a.jobs < 1:
        raise InputError(f"--jobs: must be at least 1, got {a.jobs}")
    mod = importlib.import_module(REPORTS[a.name])
    runs = a.runs or os.path.join("runs", f"report-{a.name}")

    def log(msg: str) -> None:
        print(msg, file=sys.stderr, flush=True)

    out = a.out or getattr(mod, "DEFAULT_OUT", "docs/reproduction")
    path = mod.generate(out, runs, force=a.force, jobs=a.jobs, log=log)
    print(path)
    return 0
