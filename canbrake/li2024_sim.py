"""In-process simulation of the Li 2024 heavy-haul train: a driver run that produces the reference,
and closed-loop tracking runs of the PID / SMC / RBFNN-SMC(+NDO) controllers.

The paper tracks a recorded driver's speed on the Daqin line (Fig. 4), which is not published. We
synthesise it: :func:`driver_reference` runs the full 1+105 plant over :func:`li2024_route` with a
simple driver (P speed control towards 70 km/h using at most 70 % of the locomotive envelope, force
rate-limited to 100 kN/s, cyclic air braking by the section-1.2 rules, aiming 12 km/h below the
applying speed while the air brake is on) and returns the locomotive's trajectory smoothed over 5 s.
:func:`simulate` then runs a controller on the locomotive tracking it.

All SI; traces are decimated to ``record_every_s`` except the RMSE, computed over every step.
"""
from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from canbrake.control.li2024 import (Obs, electric_brake_envelope_kn, electric_brake_envelope_n,  # noqa: F401
                                     make_controller, saturate_control_n, traction_envelope_kn, traction_envelope_n)
from canbrake.physics.heavy_haul import (DEFAULT_DT_S, G, KMH, AirBrake, Consist, CouplerBank,  # noqa: F401
                                         DraftGear, Route, basic_resistance_n, disc_block_force_kn, disturbance_n,
                                         friction_coefficient, shoe_block_force_kn)

# ---- the paper's constants as they were before they moved to scenarios/li2024_*.yaml (transition only:
# this module goes once the report runs through the node engine)
N_WAGONS = 105
LOCO_MASS_KG = 184_000.0
LOCO_LENGTH_M = 35.222
WAGON_MASS_KG = 100_000.0
WAGON_LENGTH_M = 12.0
DAVIS_HXD1 = (1.20, 0.0065, 0.000279)
DAVIS_C80 = (0.92, 0.0048, 0.000125)
MT2 = DraftGear("MT-2", (0.0, 0.020, 0.050, 0.073, 0.083), (0.0, 3.0e5, 9.0e5, 1.8e6, 2.27e6),
                unloading_ratio=0.25, slack_m=0.005, k_elastic_n_per_m=2e8, k_solid_n_per_m=2e8,
                damping_n_s_per_m=1e5)
QKX100 = DraftGear("QKX100", (0.0, 0.020, 0.060, 0.090, 0.100), (0.0, 2.5e5, 9.0e5, 2.0e6, 2.5e6),
                   unloading_ratio=0.35, slack_m=0.005, k_elastic_n_per_m=2e8, k_solid_n_per_m=2e8,
                   damping_n_s_per_m=1e5)
BETA_C = 0.19


def hxd1_pad_force_kn() -> float:
    return disc_block_force_kn(225.0, 450.0, 2.4, 0.9, 448.0, 1250.0)


def c80_shoe_force_kn() -> float:
    return shoe_block_force_kn(254.0, 430.0, 6.6, 0.9, 1, 8)


def li2024_consist(n_wagons: int = N_WAGONS) -> Consist:
    n = n_wagons + 1
    loco = np.zeros(n, bool)
    loco[0] = True
    pick = lambda a, b: np.where(loco, a, b).astype(float)  # noqa: E731
    return Consist(
        mass_kg=pick(LOCO_MASS_KG, WAGON_MASS_KG), length_m=pick(LOCO_LENGTH_M, WAGON_LENGTH_M),
        davis_a=pick(DAVIS_HXD1[0], DAVIS_C80[0]), davis_b=pick(DAVIS_HXD1[1], DAVIS_C80[1]),
        davis_c=pick(DAVIS_HXD1[2], DAVIS_C80[2]), is_loco=loco)


def li2024_route() -> Route:
    km = 1000.0
    seg = [(0, 0.0), (5, 3.0), (10, -2.0), (15, 1.0), (18, -10.0), (23.5, -3.0), (28, 4.0),
           (31, -11.0), (36, -4.0), (37.5, -10.5), (41.5, 0.0)]
    return Route(grade_start_m=np.array([a * km for a, _ in seg]), grade_permille=np.array([g for _, g in seg]),
                 curve_start_m=np.array([12.0, 26.0, 33.0]) * km, curve_end_m=np.array([13.0, 27.0, 34.0]) * km,
                 curve_radius_m=np.array([1000.0, 800.0, 1200.0]), length_m=45.0 * km)


