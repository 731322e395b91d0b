"""Delay-compensated Chen 2023 controller, registered as ``chen2023_compensated``.

The Chen 2023 law (:class:`~canbrake.control.chen.ChenConsensusController`) assumes every peer value is
of this instant. Over CAN a peer's speed and position arrive ``age`` seconds old (delay, jitter, a lost
frame held), and the law breaks in three ways (docs/delay-robustness.md):

1. a deflection computed from an old peer position is wrong by the distance run during the age,
   v·age — 25 mm per millisecond at 90 km/h, against a ±1 cm bound — and the barrier answers a wrong
   2.5 cm with an enormous force;
2. an old peer speed is biased by the deceleration during the age;
3. a delayed brake command adds dead time to loops tuned for none (the speed consensus runs at
   n·α1 = 720 1/s), and the disturbance observer, driven with the command of this instant, reads the
   command still in flight as a disturbance and "cancels" it.

This controller keeps the law and its gains, and changes what it is fed:

* **time-aligned differencing** (``align``): each ECU keeps a short history of its own sensor samples
  (``history_s``) and forms the deflection with the peer from the *same instant*:
  Δl(t−a) = x_j(t−a) − x_i(t−a) − s, which the CAN age a makes exact (no v·a error); it is then
  predicted to now with the relative speed of that instant, Δl(t) ≈ Δl(t−a) + (v_j − v_i)(t−a)·a
  (``predict``). A peer older than the history is ignored.
* **age-aware peer speed** (``speed_alignment``): ``"own_motion"`` predicts the peer's speed to now
  with this car's own measured change of speed over the age, v_j(t) ≈ v_j(t−a) + v_i(t) − v_i(t−a)
  (exact when the cars decelerate alike, whatever the rate); ``"reference"`` with the reference
  deceleration, v_j − a*·a; ``"none"`` holds it.
* **latency-aware gains** (``gain_schedule``): the network latency is estimated from the ages seen
  (a peak detector with decay ``latency_decay_s`` on the mean peer age; the command path is assumed to
  see the same latency unless ``command_latency_s`` is given). With a loop dead time τ (the command
  latency plus the peer age the law acts on), the consensus, tracking and position gains are reduced so
  that bandwidth × τ ≤ ``delay_margin`` (rad): α1 ≤ margin/(n_eig·τ), k ≤ margin/τ, and α2, δ scaled
  with the square of α1's reduction (the relative position mode keeps its damping); the barrier is
  clipped (``barrier_clip``) where it would give two coupled cars a relative stiffness above
  (margin/τ)², so it cannot fire its 10⁶ m/s² relay into a loop with dead time. Without latency the
  gains are Chen's, and so is every command.
* **observer fed with the command in flight** (``observer_delay``): the sliding-mode observer is
  driven with the command issued one estimated command latency ago, the one acting on the car now.

All of the parent's parameters are accepted (``stale_policy`` must stay ``"hold"``; this class does
the age handling). Units: SI. Limits: the ages come from the E2E alive counter, which aliases from 15
periods on; a latency on the command path alone is invisible to the ECU (set ``command_latency_s``).
"""
from __future__ import annotations

import math
from collections import deque
from dataclasses import replace
from typing import Any

import numpy as np

from canbrake.control.base import ControlOutput, Observation, register
from canbrake.control.chen import ChenConsensusController, barrier_gradient, barrier_gradient_many

_SPEED = ("own_motion", "reference", "none")


