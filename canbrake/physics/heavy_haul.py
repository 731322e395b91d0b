"""Heavy-haul 1+105 train of Li, Zeng & Yu 2024 (J. East China Jiaotong Univ. 41(5):94-104).

One HXD1 locomotive (184 t, 35.222 m) and 105 C80 wagons (100 t, 12 m), all arrays of shape
``(n_veh,) = (106,)`` indexed from the front (0 = locomotive); couplers have shape ``(n_veh-1,)``,
coupler ``j`` joins vehicles ``j`` and ``j+1``. SI inside (m, s, kg, N); the paper's kN, km/h,
N/kN and ‰ appear only in the published-parameter functions, converted at the edge.

What is modelled (paper equation numbers in brackets; MODELS.md section 2):

* locomotive traction / electric-brake envelopes (1)-(2): :func:`traction_envelope_n`,
  :func:`electric_brake_envelope_n`;
* basic running resistance per unit weight w = A + B v + C v² N/kN (3), grade i ‰ = i N/kN (4),
  curve 600/R N/kN (5): :func:`basic_resistance_n`, :class:`Route`;
* couplers with draft gears (7)-(9): :class:`CouplerBank` — a hysteretic spring with slack. The
  measured drop-hammer curves of Fig. 2 are not given as numbers, so the loading curve ``f_l`` and
  the unloading curve ``f_u = r_u · f_l`` are piecewise-linear approximations (stroke and capacity of
  MT-2 / QKX100 as catalogued; see :data:`MT2` / :data:`QKX100`). Eq. (8)'s trial force
  ``F_prev + k Δd`` is clipped into ``[f_u, f_l]`` (eq. 9), which is eq. (7)'s branch choice. The
  QKX100 velocity-switch form (6) is replaced by the same scheme with QKX100's curve. A small viscous
  damping acts while the gear is engaged (numerical and physical: it damps elastic ringing inside
  the hysteresis band).
* air brake (10)-(15): :class:`AirBrake` — shoe force, friction coefficients φ_H, φ_C, the brake
  signal travelling along the brake pipe at 200 m/s (apply) and 36 m/s (release), a first-order
  cylinder fill after the signal arrives, and the application rules of section 1.2
  (:meth:`AirBrake.rule_step`).
* disturbance (40): :func:`disturbance_n` on the locomotive and wagons 10, 20, ..., 100.

Integration: semi-implicit (symplectic) Euler with a fixed step, default 10 ms
(:data:`DEFAULT_DT_S`). The stiffest element is a coupler gear gone solid (2e8 N/m, also the eq. (8) stiffness, between two
100 t wagons, ω = √(2k/m) ≈ 63 rad/s, ω·dt ≈ 0.63 < 2), so the step is stable. The report
(:mod:`canbrake.report.li2024`) compares 10 ms with 5 ms over the first 1200 s.
"""
from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

G = 9.81
KMH = 1.0 / 3.6  # m/s per km/h
DEFAULT_DT_S = 0.01

N_WAGONS = 105
LOCO_MASS_KG = 184_000.0
LOCO_LENGTH_M = 35.222
WAGON_MASS_KG = 100_000.0
WAGON_LENGTH_M = 12.0

# basic resistance coefficients (N/kN with v in km/h), paper section 3.1
DAVIS_HXD1 = (1.20, 0.0065, 0.000279)
DAVIS_C80 = (0.92, 0.0048, 0.000125)


# ------------------------------------------------------------------------------------ envelopes
def traction_envelope_kn(v_kmh):
    """Eq. (1): HXD1 maximum traction force in kN at speed ``v_kmh`` (km/h), array or scalar."""
    v = np.abs(np.asarray(v_kmh, dtype=float))
    with np.errstate(divide="ignore"):
        hi = 34560.0 / np.maximum(v, 1e-9)
    return np.where(v <= 5.0, 760.0, np.where(v <= 65.0, 779.0 - 3.8 * v, hi))


def electric_brake_envelope_kn(v_kmh):
    """Eq. (2): HXD1 maximum electric brake force in kN at speed ``v_kmh`` (km/h)."""
    v = np.abs(np.asarray(v_kmh, dtype=float))
    with np.errstate(divide="ignore"):
        hi = 34560.0 / np.maximum(v, 1e-9)
    return np.where(v <= 5.0, 92.2 * v, np.where(v <= 75.0, 461.0, hi))


