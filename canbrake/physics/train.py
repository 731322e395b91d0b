"""Longitudinal multi-carriage train plant (Chen 2023, eq. 3), vectorised over cars, SI inside.

    m_i dv_i/dt = -F_brake,i + Φ_{i-1} - Φ_i - f_i + d_i(t)          (car 1 has no Φ_0, car n no Φ_n)
    Δl_i = x_i - x_{i+1} - s_i,     Φ_i = κ_i (1 + ε_i Δl_i²) Δl_i       (coupler i joins car i and i+1)

Geometry and sign convention
----------------------------
``s_i`` (``coupler_spacing_m``) is the *nominal* x_i − x_{i+1}; by default it is taken from the initial
positions, so the initial deflection is 0. Chen's Table 2 puts car 1 at x = 10 m and car 6 at 60 m and
the train runs towards +x (v > 0), so car 6 leads and s_i = −10 m. Equation 3 is unchanged by the
orientation — it depends only on Δl_i and the speeds, and dΔl_i/dt = v_i − v_{i+1} either way — but
the *meaning* of the sign flips: with Table 2's numbering (index grows towards the front) Δl_i > 0 is
compression (buff), with the opposite numbering (s_i > 0) it is tension. In both, Φ_i acts on car i as
−Φ_i and on car i+1 as +Φ_i: equal and opposite, restoring Δl_i towards 0.

ε < 0 (Table 2: −0.5 1/m²) makes the spring *softening*: Φ peaks at |Δl| = 1/sqrt(−3ε) (0.816 m,
43.5 kN for Table 2) and reverses beyond sqrt(−1/ε) (1.41 m). An optional end stop (``end_stop_m``)
models the end of the draft gear's travel; it is off by default (the paper has none).

End stop (draft gear travel limit, then a buffer that absorbs energy)
----------------------------------------------------------------------
Beyond |Δl| = ``end_stop_m`` the gear has used its travel and a stiff buffer element acts in
series with the end of the travel: on loading (|Δl| growing) it pushes back with
k_b·(|Δl| − end_stop_m), on unloading with (1 − a)·k_b·(|Δl| − end_stop_m), a = ``end_stop_absorption``
— the loading/unloading hysteresis of a friction or elastomer draft gear as longitudinal train
dynamics models it (two force curves, the area between them absorbed). The buffer only pushes
(never pulls cars together) and switches between the curves smoothly over a relative speed of
±``END_STOP_TRANSITION_MPS``. For two masses closing at v (reduced mass μ) this gives: the
loading curve is elastic, so the peak force is v·sqrt(k_b μ) and the overrun v·sqrt(μ/k_b); the
unloading curve returns (1 − a) of the stored energy, so the cars separate at sqrt(1 − a)·v and the
buffer absorbs a·μv²/2 per impact. While a coupler is within reach of its stop in a control period,
the plant sub-steps at most 0.05/ω_b (ω_b = sqrt(k_b/μ), the stop's frequency), and only then: a
run that never comes near a stop is integrated exactly as without one.

Forces
------
* Brake force (actuator output, + = brake) and running resistance (Davis, curve) are *dissipative*:
  they act as ``-sign(v)·F`` on a moving car; on a car at rest they are static friction and hold it up
  to their magnitude, never pushing it. So a train at rest stays at rest under a brake command and
  c0 never makes it creep backwards.
* Traction (negative actuator output), grade (−m g sin θ, θ > 0 uphill towards +x), couplers and
  disturbances are ordinary forces.

Integration: semi-implicit (symplectic) Euler on fixed sub-steps no longer than ``max_substep_s``
for the couplers; the held forces (brake command, traction, resistance, grade, disturbances) move
the position by the trapezoidal rule, exact for a force held constant over the sub-step (plain
semi-implicit Euler moves a car h²a/2 too far per step: 0.5 mm at 1 ms under Chen's ideal brake's
~1000 m/s², the size of the deflections measured; issue 12). (default 1 ms: ω = sqrt(2κ/m) ≈ 2.8 rad/s for Table 2, ωh ≈ 0.003). A car whose speed would change
sign under friction stops instead (exact stop). Internal coupler forces cancel exactly, so total
momentum is conserved to rounding when no external force acts.
"""
from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any, Callable, Sequence

import numpy as np

from canbrake.physics._train_kernel import CoupledKernel, EquippedKernel, with_table_resistance
from canbrake.physics.actuator import ActuatorState, BrakeActuator
from canbrake.physics._brakes_kernel import EquipmentKernel
from canbrake.physics import _adhesion_kernel
from canbrake.physics.brakes import BlendingState, BrakeBlending, Wheelsets
from canbrake.physics.rail import DisturbanceForce, RailConditions, _per_car
from canbrake.physics.resistance import DavisResistance, davis_1926
from canbrake.physics.wheel_adhesion import WheelSet, _axle_array

GRAVITY_MPS2 = 9.81
#: relative speed over which the end stop's buffer switches between its loading and unloading curves (m/s)
END_STOP_TRANSITION_MPS = 0.01
#: a coupler this close to its end stop (plus twice its closing travel in the period) gets the fine sub-step (m)
END_STOP_MARGIN_M = 0.001

class PlantDiverged(FloatingPointError):
    """The state became non-finite (e.g. a softening coupler was driven past its force peak)."""


GradeSpec = float | Sequence[float] | np.ndarray | Callable[[np.ndarray], np.ndarray]


@dataclass(frozen=True)
class PlantState:
    """Snapshot of the plant; arrays have shape ``(n_cars,)`` or ``(n_cars - 1,)`` for couplers."""

    time_s: float
    position_m: np.ndarray
    speed_mps: np.ndarray
    accel_mps2: np.ndarray
    deflection_m: np.ndarray
    coupler_force_n: np.ndarray
    applied_force_n: np.ndarray
    brake_effort_n: np.ndarray