class _DelayedInputObserver:
    """Wraps a :class:`~canbrake.control.observer.SlidingModeObserver` so that ``predict`` is driven
    with the force commanded ``delay_ticks`` periods ago (the one reaching the car now)."""

    def __init__(self, inner: Any, max_ticks: int) -> None:
        self.inner = inner
        self.delay_ticks = 0
        self._fifo: deque[float] = deque(maxlen=max_ticks + 1)

    @property
    def phi_hat_mps2(self) -> float:
        return self.inner.phi_hat_mps2

    def reset(self) -> None:
        self._fifo.clear()
        self.inner.reset()

    def update(self, position_m: float, speed_mps: float) -> float:
        return self.inner.update(position_m, speed_mps)

    def predict(self, brake_force_n: float) -> None:
        self._fifo.append(brake_force_n)
        d = min(self.delay_ticks, len(self._fifo) - 1)
        self.inner.predict(self._fifo[-1 - d])

    # batch form (canbrake.batch): one FIFO per point, as a ring of the last maxlen forces
    def reset_many(self, n_points: int) -> None:
        self.inner.reset_many(n_points)
        self._ring = np.zeros((self._fifo.maxlen or 1, n_points))
        self._n_in = 0

    def update_many(self, position_m: np.ndarray, speed_mps: np.ndarray) -> np.ndarray:
        return self.inner.update_many(position_m, speed_mps)

    def predict_many(self, brake_force_n: np.ndarray) -> None:
        size = self._ring.shape[0]
        self._ring[self._n_in % size] = brake_force_n
        self._n_in += 1
        d = np.minimum(self.delay_ticks, min(self._n_in, size) - 1)
        self.inner.predict_many(self._ring[(self._n_in - 1 - d) % size, np.arange(self._ring.shape[1])])


