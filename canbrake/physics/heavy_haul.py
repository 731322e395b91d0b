"""Heavy-haul train physics of Li, Zeng & Yu 2024 (J. East China Jiaotong Univ. 41(5):94-104).

Generic over the consist: arrays of shape ``(n_veh,)`` indexed from the front (0 = locomotive);
couplers have shape ``(n_veh-1,)``, coupler ``j`` joins vehicles ``j`` and ``j+1``. SI inside (m, s,
kg, N); the paper's kN, km/h, N/kN and ‰ appear only where its formulas use them. The paper's train
(HXD1 + 105 C80, Table 1, the draft-gear curves, the route) is data: ``scenarios/li2024_*.yaml`` and
``scenarios/data/li2024_route.csv``, read by :mod:`canbrake.consist.heavy_haul`.

What is modelled (paper equation numbers in brackets; MODELS.md section 2):

* locomotive traction / electric-brake envelopes (1)-(2): :class:`TractionEnvelope`, and the
  locomotive's adhesion limit: :class:`LocoAdhesion`;
* basic running resistance per unit weight w = A + B v + C v² N/kN (3): the coupled plant's Davis
  terms (:meth:`canbrake.consist.components.PerWeightResistance.davis_n_for`); grade i ‰ = i N/kN (4),
  curve 600/R N/kN (5): :class:`canbrake.physics.route.Route`;
* couplers with draft gears (7)-(9): :class:`CouplerBank` — a hysteretic spring with slack. The
  measured drop-hammer curves of Fig. 2 are not given as numbers, so the loading curve ``f_l`` and
  the unloading curve ``f_u = r_u · f_l`` are piecewise-linear (:class:`DraftGear`). Eq. (8)'s trial
  force ``F_prev + k Δd`` is clipped into ``[f_u, f_l]`` (eq. 9), which is eq. (7)'s branch choice. The
  QKX100 velocity-switch form (6) is replaced by the same scheme with QKX100's curve. A small viscous
  damping acts while the gear is engaged (numerical and physical: it damps elastic ringing inside
  the hysteresis band).
* air brake (10)-(15): :class:`AirBrake` — block forces (:func:`disc_block_force_kn`,
  :func:`shoe_block_force_kn`), friction coefficients φ_H, φ_C, the brake signal travelling along the
  brake pipe (apply and release waves), a first-order cylinder fill after the signal arrives; or ECP
  (each cylinder follows its own demand). The application rules of section 1.2 are the driver's
  (:class:`canbrake.control.li2024.LiDriver`).
* disturbance (40): :func:`canbrake.physics.rail.disturbance_n`.

The train itself is :class:`canbrake.physics.train.TrainPlant` (the coupled plant; issue 27 deleted
the heavy-haul model that stepped these parts on its own): it steps the draft gears
(:class:`CouplerBank`'s compiled ``GearKernel``) and the air brake (``AirKernel``) once per sub-step,
by semi-implicit Euler. The stiffest element is a coupler gear gone solid (2e8 N/m, also the eq. (8)
stiffness, between two 100 t wagons, ω = √(2k/m) ≈ 63 rad/s, ω·h ≈ 0.63 < 2 at the scenarios'
10 ms), so that step is stable.
"""
from __future__ import annotations

import math
from dataclasses import dataclass
import numpy as np

from canbrake.physics._heavy_haul_kernel import AirKernel, GearKernel
from canbrake.physics.route import Route  # noqa: F401 - the line, shared with the coupled plant

G = 9.81
KMH = 1.0 / 3.6  # m/s per km/h