class TrainPlant:
    """n carriages joined by n−1 couplers.

    Parameters (arrays are per car, shape ``(n,)``; coupler arrays shape ``(n-1,)``; scalars broadcast)
    ----------
    mass_kg: carriage masses (kg).
    position_m: initial positions x_i (m), along the track, +x = direction of travel.
    speed_mps: initial speeds v_i (m/s).
    coupler_stiffness_n_per_m: κ_i (N/m). Default 80 000 (Chen Table 2).
    coupler_nonlinearity_per_m2: ε_i (1/m²). Default −0.5 (Chen Table 2).
    coupler_spacing_m: nominal x_i − x_{i+1} (m); ``None`` = from the initial positions (Δl(0) = 0).
    resistance: Davis coefficients; ``None`` = :func:`davis_1926` for these masses.
    resistance_table: per car, ``(speeds m/s, forces N)`` or ``None``: a running resistance
        interpolated linearly in |v| and held flat beyond the ends, added to the Davis terms (give
        those cars zero Davis coefficients); ``None`` = no car has one.
    traction_envelope: per car, a :class:`canbrake.physics.heavy_haul.TractionEnvelope` or ``None``:
        that car's traction (a negative rail force) is at most F_T(|v|) (Li 2024 eq. 1), every sub-step.
    draft_gears: per coupler, a :class:`canbrake.physics.heavy_haul.DraftGear` (Li 2024's hysteretic
        draft gear with slack, eqs. 7-9, stepped by its compiled ``GearKernel`` once per sub-step; its
        force replaces Φ on that coupler, + where Δl > 0) or ``None`` (Chen's coupler); ``None`` = none.
    air_brake: a :class:`canbrake.physics.heavy_haul.AirBrake` over every car (cars without air brake
        rigging have no blocks: force 0), stepped by its compiled ``AirKernel`` once per sub-step after
        the speeds; its block force acts on the car's body as a dissipative force like the running
        resistance (a car with wheelsets takes no air brake); ``air_braked``: which cars have rigging.
    grade_rad: track slope θ (rad), scalar, per car, or a function of the positions returning per-car θ.
    route: a :class:`canbrake.physics.route.Route` (Li 2024 eqs. 4-5): grade i ‰ and curves 600/R N/kN
        by position, (i + 600/R)·m g/1000 N on each car at its position every sub-step, an ordinary
        force like the grade (not dissipative); ``line_rule`` (look-ahead m, steepest grade ‰, least
        length m) is the line-data rule of :meth:`downgrade_ahead`.
    static_couplers: at reset, the cars behind the first are placed so that each coupler carries the
        running and line resistance of the cars behind it at the initial speeds (a draft gear on its
        loading curve, ``CouplerBank.set_static``; Chen's coupler at Φ(Δl) = that tension), as the
        heavy-haul model starts; the positions given are the nominal ones (Δl = 0).
    electric_brake_envelope: cars with a traction envelope also have their brake effort capped at its
        electric brake F_B(v) (Li 2024 eq. 2), every sub-step; ``loco_adhesion``: per car a
        :class:`canbrake.physics.heavy_haul.LocoAdhesion` or None: that car's traction and brake
        effort capped at μ(v)·m·g (the heavy-haul model's locomotive limits, in its order).
    uncertainty: δ of Li 2024 eq. 16: every non-control force (couplers, resistance, grade, route, air
        brake) acts as (1 + δ) times its nominal value (``passive_force_n`` stays nominal).
    li_disturbance_on, li_disturbance_coef: Li 2024 eq. 40's disturbance σ_i(t)
        (:func:`canbrake.physics.rail.disturbance_n`) on the cars where ``li_disturbance_on`` is True.
    curve_resistance_n: extra dissipative resistance per car (N), e.g. Chen's 0.004·m·D_c.
    actuator: :class:`BrakeActuator` (default ideal).
    rail: :class:`RailConditions` (base μ and events); default μ = 0.3 everywhere, no events.
    disturbances: external forces, :class:`DisturbanceForce` list.
    end_stop_m: |Δl| at which the draft gear's travel ends and the buffer acts (m); ``None`` = no end stop;
        a sequence: per coupler (``None`` or ``inf``: none on that coupler).
    end_stop_stiffness_n_per_m: the buffer's loading stiffness beyond the end stop, k_b (N/m; a sequence: per coupler).
    end_stop_absorption: share a of an impact's energy the buffer absorbs (0 ≤ a < 1; unloading
        stiffness (1 − a)·k_b; a sequence: per coupler). 0 = a lossless solid stop.
    max_substep_s: longest integration sub-step (s).
    gravity_mps2: g (m/s²).
    rigid, driven_axles, rail_schedule, adhesion_curve, adhesion_v_floor_mps: rigid coupling with
        driven axles (Cai 2014), see :meth:`_rigid_init`.
    """

    def __init__(
        self,
        mass_kg: Sequence[float] | np.ndarray,
        position_m: Sequence[float] | np.ndarray,
        speed_mps: Sequence[float] | np.ndarray,
        *,
        coupler_stiffness_n_per_m: float | Sequence[float] = 80_000.0,
        coupler_nonlinearity_per_m2: float | Sequence[float] = -0.5,
        coupler_spacing_m: float | Sequence[float] | None = None,
        resistance: DavisResistance | None = None,
        grade_rad: GradeSpec = 0.0,
        curve_resistance_n: float | Sequence[float] = 0.0,
        actuator: BrakeActuator | None = None,
        rail: RailConditions | None = None,
        disturbances: Sequence[DisturbanceForce] = (),
        end_stop_m: float | Sequence[float | None] | None = None,
        end_stop_stiffness_n_per_m: float | Sequence[float] = 2.0e7,
        end_stop_absorption: float | Sequence[float] = 0.6,
        max_substep_s: float = 1e-3,
        gravity_mps2: float = GRAVITY_MPS2,
        rigid: bool = False,
        driven_axles: Sequence[Any] | None = None,
        rail_schedule: Any = None,
        adhesion_curve: str = "paper",
        adhesion_v_floor_mps: float = 0.1,
        blending: BrakeBlending | None = None,
        wheels: Wheelsets | None = None,
        wsp_valve_lag_s: float | Sequence[float] = 0.05,
        wsp_max_vent_s: float | Sequence[float] = math.inf,
        resistance_table: Sequence[tuple[Sequence[float], Sequence[float]] | None] | None = None,
        traction_envelope: Sequence[object | None] | None = None,
        draft_gears: Sequence[object | None] | None = None,
        air_brake: object | None = None,
        air_braked: Sequence[bool] | None = None,
        route: object | None = None,
        line_rule: tuple[float, float, float] = (2500.0, 8.0, 500.0),
        static_couplers: bool = False,
        electric_brake_envelope: bool = False,
        loco_adhesion: Sequence[object | None] | None = None,
        uncertainty: float = 0.0,
        li_disturbance_on: Sequence[bool] | None = None,
        li_disturbance_coef: tuple[float, float, float] = (0.0, 0.0, 0.0),
    ) -> None:
        self.mass_kg = np.asarray(mass_kg, dtype=float).copy()
        n = self.mass_kg.size
        if n < 1:
            raise ValueError("need at least one car")
        self.n_cars = n
        self._x0 = _per_car(position_m, n, "position_m")
        self._v0 = _per_car(speed_mps, n, "speed_mps")
        nc = n - 1
        self.coupler_stiffness_n_per_m = _per_car(coupler_stiffness_n_per_m, nc, "coupler_stiffness_n_per_m")
        self.coupler_nonlinearity_per_m2 = _per_car(coupler_nonlinearity_per_m2, nc, "coupler_nonlinearity_per_m2")
        if coupler_spacing_m is None:
            self.coupler_spacing_m = self._x0[:-1] - self._x0[1:]
        else:
            self.coupler_spacing_m = _per_car(coupler_spacing_m, nc, "coupler_spacing_m")
        self.resistance = resistance if resistance is not None else davis_1926(self.mass_kg)
        for arr in (self.resistance.c0_n, self.resistance.c1_n_per_mps, self.resistance.c2_n_per_mps2):
            if np.shape(arr) != (n,):
                raise ValueError("resistance coefficients must have one value per car")
        self._grade_fn: Callable[[np.ndarray], np.ndarray] | None
        if callable(grade_rad):
            self._grade_fn = grade_rad
            self._grade_force = None
        else:
            self._grade_fn = None
            self._grade_force = -self.mass_kg * gravity_mps2 * np.sin(_per_car(grade_rad, n, "grade_rad"))
        self.curve_resistance_n = _per_car(curve_resistance_n, n, "curve_resistance_n")
        self.actuator = actuator if actuator is not None else BrakeActuator.ideal()
        self.rail = rail if rail is not None else RailConditions()
        self.disturbances = tuple(disturbances)
        self._dist = [
            (d.start_s, d.end_s, _per_car(d.amplitude_n, n, "amplitude_n"), _per_car(d.offset_n, n, "offset_n"),
             2.0 * math.pi * d.frequency_hz, d.phase_rad)
            for d in self.disturbances
        ]
        self._events = [
            (ev.start_s, ev.end_s,
             None if ev.adhesion_mu is None else _per_car(ev.adhesion_mu, n, "adhesion_mu"),
             None if ev.brake_effectiveness is None else _per_car(ev.brake_effectiveness, n, "brake_effectiveness"))
            for ev in self.rail.events
        ]
        self._base_mu = _per_car(self.rail.base_adhesion_mu, n, "base_adhesion_mu")
        #: per coupler (arrays of shape (n-1,)) where the couplers' end stops differ, else one value
        self.end_stops_per_coupler = any(np.ndim(a) > 0 for a in (end_stop_m, end_stop_stiffness_n_per_m,
                                                                    end_stop_absorption))
        if self.end_stops_per_coupler:
            stop = [math.inf if x is None else x for x in np.broadcast_to(np.asarray(end_stop_m, dtype=object), (nc,))]
            end_stop_m = None if all(x == math.inf for x in stop) else _per_car(np.asarray(stop, dtype=float), nc,
                                                                                  "end_stop_m")
            end_stop_stiffness_n_per_m = _per_car(end_stop_stiffness_n_per_m, nc, "end_stop_stiffness_n_per_m")
            end_stop_absorption = _per_car(end_stop_absorption, nc, "end_stop_absorption")
        self.end_stop_m = end_stop_m
        self.end_stop_stiffness_n_per_m = (end_stop_stiffness_n_per_m if self.end_stops_per_coupler
                                           else float(end_stop_stiffness_n_per_m))  # type: ignore[arg-type]
        if not np.all((0.0 <= np.asarray(end_stop_absorption)) & (np.asarray(end_stop_absorption) < 1.0)):
            raise ValueError(f"end_stop_absorption must be in [0, 1), got {end_stop_absorption}")
        self.end_stop_absorption = (end_stop_absorption if self.end_stops_per_coupler
                                    else float(end_stop_absorption))  # type: ignore[arg-type]
        if end_stop_m is not None and not np.all(np.asarray(end_stop_m) > 0):
            raise ValueError(f"end_stop_m must be > 0, got {end_stop_m}")
        if not max_substep_s > 0:
            raise ValueError("max_substep_s must be > 0")
        self.max_substep_s = float(max_substep_s)
        self.gravity_mps2 = float(gravity_mps2)
        self._c_static = self.resistance.c0_n + self.curve_resistance_n
        self._inv_m = 1.0 / self.mass_kg
        self._kappa_eps = self.coupler_stiffness_n_per_m * self.coupler_nonlinearity_per_m2
        self._incidence = np.zeros((n, nc))
        for i in range(nc):
            self._incidence[i, i] = -1.0
            self._incidence[i + 1, i] = 1.0
        self._has_grade = self._grade_force is not None and bool(np.any(self._grade_force != 0.0))
        self.blending = blending
        self.wheels = wheels
        #: the dump valves' lag and watchdog (s): one value, or an array per car
        self.wsp_valve_lag_s = (float(wsp_valve_lag_s) if np.ndim(wsp_valve_lag_s) == 0
                                else _per_car(wsp_valve_lag_s, n, "wsp_valve_lag_s"))
        self.wsp_max_vent_s = (float(wsp_max_vent_s) if np.ndim(wsp_max_vent_s) == 0
                               else _per_car(wsp_max_vent_s, n, "wsp_max_vent_s"))
        self._lag_k: dict[tuple[str, float], np.ndarray] = {}  # 1 - exp(-h/lag) per sub-step h
        self._wheels0 = None if wheels is None else wheels.omega.copy()
        self.resistance_table = self._tables(resistance_table)
        self.traction_envelope = self._envelopes(traction_envelope)
        self._gears = self._draft_gears(draft_gears)
        self.air_brake = air_brake
        self.air_braked = None if air_brake is None else np.asarray(
            [True] * n if air_braked is None else air_braked, dtype=bool)
        if air_brake is not None and (self.air_braked.shape != (n,) or air_brake.dist.size != n):  # type: ignore[attr-defined]
            raise ValueError(f"air_brake and air_braked must cover every car ({n})")
        if air_brake is not None and wheels is not None and np.any(self.air_braked & (
                np.ones(n, dtype=bool) if wheels.active is None else np.asarray(wheels.active) > 0)):
            raise ValueError("a car with wheelsets takes no air brake (its block force acts on the body)")
        if air_brake is not None:
            self._air0 = (air_brake.fill.copy(), air_brake.ecp_target.copy(), air_brake.last_force_n.copy(),  # type: ignore[attr-defined]
                          None if air_brake.pipe is None else air_brake.pipe_pressure_pa.copy())  # type: ignore[attr-defined]
        self._li_parts(route, line_rule, static_couplers, electric_brake_envelope, loco_adhesion, uncertainty,
                       li_disturbance_on, li_disturbance_coef)
        #: a stack of plants (stack_plants): arrays have a leading points axis
        self.stacked = False
        self._kern: CoupledKernel | None = None  # built at the first step
        self._ekern: EquipmentKernel | None = None  # the brake equipment's, likewise
        self._qkern: EquippedKernel | None = None  # the period with brake equipment, likewise
        self._rigid_init(rigid, driven_axles, rail_schedule, adhesion_curve, adhesion_v_floor_mps)
        self.reset()

    def _tables(self, tables: Sequence[tuple[Sequence[float], Sequence[float]] | None] | None
                ) -> tuple[tuple[np.ndarray, np.ndarray] | None, ...] | None:
        """Check the per-car resistance tables and keep them for the kernel as offsets and two flat
        arrays (``self._tab``, None without tables)."""
        self._tab: tuple[np.ndarray, np.ndarray, np.ndarray] | None = None
        if tables is None or all(t is None for t in tables):
            return None
        if len(tables) != self.n_cars:
            raise ValueError(f"resistance_table must have one entry per car ({self.n_cars}), got {len(tables)}")
        out: list[tuple[np.ndarray, np.ndarray] | None] = []
        start = [0]
        for i, t in enumerate(tables):
            if t is None:
                out.append(None)
                start.append(start[-1])
                continue
            v, f = (np.asarray(a, dtype=float).reshape(-1) for a in t)
            if v.size < 1 or v.size != f.size or not (np.all(np.isfinite(v)) and np.all(np.isfinite(f))) \
                    or np.any(np.diff(v) <= 0.0) or v[0] < 0.0:
                raise ValueError(f"resistance_table of car {i + 1}: needs finite speeds >= 0, increasing, "
                                 "and as many finite forces")
            out.append((v, f))
            start.append(start[-1] + v.size)
        self._tab = (np.asarray(start, dtype=np.intp), np.concatenate([t[0] for t in out if t is not None]),
                     np.concatenate([t[1] for t in out if t is not None]))
        return tuple(out)

    def _draft_gears(self, gears: Sequence[object | None] | None) -> object | None:
        """The couplers with Li's draft gears as one :class:`canbrake.physics.heavy_haul.CouplerBank`
        over them (their indices in ``self.gear_couplers``); None without draft gears."""
        from canbrake.physics.heavy_haul import CouplerBank

        self.draft_gears = None if gears is None else tuple(gears)
        self.gear_couplers = np.zeros(0, dtype=np.intp)
        if gears is None or all(g is None for g in gears):
            return None
        if len(gears) != self.n_cars - 1:
            raise ValueError(f"draft_gears must have one entry per coupler ({self.n_cars - 1}), got {len(gears)}")
        self.gear_couplers = np.flatnonzero([g is not None for g in gears])
        return CouplerBank([g for g in gears if g is not None])

    def _envelopes(self, envelopes: Sequence[object | None] | None) -> tuple[object | None, ...] | None:
        """Keep the per-car traction envelopes as the kernel's rows (``self._env``, (n, 6), NaN rows
        for cars without; None without envelopes)."""
        self._env: np.ndarray | None = None
        if envelopes is None or all(e is None for e in envelopes):
            return None
        if len(envelopes) != self.n_cars:
            raise ValueError(f"traction_envelope must have one entry per car ({self.n_cars}), got {len(envelopes)}")
        fields = ("traction_start_kn", "traction_start_until_kmh", "traction_intercept_kn",
                  "traction_slope_kn_per_kmh", "traction_linear_until_kmh", "power_kn_kmh")
        self._env = np.array([[math.nan] * 6 if e is None else [float(getattr(e, k)) for k in fields]
                              for e in envelopes])
        return tuple(envelopes)

    # ------------------------------------------------------------------ state
    def reset(self) -> None:
        """Back to the initial positions and speeds, actuator at rest, t = 0."""
        self.time_s = 0.0
        #: (x, v, Δl, Φ) of the last plain compiled step's new state (couplers() while x and v are the plant's)
        self._step_couplers: tuple[np.ndarray, ...] | None = None
        self.position_m = self._x0.copy()
        self.speed_mps = self._v0.copy()
        self.accel_mps2 = np.zeros(self.n_cars)
        self._act = ActuatorState(self.actuator, self.mass_kg)
        self.applied_force_n = np.zeros(self.n_cars)
        self._rail_key: tuple[bool, ...] | None = None
        self._mu = self._base_mu.copy()
        self._eff = np.ones(self.n_cars)
        self._plain_rail = not self.actuator.adhesion_limited
        self._blend = None if self.blending is None else BlendingState(self.blending, self.mass_kg)
        self.wsp_valve = np.zeros(self.n_cars)
        self._vent_s = np.zeros(self.n_cars)
        if self.rigid:  # the body, its driven axles and their last step
            self._rigid_reset()
        if self.wheels is not None and self._wheels0 is not None:
            self.wheels.omega = self._wheels0.copy()
        if self._gears is not None:  # every draft gear in its slack, unloaded
            self._gears.force_state = np.zeros(self._gears.n)
            self._gears.defl_prev = np.zeros(self._gears.n)
        ab = self.air_brake
        if ab is not None:  # brake released, pipe charged, no command issued
            fill, target, force, pipe = self._air0
            ab.fill, ab.ecp_target, ab.last_force_n = fill.copy(), target.copy(), force.copy()
            ab.applied, ab.t_apply, ab.t_release = False, -np.inf, -np.inf
            if pipe is not None:
                ab.pipe_pressure_pa = pipe.copy()
            self._fill_before, self._air_h = ab.fill.copy(), self.max_substep_s  # what command_air redoes
        if self.static_couplers:
            self._place_static()

    def couplers(self) -> tuple[np.ndarray, np.ndarray]:
        """The couplers at the current state (:meth:`CoupledKernel.couplers`): (deflections
        Δl_i = x_i − x_{i+1} − s_i (m), forces Φ_i (N; acts as −Φ_i on car i and +Φ_i on car i+1)),
        shape ``(n-1,)``: Φ(Δl) = κ(1 + εΔl²)Δl, plus the end stop's buffer if configured (module
        docstring; its loading or unloading curve by dΔl/dt), and on couplers with draft gears the
        gears' force at this state (their history kept). After a step of the plain compiled
        kernel, the arrays its step computed for the new state (shared by the callers of that
        state: do not modify them); otherwise new arrays from one compiled call."""
        c = self._step_couplers
        if c is not None and c[0] is self.position_m and c[1] is self.speed_mps:  # the last step's state
            return c[2], c[3]
        kern = self._kern if self._kern is not None else self._kernel()
        dl, phi = kern.couplers(self.position_m, self.speed_mps)
        if self._gears is not None:  # the draft gears' force at this state, their history kept
            g, k = self._gears, self.gear_couplers
            rate = self.speed_mps[..., :-1] - self.speed_mps[..., 1:]
            phi[k] = g.kernel.step(np.ascontiguousarray(dl[k]), np.ascontiguousarray(rate[k]), g.force_state,
                                   g.defl_prev)[0]
        return dl, phi

    @property
    def deflection_m(self) -> np.ndarray:
        """Coupler deflections Δl_i = x_i − x_{i+1} − s_i (m), shape ``(n-1,)`` (:meth:`couplers`)."""
        return self.couplers()[0]

    @property
    def coupler_force_n(self) -> np.ndarray:
        """Coupler forces Φ_i (N), shape ``(n-1,)``; acts as −Φ_i on car i and +Φ_i on car i+1 (:meth:`couplers`)."""
        return self.couplers()[1]

    @property
    def air_brake_n(self) -> np.ndarray | None:
        """The air brake's block force per car (N, ≥ 0; 0 on cars without rigging); None without air brake."""
        return None if self.air_brake is None else self.air_brake.last_force_n  # type: ignore[attr-defined]

    def command_air(self, apply: float | None, ecp_demand: np.ndarray | None) -> None:
        """The air brake's commands (as the former heavy-haul model took them):
        ``apply`` the driver's valve on the leading car (≥ 0.5 apply, < 0.5 release, None/NaN unchanged;
        pneumatic mode), ``ecp_demand`` each car's cylinder target (fraction 0..1, NaN unchanged; ECP
        mode). A command that changes the brake acts from now: the cylinder fill update of the last
        sub-step (the one that reached this instant) is redone with it, and the block forces follow at
        the current speeds (the ECU's ``passive_force_n`` of this tick showed the brake before it)."""
        ab: Any = self.air_brake
        if ab is None:
            return
        changed = False
        if ab.mode == "pneumatic":
            if apply is not None and math.isfinite(apply) and (apply >= 0.5) != ab.applied:
                ab.command(self.time_s, bool(apply >= 0.5))
                changed = True
        elif ecp_demand is not None:
            dm = np.asarray(ecp_demand, dtype=float)
            ok = np.isfinite(dm)
            new = np.where(ok, np.clip(np.where(ok, dm, 0.0), 0.0, 1.0), ab.ecp_target)
            changed = bool(np.any(new != ab.ecp_target))
            ab.ecp_target = new
        if changed:  # the command acts from now: redo the fill update that reached this instant
            ab.fill = self._fill_before.copy()
            ab.step(self.time_s, self._air_h, self.speed_mps)

    @property
    def brake_effort_n(self) -> np.ndarray:
        """Actuator effort before effectiveness/adhesion (N)."""
        return self._act.effort_n

    @property
    def adhesion_mu(self) -> np.ndarray:
        """Adhesion μ per car in force for the current step."""
        return self._mu

    @property
    def brake_effectiveness(self) -> np.ndarray:
        """Brake effectiveness per car in force for the current step."""
        return self._eff

    def _substeps(self, dt_s: float) -> int:
        """Sub-steps for a control period of ``dt_s``: ``max_substep_s``, and at most 0.05/ω_b while a
        coupler can reach its end stop within the period (module docstring)."""
        n_sub = 1 if dt_s <= self.max_substep_s * (1 + 1e-9) else int(math.ceil(dt_s / self.max_substep_s - 1e-9))
        if self.end_stop_m is None or self.n_cars < 2 or self.stacked:  # a stack's is fixed (_substeps_fixed)
            return n_sub
        dl = self.deflection_m
        rate = self.speed_mps[:-1] - self.speed_mps[1:]
        if np.all(np.abs(dl) + 2.0 * np.abs(rate) * dt_s + END_STOP_MARGIN_M < self.end_stop_m):
            return n_sub
        return max(n_sub, int(math.ceil(dt_s / self._end_stop_substep_s() - 1e-9)))

    def _end_stop_substep_s(self) -> float:
        """The sub-step near an end stop (s): 0.05/ω_b, ω_b = sqrt(k_b/μ) for the lightest pair of cars."""
        m = self.mass_kg
        if self.end_stops_per_coupler:  # the couplers that have a stop, each with its own pair and buffer
            has = np.isfinite(np.asarray(self.end_stop_m, dtype=float))
            pair = (m[:-1] * m[1:] / (m[:-1] + m[1:]))[has]
            return float(np.min(0.05 / np.sqrt(np.asarray(self.end_stop_stiffness_n_per_m)[has] / pair)))
        mu = float(np.min(m[:-1] * m[1:] / (m[:-1] + m[1:])))
        return 0.05 / math.sqrt(self.end_stop_stiffness_n_per_m / mu)

    def passive_force_n(self, coupler_force_n: np.ndarray | None = None) -> np.ndarray:
        """The non-control force per car at the current state (N, + forward): the couplers' forces
        from the front and the rear, minus the running resistance (Davis, table, curve), the grade
        force and the air brake's block force, each opposing the motion (Li 2024's nominal F_i,
        what its controllers call m0·f(x); no disturbance). Shape ``(n,)``. ``coupler_force_n``:
        the couplers' forces at this state if the caller has them (:meth:`couplers`), else computed."""
        v = self.speed_mps
        speed = np.abs(v)
        f = self._incidence.dot(self.coupler_force_n if coupler_force_n is None else coupler_force_n)
        r = self._c_static + speed * (self.resistance.c1_n_per_mps + self.resistance.c2_n_per_mps2 * speed)
        if self._tab is not None:
            r = with_table_resistance(self._tab[0], self._tab[1], self._tab[2], np.ascontiguousarray(speed),
                                      np.ascontiguousarray(r, dtype=float))
        if self.air_brake is not None:
            r = r + self.air_brake.last_force_n  # type: ignore[attr-defined]
        f = f - np.sign(v) * r
        if self._grade_fn is not None:
            f = f - self._grade_force_fn(self.position_m)
        elif self._has_grade:
            f = f + self._grade_force
        if self.route is not None:
            f = f - self._route_force_n(self.position_m)
        return f

    def coupler_energy_j(self) -> float:
        """Potential energy stored in the couplers (J), without end stop: Σ κ(Δl²/2 + εΔl⁴/4)."""
        dl = self.deflection_m
        return float(np.sum(self.coupler_stiffness_n_per_m * (0.5 * dl**2 + 0.25 * self.coupler_nonlinearity_per_m2 * dl**4)))

    def snapshot(self) -> PlantState:
        """An immutable copy of the current state."""
        dl, phi = self.couplers()
        return PlantState(
            self.time_s, self.position_m.copy(), self.speed_mps.copy(), self.accel_mps2.copy(),
            dl, phi, self.applied_force_n.copy(), self._act.effort_n.copy(),
        )

    # ------------------------------------------------------------------ dynamics
    def _update_rail(self, t: float) -> None:
        if not self._events and self._rail_key is not None:  # no rail events: set once after reset
            return
        key = tuple(s <= t < e for s, e, _, _ in self._events)
        if key == self._rail_key:
            return
        self._rail_key = key
        mu = self._base_mu.copy()
        eff = np.ones(self.n_cars)
        for active, (_, _, ev_mu, ev_eff) in zip(key, self._events):
            if active:
                if ev_mu is not None:
                    mu = ev_mu
                if ev_eff is not None:
                    eff = ev_eff
        self._mu, self._eff = mu, eff
        self._plain_rail = not self.actuator.adhesion_limited and bool(np.all(eff == 1.0))

    def external_force_n(self, time_s: float) -> np.ndarray:
        """Sum of the disturbance forces per car at ``time_s`` (N, + towards +x)."""
        f = np.zeros(self.n_cars)
        for start, end, amp, off, w, ph in self._dist:
            if start <= time_s < end:
                f = f + off + amp * math.sin(w * (time_s - start) + ph)
        return f

    def step(self, dt_s: float, brake_command_n: Sequence[float] | np.ndarray | None,
             wsp_release: np.ndarray | None = None, axle_torque_nm: np.ndarray | None = None) -> None:
        """Advance ``dt_s`` seconds holding ``brake_command_n`` (N per car, + = brake, − = traction) and,
        with wheelsets, the wheel-slide-protection valve command ``wsp_release`` (0..1 per car, NaN = none);
        a rigid train with driven axles holds ``axle_torque_nm`` instead (:meth:`_step_rigid`)."""
        if self.rigid:
            return self._step_rigid(dt_s, axle_torque_nm)
        cmd = np.asarray(brake_command_n, dtype=float)
        if cmd.shape != self.speed_mps.shape:
            raise ValueError(f"brake_command_n must have shape {self.speed_mps.shape}")
        if self.blending is not None or self.wheels is not None or self._gears is not None \
                or self.air_brake is not None or self._li:
            return self._step_equipped(dt_s, cmd, wsp_release)
        n_sub = self._substeps(dt_s)
        h = dt_s / n_sub
        self._update_rail(self.time_s)
        act = self._act
        kernel = self._kern if self._kern is not None else self._kernel()
        gcb = None if self._grade_fn is None else self._grade_force_fn
        if act.params.kind == "ideal" and self._env is None:  # the rail force is held over the period
            effort = act.advance(cmd, h)
            rail = effort if self._plain_rail else act.rail_force_n(effort, self._mu, self._eff, self.gravity_mps2)
            self.time_s, x, v, acc, rail, n_bad, dl, phi = kernel.step(
                self.position_m, self.speed_mps, cmd, rail, self._mu, self._mu, self._eff, self.time_s, h, n_sub,
                True, self._plain_rail, 0.0, gcb)  # (the effort argument is not used when ideal)
        else:  # the actuator (and the traction envelopes) every sub-step
            effort = np.array(np.broadcast_to(act.effort_n, cmd.shape), dtype=float)
            lag = 0.0 if act.params.kind == "ideal" else act.lag_factor(h)
            per_car = None if isinstance(lag, float) else lag
            self.time_s, x, v, acc, rail, n_bad, dl, phi = kernel.step(
                self.position_m, self.speed_mps, cmd, self.applied_force_n, effort, self._mu, self._eff,
                self.time_s, h, n_sub, False, self._plain_rail, 0.0 if per_car is not None else lag, gcb, per_car)
            act.effort_n = effort
        if n_bad:
            if not self.stacked:
                raise PlantDiverged(self.diverged_text(float(kernel.dl_max[0])))
            x, v, acc, rail = self._park_diverged(x, v, acc, rail, kernel.bad.astype(bool), kernel.dl_max)
        self.accel_mps2 = acc
        self.position_m, self.speed_mps = x, v
        self.applied_force_n = rail
        self._step_couplers = (x, v, dl, phi)  # couplers() of this state (parked rows: other arrays, not used)

    def _grade_force_fn(self, x: np.ndarray) -> np.ndarray:
        """m g sin θ per car (N) at positions ``x`` (m), with a grade function (the kernel calls it)."""
        return self.mass_kg * self.gravity_mps2 * np.sin(np.asarray(self._grade_fn(x), dtype=float))

    def _kernel(self) -> CoupledKernel:
        """The compiled integration loop with this plant's (or stack's) constant parameters."""
        if self._kern is None:
            act = self._act
            d = self._dist
            self._kern = CoupledKernel(
                self.mass_kg, self._inv_m, self._c_static, self.resistance.c1_n_per_mps,
                self.resistance.c2_n_per_mps2, self._grade_force if self._has_grade else None,
                np.broadcast_to(act._brake_max, self.mass_kg.shape), np.broadcast_to(act._trac_max, self.mass_kg.shape),
                np.broadcast_to(act._rate_max, self.mass_kg.shape), self.coupler_spacing_m,
                self.coupler_stiffness_n_per_m, self.coupler_nonlinearity_per_m2, self._kappa_eps,
                [e[0] for e in d], [e[1] for e in d], [e[4] for e in d], [e[5] for e in d],
                np.reshape([e[2] for e in d], (len(d), self.n_cars)), np.reshape([e[3] for e in d], (len(d), self.n_cars)),
                points=self.speed_mps.shape[0] if self.stacked else 1, gravity=self.gravity_mps2,
                end_stop_m=self.end_stop_m,
                end_stop_stiffness=self.end_stop_stiffness_n_per_m, end_stop_absorption=self.end_stop_absorption,
                end_stop_transition=END_STOP_TRANSITION_MPS, unrated=act._unrated,
                jerk_limited=self.actuator.jerk_limited,
                adhesion_limited=self.actuator.adhesion_limited, instant=act._instant, envelope=self._env,
                table_start=None if self._tab is None else self._tab[0],
                table_v=None if self._tab is None else self._tab[1], table_f=None if self._tab is None else self._tab[2])
        return self._kern

    def diverged_text(self, max_deflection_m: float) -> str:
        """What this plant's divergence is reported as, now (after the step), given the last max |Δl|
        (m); a stack's rows are reported as their own plants would be."""
        text = f"train state not finite at t = {self.time_s:.3f} s; last max |Δl| = {max_deflection_m:.3g} m"
        if self.blending is not None or self.wheels is not None:
            return text
        return text + " (a softening coupler, ε < 0, reverses beyond |Δl| = sqrt(-1/ε); consider end_stop_m)"

    def _park_diverged(self, x: np.ndarray, v: np.ndarray, acc: np.ndarray, rail: np.ndarray, bad: np.ndarray,
                       dl_max: np.ndarray) -> tuple[np.ndarray, ...]:
        """A stack's rows whose state became non-finite (``bad``, (P,) bool): noted (``diverged_rows``,
        the last max |Δl| ``dl_max`` in ``diverged_dl_m``) and parked at rest, so they cannot disturb
        the others (see stack_plants)."""
        if not bad.any():
            return x, v, acc, rail
        first = bad & ~self.diverged_rows
        if first.any():
            self.diverged_dl_m = np.where(first, dl_max, self.diverged_dl_m)
        self.diverged_rows = self.diverged_rows | bad
        if self._blend is not None:
            self._blend.friction_n = np.where(bad[:, None], 0.0, self._blend.friction_n)
        return tuple(np.where(bad[:, None], 0.0, a) for a in (x, v, acc, np.broadcast_to(rail, x.shape)))

    # ------------------------------------------------------------------ brake equipment (opt-in)
    def _step_equipped(self, dt_s: float, cmd: np.ndarray, wsp_release: np.ndarray | None) -> None:
        """:meth:`step` with brake equipment (blending, wheelsets, draft gears, air brake, Li 2024's
        parts): the same forces, sub-steps and Coulomb treatment of brake and resistance, plus the
        equipment, the whole period in one compiled call (:class:`EquippedKernel`); the grade
        function, when given, is called back every sub-step."""
        n_sub = self._substeps(dt_s)
        h = dt_s / n_sub
        wsp = None if wsp_release is None else np.ascontiguousarray(wsp_release, dtype=float).reshape(-1)
        act, wheels = self._act, self.wheels
        x, v = self.position_m, self.speed_mps
        kern = self._equipped_kernel()
        blend = self._blend
        blend_k = self._lag_factor("friction", 0.0 if blend is None else blend.params.friction_lag_s, h)
        valve_k = self._lag_factor("valve", self.wsp_valve_lag_s, h)
        if blend is not None and blend.friction_n.shape != v.shape:
            blend.friction_n = np.array(np.broadcast_to(blend.friction_n, v.shape), dtype=float)
            blend.ed_n = np.array(np.broadcast_to(blend.ed_n, v.shape), dtype=float)
        if wsp is not None and self.wsp_valve.size != wsp.size:
            self.wsp_valve = np.array(np.broadcast_to(self.wsp_valve, wsp.shape), dtype=float)
            self._vent_s = np.array(np.broadcast_to(self._vent_s, wsp.shape), dtype=float)
        none = np.zeros(0)
        fr = none if blend is None else blend.friction_n.reshape(-1)
        ed = none if blend is None else blend.ed_n.reshape(-1)
        om, fo, sl = (none, none, none) if wheels is None else (
            wheels.omega.reshape(-1), wheels.force_n.reshape(-1), wheels.slip.reshape(-1))
        lag = 0.0 if act.params.kind == "ideal" else act.lag_factor(h)
        effort = act.effort_n  # the actuator's state, a copy the kernel advances
        effort = effort.astype(float).reshape(-1) if effort.shape == v.shape else \
            np.array(np.broadcast_to(effort, v.shape), dtype=float).reshape(-1)
        gears: Any = self._gears
        fs, dp = (none, none) if gears is None else (gears.force_state.copy(), gears.defl_prev.copy())
        air: Any = self.air_brake
        mode, fill, target, fill_gain, pipe, pipe_gain, t_apply, t_release, air_n = \
            -1, none, none, none, none, none, 0.0, 0.0, none
        if air is not None:
            mode = air.kernel_mode()
            fill, target, air_n = air.fill, np.ascontiguousarray(air.ecp_target, dtype=float), air.last_force_n.copy()
            fill_gain, pipe_gain = air.gains(h)
            pipe = air._no_pipe if air.pipe is None else air.pipe_pressure_pa.copy()
            t_apply, t_release = float(air.t_apply), float(air.t_release)
            self._fill_before = fill.copy()  # the kernel overwrites it before each sub-step's fill update
        self.time_s, t_last, x, v, acc, rail, dl = kern.run(
            x, v, cmd, effort, self.time_s, h, n_sub, lag if isinstance(lag, float) else 0.0,
            None if isinstance(lag, float) else lag, blend_k, valve_k, wsp, fr, ed, self.wsp_valve.reshape(-1),
            self._vent_s.reshape(-1), om, fo, sl, fs, dp, mode, fill, target, fill_gain, pipe, pipe_gain, t_apply,
            t_release, air_n, None if self._grade_fn is None else self._grade_force_fn,
            None if air is None else self._fill_before)
        act.effort_n = effort.reshape(self.speed_mps.shape)
        self._update_rail(t_last)
        if gears is not None:
            gears.force_state, gears.defl_prev = fs, dp
        if air is not None:
            self._air_h = h  # (command_air redoes the last sub-step's fill update from _fill_before)
        if air is not None and mode >= 0:
            air.last_force_n = air_n
            if air.pipe is not None:
                air.pipe_pressure_pa = pipe
        if self.stacked:
            shape = self.speed_mps.shape
            x, v, acc, rail = (a.reshape(shape) for a in (x, v, acc, rail))
            dl = dl.reshape(shape[:-1] + (self.n_cars - 1,))
            bad = ~np.isfinite(v).all(axis=-1)
            dl_max = np.max(np.abs(dl), axis=-1) if dl.shape[-1] else np.zeros(bad.shape)
            x, v, acc, rail = self._park_diverged(x, v, acc, rail, bad, dl_max)
        elif not math.isfinite(float(v.sum())):
            raise PlantDiverged(self.diverged_text(float(np.max(np.abs(dl))) if dl.size else 0.0))
        self.accel_mps2 = acc
        self.position_m, self.speed_mps = x, v
        self.applied_force_n = rail

    # ------------------------------------------------------------------ Li 2024's line and locomotive (opt-in)
    def _li_parts(self, route: object | None, line_rule: tuple[float, float, float], static_couplers: bool,
                  electric_brake_envelope: bool, loco_adhesion: Sequence[object | None] | None, uncertainty: float,
                  dist_on: Sequence[bool] | None, dist_coef: tuple[float, float, float]) -> None:
        """Check and keep the heavy-haul model's parts (class docstring: route, static_couplers,
        electric_brake_envelope, loco_adhesion, uncertainty, li_disturbance_*); ``self._li``: any of them."""
        n = self.n_cars
        self.route = route
        self.line_rule = tuple(float(x) for x in line_rule)
        if len(self.line_rule) != 3:
            raise ValueError("line_rule must be (look-ahead m, grade permille, length m)")
        if not -0.5 <= uncertainty <= 0.5:
            raise ValueError(f"uncertainty must be in [-0.5, 0.5], got {uncertainty}")
        self.uncertainty = float(uncertainty)
        self._li_dist: tuple[np.ndarray, tuple[float, float, float]] | None = None
        if dist_on is not None:
            on = np.asarray(dist_on, dtype=bool)
            if on.shape != (n,):
                raise ValueError(f"li_disturbance_on must have one value per car ({n})")
            coef = tuple(float(c) for c in dist_coef)
            if len(coef) != 3:
                raise ValueError("li_disturbance_coef must be (c0, c1, c2)")
            self._li_dist = (on, coef)  # type: ignore[assignment]
        self.static_couplers = bool(static_couplers)
        if self.static_couplers and n > 1 and not np.all(self.coupler_spacing_m > 0):
            raise ValueError("static_couplers needs the first car at the front (coupler_spacing_m > 0)")
        self.electric_brake_envelope = bool(electric_brake_envelope)
        env = self.traction_envelope
        if self.electric_brake_envelope and env is None:
            raise ValueError("electric_brake_envelope needs the cars' traction_envelope")
        self.loco_adhesion = None if loco_adhesion is None else tuple(loco_adhesion)
        if self.loco_adhesion is not None and len(self.loco_adhesion) != n:
            raise ValueError(f"loco_adhesion must have one entry per car ({n}), got {len(self.loco_adhesion)}")
        #: per limited car: (index, its envelope for the electric brake or None, its adhesion or None)
        self._limits: list[tuple[int, Any, Any]] = []
        for i in range(n):
            e = env[i] if self.electric_brake_envelope and env is not None else None
            a = None if self.loco_adhesion is None else self.loco_adhesion[i]
            if e is not None or a is not None:
                self._limits.append((i, e, a))
        self._weight_kn = self.mass_kg * self.gravity_mps2 / 1000.0
        #: any part the plain compiled step (CoupledKernel) lacks: the step with equipment (EquippedKernel) takes them
        self._li = route is not None or self.uncertainty != 0.0 or self._li_dist is not None or bool(self._limits)

    def _route_force_n(self, x: np.ndarray) -> np.ndarray:
        """The route's grade + curve force per car at positions ``x`` (N, + opposes forward motion)."""
        return self.route.force_n(self._weight_kn, x)  # type: ignore[attr-defined]

    def downgrade_ahead(self) -> bool:
        """Line data (the route's; a plant without one: False): a long downgrade under the train or
        within the look-ahead of its front (:meth:`canbrake.physics.route.Route.long_downgrade_ahead`
        with ``line_rule``); the train's rear is the first car's position less the nominal spacings."""
        if self.route is None:
            return False
        look, g, length = self.line_rule
        x0 = float(self.position_m[0])
        return self.route.long_downgrade_ahead(x0, x0 - float(np.sum(self.coupler_spacing_m)), look, g,  # type: ignore[attr-defined]
                                               length)

    def _place_static(self) -> None:
        """Static initial couplers (``static_couplers``): coupler j carries the running, route and
        grade resistance of the cars behind it at the initial speeds; each car behind the first is
        moved back by the stretches ahead of it, the draft gears set on their loading curves."""
        n = self.n_cars
        if n < 2:
            return
        x0, v = self._x0, self._v0
        speed = np.abs(v)
        r = self._c_static + speed * (self.resistance.c1_n_per_mps + self.resistance.c2_n_per_mps2 * speed)
        if self._tab is not None:
            r = with_table_resistance(self._tab[0], self._tab[1], self._tab[2], np.ascontiguousarray(speed),
                                      np.ascontiguousarray(r, dtype=float))
        if self.route is not None:
            r = r + self._route_force_n(x0)
        if self._grade_fn is not None:
            r = r + self._grade_force_fn(x0)
        elif self._has_grade:
            r = r - self._grade_force
        tension = np.cumsum(r[::-1])[::-1][1:]
        stretch = np.zeros(n - 1)
        k = self.gear_couplers
        if self._gears is not None:
            stretch[k] = self._gears.set_static(tension[k])  # type: ignore[attr-defined]
        chen = np.ones(n - 1, dtype=bool)
        chen[k] = False
        for j in np.flatnonzero(chen):  # κ(1 + εΔl²)Δl = T by Newton's method from the linear spring's T/κ
            kap, eps, t = float(self.coupler_stiffness_n_per_m[j]), float(self.coupler_nonlinearity_per_m2[j]), \
                float(tension[j])
            d = t / kap
            for _ in range(50):
                step = (kap * (1.0 + eps * d * d) * d - t) / (kap * (1.0 + 3.0 * eps * d * d))
                d -= step
                if abs(step) <= 1e-12 * max(abs(d), 1e-9):
                    break
            if not abs(kap * (1.0 + eps * d * d) * d - t) <= 1e-6 * max(abs(t), 1.0) or \
                    (eps < 0 and 3.0 * eps * d * d <= -1.0):
                raise ValueError(f"static_couplers: coupler {j + 1} cannot carry the {t:.4g} N behind it "
                                 "(beyond its force peak)")
            stretch[j] = d
        self.position_m = x0 - np.concatenate([[0.0], np.cumsum(stretch)])

    def _lag_factor(self, what: str, lag: float | tuple[float, ...] | np.ndarray, h: float) -> np.ndarray:
        """1 − exp(−h/lag) of a first-order lag (0 where lag = 0; s): one value, or one per car for
        per-car lags (computed once per sub-step length and kept)."""
        k = self._lag_k.get((what, h))
        if k is None:
            lags = np.atleast_1d(np.asarray(lag, dtype=float))
            uniq = np.unique(lags)  # per vehicle type, not per car
            ks = np.array([(1.0 - math.exp(-h / float(u))) if u > 0.0 else 0.0 for u in uniq])
            k = ks[np.searchsorted(uniq, lags)] if lags.size > 1 else ks
            self._lag_k[(what, h)] = k = np.ascontiguousarray(k, dtype=float)
        return k

    def _equip_kernel(self) -> EquipmentKernel:
        """The compiled brake-equipment sub-step with this plant's constants (built once)."""
        if self._ekern is None:
            b = self.blending
            kw = {} if self.wheels is None else self.wheels.kernel_params()
            self._ekern = EquipmentKernel(
                blending=b is not None, ed_max=0.0 if b is None else b.ed_max_decel_mps2,
                ed_power=0.0 if b is None else b.ed_power_w_per_kg, envelope=None if b is None else b.envelope,
                fade_start=1.0 if b is None else b.fade_start_mps,
                fade_end=0.0 if b is None else b.fade_end_mps, friction_lag_s=0.0 if b is None else b.friction_lag_s,
                valve_lag_s=self.wsp_valve_lag_s, max_vent_s=self.wsp_max_vent_s,
                adhesion_limited=self.actuator.adhesion_limited, gravity=self.gravity_mps2, **kw)
        return self._ekern

    def _equipped_kernel(self) -> EquippedKernel:
        """The compiled period with brake equipment with this plant's (or stack's) constants (built once)."""
        if self._qkern is None:
            act, d, n = self._act, self._dist, self.n_cars
            gears: Any = self._gears
            air: Any = self.air_brake
            lim = self._limits
            envf = ("traction_start_kn", "traction_start_until_kmh", "traction_intercept_kn",
                    "traction_slope_kn_per_kmh", "traction_linear_until_kmh", "power_kn_kmh", "brake_slope_kn_per_kmh",
                    "brake_linear_until_kmh", "brake_max_kn", "brake_constant_until_kmh")
            self._qkern = EquippedKernel(
                self._equip_kernel(), points=self.speed_mps.shape[0] if self.stacked else 1, mass=self.mass_kg,
                c_static=self._c_static, c1=self.resistance.c1_n_per_mps, c2=self.resistance.c2_n_per_mps2,
                grade_force_n=self._grade_force if self._has_grade else None,
                brake_max=np.broadcast_to(act._brake_max, self.mass_kg.shape),
                trac_max=np.broadcast_to(act._trac_max, self.mass_kg.shape),
                rate_max=np.broadcast_to(act._rate_max, self.mass_kg.shape), spacing=self.coupler_spacing_m,
                kappa=self.coupler_stiffness_n_per_m, epsilon=self.coupler_nonlinearity_per_m2,
                end_stop_m=self.end_stop_m, end_stop_stiffness=self.end_stop_stiffness_n_per_m,
                end_stop_absorption=self.end_stop_absorption, end_stop_transition=END_STOP_TRANSITION_MPS,
                gravity=self.gravity_mps2, ideal=act.params.kind == "ideal", unrated=act._unrated,
                jerk_limited=act._jerk_limited,
                instant=None if act.params.kind == "ideal" or act._instant is None else act._instant,
                envelope=self._env, table_start=None if self._tab is None else self._tab[0],
                table_v=None if self._tab is None else self._tab[1], table_f=None if self._tab is None else self._tab[2],
                dist_start=[e[0] for e in d], dist_end=[e[1] for e in d], dist_w=[e[4] for e in d],
                dist_phase=[e[5] for e in d], dist_amp=np.reshape([e[2] for e in d], (len(d), n)),
                dist_off=np.reshape([e[3] for e in d], (len(d), n)),
                gears=None if gears is None else gears.kernel, gear_couplers=self.gear_couplers,
                air=None if air is None else air.kernel, uncertainty=self.uncertainty,
                li_dist_on=None if self._li_dist is None else self._li_dist[0],
                li_dist_coef=(0.0, 0.0, 0.0) if self._li_dist is None else self._li_dist[1],
                route_brk=None if self.route is None else self.route._brk,  # type: ignore[attr-defined]
                route_val=None if self.route is None else self.route._val,  # type: ignore[attr-defined]
                weight_kn=self._weight_kn, limit_cars=[i for i, _, _ in lim],
                limit_envelope=np.reshape([[math.nan] * 10 if e is None else [float(getattr(e, k)) for k in envf]
                                           for _, e, _ in lim], (len(lim), 10)),
                limit_adhesion=[0 if a is None else (2 if a.curve == "curtius_kniffler" else 1) for _, _, a in lim],
                limit_mu0=[0.0 if a is None else float(a.mu0) for _, _, a in lim], base_mu=self._base_mu,
                event_start=[e[0] for e in self._events], event_end=[e[1] for e in self._events],
                event_mu=[e[2] for e in self._events], event_eff=[e[3] for e in self._events])
        return self._qkern

    def equipment_measurements(self) -> dict[str, np.ndarray]:
        """Per-car quantities of the brake equipment (empty without it): ``ed_brake_n`` and
        ``friction_brake_n`` (blending), ``wsp_valve`` (dump-valve opening 0..1), and per axle j
        ``axle<j>_speed_radps``, ``axle<j>_slip`` (λ, < 0 braking), ``axle<j>_adhesion_n`` (creep
        force, + forward)."""
        out: dict[str, np.ndarray] = {}
        if self._blend is not None:
            out["ed_brake_n"] = self._blend.ed_n.copy()
            out["friction_brake_n"] = self._blend.friction_n.copy()
        if self.wheels is not None:
            out["wsp_valve"] = self.wsp_valve.copy()
            w = self.wheels
            off = None if w.active is None else np.arange(w.p)[None, :] >= w.active[:, None]  # NaN: no such axle
            for j in range(w.p):  # a (n, p) array, or a stack's (P, n, p)
                for name, a in (("speed_radps", w.omega), ("slip", w.slip), ("adhesion_n", w.force_n)):
                    out[f"axle{j + 1}_{name}"] = a[..., j].copy() if off is None else np.where(off[:, j], np.nan,
                                                                                             a[..., j])
        return out

    # ------------------------------------------------------------------ rigid coupling, driven axles (Cai 2014)
    def _rigid_init(self, rigid: bool, driven_axles: Sequence[Any] | None, rail_schedule: Any, curve: str,
                    v_floor_mps: float) -> None:
        """Rigid coupling (Cai 2014 eq. 3: the in-train forces cancel in the sum, so the train is one
        body): one position x and speed v for every vehicle, ``m v̇ = Σ F_a − Σ F_d,i(v)`` with
        ``m = Σ m_i``, F_d,i the vehicles' Davis terms (c0 plus the curve resistance, c1, c2; c0
        opposes motion, none at standstill) plus sgn v · T_i(|v|) for their resistance tables. Every
        driven axle k (``driven_axles``: one :class:`canbrake.physics.wheel_adhesion.DrivenAxles` per
        vehicle, front first, or None: none) has its own wheel speed, ``J_k ω̇_k = T_k − F_a,k R_k``
        with ``F_a,k = μ(λ_k, v) N_k`` (eqs. 10–15, ``adhesion_curve`` "paper" or "physical", slip
        denominator floored at ``adhesion_v_floor_mps``) on the rail condition of the moment
        (``rail_schedule``, a :class:`~canbrake.physics.wheel_adhesion.RailSchedule`). Each sub-step
        solves wheels and body jointly by backward Euler (the compiled Newton step of
        :mod:`canbrake.physics._adhesion_kernel`, rail condition of the sub-step's start) and moves x
        by the trapezoid rule. The train starts at the front vehicle's position and speed (wheels
        rolling without slip). Brake equipment, draft gears, air brake, traction envelopes, grade,
        disturbances, rail events and end stops are not taken by a rigid train yet. Its forces are
        :meth:`rigid_measurements`' (``snapshot()`` holds its positions, speeds and accelerations;
        its coupler and applied forces there are not the rigid train's)."""
        self.rigid = bool(rigid)
        self.driven_axles = None if driven_axles is None else tuple(driven_axles)
        self.rail_schedule = rail_schedule
        #: the commands of the driven axles: axle<j>_torque_nm for j up to the most a vehicle has
        self.axle_command_names: tuple[str, ...] = ()
        if not self.rigid:
            if driven_axles is not None or rail_schedule is not None:
                raise ValueError("driven_axles and rail_schedule need rigid coupling (rigid=True) on this plant yet")
            return
        others = [name for name, on in (
            ("blending", self.blending is not None), ("wheels", self.wheels is not None),
            ("draft_gears", self._gears is not None), ("air_brake", self.air_brake is not None),
            ("traction_envelope", self._env is not None), ("disturbances", bool(self._dist)),
            ("rail events", bool(self._events)), ("grade_rad", self._has_grade or self._grade_fn is not None),
            ("end_stop_m", self.end_stop_m is not None)) if on]
        if others:
            raise ValueError(f"a rigidly coupled train takes no {others[0]} yet (mass, resistance, driven axles "
                             "and the rail schedule)")
        if rail_schedule is None:
            raise ValueError("a rigidly coupled train needs rail_schedule (its slip curve's rail conditions over time)")
        n = self.n_cars
        self._x0 = np.full(n, float(self._x0[0]))
        self._v0 = np.full(n, float(self._v0[0]))
        self.coupler_spacing_m = np.zeros(n - 1)
        axles = list(self.driven_axles) if self.driven_axles is not None else [None] * n
        if len(axles) != n:
            raise ValueError(f"driven_axles: {len(axles)} entries for {n} vehicles")
        #: per vehicle (n, 3): c0 (N, with the curve resistance), c1 (N·s/m), c2 (N·s²/m²); their sum, the body's
        self._rigid_davis = np.stack([np.asarray(self._c_static, dtype=float),
                                      np.asarray(self.resistance.c1_n_per_mps, dtype=float),
                                      np.asarray(self.resistance.c2_n_per_mps2, dtype=float)], axis=1)
        self._rigid_terms = tuple(float(a) for a in self._rigid_davis.sum(axis=0))
        #: the vehicles' tables summed on the union of their speeds (the body's: a sum of
        #: piecewise-linear, flat-ended curves is one, exactly)
        self._table_sum: tuple[np.ndarray, np.ndarray] | None = None
        if self._tab is not None and self.resistance_table is not None:
            have = [t for t in self.resistance_table if t is not None]
            union = np.unique(self._tab[1])
            self._table_sum = (union, np.sum([np.interp(union, t[0], t[1]) for t in have], axis=0))
        self.total_mass_kg = float(self.mass_kg.sum())
        veh: list[int] = []
        num: list[int] = []
        for i, ax in enumerate(axles):
            k = 0 if ax is None else len(ax.normal_load_n)
            veh += [i] * k
            num += list(range(1, k + 1))
        self.axle_vehicle = np.asarray(veh, dtype=np.int64)  # (P,) vehicle of each axle, 0-based
        self.axle_number = np.asarray(num, dtype=np.int64)  # (P,) axle number within its vehicle, 1-based
        self.max_axles = int(self.axle_number.max()) if num else 0
        self.axle_command_names = tuple(f"axle{j}_torque_nm" for j in range(1, self.max_axles + 1))

        def cat(attr: str) -> np.ndarray:
            return np.concatenate([np.asarray(getattr(a, attr), dtype=float) for a in axles if a is not None]) \
                if num else np.zeros(0)

        radius = cat("radius_m")
        v0 = float(self._v0[0])
        self._driven_w0 = np.full(len(num), v0 / radius) if num else np.zeros(0)
        self.driven = WheelSet(cat("normal_load_n"), cat("inertia_kgm2"), radius, self._driven_w0.copy(),
                               variant=curve, v_floor_mps=v_floor_mps)  # type: ignore[arg-type]
        self._mass_cumsum = np.cumsum(self.mass_kg)
        #: the measurements' names in the order of the kernel's rows (canbrake.physics._adhesion_kernel.measure)
        self._rigid_keys = ["position_m", "speed_mps", "ground_speed_mps", "accel_mps2", "applied_brake_n",
                            "resistance_n", "wheel_inertia_force_n", "deflection_m", "coupler_force_n"] + [
            f"axle{j}_{name}" for name in ("speed_radps", "slip", "mu", "adhesion_n", "applied_torque_nm")
            for j in range(1, self.max_axles + 1)]

    def _rigid_reset(self) -> None:
        """The rigid train's state at t = 0: the body at the front vehicle's position and speed,
        wheels rolling without slip, no torque."""
        self._body_x, self._body_v = float(self._x0[0]), float(self._v0[0])
        w = self.driven
        w.omega_radps = self._driven_w0.copy()
        w.last_adhesion = None
        self.axle_torque_nm = np.zeros(self.axle_vehicle.size)
        self._t0, self._k, self._h = 0.0, 0, 0.0
        self._rigid_accel = 0.0
        self._a_last = 0.0  # the body's acceleration over the last sub-step (m/s²)
        #: the wheel speeds before the last step and its length (s): the wheels' inertia force
        self._w_start: np.ndarray | None = None
        self._dt_last = 1.0
        self._fa_step: np.ndarray | None = None
        self._rigid_meas: dict[str, np.ndarray] | None = None

    def axle_torques(self, commands: Any) -> np.ndarray:
        """Per driven axle (P,), the torque (N·m, + drives forward) its vehicle's command
        ``axle<j>_torque_nm`` (arrays (n,) by name in ``commands``) asks; NaN or absent: 0."""
        return _adhesion_kernel.axle_torques([commands.get(c) for c in self.axle_command_names], self.axle_vehicle,
                                             self.axle_number)

    def _step_rigid(self, dt_s: float, torque_nm: np.ndarray | None) -> None:
        """:meth:`step` of a rigid train (:meth:`_rigid_init`) holding the driven axles' torques
        ``torque_nm`` (N·m per axle, (P,); None: none)."""
        torque = np.zeros(self.axle_vehicle.size) if torque_nm is None else np.asarray(torque_nm, dtype=float)
        self.axle_torque_nm = torque
        self._rigid_meas = None
        n_sub = self._substeps(dt_s)
        h = dt_s / n_sub
        if h != self._h:
            self._t0, self._k, self._h = self.time_s, 0, h
        wheels, rail = self.driven, self.rail_schedule
        x, v = self._body_x, self._body_v
        v_start, w_start = v, _axle_array(wheels.omega_radps, self.axle_vehicle.size)
        for _ in range(n_sub):
            cond = rail.at(self.time_s)
            v_new, fa = wheels.step_coupled(torque, v, cond, h, mass_kg=self.total_mass_kg,
                                            davis=self._rigid_terms, table=self._table_sum)
            self._a_last = (v_new - v) / h
            x += 0.5 * h * (v + v_new)
            v = v_new
            self._fa_step = fa
            self._k += 1
            self.time_s = self._t0 + self._k * h
        self._body_x, self._body_v = x, v
        self._rigid_accel = (v - v_start) / dt_s
        self._w_start, self._dt_last = w_start, dt_s
        self.position_m.fill(x)  # the train's own arrays (reset): every vehicle at the body's state
        self.speed_mps.fill(v)
        self.accel_mps2.fill(self._rigid_accel)
        if not (math.isfinite(v) and math.isfinite(x) and wheels.finite):
            raise PlantDiverged(f"rigid train: non-finite state at t = {self.time_s:g} s")

    def rigid_measurements(self) -> dict[str, np.ndarray]:
        """A rigid train's measurements of the current state, in one compiled call
        (:func:`canbrake.physics._adhesion_kernel.measure`; fresh arrays per state, shared by the
        callers of one state: do not modify them). Per vehicle (n,): ``position_m`` (the train's
        coordinate x: rigid, no lengths), ``speed_mps`` and ``ground_speed_mps`` (the speed over
        ground a radar gives, with a finer CAN format), ``accel_mps2`` (over the last control step),
        ``applied_brake_n`` (−Σ F_a of its axles: traction is negative), ``resistance_n`` (F_d,i),
        ``wheel_inertia_force_n`` (Σ J_k ω̇_k / R_k of its axles over the last step: with Σ F_d,i Cai's
        lumped disturbance F_dw, eq. 36), per driven axle j ``axle<j>_speed_radps``, ``axle<j>_slip``,
        ``axle<j>_mu``, ``axle<j>_adhesion_n`` (N), ``axle<j>_applied_torque_nm`` (NaN where the
        vehicle has fewer than j driven axles); per coupler (n−1,) ``deflection_m`` (0) and
        ``coupler_force_n``, the force the rigid coupling carries (+ compression):
        ``C_j = m_{1..j} a − Σ_{i≤j} (F_a,i − F_d,i)`` with F_a and a of the last sub-step."""
        if self._rigid_meas is None:
            self._rigid_meas = self._rigid_measure()
        return dict(self._rigid_meas)

    def _rigid_measure(self) -> dict[str, np.ndarray]:
        n, v, w = self.n_cars, self._body_v, self.driven
        cond = self.rail_schedule.at(self.time_s)
        last = w.last_adhesion
        if last is not None and last[0] is cond and last[1] == v and last[2] is w.omega_radps:
            lam, mu, fa = last[3]  # the step's own evaluation at this state
        else:
            lam, mu, fa = (np.ascontiguousarray(x, dtype=float) for x in w.adhesion(v, cond))
        table = None
        if self._tab is not None:  # each vehicle's own table (the coupled kernel's interpolation)
            table = with_table_resistance(self._tab[0], self._tab[1], self._tab[2], np.full(n, abs(v)), np.zeros(n))
        (J, R, _N), _c = w._kernel_args(cond)
        p = J.shape[0]
        rows = np.empty((7 + 5 * self.max_axles, n))
        couplers = np.empty((2, max(n - 1, 0)))
        _adhesion_kernel.measure(rows, couplers, self._body_x, v, self._rigid_accel, self._a_last, self._fa_step,
                                 lam, mu, fa, _axle_array(w.omega_radps, p), self.axle_torque_nm, self._w_start,
                                 self._dt_last, J, R, self.axle_vehicle, self.axle_number, self._rigid_davis, table,
                                 self._mass_cumsum)
        per = list(rows)
        return dict(zip(self._rigid_keys, per[:7] + list(couplers) + per[7:]))


