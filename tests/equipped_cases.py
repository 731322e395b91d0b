"""Plants with brake equipment that exercise every part of TrainPlant's equipped step (issue 27),
and their recorded runs: tests/data/equipped_ref.npz holds what main's Python sub-step loop gave
(recorded before the loop was compiled; re-recorded from the Python loop of branch lionplant, 8d75abc,
whose air command acts from its instant), tests/test_equipped_kernel.py compares bit for bit.

    python tests/equipped_cases.py   # rewrites tests/data/equipped_ref.npz (only on purpose)
"""
from __future__ import annotations

import math
from pathlib import Path
from typing import Callable

import numpy as np

from canbrake.physics import heavy_haul as hh
from canbrake.physics.actuator import BrakeActuator
from canbrake.physics.brakes import BrakeBlending, Wheelsets
from canbrake.physics.rail import DisturbanceForce, RailConditions, RailEvent
from canbrake.physics.resistance import DavisResistance
from canbrake.physics.route import Route
from canbrake.physics.train import PlantDiverged, TrainPlant, stack_plants
from canbrake.physics.wheel_adhesion import RailCondition

REF = Path(__file__).parent / "data" / "equipped_ref.npz"
G = 9.81
CURVE = RailCondition(b1=1.786, b2=40.0, b3=10.0, c1=0.040, c2=3.78, c3=33.3, peak_mu0=0.35)
ENV = hh.TractionEnvelope(traction_start_kn=300, traction_start_until_kmh=5, traction_intercept_kn=310,
                          traction_slope_kn_per_kmh=2, traction_linear_until_kmh=60, brake_slope_kn_per_kmh=10,
                          brake_linear_until_kmh=10, brake_max_kn=100, brake_constant_until_kmh=60, power_kn_kmh=6000)
GEAR = hh.DraftGear("d", (0.0, 0.02, 0.05, 0.083), (0.0, 3.0e5, 9.0e5, 2.27e6), unloading_ratio=0.25, slack_m=0.005,
                    k_elastic_n_per_m=2.0e8, k_solid_n_per_m=2.0e8, damping_n_s_per_m=1.0e5)
ROUTE = Route.from_table([0.0, 300.0, 400.0, 600.0, 900.0, 5000.0], [0.0, -12.0, -12.0, -12.0, 4.0, 4.0],
                         [0.0, 0.0, 500.0, 0.0, 0.0, 0.0])


def _li_train(mode: str, gears: list, **kw: object) -> TrainPlant:
    """A locomotive and three wagons with Li's parts (route, air brake, limits, δ, eq. 40, ...)."""
    mass = np.array([1.5e5, 9.0e4, 9.0e4, 9.0e4])
    length = np.array([20.0, 14.0, 14.0, 14.0])
    spacing = 0.5 * (length[:-1] + length[1:])
    a, b, c = np.array([1.2, 0.92, 0.92, 0.92]), np.array([0.0065, 0.0048, 0.0048, 0.0048]), \
        np.array([0.000279, 0.000125, 0.000125, 0.000125])
    w = mass * G / 1000.0
    consist = hh.Consist(mass_kg=mass, length_m=length, davis_a=a, davis_b=b, davis_c=c,
                         is_loco=np.array([1, 0, 0, 0], bool))
    air = hh.AirBrake(consist, apply_wave_mps=200.0, release_wave_mps=36.0, cylinder_tau_s=2.0, beta_c=0.8,
                      block_force_kn=np.array([0.0, 20.0, 20.0, 20.0]), n_blocks=np.array([8.0] * 4),
                      friction_coef=np.array([0.44, 0.48, 0.48, 0.48]),
                      cylinder_pressure_pa=np.array([4e5] * 4), mode=mode,
                      pipe=hh.BrakePipe() if mode == "pneumatic" else None)
    x0 = 280.0 - np.concatenate([[0.0], np.cumsum(spacing)])
    return TrainPlant(mass, x0, np.full(4, 12.0), resistance=DavisResistance(a * w, b * w * 3.6, c * w * 3.6 ** 2),
                      coupler_stiffness_n_per_m=5.0e6, coupler_nonlinearity_per_m2=0.0, draft_gears=gears,
                      air_brake=air, route=ROUTE, static_couplers=True, traction_envelope=[ENV, None, None, None],
                      electric_brake_envelope=True, uncertainty=0.05, li_disturbance_on=[True, False, True, False],
                      li_disturbance_coef=(0.002, 0.001, 0.0003), max_substep_s=2.5e-3,
                      resistance_table=[None, None, ([0.0, 5.0, 20.0], [100.0, 300.0, 900.0]), None],
                      disturbances=[DisturbanceForce(amplitude_n=[0.0, 2e3, 0.0, 1e3], frequency_hz=0.7, start_s=1.0,
                                                     end_s=7.0, offset_n=200.0, phase_rad=0.3)],
                      grade_rad=[0.0, 0.001, 0.0, -0.002], **kw)  # type: ignore[arg-type]


