"""Chen 2023 observer-driven distributed consensus braking controller, registered as ``chen2023``.

    u_i = u_i1 + u_i2 + u_i3                                                     (eq. 24)
    u_i1 = α1 Σ_j a_ij (v_i − v_j) + α2 Σ_j b_ij (x_i − x_j − θ_ij)              (eq. 25)
    u_i2 = δ Σ_j b_ij ∇U(x_ij)                                                   (eqs. 26–27)
    u_i3 = m_i (k_i v_ei + v*) + k_di φ̂_i                                         (eq. 29)

The force commanded is F_i = K_b u_i (N, + = brake). Readings taken (see docs/models-chen2023.md; all
are constructor parameters, defaults = the "paper" reading that reproduces the paper's claims):

* ``feedforward="decel"``: the v* in u_i3 is the reference deceleration a* (= −dv*/dt). ``"velocity"``
  is the literal print (a speed used as an acceleration); it leaves a large steady error.
* ``brake_gain`` K_b = 1 (u in newtons); Table 2 does not give K_b.
* ``mass_scaled=True``: u_i1 and u_i2 are multiplied by m_i, as they appear in the error dynamics
  (eq. 30), so α1 is in 1/s, α2 in 1/s², δ in m/s² per unit of ∇U. ``False``: printed as is (N).
* Consensus on positions acts on the coupler deflection: x_i − x_j − θ_ij with θ_ij the nominal
  spacing, i.e. Σ_j b_ij(...) = Δl_i − Δl_{i−1} on the path graph L_b.
* Barrier (``barrier``): the printed U = 1/(|x|² − θ1²) + 1/(θ2² − |x|²) is identically zero when
  θ1 = −θ2, so we use ``"inverse_square"``: U(z) = 1/(z − z1)² + 1/(z2 − z)² (minus its slope at 0, so
  ∇U(0) = 0), or ``"log"``: U(z) = −ln((z − z1)(z2 − z)) (likewise). Both grow without bound at the
  bounds. They act on z = Δl / ``barrier_unit_m`` (default: centimetres, θ = ±1 cm → z = ±1) and ∇U
  is dU/dz. Near the bounds z is clipped to ``barrier_clip`` × the bound (the term is finite, huge).
  The pair potential gives car i the term ∇U(Δl_i) − ∇U(Δl_{i−1}).
* Observer cancellation (``observer_cancellation="mass"``): + m_i φ̂_i (φ̂ is an acceleration). The
  printed ``"kd"`` (k_d φ̂ with k_d = 50) is too small to cancel anything.
* ``deflection_source``: ``"peer_position"`` computes Δl from the peer positions received over CAN
  (the paper: displacement is exchanged between neighbours) and needs the nominal spacing;
  ``"local"`` uses the Observation's locally measured deflections.

Stale data: a peer value never received (NaN) is always ignored. ``stale_policy="hold"`` uses the last
value as is, ``"extrapolate"`` advances it by its age (x + v·age − a*·age²/2, v − a*·age),
``"drop"`` ignores a peer whose age exceeds ``stale_timeout_s``.
"""
from __future__ import annotations

import math
from typing import Any, Sequence

import numpy as np

from canbrake.control import _chen
from canbrake.control._chen import barrier_gradient  # noqa: F401 - the scalar barrier, compiled (used here by name)
from canbrake.control.base import ControlOutput, Controller, Observation, register
from canbrake.control.observer import SlidingModeObserver

_FEEDFORWARD = ("decel", "velocity")
_BARRIERS = ("inverse_square", "log")
_CANCEL = ("mass", "kd")
_SOURCES = ("peer_position", "local")
_STALE = ("hold", "extrapolate", "drop")


def barrier_gradient_many(z: np.ndarray, z_lower: float, z_upper: float, kind: Any = "inverse_square",
                          clip: Any = 0.99) -> np.ndarray:
    """:func:`barrier_gradient` (compiled, :mod:`canbrake.control._chen`) elementwise: the same
    operations, so the same floats; ``clip`` may be an array of the shape of ``z``."""
    zl, zu = z_lower * clip, z_upper * clip
    return _barrier_terms(np.where(z > zu, zu, np.where(z < zl, zl, z)), z_lower, z_upper, kind)