# ------------------------------------------------------------------------------------ envelopes
@dataclass(frozen=True)
class TractionEnvelope:
    """Locomotive force limits of eqs. (1)-(2), kN with v in km/h.

    Traction F_T(v) = ``traction_start_kn`` for v ≤ ``traction_start_until_kmh``,
    ``traction_intercept_kn`` − ``traction_slope_kn_per_kmh``·v up to ``traction_linear_until_kmh``,
    ``power_kn_kmh``/v above. Electric brake F_B(v) = ``brake_slope_kn_per_kmh``·v for
    v ≤ ``brake_linear_until_kmh``, ``brake_max_kn`` up to ``brake_constant_until_kmh``,
    ``power_kn_kmh``/v above.
    """

    traction_start_kn: float
    traction_start_until_kmh: float
    traction_intercept_kn: float
    traction_slope_kn_per_kmh: float
    traction_linear_until_kmh: float
    brake_slope_kn_per_kmh: float
    brake_linear_until_kmh: float
    brake_max_kn: float
    brake_constant_until_kmh: float
    power_kn_kmh: float

    def traction_kn(self, v_kmh):
        """Maximum traction force (kN) at speed ``v_kmh`` (km/h), array or scalar."""
        v = np.abs(np.asarray(v_kmh, dtype=float))
        with np.errstate(divide="ignore"):
            hi = self.power_kn_kmh / np.maximum(v, 1e-9)
        return np.where(v <= self.traction_start_until_kmh, self.traction_start_kn,
                        np.where(v <= self.traction_linear_until_kmh,
                                 self.traction_intercept_kn - self.traction_slope_kn_per_kmh * v, hi))

    def electric_brake_kn(self, v_kmh):
        """Maximum electric brake force (kN, positive) at speed ``v_kmh`` (km/h)."""
        v = np.abs(np.asarray(v_kmh, dtype=float))
        with np.errstate(divide="ignore"):
            hi = self.power_kn_kmh / np.maximum(v, 1e-9)
        return np.where(v <= self.brake_linear_until_kmh, self.brake_slope_kn_per_kmh * v,
                        np.where(v <= self.brake_constant_until_kmh, self.brake_max_kn, hi))

    def saturate_n(self, u_n: float, v_mps: float) -> float:
        """Clip a force command (N, > 0 traction) into [−F_B(v), F_T(v)] (scalar fast path)."""
        v = abs(v_mps) / KMH
        if v <= self.traction_start_until_kmh:
            hi = self.traction_start_kn
        elif v <= self.traction_linear_until_kmh:
            hi = self.traction_intercept_kn - self.traction_slope_kn_per_kmh * v
        else:
            hi = self.power_kn_kmh / v
        if v <= self.brake_linear_until_kmh:
            lo = self.brake_slope_kn_per_kmh * v
        elif v <= self.brake_constant_until_kmh:
            lo = self.brake_max_kn
        else:
            lo = self.power_kn_kmh / v
        return min(max(u_n, -1000.0 * lo), 1000.0 * hi)


@dataclass(frozen=True)
class LocoAdhesion:
    """Adhesion limit of a locomotive's traction and dynamic brake: |u| ≤ μ(v)·m·g.

    ``curve`` "constant": μ = ``mu0``; "curtius_kniffler": μ(v) = ``mu0`` · (0.161 + 7.5/(v + 44)) / (0.161 +
    7.5/44), v in km/h (Curtius & Kniffler's locomotive adhesion on dry rail, 0.33 at standstill and
    0.22 at 80 km/h, scaled so that μ(0) = ``mu0``)."""

    mu0: float = 0.33
    curve: str = "constant"

    def mu(self, v_mps: float) -> float:
        """Usable adhesion coefficient at speed ``v_mps`` (m/s)."""
        if self.curve == "curtius_kniffler":
            return self.mu0 * (0.161 + 7.5 / (abs(v_mps) / KMH + 44.0)) / (0.161 + 7.5 / 44.0)
        return self.mu0


# ------------------------------------------------------------------------------------ consist
@dataclass(frozen=True)
class Consist:
    """Vehicle parameters, arrays of shape ``(n_veh,)``."""

    mass_kg: np.ndarray
    length_m: np.ndarray
    davis_a: np.ndarray  # N/kN
    davis_b: np.ndarray  # N/kN per km/h
    davis_c: np.ndarray  # N/kN per (km/h)^2
    is_loco: np.ndarray

    @property
    def n(self) -> int:
        return int(self.mass_kg.size)

    @property
    def weight_kn(self) -> np.ndarray:
        return self.mass_kg * G / 1000.0

    @property
    def spacing_m(self) -> np.ndarray:
        """Nominal centre-to-centre distance of vehicles j and j+1, shape ``(n-1,)``."""
        return 0.5 * (self.length_m[:-1] + self.length_m[1:])

    @property
    def distance_from_loco_m(self) -> np.ndarray:
        """Nominal distance of each vehicle's centre behind the locomotive's centre (m)."""
        return np.concatenate([[0.0], np.cumsum(self.spacing_m)])

    @property
    def total_mass_kg(self) -> float:
        return float(self.mass_kg.sum())

    @property
    def train_length_m(self) -> float:
        return float(self.length_m.sum())


