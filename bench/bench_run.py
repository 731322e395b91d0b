"""Benchmark: control periods per wall second of Chen case 1 (6 cars, 1 ms) for each backend,
as ratios against the in-process engine measured in the same process (`canbrake bench` prints
the same table).

    python bench/bench_run.py [--duration 1.0] [--repeat 3]
"""
from __future__ import annotations

import sys

from canbrake.cli import main

if __name__ == "__main__":
    sys.exit(main(["bench", *sys.argv[1:]]))