def traction_envelope_n(v_mps):
    """Maximum traction force (N) at speed ``v_mps`` (m/s)."""
    return 1000.0 * traction_envelope_kn(np.asarray(v_mps, dtype=float) / KMH)


def electric_brake_envelope_n(v_mps):
    """Maximum electric brake force (N, positive) at speed ``v_mps`` (m/s)."""
    return 1000.0 * electric_brake_envelope_kn(np.asarray(v_mps, dtype=float) / KMH)


def saturate_control_n(u_n: float, v_mps: float) -> float:
    """Clip a locomotive force command (N, >0 traction) into [-F_B(v), F_T(v)]."""
    v = abs(v_mps) / KMH
    hi = 760.0 if v <= 5.0 else (779.0 - 3.8 * v if v <= 65.0 else 34560.0 / v)
    lo = 92.2 * v if v <= 5.0 else (461.0 if v <= 75.0 else 34560.0 / v)
    return min(max(u_n, -1000.0 * lo), 1000.0 * hi)


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


def li2024_consist(n_wagons: int = N_WAGONS) -> Consist:
    """The paper's 1+105 HXD1 + C80 consist (or 1+``n_wagons``)."""
    n = n_wagons + 1
    loco = np.zeros(n, bool)
    loco[0] = True
    pick = lambda a, b: np.where(loco, a, b).astype(float)  # noqa: E731
    return Consist(
        mass_kg=pick(LOCO_MASS_KG, WAGON_MASS_KG), length_m=pick(LOCO_LENGTH_M, WAGON_LENGTH_M),
        davis_a=pick(DAVIS_HXD1[0], DAVIS_C80[0]), davis_b=pick(DAVIS_HXD1[1], DAVIS_C80[1]),
        davis_c=pick(DAVIS_HXD1[2], DAVIS_C80[2]), is_loco=loco)


def basic_resistance_n(consist: Consist, v_mps: np.ndarray) -> np.ndarray:
    """Eq. (3): basic running resistance magnitude (N) of every vehicle, ``w · weight``.

    ``w = A + B v + C v²`` N/kN with v in km/h, times the vehicle's weight in kN.
    """
    v = np.abs(np.asarray(v_mps, dtype=float)) / KMH
    w = consist.davis_a + consist.davis_b * v + consist.davis_c * v * v
    return w * consist.weight_kn


# ------------------------------------------------------------------------------------ route
@dataclass(frozen=True)
class Route:
    """Piecewise-constant grade and curvature along the line.

    ``grade_start_m`` (ascending, first 0) and ``grade_permille`` (+ uphill) define grade segments;
    ``curve_start_m``/``curve_end_m``/``curve_radius_m`` the curves. Beyond the last segment the
    grade stays; before 0 the line is level and straight (the paper's assumption 3).
    """

    grade_start_m: np.ndarray
    grade_permille: np.ndarray
    curve_start_m: np.ndarray = field(default_factory=lambda: np.zeros(0))
    curve_end_m: np.ndarray = field(default_factory=lambda: np.zeros(0))
    curve_radius_m: np.ndarray = field(default_factory=lambda: np.zeros(0))
    length_m: float = np.inf

    def __post_init__(self):
        brk = np.unique(np.concatenate([[0.0], self.grade_start_m, self.curve_start_m, self.curve_end_m]))
        mid = np.append(0.5 * (brk[1:] + brk[:-1]), brk[-1] + 1.0)
        object.__setattr__(self, "_brk", brk)
        object.__setattr__(self, "_val", self.grade_at(mid) + self.curve_permille_at(mid))

    def total_permille_at(self, x_m: np.ndarray) -> np.ndarray:
        """Grade + curve resistance per unit weight (N/kN) at positions ``x_m`` (table lookup)."""
        idx = np.searchsorted(self._brk, x_m, side="right") - 1
        return np.where(idx < 0, 0.0, self._val[np.clip(idx, 0, None)])

    def grade_at(self, x_m: np.ndarray) -> np.ndarray:
        """Grade (‰, + uphill) at positions ``x_m``."""
        x = np.asarray(x_m, dtype=float)
        idx = np.searchsorted(self.grade_start_m, x, side="right") - 1
        g = self.grade_permille[np.clip(idx, 0, None)]
        return np.where(idx < 0, 0.0, g)

    def curve_permille_at(self, x_m: np.ndarray) -> np.ndarray:
        """Curve resistance per unit weight 600/R (N/kN) at positions ``x_m``."""
        x = np.asarray(x_m, dtype=float)
        out = np.zeros_like(x)
        for a, b, r in zip(self.curve_start_m, self.curve_end_m, self.curve_radius_m):
            out = np.where((x >= a) & (x < b), 600.0 / r, out)
        return out

    def long_downgrade_ahead(self, x_front_m: float, x_rear_m: float, lookahead_m: float = 2500.0,
                             min_grade_permille: float = 8.0, min_length_m: float = 500.0) -> bool:
        """Is there a downgrade steeper than ``min_grade`` ‰ and longer than ``min_length`` m
        overlapping [x_rear, x_front + lookahead]? (the application rule of section 1.2)."""
        starts = self.grade_start_m
        ends = np.append(starts[1:], self.length_m)
        steep = (self.grade_permille < -min_grade_permille) & ((ends - starts) >= min_length_m)
        overl = (ends > x_rear_m) & (starts < x_front_m + lookahead_m)
        return bool(np.any(steep & overl))

    def force_n(self, consist: Consist, x_m: np.ndarray) -> np.ndarray:
        """Grade + curve resistance (N, + opposes forward motion / pulls downhill when negative)."""
        return self.total_permille_at(x_m) * consist.weight_kn