# ------------------------------------------------------------------------------------ couplers
@dataclass(frozen=True)
class DraftGear:
    """Loading curve (deflection m -> force N, piecewise linear), unloading ratio, slack, stiffness."""

    name: str
    curve_m: tuple[float, ...]
    curve_n: tuple[float, ...]
    unloading_ratio: float   # f_u = ratio * f_l
    slack_m: float           # free play on each side of neutral (tension and compression)
    k_elastic_n_per_m: float  # eq. (8) transition stiffness
    k_solid_n_per_m: float   # beyond the stroke (gear closed)
    damping_n_s_per_m: float  # viscous term while engaged


class CouplerBank:
    """All couplers of the train, vectorised; state = hysteretic force and last gear deflection.

    ``stretch_m`` = x_j − x_{j+1} − spacing_j (> 0 in tension). The gear deflection is the stretch
    beyond the slack. Tension force is positive (it pulls vehicle j+1 forward and j back).
    """

    def __init__(self, gears: list[DraftGear]):
        self.n = len(gears)
        npts = len(gears[0].curve_m)
        self.cx = np.array([g.curve_m for g in gears])          # (n, npts)
        self.cf = np.array([g.curve_n for g in gears])
        self.stroke = self.cx[:, -1]
        self.fmax = self.cf[:, -1]
        self.ru = np.array([g.unloading_ratio for g in gears])
        self.slack = np.array([g.slack_m for g in gears])
        self.ke = np.array([g.k_elastic_n_per_m for g in gears])
        self.ks = np.array([g.k_solid_n_per_m for g in gears])
        self.c = np.array([g.damping_n_s_per_m for g in gears])
        assert npts >= 3
        self.force_state = np.zeros(self.n)
        self.defl_prev = np.zeros(self.n)
        #: the compiled hysteresis step (canbrake.physics._heavy_haul_kernel)
        self.kernel = GearKernel(self.cx, self.cf, self.ru, self.slack, self.ke, self.ks, self.c)

    def gear_deflection(self, stretch_m: np.ndarray) -> np.ndarray:
        s = np.asarray(stretch_m, dtype=float)
        return np.sign(s) * np.maximum(np.abs(s) - self.slack, 0.0)

    def static_stretch_for_force(self, force_n: np.ndarray) -> np.ndarray:
        """Stretch (m) at which the loading curve gives ``force_n`` (for initial equilibrium)."""
        f = np.asarray(force_n, dtype=float)
        d = np.array([np.interp(abs(fi), cf, cx) for fi, cf, cx in zip(f, self.cf, self.cx)])
        return np.sign(f) * (d + self.slack)

    def set_static(self, force_n: np.ndarray) -> np.ndarray:
        """Put every gear on its loading curve at ``force_n``; returns the stretches (m)."""
        st = self.static_stretch_for_force(force_n)
        self.defl_prev = self.gear_deflection(st)
        self.force_state = np.asarray(force_n, dtype=float).copy()
        return st

    def step(self, stretch_m: np.ndarray, stretch_rate_mps: np.ndarray) -> np.ndarray:
        """Advance the hysteresis to the new stretches and return coupler forces (N, + tension).

        Eq. (8): trial F = F_prev + k (d − d_prev) with d the stretch beyond the slack; eq. (9)/(7):
        keep it inside the band between the unloading curve f_u = r_u f_l and the loading curve f_l
        (piecewise linear, then the solid stiffness beyond the stroke) at the current deflection d
        (|f_u(d)| ≤ |F| ≤ |f_l(d)|); plus the viscous damping while engaged. Compiled (GearKernel).
        """
        f, self.force_state, self.defl_prev = self.kernel.step(
            np.ascontiguousarray(stretch_m, dtype=float), np.ascontiguousarray(stretch_rate_mps, dtype=float),
            self.force_state, self.defl_prev)
        return f


# ------------------------------------------------------------------------------------ air brake
def disc_block_force_kn(cylinder_diameter_mm: float, cylinder_pressure_kpa: float, lever_ratio: float,
                        efficiency: float, friction_radius_mm: float, wheel_radius_mm: float) -> float:
    """Eqs. (13)-(14): disc-brake force per cylinder referred to the wheel tread (kN), full pressure.

    Eq. (13) is printed with the disc friction radius r_z; we read it as the lever ratio γ_z
    (Table 1 gives γ_z = 2.4 for HXD1; r_z then enters eq. 14 as r_z / R_c).
    """
    k1 = np.pi / 4 * cylinder_diameter_mm ** 2 * cylinder_pressure_kpa * 1.0 * lever_ratio * efficiency * 1e-6
    return float(friction_radius_mm / wheel_radius_mm * k1)


