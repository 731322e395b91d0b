"""The emergency application of the heavy-haul air brake (physics.heavy_haul.EmergencyBrake, the
scenario's ``air_brake.application``/``emergency``) and the "ECP versus the published range" report
(canbrake.report.ecp_literature)."""
from __future__ import annotations

import json
import math
from dataclasses import replace

import numpy as np
import pytest

from canbrake.build import build_plant_model
from canbrake.physics import heavy_haul as hh
from canbrake.scenario import ScenarioError, load_scenario

from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
ECP = ROOT / "scenarios" / "li2024_ecp_over_can.yaml"
EM = hh.EmergencyBrake(apply_wave_mps=250.0, cylinder_tau_s=1.0, pressure_factor=1.2, brake_factor=1.0,
                       vent_tau_s=0.3)


def _brake(n: int, *, mode: str = "pneumatic", emergency: hh.EmergencyBrake | None = None,
           pipe: hh.BrakePipe | None = None) -> hh.AirBrake:
    c = hh.Consist(mass_kg=np.full(n, 1e5), length_m=np.full(n, 12.0), davis_a=np.zeros(n), davis_b=np.zeros(n),
                   davis_c=np.zeros(n), is_loco=np.zeros(n, bool))
    return hh.AirBrake(c, apply_wave_mps=200.0, release_wave_mps=36.0, cylinder_tau_s=2.0, beta_c=0.8,
                       block_force_kn=np.full(n, 30.0), n_blocks=np.full(n, 8.0), friction_coef=np.full(n, 0.481),
                       cylinder_pressure_pa=np.full(n, 430e3), mode=mode, pipe=pipe, emergency=emergency)


def _first_fill_times(ab: hh.AirBrake, dt: float, t_end: float) -> np.ndarray:
    first = np.full(ab.dist.size, np.nan)
    v = np.full(ab.dist.size, 10.0)
    for k in range(1, int(round(t_end / dt)) + 1):
        ab.step(k * dt, dt, v)
        new = np.isnan(first) & (ab.fill > 0)
        first[new] = k * dt
    return first


@pytest.mark.parametrize("emergency, wave", [(None, 200.0), (EM, 250.0)])
def test_the_wave_front_reaches_vehicle_k_after_its_distance_over_the_wave_speed(emergency, wave):
    """The brake starts on vehicle k at the first step at or after D_k / c (c: the service wave, or
    the emergency wave of an emergency application)."""
    dt = 1e-3
    ab = _brake(80, emergency=emergency)
    ab.command(0.0, True)
    first = _first_fill_times(ab, dt, 6.0)
    expect = np.ceil(ab.dist / wave / dt - 1e-9) * dt
    expect[0] = dt  # the locomotive: at the first step after the command
    assert np.allclose(first, expect, atol=1.01 * dt)
    assert first[-1] == pytest.approx(ab.dist[-1] / wave, abs=1.01 * dt)


def test_an_emergency_fill_is_first_order_to_the_emergency_pressure_and_brakes_with_its_coefficient():
    """ECP emergency: p(t) = f · p_full · (1 − e^(−t/τ_em)) (the step's gain is exact), block force
    K = f · K_full at full fill, eq. (10) with the emergency coefficient."""
    dt, n = 0.01, 250
    em = _brake(3, mode="ecp", emergency=EM)
    sv = _brake(3, mode="ecp")
    for ab in (em, sv):
        ab.ecp_target = np.ones(3)
    v = np.array([0.0, 10.0, 20.0])
    for k in range(1, n + 1):
        fe = em.step(k * dt, dt, v)
        fs = sv.step(k * dt, dt, v)
    t = n * dt
    p_em = em.fill * em.cylinder_pressure_pa
    assert p_em == pytest.approx(1.2 * 430e3 * (1.0 - math.exp(-t / 1.0)), rel=1e-9)
    assert sv.fill * sv.cylinder_pressure_pa == pytest.approx(430e3 * (1.0 - math.exp(-t / 2.0)), rel=1e-9)
    kk = 1.2 * 30.0 * em.fill
    assert fe == pytest.approx(1000.0 * 1.0 * 8.0 * hh.friction_coefficient(kk, v / hh.KMH, 0.481) * kk, rel=1e-12)
    assert np.all(fe > fs)


def test_an_emergency_vents_the_brake_pipe_to_zero_with_its_own_lag():
    """With the brake-pipe pressure model: after the emergency wave arrives, each vehicle's pipe
    pressure decays as p0 · e^(−(t − D/c)/τ_vent) (no per-km term); the cylinders go to the emergency
    pressure (ratio × p0 caps at it)."""
    dt = 1e-3
    pipe = hh.BrakePipe(p0_pa=600e3, reduction_pa=170e3, ratio=2.6, tau_s=1.0, tau_per_km_s=4.0)
    ab = _brake(40, emergency=EM, pipe=pipe)
    ab.command(0.0, True)
    v = np.zeros(40)
    arrive = np.ceil(ab.dist / 250.0 / dt - 1e-9) * dt
    arrive[0] = dt
    for k in range(1, 4001):
        ab.step(k * dt, dt, v)
    t = 4.0
    m = np.round((t - arrive) / dt) + 1  # steps since (and including) the arrival step
    assert ab.pipe_pressure_pa == pytest.approx(600e3 * (1.0 - (1.0 - math.exp(-dt / 0.3))) ** m, rel=1e-6)
    for k in range(4001, 20001):
        ab.step(k * dt, dt, v)
    assert ab.fill * ab.cylinder_pressure_pa == pytest.approx(np.full(40, 1.2 * 430e3), rel=1e-6)