def li_pneumatic() -> TrainPlant:
    """Gears on couplers 1 and 3 (Chen's on 2), pneumatic brake with the brake pipe, a lagged
    actuator (per car, one instant), curtius-kniffler adhesion on the locomotive."""
    return _li_train("pneumatic", [GEAR, None, GEAR],
                     actuator=BrakeActuator(kind="realistic", time_constant_s=(0.3, 0.0, 0.5, 0.5),
                                            jerk_limit_mps3=2.0, brake_rating_mps2=1.5, traction_rating_mps2=1.0,
                                            adhesion_limited=False),
                     loco_adhesion=[hh.LocoAdhesion(0.3, "curtius_kniffler"), None, None, None])


def li_ecp() -> TrainPlant:
    """Gears on every coupler, ECP, an ideal actuator, constant adhesion, an end stop."""
    return _li_train("ecp", [GEAR, GEAR, GEAR], loco_adhesion=[hh.LocoAdhesion(0.25), None, None, None],
                     end_stop_m=0.09, end_stop_stiffness_n_per_m=5e7)


def _equipped(rng: np.random.Generator, **kw: object) -> TrainPlant:
    """Five cars: blending (per-car lags and fade, an ED envelope on one), wheelsets (a car
    without), dump valves, rail events, a disturbance, per-car grade, a lagged adhesion-limited actuator."""
    n = 5
    m = np.random.default_rng(11).uniform(3e4, 5e4, n)  # a stack's points share their wheelsets' loads
    v0 = rng.uniform(14.5, 15.5, n)
    ws = Wheelsets(m, [4, 4, 0, 2, 4], 0.42, 120.0, v0, curve=CURVE)
    nan5 = (math.nan,) * 5
    bl = BrakeBlending(ed_max_decel_mps2=(0.9, 0.0, 0.9, 0.9, 0.8), ed_power_w_per_kg=(math.inf, math.inf, 20.0, 25.0, 30.0),
                       friction_lag_s=(0.2, 0.0, 0.3, 0.2, 0.2),
                       envelope=(nan5, nan5, nan5, (5e3, 3.0, 3e4, 15.0, 4e5), nan5))
    rail = RailConditions(base_adhesion_mu=0.12, events=[RailEvent(1.0, 3.0, adhesion_mu=[0.05, 0.06, 0.3, 0.05, 0.07]),
                                                         RailEvent(2.0, 4.0, brake_effectiveness=0.7)])
    act = BrakeActuator(kind="realistic", time_constant_s=0.3, jerk_limit_mps3=1.5, brake_rating_mps2=1.5,
                        traction_rating_mps2=1.0, adhesion_limited=True)
    return TrainPlant(m, -20.0 * np.arange(n), v0, blending=bl, wheels=ws, actuator=act, wsp_max_vent_s=0.4,
                      wsp_valve_lag_s=(0.05, 0.05, 0.0, 0.08, 0.05), rail=rail,
                      disturbances=[DisturbanceForce(amplitude_n=1.5e3, frequency_hz=1.3, start_s=0.5, end_s=5.0)],
                      grade_rad=rng.uniform(-0.01, 0.01, n),
                      resistance_table=[None, ([0.0, 10.0, 30.0], [50.0, 400.0, 1500.0]), None, None, None],
                      **kw)  # type: ignore[arg-type]


def equipped() -> TrainPlant:
    return _equipped(np.random.default_rng(11), traction_envelope=[ENV, None, None, None, None])


def equipped_stack() -> TrainPlant:
    """Three points of the five-car train with different masses, speeds and couplers; the third
    diverges (a very softening coupler pulled past its peak) and is parked."""
    plants = [_equipped(np.random.default_rng(s), coupler_nonlinearity_per_m2=e)
              for s, e in ((11, -0.5), (12, -0.5), (13, -400.0))]
    st = stack_plants(plants)
    assert st is not None
    return st