def shoe_block_force_kn(cylinder_diameter_mm: float, cylinder_pressure_kpa: float, lever_ratio: float,
                        efficiency: float, cylinders: int, shoes: int) -> float:
    """Eq. (15): tread-brake force per shoe (kN), full pressure."""
    return float(np.pi / 4 * cylinder_diameter_mm ** 2 * cylinder_pressure_kpa * 1.0 * efficiency * lever_ratio
                 * (cylinders / shoes) * 1e-6)


def friction_coefficient(k_kn, v_kmh, coef):
    """Eqs. (11)-(12): φ = coef·(K + 200)/(4K + 200)·(2v + 150)/(3v + 150), K in kN, v in km/h;
    ``coef`` is 0.441 for HXD1 (φ_H) and 0.481 for C80's high-friction shoe (φ_C), per vehicle."""
    k = np.asarray(k_kn, dtype=float)
    v = np.abs(np.asarray(v_kmh, dtype=float))
    return coef * (k + 200.0) / (4.0 * k + 200.0) * (2.0 * v + 150.0) / (3.0 * v + 150.0)


def ecp_fill_for_force(force_n: float, v_mps: float, k_full_kn: float, n_blocks: float, friction_coef: float,
                       beta_c: float) -> float:
    """The cylinder fill (fraction of full service, 0..1) at which eq. (10) with eqs. (11)-(12) gives
    the retarding force ``force_n`` (N) at speed ``v_mps``: the inverse of the air brake's force law
    (:class:`canbrake.physics._heavy_haul_kernel.AirKernel`), for a vehicle whose full-pressure block
    force is ``k_full_kn`` (kN), with ``n_blocks`` blocks, friction ``coef`` and eq. (10)'s β_c.

    With K = k_full·fill the force is F = 1000·β_c·n·coef·s(v)·K(K + 200)/(4K + 200), s(v) =
    (2v + 150)/(3v + 150) (v in km/h), increasing in K; solving K(K + 200)/(4K + 200) = c for K ≥ 0
    gives K = (−(200 − 4c) + sqrt((200 − 4c)² + 800c))/2. Forces ≤ 0 give 0; beyond full service 1.
    """
    if not force_n > 0.0:
        return 0.0
    vk = abs(v_mps / KMH)
    c = force_n / (1000.0 * beta_c * n_blocks * friction_coef * (2.0 * vk + 150.0) / (3.0 * vk + 150.0))
    b = 200.0 - 4.0 * c
    k = 0.5 * (-b + math.sqrt(b * b + 800.0 * c))
    return min(1.0, k / k_full_kn)


@dataclass(frozen=True)
class BrakePipe:
    """Brake-pipe pressure per vehicle (opt-in refinement of the pneumatic brake, SI: Pa, s).

    The driver's valve lowers the pipe pressure at the locomotive from ``p0_pa`` by ``reduction_pa``
    (apply) or restores it (release). The change travels along the pipe at the apply / release wave
    speed of :class:`AirBrake`; once it has reached vehicle k (distance D_k behind the locomotive)
    the local pipe pressure moves towards its new value with a first-order lag
    τ_k = ``tau_s`` + ``tau_per_km_s`` · D_k / 1000 (the pipe's flow resistance: the rear drains and
    recharges more slowly, so the pressure drop and the brake build up along the train). Each
    vehicle's control valve (distributor) sets its cylinder target to ``ratio`` × (p0 − p_pipe),
    clipped to [0, the vehicle's full cylinder pressure]; the cylinder follows with the air brake's
    ``cylinder_tau_s``.
    """

    p0_pa: float = 600e3
    reduction_pa: float = 170e3
    ratio: float = 2.6
    tau_s: float = 1.0
    tau_per_km_s: float = 4.0