def test_the_scenario_parameter_is_validated_and_its_default_changes_nothing():
    base = load_scenario(ECP)
    assert base.consist.air_brake.application == "service"
    ab = base.consist.air_brake_physics()
    assert ab.emergency is None and ab.tau == 2.0 and ab.apply_wave == 200.0 and ab.beta_c == 0.8
    assert np.all(ab.cylinder_pressure_pa[1:] == 430e3)
    em = load_scenario(ECP, overrides={"train.air_brake.application": "emergency"})
    ab = em.consist.air_brake_physics()
    assert ab.emergency is not None and ab.tau == 1.0 and ab.apply_wave == 250.0 and ab.beta_c == 1.0
    assert ab.cylinder_pressure_pa[1:] == pytest.approx(1.2 * 430e3)
    with pytest.raises(ScenarioError, match="emergency"):
        load_scenario(ECP, overrides={"train.air_brake.application": "emergency", "train.air_brake.emergency": None})
    with pytest.raises(ScenarioError, match="pressure_factor"):
        load_scenario(ECP, overrides={"train.air_brake.emergency.pressure_factor": 0.9})
    with pytest.raises(ScenarioError, match="application"):
        load_scenario(ECP, overrides={"train.air_brake.application": "panic"})


def _plant_decel(overrides: dict, seconds: float = 10.0) -> float:
    """Speed lost (m/s) by the locomotive of the 1 + 105 plant in ``seconds`` of a full application
    from t = 0 (plant only, no bus)."""
    scn = load_scenario(ECP, overrides=overrides)
    p = build_plant_model(scn)
    n = p.n_vehicles
    cmd = {"brake_force_n": np.zeros(n), "airbrake_apply": np.full(n, 1.0), "ecp_demand": np.ones(n)}
    v0 = float(p.measurements()["speed_mps"][0])
    for _ in range(int(round(seconds / scn.control_period_s))):
        p.step(scn.control_period_s, cmd)
    return v0 - float(p.measurements()["speed_mps"][0])


@pytest.mark.parametrize("mode", ["ecp", "pneumatic"])
def test_an_emergency_application_slows_the_train_more_than_full_service(mode):
    sv = _plant_decel({"train.air_brake.mode": mode})
    em = _plant_decel({"train.air_brake.mode": mode, "train.air_brake.application": "emergency"})
    assert em > 1.2 * sv > 0


def test_the_report_replaces_its_section_and_keeps_the_rest(tmp_path):
    """A short case (6 s) without the step check: the section's stopping-distance cells are the runs'
    report.json values; the text around the section is kept and a second generation does not
    duplicate it."""
    from canbrake.report import ecp_literature as L

    doc = tmp_path / "docs" / L.DOC
    doc.parent.mkdir()
    doc.write_text("# Mixed trains\n\nsomeone else's section\n", encoding="utf-8")
    case = replace(L.CASES[1], duration_s=6.0, sets=L.CASES[1].sets + (("train.air_brake.emergency.pressure_factor", 1.1),))
    for _ in range(2):
        L.generate(tmp_path / "docs", tmp_path / "runs", cases=[case], step_check=False, log=lambda m: None)
    text = doc.read_text(encoding="utf-8")
    assert text.count(L.BEGIN) == 1 and text.count(L.END) == 1 and "someone else's section" in text
    assert text.index("someone else's section") < text.index(L.BEGIN)
    rows = [ln for ln in text.splitlines() if ln.startswith(f"| {case.key} ")]
    assert len(rows) == 1
    e, p = case.specs()
    re_ = json.loads((tmp_path / "runs" / e.key / "report.json").read_text())
    rp = json.loads((tmp_path / "runs" / p.key / "report.json").read_text())
    cells = [c.strip() for c in rows[0].split("|")[1:-1]]
    assert cells[9] == f"{L.brake_delays(tmp_path / 'runs' / e.key, 5.0)['mean_half_s']:.2f} / " \
                       f"{L.brake_delays(tmp_path / 'runs' / p.key, 5.0)['mean_half_s']:.2f}"
    assert cells[10] == f"{re_['max_tension_n'] / 1e3:.0f} / {rp['max_tension_n'] / 1e3:.0f}"
    scn = load_scenario(tmp_path / "runs" / e.key / "scenario.yaml")
    assert scn.consist.air_brake.application == "emergency" and scn.consist.air_brake.emergency.pressure_factor == 1.1
