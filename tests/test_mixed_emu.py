"""scenarios/emu8_low_adhesion.yaml (8-car EMU, EP brake, blending, wheels per axle, WSP, a low-adhesion
section) and its report (canbrake.report.mixed_emu), plus the slide-episode metric
(canbrake.analysis.metrics.slide_episodes)."""
from __future__ import annotations

import json
import math

import numpy as np
import pytest

from canbrake.analysis.metrics import SLIDE_SLIP, slide_episodes
from canbrake.report import mixed_emu as X
from canbrake.scenario import load_scenario

from conftest import SCENARIOS

SCN = SCENARIOS / X.SCENARIO


# ----------------------------------------------------------------------------- the metric (fast)
def test_slide_episodes_counts_each_uninterrupted_slide_and_its_duration():
    t = np.arange(0.0, 10.0, 0.01)  # 1000 samples of 10 ms
    lam = np.zeros((t.size, 4))
    lam[100:150, 2] = -0.8        # 0.5 s on one axle
    lam[300:400, 0] = -1.0        # 1.0 s, another axle overlapping ...
    lam[350:420, 3] = -0.6        # ... and extending it: one episode of 1.2 s
    lam[500:600, 1] = -0.4        # below the threshold: no slide
    s = slide_episodes(t, lam)
    assert s["episodes"] == 2
    assert s["duration_s"] == pytest.approx(0.5 + 1.2, abs=1e-9)
    assert s["longest_s"] == pytest.approx(1.2, abs=1e-9)
    assert slide_episodes(t, lam, threshold=0.3)["episodes"] == 3  # the 0.4 slip counts at a lower threshold
    assert slide_episodes(t, np.zeros(t.size)) == {"episodes": 0, "duration_s": 0.0, "longest_s": 0.0}
    # a slide to the end of the trace counts until the end (the last sample for the median step)
    lam2 = np.zeros(t.size)
    lam2[-10:] = -1.0
    assert slide_episodes(t, lam2)["duration_s"] == pytest.approx(0.1, abs=1e-9)
    assert 0.16 < SLIDE_SLIP  # past the peak of Cai's curve (|λ| ≈ 0.164)


def test_the_scenario_is_the_emu_it_says_and_its_section_moves_along_the_train():
    """Tc-M-M-T-T-M-M-Tc, one ECU per car, wheels, blending, EP brake; every car is in the section
    once, the cars enter it in order front to rear, and no two rail events overlap."""
    scn = load_scenario(SCN)
    assert scn.n_cars == scn.n_ecus == 8
    m = scn.vehicle_masses_kg()
    assert list(m[[1, 2, 5, 6]]) == [46000.0] * 4 and list(m[[0, 3, 4, 7]]) == [40000.0] * 4
    b = scn.consist.brakes
    assert b.wheels is not None and b.blending is not None and not b.wsp.enabled
    assert load_scenario(SCN, profile="wsp").consist.brakes.wsp.enabled
    assert load_scenario(SCN, profile="dry").events == []
    ev = scn.events
    assert all(a.stop_s <= b.start_s + 1e-9 for a, b in zip(ev, ev[1:]))
    low = np.array([np.asarray(e.adhesion_mu, float) < 0.1 for e in ev])  # (events, cars)
    enter = [float(ev[int(np.argmax(low[:, i]))].start_s) for i in range(8)]
    assert all(low[:, i].any() for i in range(8)) and enter == sorted(enter)
    # car i enters when the reference has run 120 + 22 (i - 1) m
    v0, a = 100 / 3.6, scn.reference.decel_mps2
    for i, t in enumerate(enter):
        assert v0 * t - 0.5 * a * t * t == pytest.approx(120 + 22 * i, abs=0.3)


# ----------------------------------------------------------------------------- the runs (slow)
@pytest.fixture(scope="module")
def runs(tmp_path_factory):
    """The report's three cases, run in process (each ~5 s), reduced by the report's reduce_run."""
    d = tmp_path_factory.mktemp("mixed_emu")
    for c in X.CASES:
        X.execute(c, str(d), False, None)
    return d, {c.key: json.loads((d / c.key / "report.json").read_text()) for c in X.CASES}


@pytest.mark.slow
def test_dry_rail_stops_at_the_reference_distance_without_a_slide(runs):
    """On dry rail the ECUs track the reference, so the lead car stops close to v0^2 / (2 a) of the
    reference, and no wheel passes the slip curve's peak (μ 0.25 · 0.7 at speed > 0.085 + wheel inertia)."""
    r = runs[1]["dry"]
    scn = load_scenario(SCN, profile="dry")
    v0, a = scn.initial.speed_kmh / 3.6, scn.reference.decel_mps2
    assert r["stopping_distance_m"] == pytest.approx(v0 * v0 / (2 * a), rel=0.01)
    assert r["slide_episodes"] == 0 and r["slide_s"] == 0.0
    assert r["worst_slip"] > -0.1
    assert r["status"] == "ok" and r["verdict"] == "ok"


