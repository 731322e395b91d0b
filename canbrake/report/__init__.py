"""Generated reproduction reports (``canbrake report NAME``).

Each report is a module with ``generate(out_dir, runs_dir, force=False, jobs=2, log=print) -> Path``
that runs (or reuses) its runs and writes a Markdown document with figures.
"""
from __future__ import annotations

REPORTS = {"chen2023": "canbrake.report.chen2023", "li2024": "canbrake.report.li2024",
           "cai2014": "canbrake.report.cai2014", "safety": "canbrake.report.safety", "ecp": "canbrake.report.ecp",
           "delay": "canbrake.report.delay", "ecp_literature": "canbrake.report.ecp_literature",
           "mixed_emu": "canbrake.report.mixed_emu", "hh_consensus": "canbrake.report.hh_consensus"}