#: per-car arrays of a plant that a stack holds per point (shape (P, n) or (P, n-1))
_STACKED = ("mass_kg", "_inv_m", "coupler_spacing_m", "coupler_stiffness_n_per_m", "coupler_nonlinearity_per_m2",
            "_kappa_eps", "_c_static", "position_m", "speed_mps", "accel_mps2", "applied_force_n")


def stack_plants(plants: Sequence[TrainPlant]) -> TrainPlant | None:
    """One plant that steps P plants of the same kind at once (the batch engine's sweep points):
    a copy of the first whose per-car arrays and state have a leading points axis, shape (P, n).
    :meth:`TrainPlant.step` then computes every point's row with the operations a single plant
    uses, so each row equals its own plant's state bit for bit (tests/test_batch_sweep.py). A
    point whose state becomes non-finite is flagged in ``diverged_rows`` and parked at rest.

    Per-vehicle resistance tables, traction envelopes, per-coupler end stops and wheelsets (axles,
    radius, inertia, normal loads, slip curves) are rows the kernels share between the points of a
    stack: they qualify when every point has the same ones (the wheels' state, ω, creep force and
    slip, is per point: (P, n, p)).

    None where the plants do not qualify: draft gears, air brakes or rigid coupling (their state is
    the plant's, not a stack's), an end stop that can refine the sub-step (it would depend on each point's state), a grade function, or plants that differ in anything but their per-car
    arrays (actuator, blending, end stops, resistance tables, traction envelopes, wheelsets, rail
    conditions, disturbances, sub-step, dump valves, gravity)."""
    import copy

    def same(a: object, b: object) -> bool:
        """Equal values (None, scalars, arrays or tuples of arrays; NaN equals NaN)."""
        if a is None or b is None:
            return a is b
        if isinstance(a, tuple):
            return isinstance(b, tuple) and len(a) == len(b) and all(same(x, y) for x, y in zip(a, b))
        a, b = np.asarray(a), np.asarray(b)
        return a.shape == b.shape and bool(np.array_equal(a, b, equal_nan=a.dtype.kind == "f"))

    def same_wheels(a: Wheelsets | None, b: Wheelsets | None) -> bool:
        if a is None or b is None:
            return a is b
        return (a.p == b.p and a.iters == b.iters and a.curves == b.curves and same(a.v_floor, b.v_floor)
                and same(a.R, b.R) and same(a.J, b.J) and same(a.N, b.N) and same(a.active, b.active))

    p0 = plants[0]
    for p in plants:
        if (not same_wheels(p.wheels, p0.wheels) or p._gears is not None or p.air_brake is not None or p._li
                or p._grade_fn is not None or not _substeps_fixed(p)
                or not same(p.wsp_valve_lag_s, p0.wsp_valve_lag_s) or not same(p.wsp_max_vent_s, p0.wsp_max_vent_s)
                or not same(p._tab, p0._tab) or not same(p._env, p0._env)
                or repr(p.blending) != repr(p0.blending) or not same(p.end_stop_m, p0.end_stop_m)
                or not same(p.end_stop_stiffness_n_per_m, p0.end_stop_stiffness_n_per_m)
                or not same(p.end_stop_absorption, p0.end_stop_absorption)
                or p.n_cars != p0.n_cars or repr(p.actuator) != repr(p0.actuator) or repr(p.rail) != repr(p0.rail)
                or repr(p.disturbances) != repr(p0.disturbances) or p.max_substep_s != p0.max_substep_s
                or p.gravity_mps2 != p0.gravity_mps2 or p.time_s != p0.time_s or p.rigid
                or p._act.params.kind != "ideal" and np.any(p._act.effort_n != 0.0)):
            return None
    st = copy.copy(p0)
    st.stacked = True
    st._kern = None
    st._step_couplers = None
    st._ekern = None
    st._qkern = None
    for name in _STACKED:
        setattr(st, name, np.stack([np.broadcast_to(np.asarray(getattr(p, name), dtype=float),
                                                    np.shape(getattr(p0, name))) for p in plants]))
    res = copy.copy(p0.resistance)
    for name in ("c0_n", "c1_n_per_mps", "c2_n_per_mps2"):
        object.__setattr__(res, name, np.stack([np.asarray(getattr(p.resistance, name), dtype=float)
                                                for p in plants]))
    st.resistance = res
    st._has_grade = any(p._has_grade for p in plants)
    st._grade_force = None if p0._grade_force is None else np.stack([p._grade_force for p in plants])
    st._act = ActuatorState(p0.actuator, st.mass_kg)
    st._blend = None if p0.blending is None else BlendingState(p0.blending, st.mass_kg)
    if p0.wheels is not None:  # the rows shared, the state per point
        st.wheels = copy.copy(p0.wheels)
        st.wheels.omega = np.stack([p.wheels.omega for p in plants])
        st.wheels.force_n = np.stack([p.wheels.force_n for p in plants])
        st.wheels.slip = np.stack([p.wheels.slip for p in plants])
        st.wheels._kern = None
        st.wsp_valve = np.stack([np.broadcast_to(p.wsp_valve, p.speed_mps.shape) for p in plants])
        st._vent_s = np.stack([np.broadcast_to(p._vent_s, p.speed_mps.shape) for p in plants])
    st._mu = np.broadcast_to(p0._mu, st.speed_mps.shape).copy()
    st._eff = np.ones(st.speed_mps.shape)
    st._base_mu = p0._base_mu
    st._rail_key = None
    st.diverged_rows = np.zeros(len(plants), dtype=bool)
    st.diverged_dl_m = np.zeros(len(plants))
    return st


def _substeps_fixed(p: TrainPlant) -> bool:
    """Whether ``p``'s sub-step never depends on its state: no end stop, or one whose own step
    (0.05/ω_b for the lightest pair of cars) is no shorter than ``max_substep_s``."""
    return p.end_stop_m is None or p.n_cars < 2 or p._end_stop_substep_s() >= p.max_substep_s
