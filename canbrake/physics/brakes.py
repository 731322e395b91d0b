"""Brake equipment of a coupled (metro) car beyond a force actuator: electro-dynamic / friction
blending, wheelsets with wheel–rail adhesion under braking, the wheel-slide-protection dump valve.

Vectorised over cars (shape ``(n,)``) and axles (shape ``(n, p)``); SI throughout (m, s, m/s, N,
N·m, kg·m², rad/s). No CAN here: the wheel-slide-protection *logic* is an ECU function
(:mod:`canbrake.control.brake_functions`); the plant only has the valve it drives.

Blending (:class:`BrakeBlending`)
    The car's brake demand (the actuator's effort, + brakes) goes first to the electro-dynamic (ED)
    brake of its traction motors, up to what the ED brake can give at the car's speed,
    ``F_ed,max(v) = m · min(a_ed, P/(m|v|)) · fade(v)``, with ``fade`` rising linearly from 0 at
    ``fade_end_mps`` to 1 at ``fade_start_mps`` (an ED brake loses its force as the motor's back-EMF
    vanishes near standstill). The friction brake supplies the rest and follows its share with a
    first-order lag ``friction_lag_s`` (relay valve and cylinder fill), so when the ED brake fades
    the total dips by about ``friction_lag_s · dF_ed/dt`` until the friction brake catches up. Traction
    (a negative effort) is not blended.

Wheelsets (:class:`Wheelsets`)
    ``p`` axles per car, each with its own angular speed ω, radius R, inertia J and normal load
    N = m g / p. The brake torque T_b (the car's brake force · R / p) acts on the wheel as Coulomb
    friction (it opposes ω and holds a locked wheel up to its magnitude); the rail acts on the
    wheel with the creep force F = μ(λ, v) N of Cai et al. 2014 (eqs. 10–15, the "physical" variant
    of :mod:`canbrake.physics.wheel_adhesion`: the printed slip curve scaled to a peak μ per car,
    times the speed decay μ_max(v)/μ_max(0)). Braking gives negative creep λ = (ωR − v)/max(ωR, v,
    v_floor) < 0. When T_b exceeds what the rail can take (≈ μ_peak N R) the wheel decelerates
    faster than the car, λ runs past the adhesion peak, μ falls and the wheel locks: a skid is the
    physical result of low μ, not a force cap. Wheels and car body are solved together by backward
    Euler (Newton on the arrow-shaped Jacobian, as :meth:`WheelSet.step_coupled`), because the
    creep force is stiff near standstill (time constants below a millisecond).

The three are computed by one compiled sub-step, :mod:`canbrake.physics._brakes_kernel`, called by
:meth:`canbrake.physics.train.TrainPlant.step`; the classes here hold their parameters and state.

Dump valve
    Wheel-slide protection vents the brake cylinders of a car through its dump valves: the brake
    torque is multiplied by ``1 − r`` with r the valve opening, which follows the ECU's
    ``wsp_release`` command (0..1) with a first-order lag (default 0.05 s); the dump valve acts
    downstream of the brake control, so it bypasses the service brake's jerk limit.
"""
from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Sequence

import numpy as np

from canbrake.physics.wheel_adhesion import RailCondition

#: Cai 2014's dry-rail slip curve (eq. 41), the default shape of the coupled train's wheels
CAI_DRY = RailCondition(b1=1.786, b2=40.0, b3=10.0, c1=0.040, c2=3.78, c3=33.3, peak_mu0=0.35)