class _RuleAirBrake(AirBrake):
    """The air brake with the section-1.2 rules inside the plant, as before."""

    def __init__(self, consist: Consist, **kw):
        loco = consist.is_loco
        super().__init__(consist, apply_wave_mps=kw.pop("apply_wave_mps", 200.0),
                         release_wave_mps=kw.pop("release_wave_mps", 36.0), cylinder_tau_s=kw.pop("cylinder_tau_s", 2.0),
                         beta_c=BETA_C, block_force_kn=np.where(loco, hxd1_pad_force_kn(), c80_shoe_force_kn()),
                         n_blocks=np.where(loco, 16, 8).astype(float), friction_coef=np.where(loco, 0.441, 0.481),
                         cylinder_pressure_pa=np.where(loco, 450e3, 430e3))
        self.apply_min, self.release_drop, self.release_floor, self.min_interval, self.lookahead = 60.0, 10.0, 35.0, 160.0, 2500.0
        self.v_apply_kmh = 0.0

    def rule_step(self, t_s: float, v_loco_mps: float, x_loco_m: float, route: Route) -> None:
        v = v_loco_mps / KMH
        if not self.applied:
            if (v > self.apply_min and t_s - self.t_apply >= self.min_interval
                    and route.long_downgrade_ahead(x_loco_m, x_loco_m - self.dist[-1], self.lookahead)):
                self.command(t_s, True)
                self.v_apply_kmh = v
        elif v <= self.v_apply_kmh - self.release_drop and v >= self.release_floor:
            self.command(t_s, False)

UNCERTAINTY = 0.01  # δ = 1 % of the non-control force, on every vehicle (eq. 16's ΔF_i)
V0_KMH = 50.0
CRUISE_KMH = 70.0


class HeavyHaulPlant:
    """State (positions, speeds, coupler hysteresis, air brake) and one fixed step of eq. (16)."""

    def __init__(self, consist: Consist | None = None, route: Route | None = None, v0_mps: float = V0_KMH * KMH,
                 x0_m: float = 0.0, uncertainty: float = UNCERTAINTY, disturbance: bool = False,
                 dt_s: float = DEFAULT_DT_S, airbrake_schedule: list[tuple[float, bool]] | None = None,
                 **airbrake_kw):
        self.c = consist or li2024_consist()
        self._weight_kn = self.c.weight_kn
        self.route = route or li2024_route()
        self.dt = dt_s
        self.unc, self.dist_on = uncertainty, disturbance
        # None: the section-1.2 rules decide; else replay these (time, apply?) driver's-valve commands
        self.schedule = None if airbrake_schedule is None else sorted(airbrake_schedule)
        self._sched_i = 0
        self.cp = CouplerBank([QKX100] + [MT2] * (self.c.n - 2))
        self.ab = _RuleAirBrake(self.c, **airbrake_kw)
        self.t = 0.0
        self.v = np.full(self.c.n, float(v0_mps))
        # static initial tensions: each coupler carries the running + grade resistance behind it
        xs = x0_m - self.c.distance_from_loco_m
        res = basic_resistance_n(self.c, self.v) + self.route.force_n(self.c, xs)
        tension = np.cumsum(res[::-1])[::-1][1:]
        stretch = self.cp.set_static(tension)
        self.x = x0_m - np.concatenate([[0.0], np.cumsum(self.c.spacing_m + stretch)])
        self.fc = self._coupler_forces()
        self._fi = None

    def _coupler_forces(self) -> np.ndarray:
        stretch = self.x[:-1] - self.x[1:] - self.c.spacing_m
        rate = self.v[:-1] - self.v[1:]
        return self.cp.step(stretch, rate)

    def passive_forces(self) -> tuple[np.ndarray, np.ndarray]:
        """Non-control force per vehicle F_i (N) and the air-brake force (N) at the current state."""
        sgn = np.sign(self.v)
        fw = basic_resistance_n(self.c, self.v) * sgn
        ff = self.route.force_n(self.c, self.x)
        fa = self.ab.last_force_n * sgn
        fc = self.fc
        front = np.concatenate([[0.0], fc])
        rear = np.concatenate([fc, [0.0]])
        return front - rear - fw - ff - fa, fa

    def loco_f_nominal(self) -> float:
        """f(x) of eq. (17) = −(F_C0 + F_W0 + F_f0 + F_a0)/m0 (m/s²), nominal (no ΔF)."""
        if self._fi is None:
            self._fi, _ = self.passive_forces()
        return float(self._fi[0] / self.c.mass_kg[0])

    def step(self, u_n: float) -> None:
        fi = self._fi if self._fi is not None else self.passive_forces()[0]
        total = fi * (1.0 + self.unc)
        total[0] += u_n
        if self.dist_on:
            idx = np.arange(self.c.n)
            total += disturbance_n(self.c, self.t, self.v, (idx == 0) | ((idx % 10 == 0) & (idx <= 100)), (0.002, 0.001, 0.0003))
        acc = total / self.c.mass_kg
        self.v = self.v + acc * self.dt
        self.x = self.x + self.v * self.dt
        self.t += self.dt
        self.fc = self._coupler_forces()
        if self.schedule is None:
            self.ab.rule_step(self.t, float(self.v[0]), float(self.x[0]), self.route)
        else:
            while self._sched_i < len(self.schedule) and self.schedule[self._sched_i][0] <= self.t + 1e-9:
                self.ab.command(self.schedule[self._sched_i][0], bool(self.schedule[self._sched_i][1]))
                self._sched_i += 1
        self.ab.step(self.t, self.dt, self.v)
        self._fi = None


