"""`canbrake bench`: every performance figure beside its baseline, ratio and target (issue 13);
writes bench/results.json (with ``--only``: bench/results-GROUPS.json) and prints the table. A failed or diverged case is a row, not a traceback."""
from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path
from typing import Any


def _cmd(a: argparse.Namespace) -> int:
    from canbrake.benchmark import GROUPS, OPT_IN_GROUPS, notes, run_bench, table

    only = tuple(x.strip() for x in a.only.split(",")) if a.only else GROUPS
    bad = [x for x in only if x not in GROUPS + OPT_IN_GROUPS]
    if bad:
        print(f"canbrake bench: --only: unknown group {bad[0]!r} (choose from {', '.join(GROUPS + OPT_IN_GROUPS)})",
              file=sys.stderr)
        return 2
    if a.only and a.doc:
        print("canbrake bench: --doc: the generated section is the whole table; run it without --only",
              file=sys.stderr)
        return 2
    if a.quick:
        a.duration, a.repeat, a.realtime, a.scale_ticks = min(a.duration, 0.5), 1, min(a.realtime, 2.0), 50
        a.sweep_duration = min(a.sweep_duration, 0.5)
    if a.heavy:  # the 60 s realtime runs (the 10 ms run twice as long: 12,000 periods resolve 0.01 %)
        a.realtime = max(a.realtime, 60.0)
    log = (lambda s: print(s, file=sys.stderr, flush=True)) if not a.quiet else (lambda s: None)
    res = run_bench(only=only, duration_s=a.duration, repeat=a.repeat, realtime_s=a.realtime,
                    scale_ticks=a.scale_ticks, heavy=a.heavy, log=log, sweep_s=a.sweep_duration)
    # a run of some groups does not replace the results of every group (docs/performance.md's)
    out = Path(a.out or ("bench/results.json" if not a.only else f"bench/results-{'+'.join(only)}.json"))
    try:
        out.parent.mkdir(parents=True, exist_ok=True)
        out.write_text(json.dumps(res, indent=1) + "\n")
    except OSError as e:
        print(f"canbrake bench: cannot write {out}: {e.strerror or e}", file=sys.stderr)
        return 2
    m = res["machine"]
    print(f"{m['cpu']} x{m['cores']}, load {m['load_avg_1_5_15'][0]:.2f} -> {res['load_avg_at_end'][0]:.2f}, "
          f"{m['utc']} UTC, {res['bench_wall_s']:.0f} s")
    print(table(res, markdown=a.markdown))
    print(notes(res))
    from canbrake.benchmark import plot_106, plot_scale, write_doc

    pngs = [p for p in ((plot_scale(res, a.plot), plot_106(res, Path(a.plot).with_name("scale_106.png")))
                        if "scale" in only else ()) if p]
    if a.doc:
        try:
            pngs.append(write_doc(res, a.doc))
        except OSError as e:
            print(f"canbrake bench: --doc: cannot write {a.doc}: {e.strerror or e}", file=sys.stderr)
            return 2
    print(f"written: {out}" + "".join(f", {p}" for p in pngs))
    return 0


def register(sub: Any) -> None:
    p = sub.add_parser("bench", help="measure every performance figure against its baseline and target",
                       description="Codec, lockstep, realtime, scale and sweep figures, each beside "
                                   "a baseline measured in the same run, the ratio, the ratio to the floor of "
                                   "canbrake's process layout measured in the same run (canbrake.floor) and the "
                                   "target. Memory as PSS per process. Writes bench/results.json.")
    p.add_argument("scenario", nargs="?", default=None, help="ignored (kept for compatibility): the figures "
                   "use the repository's scenarios")
    p.add_argument("--duration", type=float, default=1.0, help="simulated seconds per lockstep run (default 1)")
    p.add_argument("--repeat", type=int, default=3, help="lockstep rounds, median taken (default 3)")
    p.add_argument("--realtime", type=float, default=5.0,
                   help="seconds of each 1 ms realtime run (the 10 ms run is twice as long; default 5); "
                        "the deadline-miss targets are judged over 60 s and 120 s (--heavy): shorter runs are "
                        "measured, and judged only when their misses alone miss the target")
    p.add_argument("--scale-ticks", type=int, default=200, help="periods per scale run (default 200)")
    p.add_argument("--sweep-duration", type=float, default=10.0,
                   help="simulated seconds per point of the sweep figure (default 10)")
    p.add_argument("--only", default="", help="comma-separated groups: codec,lockstep,realtime,scale,sweep (the "
                   "floor, which lockstep, realtime and scale figures are compared with, runs with any of those three); "
                   "opt-in: whole (Cai case 4 run whole with one process per ECU, minutes)")
    p.add_argument("--quick", action="store_true", help="short runs, one round (a smoke test of the bench)")
    p.add_argument("--heavy", action="store_true",
                   help="scale: also 48 cars with one process per ECU and the 106-ECU train with one process "
                        "per ECU (108 processes); realtime runs of at least 60 s; the opt-in group whole (long)")
    p.add_argument("--doc", default="", metavar="MD",
                   help="also write the figures into this Markdown file's generated section (e.g. "
                        "docs/performance.md; its plots go to figures/ beside it)")
    p.add_argument("--markdown", action="store_true", help="print the table as Markdown")
    p.add_argument("--quiet", action="store_true", help="no progress lines on stderr")
    p.add_argument("--out", default="", help="where to write the results (JSON; default bench/results.json, "
                   "with --only bench/results-GROUPS.json)")
    p.add_argument("--plot", default="bench/scale.png", help="where to write the scale plot (PNG)")
    p.set_defaults(func=_cmd)