@dataclass(frozen=True)
class BrakeBlending:
    """ED / friction blending parameters (per unit mass; one value for every car, or one per car).

    ``ed_max_decel_mps2``: ED brake force / m at full capacity (m/s²; 0: the car has no ED brake,
    e.g. a trailer); ``ed_power_w_per_kg``: ED power limit per unit mass (W/kg; inf = none);
    ``fade_start_mps`` / ``fade_end_mps``: the ED force fades linearly to zero between these speeds
    (m/s); ``friction_lag_s``: first-order lag of the friction brake behind its share of the demand
    (s; 0 = immediate); the fade speeds and the lag may be one per car too (a car without blending:
    ``ed_max_decel_mps2`` 0 and ``friction_lag_s`` 0, friction only). ``envelope``: None, or per car the ED brake's own force envelope
    ``(slope N·s/m, v1 m/s, F_max N, v2 m/s, power W)`` (Li 2024 eq. 2: F = slope·|v| up to v1, F_max
    up to v2, power/|v| above; it replaces that car's ``ed_max``/``ed_power`` and fade), NaN for the
    cars without one.
    """

    ed_max_decel_mps2: float | tuple[float, ...] = 1.0
    ed_power_w_per_kg: float | tuple[float, ...] = math.inf
    fade_start_mps: float | tuple[float, ...] = 10.0 / 3.6
    fade_end_mps: float | tuple[float, ...] = 3.0 / 3.6
    friction_lag_s: float | tuple[float, ...] = 0.2
    envelope: tuple[tuple[float, float, float, float, float], ...] | None = None

    def __post_init__(self) -> None:
        if not (np.all(np.asarray(self.fade_start_mps) > np.asarray(self.fade_end_mps))
                and np.all(np.asarray(self.fade_end_mps) >= 0.0)):
            raise ValueError("blending: need fade_start > fade_end >= 0")
        if np.any(np.asarray(self.ed_max_decel_mps2) < 0) or np.any(np.asarray(self.friction_lag_s) < 0):
            raise ValueError("blending: ED capacity and friction lag must be >= 0")


class BlendingState:
    """Blending of every car: friction-brake state (N) and the last split."""

    def __init__(self, params: BrakeBlending, mass_kg: np.ndarray) -> None:
        self.params = params
        self.mass_kg = mass_kg
        self.friction_n = np.zeros_like(mass_kg)
        self.ed_n = np.zeros_like(mass_kg)