@pytest.mark.slow
def test_wsp_on_dry_rail_never_vents_and_changes_nothing(runs):
    """No axle passes the release threshold on dry rail, so the dump valves stay shut and the stop is
    that of the run without WSP."""
    d, res = runs
    X.execute(X.Case("dry-wsp", "dry rail, WSP", "dry_wsp"), str(d), False, None)
    r = json.loads((d / "dry-wsp" / "report.json").read_text())
    assert r["wsp_venting_s"] == 0.0 and r["slide_episodes"] == 0
    assert r["stopping_distance_m"] == pytest.approx(res["dry"]["stopping_distance_m"], abs=1e-6)


@pytest.mark.slow
def test_low_adhesion_without_wsp_locks_wheels_and_wsp_prevents_it(runs):
    """μ = 0.06 cannot carry the 0.83 m/s² service brake (μ g = 0.59 m/s² at standstill, less at speed):
    without WSP the brake torque locks wheels (λ → −1) of every car in the section; WSP vents the
    brake as soon as the slip passes its release threshold, so the slip stays near it and the slide
    time is (much) shorter. Less adhesion: a longer stop than on dry rail, in either case."""
    r = runs[1]
    lo, ws, dry = r["low"], r["low-wsp"], r["dry"]
    scn = load_scenario(SCN, profile="wsp")
    assert lo["worst_slip"] < -0.99 and lo["slide_episodes"] >= 8 and lo["cars_sliding"] == list(range(1, 9))
    assert ws["slide_s"] < lo["slide_s"]
    assert ws["worst_slip"] > -(scn.consist.brakes.wsp.slip_release + 0.1)
    assert ws["wsp_venting_s"] > 0 and lo["wsp_venting_s"] == 0
    assert lo["stopping_distance_m"] > dry["stopping_distance_m"] and ws["stopping_distance_m"] > dry["stopping_distance_m"]
    # sliding cars brake less than their neighbours: the couplers carry far more than on dry rail
    assert min(lo["max_compression_n"], ws["max_compression_n"]) > 10 * dry["max_compression_n"]
    assert all(math.isfinite(x["stopping_distance_m"]) for x in r.values())


@pytest.mark.slow
def test_the_report_writes_its_section_between_its_markers_and_keeps_the_rest(runs, tmp_path):
    d, res = runs
    doc = tmp_path / "mixed-trains.md"
    doc.write_text("# Mixed trains\n\nkeep me\n\n<!-- begin: other -->\nother\n<!-- end: other -->\n")
    X.generate(tmp_path, d, step_check=False, log=lambda m: None)
    text = doc.read_text()
    assert "keep me" in text and "<!-- begin: other -->\nother\n<!-- end: other -->" in text
    sec = text[text.index(X.BEGIN):text.index(X.END)]
    for c in X.CASES:
        row = next(ln for ln in sec.splitlines() if ln.startswith(f"| {c.label} |"))
        assert f"| {res[c.key]['stopping_distance_m']:.1f} |" in row
    X.generate(tmp_path, d, step_check=False, log=lambda m: None)  # again: replaced, not appended
    assert doc.read_text().count(X.BEGIN) == 1


def test_a_motor_car_of_all_three_papers_builds_and_runs_with_one_process_per_ecu(tmp_path):
    """Profile li_envelope: a motor car with Chen's nonlinear coupler, Li 2024's electric-brake
    envelope (eq. 2) and Cai 2014's slip curve on each of its axles, beside trailer cars without ED
    brake; one process per ECU on the memory bus. At ~100 km/h the envelope's power limit (2,880 kN
    km/h) caps a motor car's ED brake at 28.8 kN; a trailer's is zero."""
    import canbrake

    scn = load_scenario("emu8_low_adhesion", profile="li_envelope")
    t = scn.consist
    assert t.coupler.stiffness_n_per_m == 2.0e6 and t.brakes.wheels.axles == 4 and t.brakes.wheels.b1 == 1.786
    models = [c.model if c is not None else "default" for c in t.brakes.blending.per_car]
    assert models == ["none", "envelope", "envelope", "none", "none", "envelope", "envelope", "none"]
    r = canbrake.run("emu8_low_adhesion", profile="li_envelope", duration_s=1.0, out=tmp_path / "r", plots=False)
    assert r.summary["status"] == "ok"
    s = r.signals
    ed = s[[f"ed_brake_n_c{i}" for i in range(1, 9)]].to_numpy()
    assert (ed[:, [0, 3, 4, 7]] == 0).all()
    assert ed[:, [1, 2, 5, 6]].max() == pytest.approx(2880e3 / 3.6 / float(s["speed_mps_c2"].iloc[-1]), rel=0.02)
