"""Chen 2023 runs through the node engine for the tests: Table 2 comes from the scenario files.

:func:`chen_scenario` loads ``scenarios/chen2023_case*.yaml`` with dotted-key overrides (the same
mechanism as ``canbrake run --set``); :func:`run_engine` runs it in process on the node engine
(plant node, one ECU node per car, CAN frames from the generated DBC) and reads ``signals.csv``
back as a :class:`ChenTrace`.
"""
from __future__ import annotations

import math
import tempfile
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from canbrake.analysis.metrics import settling_time_s
from canbrake.analysis.summary import read_signals
from canbrake.run import run_scenario
from canbrake.scenario import Scenario, load_scenario

SCENARIOS = Path(__file__).resolve().parents[1] / "scenarios"
CASES = {1: SCENARIOS / "chen2023_case1_fine_rail.yaml", 2: SCENARIOS / "chen2023_case2_poor_rail.yaml",
         3: SCENARIOS / "chen2023_case3_disturbance.yaml"}


def chen_scenario(case: int = 1, *, duration_s: float, profile: str | None = None, **overrides: Any) -> Scenario:
    """Chen case ``case`` cut to ``duration_s``; ``overrides`` are dotted keys with ``__`` for ``.``
    (``controller__params__observer=False``) or a dict given as ``set={...}``."""
    sets = {k.replace("__", "."): v for k, v in overrides.items() if k != "set"}
    sets.update(overrides.get("set", {}))
    sets["duration_s"] = duration_s
    return load_scenario(CASES[case], profile=profile, overrides=sets)


@dataclass
class ChenTrace:
    """signals.csv of one run as arrays: (N,) per tick, (N, n) per car, (N, n-1) per coupler.

    Row k is the state at tick k and the command computed from it (held over [t_k, t_k+1]); the
    last row has no command (NaN). ``applied_force_n`` is the rail force of the period ending at
    tick k. ``diag[name]`` are the ECUs' diagnostics (N, n)."""

    scn: Scenario
    cols: dict[str, np.ndarray]

    def _stack(self, prefix: str, count: int) -> np.ndarray:
        return np.column_stack([self.cols[f"{prefix}{c}"] for c in range(1, count + 1)])

    def __post_init__(self) -> None:
        n = self.scn.n_cars
        self.t_s = self.cols["t_s"]
        self.ref_speed_mps = self.cols["ref_speed_mps"]
        self.position_m = self._stack("position_m_c", n)
        self.speed_mps = self._stack("speed_mps_c", n)
        self.accel_mps2 = self._stack("accel_mps2_c", n)
        self.command_n = self._stack("brake_cmd_n_c", n)
        self.applied_force_n = self._stack("brake_applied_n_c", n)
        self.deflection_m = self._stack("deflection_m_k", n - 1)
        self.coupler_force_n = self._stack("coupler_force_n_k", n - 1)
        self.mass_kg = self.scn.vehicle_masses_kg()

    def diag(self, name: str) -> np.ndarray:
        """ECU diagnostic ``name`` per car, (N, n)."""
        return self._stack(f"{name}_c", self.scn.n_cars)

    @property
    def speed_error_mps(self) -> np.ndarray:
        """v_i − v* (m/s), (N, n)."""
        return self.speed_mps - self.ref_speed_mps[:, None]

    def window(self, t_from_s: float = 0.0, t_to_s: float = math.inf) -> np.ndarray:
        """Boolean mask of the rows with t_from_s <= t <= t_to_s."""
        return (self.t_s >= t_from_s - 1e-12) & (self.t_s <= t_to_s + 1e-12)

    def max_abs_deflection_m(self, t_from_s: float = 0.0) -> float:
        """max |Δl| over couplers from ``t_from_s`` on (m)."""
        return float(np.max(np.abs(self.deflection_m[self.window(t_from_s)])))

    def convergence_time_s(self, tol_mps: float, t_from_s: float = 0.0) -> float:
        """Time after ``t_from_s`` from which every |v_i − v*| stays ≤ ``tol_mps`` (inf: never)."""
        t = settling_time_s(self.t_s, self.speed_error_mps, tol_mps, t_from_s)
        return math.inf if t is None else t - t_from_s


def run_engine(scn: Scenario, out_dir: str | Path | None = None) -> ChenTrace:
    """Run ``scn`` in process on the node engine and return its trace."""
    if out_dir is None:
        with tempfile.TemporaryDirectory(prefix="canbrake-chen-") as tmp:
            return run_engine(scn, tmp)
    s = run_scenario(scn, out_dir, backend="inprocess", plots=False)
    assert s["status"] == "ok", s.get("message")
    return ChenTrace(scn, read_signals(Path(out_dir) / "signals.csv"))
