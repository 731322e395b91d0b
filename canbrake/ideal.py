"""Ideal-communication closed loop: plant + one controller per car, no bus.

Every control period ``dt_s`` each controller sees the exact sampled plant state of the same instant
(own and peer speeds/positions with age 0, local coupler deflections), computes its brake force, and
the plant integrates one period with the forces held (zero-order hold). This is the reference that
bus-in-the-loop runs are compared against, and the fast loop for tests and tuning.
"""
from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Sequence

import numpy as np

from canbrake.control.base import Controller, Observation
from canbrake.physics.train import TrainPlant


@dataclass(frozen=True)
class BrakingReference:
    """v*(t) = v*(t0) − a*·(t − t0), floored at 0 (m/s); a* > 0 decelerates (m/s²)."""

    initial_speed_mps: float
    decel_mps2: float
    start_s: float = 0.0

    def speed_mps(self, time_s: float) -> float:
        """Reference speed (m/s) at ``time_s``."""
        v = self.initial_speed_mps - self.decel_mps2 * max(time_s - self.start_s, 0.0)
        return v if v > 0.0 else 0.0

    def decel_mps2_at(self, time_s: float) -> float:
        """Reference deceleration a* (m/s²) at ``time_s``: 0 once v* has reached 0."""
        return self.decel_mps2 if self.speed_mps(time_s) > 0.0 else 0.0


@dataclass
class IdealResult:
    """Sampled trace, one row per control tick (N = steps + 1 rows, the first at t = 0).

    Shapes: ``t_s`` (N,), per-car arrays (N, n), coupler arrays (N, n−1). Units in the names.
    Row k holds the state *at* tick k and the command computed from it (held over [t_k, t_k+1]);
    ``applied_force_n`` is the rail force at the end of the period before tick k.
    """

    t_s: np.ndarray
    position_m: np.ndarray
    speed_mps: np.ndarray
    accel_mps2: np.ndarray
    deflection_m: np.ndarray
    coupler_force_n: np.ndarray
    command_n: np.ndarray
    applied_force_n: np.ndarray
    observer_accel_mps2: np.ndarray
    ref_speed_mps: np.ndarray
    diagnostics: dict[str, np.ndarray] = field(default_factory=dict)

    # short aliases
    @property
    def t(self) -> np.ndarray:
        return self.t_s

    @property
    def x(self) -> np.ndarray:
        return self.position_m

    @property
    def v(self) -> np.ndarray:
        return self.speed_mps

    @property
    def speed_error_mps(self) -> np.ndarray:
        """v_i − v* (m/s), shape (N, n)."""
        return self.speed_mps - self.ref_speed_mps[:, None]

    def window(self, t_from_s: float = 0.0, t_to_s: float = math.inf) -> np.ndarray:
        """Boolean mask of the rows with t_from_s <= t <= t_to_s."""
        return (self.t_s >= t_from_s - 1e-12) & (self.t_s <= t_to_s + 1e-12)

    def max_abs_deflection_m(self, t_from_s: float = 0.0, t_to_s: float = math.inf) -> float:
        """max |Δl| over couplers and the time window (m)."""
        w = self.window(t_from_s, t_to_s)
        return float(np.max(np.abs(self.deflection_m[w]))) if self.deflection_m.size else 0.0

    def rmse_mps(self, t_from_s: float = 0.0, t_to_s: float = math.inf) -> float:
        """Root-mean-square speed error over cars and the window (m/s)."""
        w = self.window(t_from_s, t_to_s)
        return float(np.sqrt(np.mean(self.speed_error_mps[w] ** 2)))

    def convergence_time_s(self, tol_mps: float, t_from_s: float = 0.0, t_to_s: float = math.inf) -> float:
        """Time after ``t_from_s`` from which every |v_i − v*| stays ≤ ``tol_mps`` until ``t_to_s``.

        ``inf`` if the error is still above the tolerance at the end of the window.
        """
        w = self.window(t_from_s, t_to_s)
        t = self.t_s[w]
        bad = np.any(np.abs(self.speed_error_mps[w]) > tol_mps, axis=1)
        if not bad.any():
            return 0.0
        last_bad = int(np.nonzero(bad)[0][-1])
        if last_bad == t.size - 1:
            return math.inf
        return float(t[last_bad + 1] - t_from_s)