@register("chen2023_compensated")
class ChenCompensatedController(ChenConsensusController):
    """Chen 2023 with age-aware peer data and latency-aware gains (see the module docstring).

    Extra parameters: ``align`` (bool), ``predict`` (bool), ``speed_alignment``
    ("own_motion" | "reference" | "none"), ``history_s`` (s), ``gain_schedule`` (bool),
    ``delay_margin`` (rad), ``latency_decay_s`` (s), ``command_latency_s`` (s; None = as measured on
    the peers' state frames), ``observer_delay`` (bool).
    """

    diagnostic_names = ChenConsensusController.diagnostic_names + ("latency_estimate_s", "gain_scale")

    def __init__(self, car_index: int, n_cars: int, mass_kg: float, dt_s: float, *, align: bool = True,
                 predict: bool = True, speed_alignment: str = "own_motion", history_s: float = 0.25,
                 gain_schedule: bool = True, delay_margin: float = 0.8, latency_decay_s: float = 0.5,
                 command_latency_s: float | None = None, observer_delay: bool = True, **chen: Any) -> None:
        if chen.get("stale_policy", "hold") != "hold":
            raise ValueError("chen2023_compensated handles peer ages itself; leave stale_policy at 'hold'")
        if speed_alignment not in _SPEED:
            raise ValueError(f"speed_alignment must be one of {_SPEED}, not {speed_alignment!r}")
        if not history_s > 0:
            raise ValueError("history_s must be > 0")
        if not delay_margin > 0:
            raise ValueError("delay_margin must be > 0")
        if command_latency_s is not None and command_latency_s < 0:
            raise ValueError("command_latency_s must be >= 0 (or null: as measured)")
        super().__init__(car_index, n_cars, mass_kg, dt_s, **chen)
        self.align = bool(align)
        self.predict = bool(predict)
        self.speed_alignment = speed_alignment
        self.history_s = float(history_s)
        self.gain_schedule = bool(gain_schedule)
        self.delay_margin = float(delay_margin)
        self.latency_decay_s = float(latency_decay_s)
        self.command_latency_s = None if command_latency_s is None else float(command_latency_s)
        self.observer_delay = bool(observer_delay)
        self._n_hist = max(2, int(math.ceil(self.history_s / self.dt_s)) + 1)
        self._nominal = (self.alpha1, self.alpha2, self.delta, self.k, self.barrier_clip)
        # largest Laplacian eigenvalue of the velocity graph: n (complete graph), < 4 (path)
        self._eig = float(n_cars) if self.velocity_graph == "all" else 4.0
        self._obs = _DelayedInputObserver(self._obs, self._n_hist)
        self._decay = math.exp(-self.dt_s / self.latency_decay_s) if self.latency_decay_s > 0 else 0.0
        self._reset_history()

    def reset(self) -> None:
        super().reset()
        if hasattr(self, "_n_hist"):
            self._reset_history()

    def _reset_history(self) -> None:
        self._hist_x = np.full(self._n_hist, np.nan)
        self._hist_v = np.full(self._n_hist, np.nan)
        self._hist_tick = np.full(self._n_hist, -1, dtype=np.int64)
        self._latency_s = 0.0
        self._clip_key: tuple | None = None
        self._clip = self._nominal[4]

    # ------------------------------------------------------------------
    def _own_at(self, tick: int) -> tuple[float, float] | None:
        """Own (position, speed) at ``tick`` from the history, None if not held."""
        slot = tick % self._n_hist
        if tick < 0 or self._hist_tick[slot] != tick:
            return None
        return float(self._hist_x[slot]), float(self._hist_v[slot])

    def _aligned(self, obs: Observation) -> Observation:
        """The observation with every peer value predicted to this instant (age 0), NaN if unusable."""
        n, i = self.n_cars, self.car_index
        px = obs.peer_position_m.astype(float).copy()
        pv = obs.peer_speed_mps.astype(float).copy()
        ages = obs.peer_age_s
        x_now, v_now = obs.position_m, obs.speed_mps
        for j in range(n):
            if j == i:
                continue
            a = float(ages[j])
            if not (px[j] == px[j]) or not math.isfinite(a):
                continue
            lag = int(round(a / self.dt_s))
            if lag <= 0:
                continue
            own = self._own_at(obs.tick - lag)
            if own is None:
                if self.align:
                    px[j] = pv[j] = np.nan
                continue
            x_then, v_then = own
            if self.align:
                rel = px[j] - x_then  # x_j − x_i at the same instant
                if self.predict:
                    rel += (pv[j] - v_then) * a
                px[j] = x_now + rel
            if self.speed_alignment == "own_motion":
                pv[j] = pv[j] + (v_now - v_then)
            elif self.speed_alignment == "reference":
                pv[j] = pv[j] - obs.ref_decel_mps2 * a
        return replace(obs, peer_position_m=px, peer_speed_mps=pv,
                       peer_age_s=np.where(np.isnan(pv), np.inf, 0.0))

    def _update_latency(self, obs: Observation) -> None:
        ages = np.delete(obs.peer_age_s, self.car_index)
        ages = ages[np.isfinite(ages)]
        now = float(ages.mean()) if ages.size else 0.0
        self._latency_s = max(now, self._latency_s * self._decay)

    def _barrier_stiffness(self, z: Any, delta: Any, grad: Any = barrier_gradient) -> Any:
        """δ·U''(z) per metre of deflection (1/s², mass-scaled), by differencing the parent's ∇U
        (``grad``: barrier_gradient, or barrier_gradient_many for arrays)."""
        h = 1e-4
        lo, hi = self._z_lower, self._z_upper
        g = (grad(z + h, lo, hi, self.barrier, 0.999999) - grad(z - h, lo, hi, self.barrier, 0.999999)) / (2 * h)
        return delta * g / self.barrier_unit_m

    def _barrier_clip_for(self, omega2_max: float, delta: float, nominal_clip: float) -> float:
        """Largest clip ≤ nominal where the barrier's stiffness stays ≤ ``omega2_max`` / 2 (two cars
        share a coupler, so the relative mode sees twice the stiffness)."""
        if delta <= 0:
            return nominal_clip
        limit = 0.5 * omega2_max

        def stiff(c: float) -> float:  # the parent clips z to [c·z_lower, c·z_upper]
            return max(self._barrier_stiffness(c * self._z_upper, delta),
                       self._barrier_stiffness(c * self._z_lower, delta))

        if stiff(nominal_clip) <= limit:
            return nominal_clip
        lo, hi = 1e-3, nominal_clip
        if stiff(lo) > limit:
            return lo
        for _ in range(40):
            mid = 0.5 * (lo + hi)
            if stiff(mid) <= limit:
                lo = mid
            else:
                hi = mid
        return lo

    def _schedule(self) -> float:
        """Set the gains for the current latency estimate; returns the scale of α1."""
        a1, a2, dl, k, clip = self._nominal
        cmd = self._latency_s if self.command_latency_s is None else self.command_latency_s
        tau = cmd + self._latency_s
        s = 1.0
        kk = k
        if self.gain_schedule and tau > 0:
            s = min(1.0, self.delay_margin / (self._eig * a1 * tau)) if a1 > 0 else 1.0
            kk = min(k, self.delay_margin / tau)
            key = (round(tau / self.dt_s), s)
            if key != self._clip_key:
                self._clip_key = key
                self._clip = self._barrier_clip_for((self.delay_margin / tau) ** 2, dl * s * s, clip)
            clip = self._clip
        self.alpha1, self.alpha2, self.delta, self.k, self.barrier_clip = a1 * s, a2 * s * s, dl * s * s, kk, clip
        if self.observer_delay:
            self._obs.delay_ticks = int(round(cmd / self.dt_s))
        return s

    def step(self, obs: Observation) -> ControlOutput:
        """Brake force (N) for this period from ``obs`` (ages handled here)."""
        self._update_latency(obs)
        scale = self._schedule()
        slot = obs.tick % self._n_hist
        self._hist_x[slot], self._hist_v[slot], self._hist_tick[slot] = obs.position_m, obs.speed_mps, obs.tick
        out = super().step(self._aligned(obs))
        out.diagnostics["latency_estimate_s"] = self._latency_s
        out.diagnostics["gain_scale"] = scale
        return out

    # ------------------------------------------------------------------ batch form
    def batchable(self) -> bool:
        """Whether :meth:`step_batch` covers this configuration: peer positions as received and at
        most 9 cars (the mean peer age is summed as numpy sums at most 8 values: in order)."""
        return (type(self).step is ChenCompensatedController.step and self.deflection_source == "peer_position"
                and self.n_cars <= 9)

    def step_batch(self, obs: Observation) -> ControlOutput:
        """:meth:`step` for P sweep points at once (:mod:`canbrake.batch`): scalars of ``obs`` of
        shape (P,), peer arrays (P, n_cars); the gains, the latency estimate and the history become
        one per point at the first call. The same operations in the same order as :meth:`step`, so
        the same floats (tests/test_control.py)."""
        P = obs.speed_mps.shape[0]
        if not hasattr(self, "_b_hist_x"):
            self._b_hist_x = np.full((self._n_hist, P), np.nan)
            self._b_hist_v = np.full((self._n_hist, P), np.nan)
            self._b_hist_tick = np.full((self._n_hist, P), -1, dtype=np.int64)
            self._b_latency = np.zeros(P)
            self._b_key_r = np.full(P, -1, dtype=np.int64)
            self._b_key_s = np.full(P, np.nan)
            self._b_clip = np.full(P, self._nominal[4])
        # latency: peak detector on the mean finite peer age (_update_latency)
        ages = np.delete(obs.peer_age_s, self.car_index, axis=1)
        fin = np.isfinite(ages)
        cnt = fin.sum(axis=1)
        now = np.where(cnt > 0, np.where(fin, ages, 0.0).sum(axis=1) / np.maximum(cnt, 1), 0.0)
        dec = self._b_latency * self._decay
        self._b_latency = np.where(dec > now, dec, now)
        scale = self._schedule_many()
        slot = obs.tick % self._n_hist
        self._b_hist_x[slot], self._b_hist_v[slot], self._b_hist_tick[slot] = obs.position_m, obs.speed_mps, obs.tick
        out = ChenConsensusController.step_batch(self, self._aligned_many(obs))
        out.diagnostics["latency_estimate_s"] = self._b_latency
        out.diagnostics["gain_scale"] = scale
        return out

    def _schedule_many(self) -> np.ndarray:
        """:meth:`_schedule` per point; the barrier clip is re-solved for the points whose key
        (τ in periods, α1's scale) changed, by the same bisection on arrays."""
        a1, a2, dl, k, clip = self._nominal
        lat = self._b_latency
        cmd = lat if self.command_latency_s is None else np.full_like(lat, self.command_latency_s)
        tau = cmd + lat
        s = np.ones_like(tau)
        kk = np.full_like(tau, k)
        clip_now = np.full_like(tau, clip)
        if self.gain_schedule:
            on = tau > 0
            with np.errstate(divide="ignore", invalid="ignore"):
                if a1 > 0:
                    s = np.where(on, np.minimum(1.0, self.delay_margin / (self._eig * a1 * tau)), 1.0)
                kk = np.where(on, np.minimum(k, self.delay_margin / tau), k)
                r = np.where(on, np.round(tau / self.dt_s), -1).astype(np.int64)
                changed = on & ((r != self._b_key_r) | (s != self._b_key_s))
                if changed.any():
                    idx = np.flatnonzero(changed)
                    self._b_key_r[idx], self._b_key_s[idx] = r[idx], s[idx]
                    om = self.delay_margin / tau[idx]
                    self._b_clip[idx] = self._barrier_clip_for_many(om * om, dl * s[idx] * s[idx], clip)
            clip_now = np.where(on, self._b_clip, clip)
        self.alpha1, self.alpha2, self.delta, self.k, self.barrier_clip = a1 * s, a2 * s * s, dl * s * s, kk, clip_now
        if self.observer_delay:
            self._obs.delay_ticks = np.round(cmd / self.dt_s).astype(np.int64)
        return s

    def _barrier_clip_for_many(self, omega2_max: np.ndarray, delta: np.ndarray, nominal_clip: float) -> np.ndarray:
        """:meth:`_barrier_clip_for` on arrays (one bisection per entry, the same steps)."""
        limit = 0.5 * omega2_max

        def stiff(c: np.ndarray) -> np.ndarray:
            a = self._barrier_stiffness(c * self._z_upper, delta, barrier_gradient_many)
            b = self._barrier_stiffness(c * self._z_lower, delta, barrier_gradient_many)
            return np.where(b > a, b, a)

        out = np.full(limit.shape, nominal_clip)
        todo = (delta > 0) & ~(stiff(np.full(limit.shape, nominal_clip)) <= limit)
        lo, hi = np.full(limit.shape, 1e-3), np.full(limit.shape, nominal_clip)
        floor = todo & (stiff(lo) > limit)
        out[floor] = 1e-3
        todo &= ~floor
        if todo.any():
            for _ in range(40):
                mid = 0.5 * (lo + hi)
                ok = stiff(mid) <= limit
                lo = np.where(ok, mid, lo)
                hi = np.where(ok, hi, mid)
            out[todo] = lo[todo]
        return out

    def _aligned_many(self, obs: Observation) -> Observation:
        """:meth:`_aligned` for every point: peer values predicted to this instant (NaN if unusable)."""
        n, i = self.n_cars, self.car_index
        px = obs.peer_position_m.astype(float).copy()
        pv = obs.peer_speed_mps.astype(float).copy()
        ages = obs.peer_age_s
        x_now, v_now = obs.position_m, obs.speed_mps
        pts = np.arange(px.shape[0])
        for j in range(n):
            if j == i:
                continue
            a = ages[:, j]
            valid = ~np.isnan(px[:, j]) & np.isfinite(a)
            lag = np.where(valid, np.round(np.where(valid, a, 0.0) / self.dt_s), 0).astype(np.int64)
            use = valid & (lag > 0)
            if not use.any():
                continue
            then = obs.tick - lag
            slot = then % self._n_hist
            held = use & (then >= 0) & (self._b_hist_tick[slot, pts] == then)
            if self.align:
                gone = use & ~held
                px[gone, j] = np.nan
                pv[gone, j] = np.nan
            x_then, v_then = self._b_hist_x[slot, pts], self._b_hist_v[slot, pts]
            if self.align:
                rel = px[:, j] - x_then
                if self.predict:
                    rel = rel + (pv[:, j] - v_then) * a
                px[:, j] = np.where(held, x_now + rel, px[:, j])
            if self.speed_alignment == "own_motion":
                pv[:, j] = np.where(held, pv[:, j] + (v_now - v_then), pv[:, j])
            elif self.speed_alignment == "reference":
                pv[:, j] = np.where(held, pv[:, j] - obs.ref_decel_mps2 * a, pv[:, j])
        return replace(obs, peer_position_m=px, peer_speed_mps=pv,
                       peer_age_s=np.where(np.isnan(pv), np.inf, 0.0))