def li2024_route() -> Route:
    """A synthesised 45 km route with long downgrades near 20, 34 and 39 km.

    The paper's Datong South - Dongjingji profile (Fig. 3) is not published as numbers; this profile
    is ours: level start (assumption 3), mild up/down grades, three long downgrades of 10-11 ‰
    (Daqin's ruling grade is 12 ‰) and three curves.
    """
    km = 1000.0
    seg = [(0, 0.0), (5, 3.0), (10, -2.0), (15, 1.0), (18, -10.0), (23.5, -3.0), (28, 4.0),
           (31, -11.0), (36, -4.0), (37.5, -10.5), (41.5, 0.0)]
    return Route(grade_start_m=np.array([a * km for a, _ in seg]), grade_permille=np.array([g for _, g in seg]),
                 curve_start_m=np.array([12.0, 26.0, 33.0]) * km, curve_end_m=np.array([13.0, 27.0, 34.0]) * km,
                 curve_radius_m=np.array([1000.0, 800.0, 1200.0]), length_m=45.0 * km)


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


#: MT-2 (C80): 83 mm stroke, ≈2.27 MN at full stroke, energy absorption ≈ 75 % (approximated)
MT2 = DraftGear("MT-2", (0.0, 0.020, 0.050, 0.073, 0.083), (0.0, 3.0e5, 9.0e5, 1.8e6, 2.27e6),
                unloading_ratio=0.25, slack_m=0.005, k_elastic_n_per_m=2e8, k_solid_n_per_m=2e8,
                damping_n_s_per_m=1e5)