def simulate_ideal(
    plant: TrainPlant,
    controllers: Sequence[Controller],
    reference: BrakingReference,
    duration_s: float,
    dt_s: float = 1e-3,
) -> IdealResult:
    """Run the sampled closed loop for ``duration_s`` seconds at control period ``dt_s``.

    ``plant`` is advanced in place (from its current state); ``controllers[i]`` drives car i.
    """
    n = plant.n_cars
    if len(controllers) != n:
        raise ValueError(f"need one controller per car ({n}), got {len(controllers)}")
    steps = int(round(duration_s / dt_s))
    rows = steps + 1
    t_out = np.empty(rows)
    x_out = np.empty((rows, n))
    v_out = np.empty((rows, n))
    a_out = np.empty((rows, n))
    cmd_out = np.empty((rows, n))
    app_out = np.empty((rows, n))
    ref_out = np.empty(rows)
    diag_names: list[str] = []
    for c in controllers:
        for name in c.diagnostic_names:
            if name not in diag_names:
                diag_names.append(name)
    diag_rows: list[list[dict[str, float]]] = []

    zero_age = np.zeros(n)
    zero_age.setflags(write=False)
    cmd = np.zeros(n)
    t0 = plant.time_s
    car_range = range(n)
    for k in range(rows):
        t = t0 + k * dt_s
        x = plant.position_m.copy()
        v = plant.speed_mps.copy()
        x.setflags(write=False)
        v.setflags(write=False)
        vref = reference.speed_mps(t)
        aref = reference.decel_mps2_at(t)
        t_out[k] = t
        x_out[k] = x
        v_out[k] = v
        a_out[k] = plant.accel_mps2
        app_out[k] = plant.applied_force_n
        ref_out[k] = vref
        dl_list = [None, *plant.deflection_m.tolist(), None]
        xs = x.tolist()
        vs = v.tolist()
        diags = []
        for i in car_range:
            out = controllers[i].step(
                Observation(
                    tick=k,
                    time_s=t,
                    speed_mps=vs[i],
                    position_m=xs[i],
                    ref_speed_mps=vref,
                    ref_decel_mps2=aref,
                    peer_speed_mps=v,
                    peer_position_m=x,
                    peer_age_s=zero_age,
                    deflection_front_m=dl_list[i],  # coupler to car i-1
                    deflection_rear_m=dl_list[i + 1],  # coupler to car i+1
                )
            )
            cmd[i] = out.brake_force_n
            diags.append(out.diagnostics)
        diag_rows.append(diags)
        cmd_out[k] = cmd
        if k < steps:
            plant.step(dt_s, cmd)
    dl_out = x_out[:, :-1] - x_out[:, 1:] - plant.coupler_spacing_m
    phi_out = plant.coupler_force_from_deflection(dl_out)
    diag = {name: np.full((rows, n), np.nan) for name in diag_names}
    for i in car_range:
        names = tuple(controllers[i].diagnostic_names)
        col = [row[i] for row in diag_rows]
        if names and all(tuple(d) == names for d in col):  # fast path: fixed key order
            block = np.array([list(d.values()) for d in col], dtype=float)
            for j, name in enumerate(names):
                diag[name][:, i] = block[:, j]
        else:
            for k, d in enumerate(col):
                for name, val in d.items():
                    if name in diag:
                        diag[name][k, i] = val
    obs_out = diag.get("observer_accel_mps2", np.full((rows, n), np.nan))
    return IdealResult(
        t_s=t_out,
        position_m=x_out,
        speed_mps=v_out,
        accel_mps2=a_out,
        deflection_m=dl_out,
        coupler_force_n=phi_out,
        command_n=cmd_out,
        applied_force_n=app_out,
        observer_accel_mps2=obs_out,
        ref_speed_mps=ref_out,
        diagnostics=diag,
    )