def graded_blending() -> TrainPlant:
    """Blending alone (no wheels: the Coulomb step), a grade function, an end stop, ideal brake
    capped at the adhesion."""
    return TrainPlant([4e4, 3.5e4, 4.5e4], [0.0, -20.0, -40.0], [15.0, 15.2, 14.9],
                      blending=BrakeBlending(ed_max_decel_mps2=0.8, friction_lag_s=0.25),
                      actuator=BrakeActuator.ideal(adhesion_limited=True),
                      rail=RailConditions(base_adhesion_mu=0.1),
                      grade_rad=lambda x: 0.004 * np.sin(np.asarray(x) / 50.0), end_stop_m=0.05)


CASES: dict[str, Callable[[], TrainPlant]] = {
    "li_pneumatic": li_pneumatic, "li_ecp": li_ecp, "equipped": equipped, "equipped_stack": equipped_stack,
    "graded_blending": graded_blending,
    "diverging": lambda: _equipped(np.random.default_rng(13), coupler_nonlinearity_per_m2=-400.0)}


def _commands(name: str, k: int, shape: tuple[int, ...], rng: np.random.Generator
              ) -> tuple[np.ndarray, np.ndarray | None, float | None, np.ndarray | None]:
    """Period k's brake command (N per car), dump-valve command, driver's valve and ECP demand."""
    n = shape[-1]
    if name.startswith("li"):
        cmd = np.zeros(n)
        cmd[0] = -2.5e5 if k < 150 else (1.2e5 if k < 450 else -8e4)  # traction, electric brake, traction
        apply = 1.0 if 200 <= k < 500 else 0.0
        ecp = np.where(np.arange(n) > 0, 0.6 if 200 <= k < 500 else 0.1, np.nan) if k % 50 == 0 else None
        return cmd, None, apply, ecp
    cmd = rng.uniform(-2e4, 6e4, shape)
    if k % 7 == 0:
        cmd[..., 1] = 0.0
    wsp = None
    if name != "graded_blending" and k % 3:
        wsp = rng.choice([np.nan, 0.0, 0.4, 1.0], int(np.prod(shape)))
    return cmd, wsp, None, None


def run(name: str, periods: int = 600, dt: float = 0.01) -> dict[str, np.ndarray]:
    """Every period's state of case ``name``: positions, speeds, accelerations, rail forces,
    efforts, coupler forces and the equipment's state (one array per quantity, periods first)."""
    p = CASES[name]()
    rng = np.random.default_rng(5)
    rec: dict[str, list[np.ndarray]] = {}
    for k in range(periods):
        cmd, wsp, apply, ecp = _commands(name, k, p.speed_mps.shape, rng)
        p.command_air(apply, ecp)
        try:
            p.step(dt, cmd, wsp)
        except PlantDiverged as exc:  # its message, and the state the step left behind
            rec["diverged_message"] = [np.array(str(exc))]
            break
        got = {"position_m": p.position_m, "speed_mps": p.speed_mps, "accel_mps2": p.accel_mps2,
               "applied_force_n": p.applied_force_n, "brake_effort_n": p.brake_effort_n,
               "time_s": np.array(p.time_s)}
        if not p.stacked:
            got["coupler_force_n"] = p.coupler_force_n
        for key, val in p.equipment_measurements().items():
            got[key] = val
        if p.air_brake is not None:
            got["air_brake_n"] = p.air_brake_n
            got["air_fill"] = p.air_brake.fill
            if p.air_brake.pipe is not None:
                got["pipe_pa"] = p.air_brake.pipe_pressure_pa
        if p._gears is not None:
            got["gear_force_state"] = p._gears.force_state
            got["gear_defl_prev"] = p._gears.defl_prev
        if p.stacked:
            got["diverged_rows"] = p.diverged_rows.astype(float)
            got["diverged_dl_m"] = p.diverged_dl_m
        for key, val in got.items():
            rec.setdefault(key, []).append(np.array(val, dtype=float, copy=True))
    if p.wheels is not None:  # the wheels' state the last step left (a diverged one included)
        rec["final_omega"] = [p.wheels.omega.copy()]
    return {k: np.stack(v) for k, v in rec.items()}


def main() -> None:
    out = {}
    for name in CASES:
        for key, val in run(name).items():
            out[f"{name}/{key}"] = val
    np.savez_compressed(REF, **out)
    print(f"wrote {REF} ({len(out)} arrays)")


if __name__ == "__main__":
    main()
