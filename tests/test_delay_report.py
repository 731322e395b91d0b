"""``canbrake report delay`` (canbrake/report/delay.py) on a tiny grid: its threshold logic against
the E2E window derived from the lockstep rules, and the document it writes."""
from __future__ import annotations

import math

import pytest

from canbrake.report import delay as D
from canbrake.scenario import load_scenario
from canbrake.sweep import UNSTABLE_SPEED_ERROR_KMH


@pytest.mark.slow
def test_delay_report_finds_the_e2e_window_where_the_lockstep_rules_put_it(tmp_path):
    # Realistic profile (T = 10 ms, a slow loop), cars at 90 km/h, delay on the commands only.
    # A command delayed by d is used m = floor(d/T + 1/2) periods late; the brake unit accepts
    # m <= E2E_MAX_LAG. So from the first grid value with m > E2E_MAX_LAG no command is ever
    # accepted, the train coasts, and after D seconds its speed error is about a*·D: unstable
    # (>= UNSTABLE_SPEED_ERROR_KMH) if a*·D is. Below it the slow loop still brakes.
    scn = load_scenario(D.scenario_path(), profile="realistic")
    T, dur = scn.control_period_s, 2.0
    a_kmh_s = scn.reference.decel_kmh_per_s
    assert a_kmh_s * dur > 1.5 * UNSTABLE_SPEED_ERROR_KMH  # the premise: coasting is judged unstable
    grid_ms = (0, 60, 70, 80)
    spec = D.SweepSpec("realistic_cmd", "realistic, commands late", "realistic",
                       ("cmd_delay=" + ",".join(str(g) for g in grid_ms) + "ms",), seeds=1, duration_s=dur,
                       sets=(("initial.speed_kmh", 90),), controllers=("chen2023",), maps=False)
    rows, axes_list = D.run_spec(spec, tmp_path / "runs", D.scenario_path(), workers=0, log=lambda m: None)
    cells = D.threshold_cells(rows, axes_list, "chen2023")
    expected = next(g / 1000 for g in grid_ms if math.floor(g / 1000 / T + D.LOCKSTEP_HALF) > D.E2E_MAX_LAG)
    assert cells["cmd_delay"][D.FLAGS.index("unstable")] == pytest.approx(expected)
    coast = next(r for r in rows if r["cmd_delay_s"] == pytest.approx(expected))
    assert float(coast["final_speed_error_kmh_max"]) == pytest.approx(a_kmh_s * dur, rel=0.25)


@pytest.mark.slow
def test_delay_report_writes_its_tables_and_commands(tmp_path):
    sweeps = (D.SweepSpec("paper", "paper profile", "paper", ("delay=0,2ms", "loss=0,50%"), seeds=1,
                          duration_s=0.02, controllers=("chen2023",)),)
    md = D.generate(tmp_path / "docs", tmp_path / "runs", jobs=0, sweeps=sweeps, log=lambda m: None)
    text = md.read_text()
    assert "| paper profile (0–2 ms × 0–50 %, 0.02 s) | chen2023 |" in text
    assert "canbrake sweep scenarios/chen2023_case1_fine_rail.yaml --profile paper --grid delay=0,2ms" in text
    assert (tmp_path / "docs" / "figures" / "delay-robustness" / "paper_safety.png").exists()


def test_a_pre_fix_threshold_agrees_when_it_lies_between_our_grid_points():
    from canbrake.sweep import parse_grid

    ax = parse_grid("delay=0:50ms:6")  # 0, 10, ..., 50 ms
    assert D.compare_old("15 ms", ax, 0.02) is None          # 10 < 15 <= 20
    assert D.compare_old("> 50 ms", ax, None) is None
    assert "not at 40 ms" in D.compare_old("35 ms", ax, 0.05)   # 35 is not in (40, 50]
    assert "not reached" in D.compare_old("35 ms", ax, None)
    assert D.compare_old("> 50 ms", ax, 0.03) is not None
    loss = parse_grid("loss=0,20,50%")
    assert D.compare_old("45 %", loss, 0.5) is None and D.compare_old("10 %", loss, 0.5) is not None