def _barrier_terms(z: Any, z_lower: float, z_upper: float, kind: str) -> Any:
    """∇U(z) − ∇U(0) for a clipped z, a float or an array (operators only, so both give the same floats)."""
    if kind == "inverse_square":
        # cubes as products, not ** 3: numpy's vectorised power rounds differently from libm's pow in
        # ~5 % of cases, and the batch form must give the same floats
        a, b = z_upper - z, z - z_lower
        g = 2.0 / (a * a * a) - 2.0 / (b * b * b)
        g0 = 2.0 / z_upper**3 - 2.0 / (-z_lower) ** 3
    elif kind == "log":
        g = 1.0 / (z_upper - z) - 1.0 / (z - z_lower)
        g0 = 1.0 / z_upper - 1.0 / (-z_lower)
    else:  # pragma: no cover - validated in the constructor
        raise ValueError(kind)
    return g - g0


@register("chen2023")
class ChenConsensusController(Controller):
    """One carriage's Chen 2023 controller. Units: SI; parameters below.

    Gains: ``alpha1`` (1/s if mass-scaled, else N·s/m), ``alpha2`` (1/s² or N/m), ``k`` (1/s),
    ``k_d`` (kg, used with ``observer_cancellation="kd"``), ``delta`` (m/s² or N per unit ∇U).
    Safety bounds ``theta_lower_m``, ``theta_upper_m`` (m) on the deflection.
    Observer: ``gamma1_mps`` (m/s), ``gamma2_mps2`` (m/s²), ``observer_boundary_pos_m`` (m),
    ``observer_boundary_vel_mps`` (m/s; ``None`` = max(0.01, 2·dt·γ2): 0.01 at 1 ms, 0.1 at 10 ms),
    ``observer_filter_s`` (s), ``observer_limit_mps2`` (m/s²),
    ``observer_error_limit_mps`` (m/s, anti-windup clamp of |v − v̂|; ``None`` = 5 × the boundary),
    ``observer_actuator_lag_s`` (s, first-order model of the brake lag the observer is driven with;
    0 = the command acts at once).
    Saturation: ``brake_force_max_n``, ``traction_force_max_n`` (N; inf = none), or per unit mass
    ``brake_rating_mps2``, ``traction_rating_mps2`` (m/s², × this car's mass; the tighter one wins).
    ``nominal_spacing_m``: nominal x_i − x_{i+1} (m), scalar or n−1 values; ``None`` = latched from
    the first observation that has the neighbours' positions (assumes the train starts undeflected).
    ``velocity_graph``: ``"all"`` (L_a, eq. 6) or ``"neighbours"``.
    """

    diagnostic_names = (
        "observer_accel_mps2",
        "u_consensus_n",
        "u_potential_n",
        "u_tracking_n",
        "u_observer_n",
        "deflection_front_m",
        "deflection_rear_m",
    )

    def __init__(
        self,
        car_index: int,
        n_cars: int,
        mass_kg: float,
        dt_s: float,
        *,
        alpha1: float = 120.0,
        alpha2: float = 100.0,
        k: float = 36.0,
        k_d: float = 50.0,
        delta: float = 2.0,
        theta_lower_m: float = -0.01,
        theta_upper_m: float = 0.01,
        feedforward: str = "decel",
        brake_gain: float = 1.0,
        mass_scaled: bool = True,
        consensus: bool = True,
        potential_field: bool = True,
        barrier: str = "inverse_square",
        barrier_unit_m: float = 0.01,
        barrier_clip: float = 0.99,
        observer: bool = True,
        observer_cancellation: str = "mass",
        gamma1_mps: float = 1.0,
        gamma2_mps2: float = 5.0,
        observer_boundary_pos_m: float = 1e-3,
        observer_boundary_vel_mps: float | None = None,
        observer_filter_s: float = 0.005,
        observer_limit_mps2: float = 5.0,
        observer_error_limit_mps: float | None = None,
        observer_actuator_lag_s: float = 0.0,
        deflection_source: str = "peer_position",
        nominal_spacing_m: float | Sequence[float] | None = None,
        velocity_graph: str = "all",
        stale_policy: str = "hold",
        stale_timeout_s: float = math.inf,
        brake_force_max_n: float = math.inf,
        traction_force_max_n: float = math.inf,
        brake_rating_mps2: float = math.inf,
        traction_rating_mps2: float = math.inf,
    ) -> None:
        super().__init__(car_index, n_cars, mass_kg, dt_s)
        for name, val, allowed in (
            ("feedforward", feedforward, _FEEDFORWARD),
            ("barrier", barrier, _BARRIERS),
            ("observer_cancellation", observer_cancellation, _CANCEL),
            ("deflection_source", deflection_source, _SOURCES),
            ("stale_policy", stale_policy, _STALE),
            ("velocity_graph", velocity_graph, ("all", "neighbours")),
        ):
            if val not in allowed:
                raise ValueError(f"{name} must be one of {allowed}, not {val!r}")
        if not theta_lower_m < 0.0 < theta_upper_m:
            raise ValueError("need theta_lower_m < 0 < theta_upper_m")
        if not 0.0 < barrier_clip < 1.0:
            raise ValueError("barrier_clip must be in (0, 1)")
        self.alpha1 = float(alpha1)
        self.alpha2 = float(alpha2)
        self.k = float(k)
        self.k_d = float(k_d)
        self.delta = float(delta)
        self.theta_lower_m = float(theta_lower_m)
        self.theta_upper_m = float(theta_upper_m)
        self.feedforward = feedforward
        self.brake_gain = float(brake_gain)
        self.mass_scaled = bool(mass_scaled)
        self.consensus = bool(consensus)
        self.potential_field = bool(potential_field)
        self.barrier = barrier
        self.barrier_unit_m = float(barrier_unit_m)
        self.barrier_clip = float(barrier_clip)
        self.observer = bool(observer)
        self.observer_cancellation = observer_cancellation
        self.observer_actuator_lag_s = float(observer_actuator_lag_s)
        self.deflection_source = deflection_source
        self.velocity_graph = velocity_graph
        self.stale_policy = stale_policy
        self.stale_timeout_s = float(stale_timeout_s)
        self.brake_force_max_n = float(brake_force_max_n)
        self.traction_force_max_n = float(traction_force_max_n)
        # per-mass ratings (one value for a whole train in a scenario) tighten the force limits
        self.brake_force_max_n = min(self.brake_force_max_n, float(brake_rating_mps2) * self.mass_kg)
        self.traction_force_max_n = min(self.traction_force_max_n, float(traction_rating_mps2) * self.mass_kg)
        if observer_boundary_vel_mps is None:  # keep dt·γ2/b ≤ 0.5 whatever the period
            observer_boundary_vel_mps = max(0.01, 2.0 * float(dt_s) * float(gamma2_mps2))
        if observer_error_limit_mps is None:
            observer_error_limit_mps = 5.0 * float(observer_boundary_vel_mps)
        self._obs = SlidingModeObserver(
            self.mass_kg,
            self.dt_s,
            gamma1_mps=gamma1_mps,
            gamma2_mps2=gamma2_mps2,
            boundary_pos_m=observer_boundary_pos_m,
            boundary_vel_mps=observer_boundary_vel_mps,
            filter_s=observer_filter_s,
            limit_mps2=observer_limit_mps2,
            error_limit_mps=observer_error_limit_mps,
        )
        i, n = car_index, n_cars
        adj = np.ones(n, dtype=bool) if velocity_graph == "all" else np.zeros(n, dtype=bool)
        if velocity_graph == "neighbours":
            adj[max(i - 1, 0): i + 2] = True
        adj[i] = False
        self._adj_a = adj
        self._adj_tuple = tuple(int(j) for j in np.flatnonzero(adj))  # the neighbours, in order (compiled step)
        self._adj_f = adj.astype(float)
        self._n_adj = int(np.count_nonzero(adj))
        self._spacing_cfg = nominal_spacing_m
        self._z_lower = self.theta_lower_m / self.barrier_unit_m
        self._z_upper = self.theta_upper_m / self.barrier_unit_m
        self._scale = self.mass_kg if self.mass_scaled else 1.0
        self._lag_alpha = (
            1.0 if self.observer_actuator_lag_s <= 0 else 1.0 - math.exp(-self.dt_s / self.observer_actuator_lag_s)
        )
        self.reset()

    # ------------------------------------------------------------------
    def reset(self) -> None:
        """Initial state: observer uninitialised, spacing not latched, no force applied."""
        self._obs.reset()
        self._force_model_n = 0.0
        self._spacing_front: float | None = None
        self._spacing_rear: float | None = None
        cfg = self._spacing_cfg
        i, n = self.car_index, self.n_cars
        if cfg is not None:
            arr = np.asarray(cfg, dtype=float)
            if arr.ndim == 0:
                arr = np.full(n - 1, float(arr))
            if arr.shape != (n - 1,):
                raise ValueError(f"nominal_spacing_m: expected a scalar or {n - 1} values")
            self._spacing_front = float(arr[i - 1]) if i > 0 else None
            self._spacing_rear = float(arr[i]) if i < n - 1 else None
        self._latched = cfg is not None

    @property
    def observer_estimate_mps2(self) -> float:
        """Current φ̂ (m/s²)."""
        return self._obs.phi_hat_mps2

    # ------------------------------------------------------------------
    #: Brake force (N) for this period from ``obs``: eqs. 24-29 as in the module docstring, compiled
    #: (:func:`canbrake.control._chen.step`, every stale policy and deflection source; the observer in Python)
    step = _chen.step

    @staticmethod
    def _output(force: Any, phi_hat: Any, kb: float, u1: Any, u2: Any, u3: Any, force_obs: Any, front: Any,
                rear: Any, nan: Any) -> ControlOutput:
        """The batch form's result (arrays); ``nan`` stands for an unknown deflection (None); the
        compiled :meth:`step` makes the same for scalars."""
        return ControlOutput(
            brake_force_n=force,
            diagnostics={
                "observer_accel_mps2": phi_hat,
                "u_consensus_n": kb * u1,
                "u_potential_n": kb * u2,
                "u_tracking_n": kb * u3,
                "u_observer_n": force_obs,
                "deflection_front_m": nan if front is None else front,
                "deflection_rear_m": nan if rear is None else rear,
            },
        )

    # ------------------------------------------------------------------ batch form
    def batchable(self) -> bool:
        """Whether :meth:`step_batch` covers this configuration (peer positions held as received)."""
        return (type(self).step is ChenConsensusController.step and self.stale_policy == "hold"
                and self.deflection_source == "peer_position")

    def step_batch(self, obs: Observation) -> ControlOutput:
        """:meth:`step` for P sweep points at once (the batch engine, :mod:`canbrake.batch`).

        Every scalar field of ``obs`` has shape (P,), every peer array (P, n_cars); the result's
        fields have shape (P,). The first call makes the state per point (this object then serves
        only batches). The operations are those of :meth:`step` in the same order, so each point's
        force equals the one its own controller computes, bit for bit (tests/test_batch_sweep.py).
        Gains may be arrays of shape (P,) (:class:`~canbrake.control.chen_compensated.ChenCompensatedController`
        schedules them per point)."""
        if not hasattr(self, "_batch"):
            self._batch = ChenBatch([self], obs.speed_mps.shape[0], own_observer=True)
        return self._batch.step(obs)

    @classmethod
    def group_key(cls, ctrl: "ChenConsensusController") -> tuple | None:
        """What controllers of several ECU slots must share to step as one :class:`ChenGroup`
        (everything but the car index and the mass-derived values), or None if ``ctrl`` has
        no batch form."""
        if type(ctrl) is not ChenConsensusController or not ctrl.batchable():
            return None
        o = ctrl._obs
        return (ctrl.n_cars, ctrl.dt_s, ctrl.alpha1, ctrl.alpha2, ctrl.k, ctrl.k_d, ctrl.delta, ctrl.theta_lower_m,
                ctrl.theta_upper_m, ctrl.feedforward, ctrl.brake_gain, ctrl.mass_scaled, ctrl.consensus,
                ctrl.potential_field, ctrl.barrier, ctrl.barrier_unit_m, ctrl.barrier_clip, ctrl.observer,
                ctrl.observer_cancellation, ctrl._lag_alpha, ctrl.velocity_graph, o.gamma1_mps, o.gamma2_mps2,
                o.boundary_pos_m, o.boundary_vel_mps, o._alpha, o.limit_mps2, o.error_limit_mps)

    @classmethod
    def batch_group(cls, ctrls: Sequence["ChenConsensusController"], n_points: int) -> "ChenBatch":
        """One batch object stepping ``ctrls`` (ECU slots with equal :meth:`group_key`) for
        ``n_points`` points at once (:class:`ChenBatch`)."""
        return ChenBatch(ctrls, n_points)