class Wheelsets:
    """The axles of every car of a coupled train: ω of shape ``(n, p)`` (see the module docstring).

    ``mass_kg`` (n,) car masses (the normal load per axle is m g / p); ``radius_m``, ``inertia_kgm2``
    per wheelset; ``curve`` the slip-curve shape (peak scaled to each car's μ); ``v_floor_mps`` the
    slip denominator's floor (m/s); both one for the train or one per car; ``speed_mps`` (n,)
    initial speeds (wheels roll without slip).
    ``axles``, ``radius_m`` and ``inertia_kgm2`` may be one per car (``axles`` 0: a car without
    wheels, braking as a train without wheelsets does); p is then the most axles of a car and a
    car's axles beyond its own are inactive (``active``: axles per car; ω, force and slip 0).
    """

    def __init__(self, mass_kg: np.ndarray, axles: int | Sequence[int], radius_m: float | Sequence[float],
                 inertia_kgm2: float | Sequence[float], speed_mps: np.ndarray, *,
                 curve: RailCondition | Sequence[RailCondition] = CAI_DRY, v_floor_mps: float | Sequence[float] = 0.1,
                 gravity_mps2: float = 9.81, newton_iters: int = 5) -> None:
        n_cars = np.size(mass_kg)
        curves = (curve,) if isinstance(curve, RailCondition) else tuple(curve)
        floors = np.atleast_1d(np.asarray(v_floor_mps, dtype=float))
        if len(curves) not in (1, n_cars) or floors.size not in (1, n_cars) or np.any(~(floors > 0)):
            raise ValueError(f"wheelsets: need one slip curve and one v_floor_mps > 0 for the train or one per car "
                             f"({n_cars}), got {len(curves)} and {floors.size}")
        if len(set(curves)) == 1 and np.all(floors == floors[0]):  # one for the train
            curves, floors = curves[:1], floors[:1]
        #: the slip curve of every car (one entry: the train's), and the slip denominator's floor (m/s)
        self.curves: tuple[RailCondition, ...] = curves
        self.v_floor: np.ndarray = floors
        self.curve = curves[0]
        self._mu0 = np.array([float(c.mu_max(0.0)) for c in curves])
        self._peak_curve = np.array([c.peak_curve for c in curves])
        self.iters = int(newton_iters)
        self.active: np.ndarray | None = None
        if np.ndim(axles) or np.ndim(radius_m) or np.ndim(inertia_kgm2):  # per car
            n = np.size(mass_kg)
            na = np.broadcast_to(np.asarray(axles, dtype=np.intp), (n,))
            R = np.broadcast_to(np.asarray(radius_m, dtype=float), (n,)).copy()
            J = np.broadcast_to(np.asarray(inertia_kgm2, dtype=float), (n,)).copy()
            if np.any(na < 0) or not np.any(na > 0) or np.any((na > 0) & ((R <= 0) | (J <= 0))):
                raise ValueError("wheelsets: need axles >= 0 per car (some > 0), radius > 0, inertia > 0")
            R[na == 0], J[na == 0] = 1.0, 1.0  # unused
            self.p = int(na.max())
            self.active = na.copy()
            self.R, self.J = R, J
            on = np.arange(self.p)[None, :] < na[:, None]
            load = np.asarray(mass_kg, dtype=float) * gravity_mps2 / np.maximum(na, 1)
            self.N = np.where(on, load[:, None], 0.0)
            self.omega = np.where(on, (np.asarray(speed_mps, dtype=float) / R)[:, None], 0.0)
            self.force_n = np.zeros_like(self.omega)
            self.slip = np.zeros_like(self.omega)
            self._kern = None
            return
        if axles < 1 or radius_m <= 0 or inertia_kgm2 <= 0:
            raise ValueError("wheelsets: need axles >= 1, radius > 0, inertia > 0")
        self.p = int(axles)
        self.R = float(radius_m)
        self.J = float(inertia_kgm2)
        self.N = np.repeat((np.asarray(mass_kg, dtype=float) * gravity_mps2 / axles)[:, None], axles, axis=1)
        self.omega = np.repeat((np.asarray(speed_mps, dtype=float) / radius_m)[:, None], axles, axis=1)
        self.force_n = np.zeros_like(self.omega)
        self.slip = np.zeros_like(self.omega)
        self._kern = None  # the compiled step, built at the first step

    def kernel_params(self) -> dict:
        """The wheelsets' constants as :class:`~canbrake.physics._brakes_kernel.EquipmentKernel` takes them."""
        cs = self.curves
        curve = {k: np.array([getattr(c, k) for c in cs], dtype=float) for k in ("b1", "b2", "b3", "c1", "c2", "c3")}
        return dict(axles=self.p, R=self.R, J=self.J, N=self.N, active=self.active, **curve, mu0=self._mu0,
                    peak_curve=self._peak_curve, v_floor=self.v_floor, iters=self.iters)

    def step(self, h_s: float, v0: np.ndarray, mass_kg: np.ndarray, other_n: np.ndarray, brake_torque_nm: np.ndarray,
             drive_torque_nm: np.ndarray, mu_peak: np.ndarray) -> np.ndarray:
        """One backward-Euler step of wheels and car bodies (compiled:
        :meth:`~canbrake.physics._brakes_kernel.EquipmentKernel.wheels_step`); returns the new car
        speeds (n,).

        Solves J(ω − ω0) = h(T_d − T_b sgn ω − F R) per axle and m(v − v0) = h(Σ F + other) per car
        (``other_n``: the car's forces besides the creep forces, held over the step; torques (n, p)
        N·m, ``mu_peak`` (n,)). A wheel whose ω would pass through zero under the brake locks (ω = 0)
        and stays locked while the brake torque holds it against the rail (Coulomb friction). Creep
        forces are left in :attr:`force_n`, slips in :attr:`slip`.
        """
        if self._kern is None:
            from canbrake.physics._brakes_kernel import EquipmentKernel
            self._kern = EquipmentKernel(blending=False, ed_max=0.0, ed_power=0.0, fade_start=1.0, fade_end=0.0,
                                         friction_lag_s=0.0, valve_lag_s=0.0, max_vent_s=math.inf,
                                         adhesion_limited=False, gravity=0.0, **self.kernel_params())
        f64 = lambda a: np.ascontiguousarray(a, dtype=float).reshape(-1)  # noqa: E731
        self.omega = np.array(self.omega, dtype=float)
        self.force_n = np.zeros_like(self.omega)
        self.slip = np.zeros_like(self.omega)
        return self._kern.wheels_step(h_s, f64(v0), f64(np.broadcast_to(mass_kg, np.shape(v0))),
                                      f64(np.broadcast_to(other_n, np.shape(v0))),
                                      f64(np.broadcast_to(brake_torque_nm, self.omega.shape)),
                                      f64(np.broadcast_to(drive_torque_nm, self.omega.shape)),
                                      f64(np.broadcast_to(mu_peak, np.shape(v0))), self.omega.reshape(-1),
                                      self.force_n.reshape(-1), self.slip.reshape(-1))