@dataclass
class Reference:
    t_s: np.ndarray
    x_m: np.ndarray
    v_mps: np.ndarray
    a_mps2: np.ndarray
    dt_s: float
    #: the driver run's air-brake commands (time s, apply?) — replayed in the tracking runs
    airbrake_events: list[tuple[float, bool]] = field(default_factory=list)


def driver_reference(duration_s: float = 2500.0, dt_s: float = DEFAULT_DT_S, smooth_s: float = 5.0,
                     route: Route | None = None, n_wagons: int = 105) -> tuple[Reference, dict]:
    """Run the synthetic driver over the route; return the smoothed reference and the raw trace."""
    c = li2024_consist(n_wagons)
    plant = HeavyHaulPlant(c, route, dt_s=dt_s, uncertainty=0.0)
    n = int(round(duration_s / dt_s))
    t = np.arange(n) * dt_s
    x = np.empty(n)
    v = np.empty(n)
    uu = np.empty(n)
    u = 0.0
    kp = 3e6  # N per m/s
    share = 0.7  # fraction of the envelope the driver uses
    for k in range(n):
        v0 = float(plant.v[0])
        x[k], v[k] = plant.x[0], v0
        tgt = (plant.ab.v_apply_kmh - 12.0) * KMH if plant.ab.applied else CRUISE_KMH * KMH
        want = min(max(kp * (tgt - v0), -share * float(electric_brake_envelope_n(v0))), share * float(traction_envelope_n(v0)))
        u += min(max(want - u, -1e5 * dt_s), 1e5 * dt_s)
        uu[k] = u
        plant.step(u)
    w = max(1, int(round(smooth_s / dt_s)))
    ker = np.ones(w) / w
    pad = w // 2
    vp = np.concatenate([np.full(pad, v[0]), v, np.full(w - pad - 1, v[-1])])
    vs = np.convolve(vp, ker, mode="valid")[:n]
    vs[0] = v[0]
    xs = x[0] + np.concatenate([[0.0], np.cumsum(0.5 * (vs[1:] + vs[:-1]) * dt_s)])
    a = np.gradient(vs, dt_s)
    raw = {"t_s": t, "x_m": x, "v_mps": v, "u_n": uu, "airbrake_events": list(plant.ab.events)}
    evs = [(t_ev, e == "apply") for t_ev, e in plant.ab.events]
    return Reference(t, xs, vs, a, dt_s, evs), raw