class ChenBatch:
    """The batch form of :class:`ChenConsensusController`: P sweep points of S ECU slots, flattened
    to N = P·S elements (point-major: element p·S + s), every array of shape (N,), peer arrays
    (N, n_cars). ``ctrls``: one controller per slot, all with the same
    :meth:`ChenConsensusController.group_key` (they differ in car index and mass only); the gains
    are read from the first at every step (scalars, or arrays (N,)).

    Per element, :meth:`step` does the operations of :meth:`ChenConsensusController.step` in the
    same order: a neighbour the car does not have contributes an exact ``+ 0.0`` / ``- 0.0`` and a
    peer outside its velocity graph ``+ 0.0`` (a sum that starts at +0.0 never becomes -0.0, so
    adding +0.0 leaves it bit for bit), so every element gets its own controller's floats
    (tests/test_control.py, tests/test_batch_sweep.py). One slot and its own observer
    (``own_observer``) is :meth:`ChenConsensusController.step_batch`; several slots (the batch
    engine's :meth:`~canbrake.batch.BatchEngine._compute`) step on a copy of the first slot's
    observer with each element's mass."""

    def __init__(self, ctrls: Sequence[ChenConsensusController], n_points: int, own_observer: bool = False) -> None:
        import copy

        c0 = ctrls[0]
        self.c0, self.n, P = c0, c0.n_cars, n_points
        self.N = N = P * len(ctrls)
        tile = lambda f: np.tile(np.asarray([f(c) for c in ctrls]), P)  # noqa: E731 - per element
        idx = tile(lambda c: c.car_index)
        self.hf, self.hr = idx > 0, idx < self.n - 1
        self.fi, self.ri = np.where(self.hf, idx - 1, 0), np.where(self.hr, idx + 1, 0)
        self.ar = np.arange(N)
        self.mass = tile(lambda c: c.mass_kg).astype(float)
        self.scale = tile(lambda c: c._scale).astype(float)
        self.bmax = tile(lambda c: c.brake_force_max_n).astype(float)
        self.tmax = -tile(lambda c: c.traction_force_max_n).astype(float)
        self.adj = np.tile(np.stack([c._adj_a for c in ctrls]), (P, 1))  # (N, n)
        self.latched = tile(lambda c: c._latched).astype(bool)
        self.b_front = tile(lambda c: np.nan if c._spacing_front is None else c._spacing_front).astype(float)
        self.b_rear = tile(lambda c: np.nan if c._spacing_rear is None else c._spacing_rear).astype(float)
        if own_observer:
            self.obs = c0._obs
        else:
            self.obs = copy.copy(c0._obs)
            self.obs.mass_kg = self.mass  # type: ignore[assignment]
        self.obs.reset_many(N)
        self.force_model_n = np.zeros(N)
        self.diagnostic_names = c0.diagnostic_names

    def step(self, obs: Observation) -> ControlOutput:
        """One period of every element (shapes in the class docstring)."""
        c = self.c0
        v, x = obs.speed_mps, obs.position_m
        N = self.N
        kb = c.brake_gain
        px = obs.peer_position_m
        pxf, pxr = px[self.ar, self.fi], px[self.ar, self.ri]
        hf, hr = self.hf, self.hr
        # deflections: the spacing is latched once both neighbours' positions have arrived
        new = ~self.latched & (~hf | ~np.isnan(pxf)) & (~hr | ~np.isnan(pxr))
        if new.any():
            self.b_front = np.where(new & hf, pxf - x, self.b_front)
            self.b_rear = np.where(new & hr, x - pxr, self.b_rear)
            self.latched = self.latched | new
        front = np.where(hf, (pxf - x) - self.b_front, np.nan)  # NaN = unknown or no such neighbour
        rear = np.where(hr, (x - pxr) - self.b_rear, np.nan)
        f_ok, r_ok = ~np.isnan(front), ~np.isnan(rear)

        u1: Any = 0.0
        if c.consensus:
            pos = (0.0 + np.where(r_ok, rear, 0.0)) - np.where(f_ok, front, 0.0)
            pv = obs.peer_speed_mps
            total, cnt = np.zeros(N), np.zeros(N)
            for j in range(self.n):  # peer by peer in index order, as step sums
                pj = pv[:, j]
                ok = (pj == pj) & self.adj[:, j]
                total = total + np.where(ok, pj, 0.0)
                cnt = cnt + ok
            sd = np.where(cnt > 0, cnt * v - total, 0.0)
            u1 = self.scale * (c.alpha1 * sd + c.alpha2 * pos)

        u2: Any = 0.0
        if c.potential_field:
            unit, zl, zu, kind, clip = c.barrier_unit_m, c._z_lower, c._z_upper, c.barrier, c.barrier_clip
            g = 0.0 + np.where(r_ok, barrier_gradient_many(rear / unit, zl, zu, kind, clip), 0.0)
            g = g - np.where(f_ok, barrier_gradient_many(front / unit, zl, zu, kind, clip), 0.0)
            u2 = self.scale * c.delta * g

        ff = obs.ref_decel_mps2 if c.feedforward == "decel" else obs.ref_speed_mps
        m = self.mass
        u3 = m * (c.k * (v - obs.ref_speed_mps) + ff)

        phi_hat = self.obs.update_many(x, v)
        force_obs: Any = 0.0
        if c.observer:
            force_obs = m * phi_hat if c.observer_cancellation == "mass" else kb * c.k_d * phi_hat

        force = kb * (u1 + u2 + u3) + force_obs
        force = np.where(force > self.bmax, self.bmax, np.where(force < self.tmax, self.tmax, force))
        self.force_model_n = self.force_model_n + c._lag_alpha * (force - self.force_model_n)
        self.obs.predict_many(self.force_model_n)
        return c._output(force, phi_hat, kb, u1, u2, u3, force_obs, front, rear, None)