@dataclass(frozen=True)
class EmergencyBrake:
    """An emergency application of the automatic air brake or ECP (SI: m/s, s; factors dimensionless).

    Replaces the full-service application of :class:`AirBrake` for a whole run (a stop test's
    application): the brake pipe is vented at the driver's valve and at every control valve it
    reaches (quick action), so the signal travels at ``apply_wave_mps`` (faster than the service
    wave); the emergency valve fills each cylinder with the lag ``cylinder_tau_s`` to
    ``pressure_factor`` × the vehicle's full-service cylinder pressure (the auxiliary and emergency
    reservoirs equalise into the cylinder); the block force K (eqs. 13-15, linear in the cylinder
    pressure) scales with it and eq. (10)'s coefficient is ``brake_factor`` instead of the service
    β_c. With a :class:`BrakePipe` the pipe is vented to 0 Pa with the lag ``vent_tau_s`` at every
    vehicle (no per-km term: every valve vents locally). ECP: the same cylinder pressure, lag and
    coefficient on every wagon at once (no wave)."""

    apply_wave_mps: float
    cylinder_tau_s: float
    pressure_factor: float = 1.0
    brake_factor: float = 1.0
    vent_tau_s: float = 0.5


class AirBrake:
    """Brake-pipe signal propagation and cylinder fill (pneumatic), or per-vehicle demands (ECP).

    The locomotive's driver's valve issues apply/release; vehicle k (centre at distance D_k behind
    the locomotive's centre) sees an apply signal D_k / 200 m/s and a release signal D_k / 36 m/s
    after it was issued. After the signal arrives the cylinder fills/empties with a first-order lag
    ``cylinder_tau_s`` (assumed, not in the paper). ``fill`` in [0, 1] is the fraction of Table 1's
    cylinder pressure p_z. In ``ecp`` mode each cylinder follows ``ecp_target`` with the same lag.
    Per-vehicle arrays (n,): ``block_force_kn`` (K per block at full pressure, eqs. 13-15),
    ``n_blocks``, ``friction_coef`` (eqs. 11-12), ``cylinder_pressure_pa``; ``beta_c`` is eq. (10)'s β_c.
    ``emergency``: every application of the run is an emergency one (:class:`EmergencyBrake`: its
    wave speed, cylinder lag, pressure and coefficient replace the service ones); None: service.
    """

    def __init__(self, consist: Consist, *, apply_wave_mps: float, release_wave_mps: float, cylinder_tau_s: float,
                 beta_c: float, block_force_kn: np.ndarray, n_blocks: np.ndarray, friction_coef: np.ndarray,
                 cylinder_pressure_pa: np.ndarray, mode: str = "pneumatic", pipe: BrakePipe | None = None,
                 emergency: EmergencyBrake | None = None):
        if mode not in ("pneumatic", "ecp"):
            raise ValueError(f"air brake mode must be 'pneumatic' or 'ecp', got {mode!r}")
        self.emergency = emergency
        if emergency is not None:  # the emergency application's brake in place of the service one
            apply_wave_mps, cylinder_tau_s, beta_c = emergency.apply_wave_mps, emergency.cylinder_tau_s, \
                emergency.brake_factor
            block_force_kn = np.asarray(block_force_kn, dtype=float) * emergency.pressure_factor
            cylinder_pressure_pa = np.asarray(cylinder_pressure_pa, dtype=float) * emergency.pressure_factor
            if pipe is not None:
                pipe = BrakePipe(p0_pa=pipe.p0_pa, reduction_pa=pipe.p0_pa, ratio=pipe.ratio,
                                 tau_s=emergency.vent_tau_s, tau_per_km_s=0.0)
        self.consist = consist
        self.mode = mode
        self.dist = consist.distance_from_loco_m
        self.apply_wave, self.release_wave = apply_wave_mps, release_wave_mps
        self.tau = cylinder_tau_s
        self.beta_c = beta_c
        self.applied = False
        self.t_apply = -np.inf
        self.t_release = -np.inf
        self.fill = np.zeros(consist.n)
        #: ECP mode: each vehicle's cylinder target (fraction of full service), held between demands
        self.ecp_target = np.zeros(consist.n)
        self.last_force_n = np.zeros(consist.n)
        self.events: list[tuple[float, str]] = []
        self.k_full_kn = np.asarray(block_force_kn, dtype=float)
        self.n_blocks = np.asarray(n_blocks, dtype=float)
        self.friction_coef = np.asarray(friction_coef, dtype=float)
        self.cylinder_pressure_pa = np.asarray(cylinder_pressure_pa, dtype=float)
        self.pipe = pipe if mode == "pneumatic" else None
        if self.pipe is not None:
            self.pipe_tau_s = self.pipe.tau_s + self.pipe.tau_per_km_s * self.dist / 1000.0
            self.pipe_pressure_pa = np.full(consist.n, self.pipe.p0_pa)
        pp = self.pipe or BrakePipe(0.0, 0.0, 0.0)
        #: the compiled fill and force step (canbrake.physics._heavy_haul_kernel)
        self.kernel = AirKernel(self.dist, self.k_full_kn, self.n_blocks, self.friction_coef, self.cylinder_pressure_pa,
                                beta_c=float(beta_c), apply_wave=apply_wave_mps, release_wave=release_wave_mps,
                                p0=pp.p0_pa, reduction=pp.reduction_pa, ratio=pp.ratio)
        self._gains_dt = None
        self._no_pipe = np.zeros(consist.n)

    def command(self, t_s: float, apply: bool) -> None:
        """Driver's valve: issue an apply (True) or a release (False) at time ``t_s``."""
        if apply and not self.applied:
            self.applied, self.t_apply = True, t_s
            self.events.append((t_s, "apply"))
        elif not apply and self.applied:
            self.applied, self.t_release = False, t_s
            self.events.append((t_s, "release"))

    def signal(self, t_s: float) -> np.ndarray:
        """Per vehicle: True where the last signal that has arrived is 'apply'."""
        if self.t_apply == -np.inf:
            return np.zeros(self.dist.size, bool)
        arr_a = self.t_apply + self.dist / self.apply_wave
        arr_r = self.t_release + self.dist / self.release_wave
        got_a = t_s >= arr_a
        got_r = t_s >= arr_r
        # the later-issued command wins once it has arrived
        if self.t_apply >= self.t_release:
            return got_a
        return got_a & ~got_r

    def kernel_mode(self) -> int:
        """How a step moves the cylinders (:class:`AirKernel`): 0 ECP, 1 the pneumatic signal, 2 the
        brake-pipe pressure, −1 not at all (pneumatic, never applied)."""
        if self.mode == "ecp":
            return 0
        if self.t_apply == -np.inf:
            return -1
        return 2 if self.pipe is not None else 1

    def gains(self, dt_s: float) -> tuple[np.ndarray, np.ndarray]:
        """The first-order lags' gains over ``dt_s``, 1 − e^(−dt/τ), per vehicle: cylinders, brake pipe."""
        if self._gains_dt != dt_s:
            n = self.dist.size
            fill = np.ascontiguousarray(np.broadcast_to(1.0 - np.exp(-dt_s / self.tau), (n,)), dtype=float)
            pipe = self._no_pipe if self.pipe is None else 1.0 - np.exp(-dt_s / self.pipe_tau_s)
            self._gains, self._gains_dt = (fill, pipe), dt_s
        return self._gains

    def step(self, t_s: float, dt_s: float, v_mps: np.ndarray) -> np.ndarray:
        """Advance cylinder fills by ``dt_s`` and return the air-brake force per vehicle (N, ≥ 0).

        ECP: each cylinder follows its ``ecp_target``; pneumatic: the signal that has arrived
        (:meth:`signal`), or with a :class:`BrakePipe` the local pipe pressure (first-order lag
        towards p0 or p0 − reduction) sets the target ``ratio`` (p0 − p_pipe), clipped to the full
        pressure; the cylinder follows with ``cylinder_tau_s``. Compiled (:class:`AirKernel`)."""
        mode = self.kernel_mode()
        if mode < 0:
            return self.last_force_n
        fill_gain, pipe_gain = self.gains(dt_s)
        pipe = self._no_pipe if self.pipe is None else self.pipe_pressure_pa.copy()
        self.last_force_n = self.kernel.step(mode, t_s, np.ascontiguousarray(v_mps, dtype=float), self.fill,
                                             np.ascontiguousarray(self.ecp_target, dtype=float), fill_gain, pipe,
                                             pipe_gain, self.t_apply, self.t_release)
        if self.pipe is not None:
            self.pipe_pressure_pa = pipe
        return self.last_force_n

    def force_n(self, v_mps: np.ndarray) -> np.ndarray:
        """Eq. (10): F_a = β_c Σ φ K over the blocks of each vehicle, at the current fills (N)."""
        z = self._no_pipe
        return self.kernel.step(3, 0.0, np.ascontiguousarray(v_mps, dtype=float), self.fill, z, z, z, z, 0.0, 0.0)