#: QKX100 (HXD1): 100 mm stroke, ≈2.5 MN at full stroke (approximated)
QKX100 = DraftGear("QKX100", (0.0, 0.020, 0.060, 0.090, 0.100), (0.0, 2.5e5, 9.0e5, 2.0e6, 2.5e6),
                   unloading_ratio=0.35, slack_m=0.005, k_elastic_n_per_m=2e8, k_solid_n_per_m=2e8,
                   damping_n_s_per_m=1e5)


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
        self._rows = np.arange(self.n)
        self.force_state = np.zeros(self.n)
        self.defl_prev = np.zeros(self.n)

    @classmethod
    def li2024(cls, n_couplers: int) -> "CouplerBank":
        """Coupler 0 (locomotive-wagon 1) with QKX100's curve, the others MT-2."""
        return cls([QKX100] + [MT2] * (n_couplers - 1))

    def loading_n(self, d_abs: np.ndarray) -> np.ndarray:
        """f_l(|d|) (N) for gear deflections |d| (m), vectorised over couplers."""
        d = np.asarray(d_abs, dtype=float)
        k = (d[:, None] > self.cx[:, 1:-1]).sum(axis=1)  # segment index per coupler
        r = self._rows
        x0, x1, f0, f1 = self.cx[r, k], self.cx[r, k + 1], self.cf[r, k], self.cf[r, k + 1]
        out = f0 + (f1 - f0) * (d - x0) / (x1 - x0)
        beyond = d > self.stroke
        return np.where(beyond, self.fmax + self.ks * (d - self.stroke), out)

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

        Eq. (8): trial F = F_prev + k (d − d_prev); eq. (9)/(7): keep it inside the band between the
        unloading and the loading curve at the current deflection d (|f_u(d)| ≤ |F| ≤ |f_l(d)|).
        """
        d = self.gear_deflection(stretch_m)
        trial = self.force_state + self.ke * (d - self.defl_prev)
        fl = self.loading_n(np.abs(d))
        fu = self.ru * np.minimum(fl, self.fmax) + np.where(np.abs(d) > self.stroke, fl - self.fmax, 0.0)
        pos = d >= 0
        lo = np.where(pos, fu, -fl)
        hi = np.where(pos, fl, -fu)
        f = np.clip(trial, lo, hi)
        f = np.where(d == 0.0, 0.0, f)
        self.force_state = f
        self.defl_prev = d
        engaged = d != 0.0
        return f + np.where(engaged, self.c * stretch_rate_mps, 0.0)


# ------------------------------------------------------------------------------------ air brake
# Table 1 (d_z mm, p_z kPa, γ_z, η_z, n_z, n_k; HXD1 also R_c, r_z mm)
HXD1_BRAKE = dict(d_z=225.0, p_z=450.0, gamma_z=2.4, eta_z=0.9, n_z=16, n_k=32, R_c=1250.0, r_z=448.0)
C80_BRAKE = dict(d_z=254.0, p_z=430.0, gamma_z=6.6, eta_z=0.9, n_z=1, n_k=8)
#: common (service) braking factor β_c of eq. (10). NOT given in the paper; assumed value for a
#: 50 kPa brake-pipe reduction (our assumption, documented in the report).
BETA_C = 0.19


def hxd1_pad_force_kn(p_fraction: float = 1.0) -> float:
    """Eqs. (13)-(14): HXD1 force per brake cylinder referred to the wheel tread (kN).

    Eq. (13) is printed with the disc friction radius r_z; we read it as the lever ratio γ_z
    (Table 1 gives γ_z = 2.4 for HXD1; r_z = 448 mm then enters eq. 14 as r_z / R_c).
    """
    b = HXD1_BRAKE
    k1 = np.pi / 4 * b["d_z"] ** 2 * b["p_z"] * p_fraction * b["gamma_z"] * b["eta_z"] * 1e-6
    return float(b["r_z"] / b["R_c"] * k1)


def c80_shoe_force_kn(p_fraction: float = 1.0) -> float:
    """Eq. (15): C80 force per brake shoe (kN)."""
    b = C80_BRAKE
    return float(np.pi / 4 * b["d_z"] ** 2 * b["p_z"] * p_fraction * b["eta_z"] * b["gamma_z"]
                 * (b["n_z"] / b["n_k"]) * 1e-6)


def friction_coefficient(k_kn, v_kmh, loco):
    """Eqs. (11)-(12): φ_H (locomotive, 0.441) / φ_C (C80 high-friction shoe, 0.481)."""
    k = np.asarray(k_kn, dtype=float)
    v = np.abs(np.asarray(v_kmh, dtype=float))
    coef = np.where(loco, 0.441, 0.481)
    return coef * (k + 200.0) / (4.0 * k + 200.0) * (2.0 * v + 150.0) / (3.0 * v + 150.0)


class AirBrake:
    """Brake-pipe signal propagation, cylinder fill and the application rules (section 1.2).

    The locomotive's driver's valve issues apply/release; vehicle k (centre at distance D_k behind
    the locomotive's centre) sees an apply signal D_k / 200 m/s and a release signal D_k / 36 m/s
    after it was issued. After the signal arrives the cylinder fills/empties with a first-order lag
    ``cylinder_tau_s`` (assumed, not in the paper). ``fill`` in [0, 1] is the fraction of Table 1's
    cylinder pressure p_z.
    """

    def __init__(self, consist: Consist, apply_wave_mps: float = 200.0, release_wave_mps: float = 36.0,
                 cylinder_tau_s: float = 2.0, beta_c: float = BETA_C, apply_min_kmh: float = 60.0,
                 release_drop_kmh: float = 10.0, release_floor_kmh: float = 35.0, min_interval_s: float = 160.0,
                 lookahead_m: float = 2500.0):
        self.consist = consist
        self.dist = consist.distance_from_loco_m
        self.apply_wave, self.release_wave = apply_wave_mps, release_wave_mps
        self.tau = cylinder_tau_s
        self.beta_c = beta_c
        self.apply_min, self.release_drop, self.release_floor = apply_min_kmh, release_drop_kmh, release_floor_kmh
        self.min_interval, self.lookahead = min_interval_s, lookahead_m
        self.applied = False
        self.t_apply = -np.inf
        self.t_release = -np.inf
        self.v_apply_kmh = 0.0
        self.fill = np.zeros(consist.n)
        self.last_force_n = np.zeros(consist.n)
        self.events: list[tuple[float, str]] = []
        loco = consist.is_loco
        self.k_full_kn = np.where(loco, hxd1_pad_force_kn(), c80_shoe_force_kn())
        self.n_blocks = np.where(loco, HXD1_BRAKE["n_z"], C80_BRAKE["n_k"]).astype(float)

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

    def rule_step(self, t_s: float, v_loco_mps: float, x_loco_m: float, route: Route) -> None:
        """Section 1.2: apply above 60 km/h with a long (> 8 ‰, ≥ 500 m) downgrade within 2.5 km
        ahead (or under the train), at least 160 s after the previous application; release once the
        speed is 10 km/h below the applying speed, but never below 35 km/h."""
        v = v_loco_mps / KMH
        if not self.applied:
            if (v > self.apply_min and t_s - self.t_apply >= self.min_interval
                    and route.long_downgrade_ahead(x_loco_m, x_loco_m - self.dist[-1], self.lookahead)):
                self.command(t_s, True)
                self.v_apply_kmh = v
        elif v <= self.v_apply_kmh - self.release_drop and v >= self.release_floor:
            self.command(t_s, False)

    def step(self, t_s: float, dt_s: float, v_mps: np.ndarray) -> np.ndarray:
        """Advance cylinder fills by ``dt_s`` and return the air-brake force per vehicle (N, ≥ 0)."""
        if self.t_apply == -np.inf:
            return self.last_force_n
        target = self.signal(t_s).astype(float)
        self.fill += (target - self.fill) * (1.0 - np.exp(-dt_s / self.tau))
        self.last_force_n = self.force_n(v_mps)
        return self.last_force_n

    def force_n(self, v_mps: np.ndarray) -> np.ndarray:
        """Eq. (10): F_a = β_c Σ φ K over the blocks of each vehicle, at the current fills (N)."""
        k = self.k_full_kn * self.fill
        phi = friction_coefficient(k, np.asarray(v_mps) / KMH, self.consist.is_loco)
        return 1000.0 * self.beta_c * self.n_blocks * phi * k


# ------------------------------------------------------------------------------------ disturbance
def disturbance_n(consist: Consist, t_s: float, v_mps: np.ndarray) -> np.ndarray:
    """Eq. (40), σ_i in N: m_i {0.002 + 0.001 sin(t+1) + 0.0003 ∛v [sin(2t+2) + cos(3t+1)]}
    on the locomotive and wagons 10, 20, ..., 100 (zero elsewhere); v in m/s (SI reading)."""
    idx = np.arange(consist.n)
    on = (idx == 0) | ((idx % 10 == 0) & (idx <= 100))
    v = np.abs(np.asarray(v_mps, dtype=float))
    acc = 0.002 + 0.001 * np.sin(t_s + 1.0) + 0.0003 * np.cbrt(v) * (np.sin(2 * t_s + 2.0) + np.cos(3 * t_s + 1.0))
    return np.where(on, consist.mass_kg * acc, 0.0)
