"""Benchmark: wall time of one plant model ``step()`` (the physics alone, no bus, no controller).

Builds the plant of a scenario exactly as a run does (:func:`canbrake.build.build_plant_model`)
and steps it with held commands: Chen case 1 (6 cars, 1 ms, ideal actuator, every car braking at
its share of 0.97 m/s²), its realistic profile (10 ms, lagged actuator, end stops, blending), Chen
case 2 with brake equipment (blending, 4 wheelsets per car, with and without the dump valves) and
Li 2024's 1 + 105 ECP train (every wagon at full service, the locomotive coasting) at 10 ms and at
the scenario's own period, Cai 2014's case 4 trains (2000 N·m on every driven axle, 1 ms). Prints microseconds per step (best of ``--repeat``); no assertions. ``--clock cpu`` times the
process's CPU time instead of the wall clock (steadier on a shared machine).

    python bench/bench_plant_step.py [--steps 2000] [--repeat 3] [--clock wall|cpu]
"""
from __future__ import annotations

import argparse
import time
from pathlib import Path

import numpy as np

from canbrake.build import build_plant_model
from canbrake.scenario import load_scenario

ROOT = Path(__file__).resolve().parent.parent / "scenarios"


def chen(profile: str | None) -> tuple[object, float, dict[str, np.ndarray]]:
    scn = load_scenario(ROOT / "chen2023_case1_fine_rail.yaml", profile=profile)
    plant = build_plant_model(scn)
    return plant, scn.control_period_s, {"brake_force_n": plant.mass_kg * 0.97}


def chen_wheels(wsp: bool) -> tuple[object, float, dict[str, np.ndarray]]:
    """Chen case 2 on poor rail with brake equipment: blending, four wheelsets per car with Cai's
    creep force, and (``wsp``) the dump valves half open on every car."""
    scn = load_scenario(ROOT / "chen2023_case2_low_adhesion.yaml", profile="wsp" if wsp else None)
    plant = build_plant_model(scn)
    cmd = {"brake_force_n": plant.mass_kg * 0.97}
    if wsp:
        cmd["wsp_release"] = np.full(plant.mass_kg.size, 0.5)
    return plant, scn.control_period_s, cmd


def ecp(dt_s: float | None) -> tuple[object, float, dict[str, np.ndarray]]:
    scn = load_scenario(ROOT / "li2024_ecp_over_can.yaml")
    plant = build_plant_model(scn)
    n = plant.n_vehicles
    demand = np.ones(n)
    demand[0] = np.nan
    return plant, dt_s or scn.control_period_s, {"brake_force_n": np.full(n, np.nan), "ecp_demand": demand}


def cai(name: str) -> tuple[object, float, dict[str, np.ndarray]]:
    scn = load_scenario(ROOT / name)
    plant = build_plant_model(scn)
    n = plant.n_vehicles
    return plant, scn.control_period_s, {c: np.full(n, 2000.0) for c in plant.command_names}


def per_step_us(make, steps: int, repeat: int, clock=time.perf_counter) -> float:
    best = float("inf")
    for _ in range(repeat):
        plant, dt, cmd = make()
        plant.step(dt, cmd)  # first step: caches, command change
        t0 = clock()
        for _ in range(steps):
            plant.step(dt, cmd)
        best = min(best, (clock() - t0) / steps)
    return best * 1e6


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--steps", type=int, default=2000)
    ap.add_argument("--repeat", type=int, default=3)
    ap.add_argument("--clock", choices=("wall", "cpu"), default="wall")
    a = ap.parse_args()
    clock = time.process_time if a.clock == "cpu" else time.perf_counter
    rows = [("chen case 1, paper (1 ms)", lambda: chen(None), a.steps),
            ("chen case 1, realistic (10 ms)", lambda: chen("realistic"), a.steps),
            ("chen case 2 wheelsets+blending (10 ms)", lambda: chen_wheels(False), a.steps // 4),
            ("chen case 2 wheelsets+blending+WSP", lambda: chen_wheels(True), a.steps // 4),
            ("li2024 1+105 ECP, 10 ms", lambda: ecp(0.01), max(a.steps // 10, 20)),
            ("li2024 1+105 ECP, 50 ms (scenario)", lambda: ecp(None), max(a.steps // 50, 10)),
            ("cai2014 case 4 (1 ms)", lambda: cai("cai2014_case4.yaml"), a.steps),
            ("cai2014 CRH3 case 4 (1 ms)", lambda: cai("cai2014_crh3_case4.yaml"), a.steps)]
    for name, make, steps in rows:
        print(f"{name:40s} {per_step_us(make, steps, a.repeat, clock):10.1f} us/step")


if __name__ == "__main__":
    main()
