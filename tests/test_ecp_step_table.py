"""The ECP report's step-size table goes through the shared step helpers
(:func:`canbrake.analysis.metrics.step_convergence`): a unit test on made-up run results, no runs."""
from __future__ import annotations

import math

from canbrake.report import ecp

H0 = 0.01


def _run(stop: float, comp: float, tens: float, half: float) -> dict:
    return {"stopping_distance_m": stop, "max_compression_n": -comp, "max_tension_n": tens,
            "last_wagon_half_s": half}


def _res(chains: dict[str, list[dict]]) -> dict:
    res = {}
    for base, runs in chains.items():
        res[base] = runs[0]
        for d, r in zip(ecp.STEP_DIVISORS, runs[1:]):
            res[f"{base}-h{1000 * H0 / d:g}ms"] = r
    return res


def test_the_step_table_gives_the_relative_change_to_the_next_finer_step():
    # ECP: the stopping distance moves 800 -> 796 -> 795 m, everything else fixed:
    # changes |800 - 796| / 800 = 0.5 % and |796 - 795| / 796 = 0.126 %
    ecp_runs = [_run(800.0, 1e6, 5e5, 10.0), _run(796.0, 1e6, 5e5, 10.0), _run(795.0, 1e6, 5e5, 10.0)]
    pn = [_run(900.0, 2e6, 7e5, 60.0)] * 3
    lines, converged, worst = ecp.step_table(_res({"ecp-250k": ecp_runs, "pneumatic-250k": pn}), H0)
    assert converged
    assert math.isclose(worst, 4.0 / 800.0)
    rows = [ln for ln in lines[2:]]
    assert len(rows) == 6
    assert rows[0].startswith("| ECP, 250 kbit/s | 10 ms | 800.0 | 1000.0 | 500.0 | 10.00 s |")
    assert rows[0].endswith(f"| {100 * 4 / 800:.2f} % |")
    assert rows[1].endswith(f"| {100 * 1 / 796:.2f} % |")
    assert rows[2].endswith("| — |")
    assert rows[3].endswith("| 0.00 % |")


def test_a_change_of_one_percent_or_more_at_the_first_halving_is_not_converged():
    # peak tension 500 -> 490 kN at the first halving: 2 % (>= STEP_TOL), then unchanged
    runs = [_run(800.0, 1e6, 5.0e5, 10.0), _run(800.0, 1e6, 4.9e5, 10.0), _run(800.0, 1e6, 4.9e5, 10.0)]
    lines, converged, worst = ecp.step_table(_res({"ecp-250k": runs}), H0)
    assert not converged
    assert math.isclose(worst, 0.02)
    assert lines[2].endswith("| 2.00 % |")


def test_never_on_both_steps_is_unchanged_and_on_one_is_a_change():
    inf = math.inf
    both = [_run(inf, 1e6, 5e5, inf)] * 3  # no stop, no half pressure at any step
    _, converged, worst = ecp.step_table(_res({"ecp-250k": both}), H0)
    assert converged and worst == 0.0
    one = [_run(inf, 1e6, 5e5, 10.0), _run(812.0, 1e6, 5e5, 10.0), _run(812.0, 1e6, 5e5, 10.0)]
    lines, converged, worst = ecp.step_table(_res({"ecp-250k": one}), H0)
    assert not converged and worst is None
    assert "changed" in lines[2] and lines[2].startswith("| ECP, 250 kbit/s | 10 ms | — |")