def simulate(controller: str, ref: Reference, *, disturbance: bool = False, reading: str = "listed",
             airbrake: str = "replay",
             duration_s: float | None = None, record_every_s: float = 0.1, n_wagons: int = 105,
             record_couplers=(0, 10, 52, 104)) -> dict[str, np.ndarray]:
    """Closed-loop run of ``controller`` on the locomotive tracking ``ref``.

    ``airbrake="replay"`` (default) replays the driver run's air-brake commands: the driver operates
    the air brake, the controller only the locomotive force (as in the paper, where u_0 is the only
    control). ``"rules"`` lets the section-1.2 rules act on the controlled train's own state; near the
    60 km/h threshold a small tracking error then delays an application and the reference becomes
    infeasible for the locomotive alone (see the report).

    Returns a dict of arrays (decimated): ``t_s, v_ref_mps, v_mps, x_err_m, u_n, airbrake_fill_mean,
    airbrake_command`` (driver's valve: 1 applied, 0 released), ``coupler_n`` (n_rec, len(record_couplers)), ``coupler_max_tension_n`` /
    ``coupler_max_compression_n`` (over the train, per record), ``s``, ``delta_hat``, ``d_hat``; and
    scalars ``rmse_kmh`` (every step), ``err_min_kmh``, ``err_max_kmh``, ``max_tension_n``,
    ``max_compression_n`` (every step), ``u_sat_fraction``.
    """
    dt = ref.dt_s
    c = li2024_consist(n_wagons)
    if airbrake not in ("replay", "rules"):
        raise ValueError("airbrake must be 'replay' (the driver run's commands) or 'rules' (section 1.2 on the actual state)")
    plant = HeavyHaulPlant(c, dt_s=dt, disturbance=disturbance, x0_m=float(ref.x_m[0]), v0_mps=float(ref.v_mps[0]),
                           airbrake_schedule=list(ref.airbrake_events) if airbrake == "replay" else None)
    ctl = make_controller(controller, dt, float(c.mass_kg[0]), reading=reading)
    n = ref.t_s.size if duration_s is None else min(ref.t_s.size, int(round(duration_s / dt)))
    every = max(1, int(round(record_every_s / dt)))
    rec: dict[str, list] = {k: [] for k in ("t_s", "v_ref_mps", "v_mps", "x_err_m", "u_n", "airbrake_fill_mean",
                                            "airbrake_command", "coupler_n", "coupler_max_tension_n",
                                            "coupler_max_compression_n", "s", "delta_hat", "d_hat", "x_m")}
    sq = 0.0
    emin, emax = np.inf, -np.inf
    tmax, cmax = 0.0, 0.0
    nsat = 0
    cols = np.asarray(record_couplers)
    cols = cols[cols < c.n - 1]
    for k in range(n):
        v0 = float(plant.v[0])
        o = Obs(plant.t, float(plant.x[0]), v0, float(ref.x_m[k]), float(ref.v_mps[k]), float(ref.a_mps2[k]),
                plant.loco_f_nominal())
        u, diag = ctl.step(o)
        if u != diag["u_raw_n"]:
            nsat += 1
        err = (v0 - ref.v_mps[k]) / KMH
        sq += err * err
        emin, emax = min(emin, err), max(emax, err)
        fc = plant.fc
        fmx, fmn = float(fc.max()), float(fc.min())
        tmax, cmax = max(tmax, fmx), min(cmax, fmn)
        if k % every == 0:
            rec["t_s"].append(plant.t)
            rec["v_ref_mps"].append(ref.v_mps[k])
            rec["v_mps"].append(v0)
            rec["x_err_m"].append(o.x_m - o.x_ref_m)
            rec["x_m"].append(o.x_m)
            rec["u_n"].append(u)
            rec["airbrake_fill_mean"].append(float(plant.ab.fill.mean()))
            rec["airbrake_command"].append(float(plant.ab.applied))
            rec["coupler_n"].append(fc[cols].copy())
            rec["coupler_max_tension_n"].append(fmx)
            rec["coupler_max_compression_n"].append(fmn)
            rec["s"].append(diag.get("s", np.nan))
            rec["delta_hat"].append(diag.get("delta_hat", np.nan))
            rec["d_hat"].append(diag.get("d_hat", np.nan))
        plant.step(u)
    out = {k: np.asarray(vv) for k, vv in rec.items()}
    out.update(rmse_kmh=np.sqrt(sq / n), err_min_kmh=emin, err_max_kmh=emax, max_tension_n=tmax,
               max_compression_n=cmax, u_sat_fraction=nsat / n, recorded_couplers=cols,
               n_airbrake_applications=sum(1 for _, e in plant.ab.events if e == "apply"))
    return out
