"""Built-in scenarios (package data, `canbrake scenarios`, `canbrake init`, `canbrake run NAME`),
the pytest plugin's helpers, and the run plots."""
from __future__ import annotations

import json
import os
import subprocess
import sys
import tomllib
from pathlib import Path

import numpy as np
import pytest
import yaml

from canbrake.analysis.metrics import Trace
from canbrake.analysis.plots import PlotMeta, figures
from canbrake.builtin import builtin_dir, builtin_scenarios, find_scenario
from canbrake.cli import main

from conftest import ROOT, SCENARIOS


def test_builtin_scenarios_are_the_repository_files():
    names = sorted(p.stem for p in SCENARIOS.glob("*.yaml"))
    assert [b.name for b in builtin_scenarios()] == names and names
    for b in builtin_scenarios():
        assert b.path.read_bytes() == (SCENARIOS / b.path.name).read_bytes()
        assert b.description == yaml.safe_load(b.path.read_text())["description"]
    assert builtin_dir().resolve() == SCENARIOS.resolve()


def test_pyproject_ships_scenarios_and_the_plugin():
    meta = tomllib.loads((ROOT / "pyproject.toml").read_text())
    assert "scenarios/*.yaml" in meta["tool"]["setuptools"]["package-data"]["canbrake"]
    assert meta["project"]["entry-points"]["pytest11"] == {"canbrake.testing": "canbrake.testing"}
    assert (ROOT / "canbrake" / "scenarios").resolve() == SCENARIOS.resolve()


def test_cli_scenarios_lists_one_line_each(capsys):
    assert main(["scenarios"]) == 0
    lines = capsys.readouterr().out.splitlines()
    assert len(lines) == len(builtin_scenarios())
    for line, b in zip(lines, builtin_scenarios()):
        assert line.split()[0] == b.name and line.endswith(b.description)


def test_cli_init_copies_and_refuses_to_overwrite(tmp_path, capsys):
    assert main(["init", "chen2023_case2_poor_rail", str(tmp_path / "mine")]) == 0
    copied = tmp_path / "mine" / "chen2023_case2_poor_rail.yaml"
    assert copied.read_text() == (SCENARIOS / copied.name).read_text()
    assert main(["init", "chen2023_case2_poor_rail", str(tmp_path / "mine")]) == 2
    assert "already exists" in capsys.readouterr().err
    assert main(["init", "nope", str(tmp_path)]) == 2
    assert "not a built-in scenario" in capsys.readouterr().err


def test_run_resolves_a_builtin_name_only_when_no_file_exists(tmp_path, monkeypatch, capsys):
    monkeypatch.chdir(tmp_path)
    assert find_scenario("chen2023_case1_fine_rail") == builtin_dir() / "chen2023_case1_fine_rail.yaml"
    assert find_scenario("scenarios/chen2023_case1_fine_rail.yaml").parent == builtin_dir()
    local = tmp_path / "chen2023_case1_fine_rail"
    local.write_text("name: mine\n")
    assert find_scenario("chen2023_case1_fine_rail") == Path("chen2023_case1_fine_rail")  # the file wins
    local.unlink()
    assert main(["run", "chen2023_case1_fine_rail", "--bus", "inprocess", "--duration", "0.01", "--no-plots",
                 "--out", "r"]) == 0
    assert json.loads((tmp_path / "r" / "summary.json").read_text())["scenario"] == "chen2023_case1_fine_rail"
    assert main(["run", "no_such", "--bus", "inprocess"]) == 2
    assert "nor a built-in scenario" in capsys.readouterr().err


# ----------------------------------------------------------------------------- plugin helpers
def _fake_run(tmp_path: Path, *, deflection: float = 0.0, speed_err: float = 0.0, summary: dict | None = None):
    """A 2-car run directory: v* = 20 m/s falling at 1 m/s², car 2 off by ``speed_err`` from 0.5 s,
    the coupler at ``deflection`` from 0.7 s."""
    from canbrake.api import RunResult

    t = np.round(np.arange(0, 1.001, 0.1), 3)
    v = 20.0 - t
    x = 20.0 * t - 0.5 * t ** 2
    cols = {"t_s": t, "ref_speed_mps": v, "position_m_c1": x, "speed_mps_c1": v,
            "position_m_c2": x - 10, "speed_mps_c2": v + np.where(t >= 0.5, speed_err, 0.0),
            "deflection_m_k1": np.where(t >= 0.7, deflection, 0.0)}
    lines = [",".join(cols)] + [",".join(f"{cols[c][i]:.9g}" for c in cols) for i in range(len(t))]
    (tmp_path / "signals.csv").write_text("\n".join(lines) + "\n")
    return RunResult(tmp_path, summary or {"status": "ok"})


def test_railway_assertions_say_what_failed(tmp_path):
    from canbrake import testing as T

    r = _fake_run(tmp_path, deflection=-0.0123, speed_err=0.25)
    with pytest.raises(AssertionError, match=r"coupler 1–2 deflected 1.23 cm at t = 0.700 s, beyond the ±1 cm bound"):
        T.assert_deflection_within(r, 0.01)
    T.assert_deflection_within(r, 0.013)
    with pytest.raises(AssertionError, match=r"car 2 ran \+0.9 km/h off .* at t = 0.500 s, outside the ±0.5 km/h"):
        T.assert_speed_band(r, 0.5)
    T.assert_speed_band(r, 1.0)
    T.assert_speed_band(r, 0.5, cars=[1])



def test_stopping_distance_against_v2_over_2a(tmp_path):
    from canbrake import testing as T
    from canbrake.api import load_scenario

    r = _fake_run(tmp_path)
    r.scenario = load_scenario("chen2023_case1_fine_rail", reference__speed_kmh=72.0,
                               reference__decel_kmh_per_s=3.6)  # v0* = 20 m/s, a* = 1 m/s²
    # on the reference: travelled 19.5 m at 19 m/s -> 19.5 + 19²/2 = 200 m = 20²/2
    T.assert_stopping_distance(r, tolerance_m=0.01)
    with pytest.raises(AssertionError, match=r"car 1 still at 68.4 km/h, would stop after 200.00 m, more than "
                                             r"the allowed 150.00 m"):
        T.assert_stopping_distance(r, 150.0)


def test_deadline_and_e2e_assertions(tmp_path):
    from canbrake import testing as T

    r = _fake_run(tmp_path, summary={"ticks": 100, "deadline_misses": {"plant": 3, "ecus": 1, "max_lateness_s": 0.002},
                                     "frames": {"commands_corrupted": 4, "peer_frames_corrupted": 1}})
    with pytest.raises(AssertionError, match=r"3 plant deadline misses \(3.0% of 100 periods\) and 1 ECU"):
        T.assert_no_deadline_misses(r)
    T.assert_no_deadline_misses(r, allowed=4)
    with pytest.raises(AssertionError, match=r"5 frames failed the E2E check \(4 brake commands .* 1 peer"):
        T.assert_e2e_rejections(r)
    T.assert_e2e_rejections(r, at_least=5)
    with pytest.raises(AssertionError, match="expected at least 6"):
        T.assert_e2e_rejections(r, at_least=6)


@pytest.mark.slow
def test_user_test_file_passes_with_the_plugin(tmp_path):
    """examples/tests/test_my_controller.py, run as a user runs it (the plugin by its entry point
    when canbrake is installed; here by -p, which is the same module)."""
    env = dict(os.environ, PYTHONPATH=str(ROOT))
    p = subprocess.run([sys.executable, "-m", "pytest", "-q", "-p", "canbrake.testing", "-p", "no:cacheprovider",
                        str(ROOT / "examples" / "tests")], cwd=tmp_path, env=env, capture_output=True, text=True,
                       timeout=600)
    assert p.returncode == 0, p.stdout[-3000:] + p.stderr[-2000:]
    assert "5 passed" in p.stdout


# ----------------------------------------------------------------------------- plots
def _trace(n: int = 3, T: int = 200) -> Trace:
    t = np.linspace(0, 2, T)
    v = 25 - 0.97 * t
    speed = np.tile(v[:, None], (1, n))
    force = np.full((T, n), 20e3)
    force[:3] = 22e6  # the paper profile's first instants
    return Trace(t_s=t, ref_speed_mps=v, position_m=np.cumsum(speed, axis=0) * (t[1] - t[0]), speed_mps=speed,
                 accel_mps2=np.full((T, n), -0.97), brake_cmd_n=force, brake_applied_n=force,
                 deflection_m=np.zeros((T, n - 1)), coupler_force_n=np.zeros((T, n - 1)))


def test_plots_titles_limits_and_scales():
    meta = PlotMeta(scenario="case1", profile="paper", controller="chen2023", bus="memory", mode="lockstep",
                    ref_decel_mps2=0.97)
    figs = figures(_trace(), meta)
    assert set(figs) == {"overview", "speeds", "errors", "decel", "deflections", "forces", "stopping"}
    for f in figs.values():
        title = f._suptitle.get_text().replace("\n", " ")
        for part in ("case1", "profile paper", "controller chen2023", "bus memory"):
            assert part in title
    ax = figs["forces"].axes[0]
    assert ax.get_yscale() == "symlog" and "+ brakes" in ax.get_ylabel()  # 22 MN would hide 20 kN
    decel_labels = [ln.get_label() for ln in figs["decel"].axes[0].get_lines()]
    assert any("emergency 1.5" in s for s in decel_labels) and any("comfort" in s for s in decel_labels)
    defl_labels = [ln.get_label() for ln in figs["deflections"].axes[0].get_lines()]
    assert "bound ±1 cm" in defl_labels
    # the stopping-distance reference is v0²/2a*
    stop = [ln for ln in figs["stopping"].axes[0].get_lines() if ln.get_label().startswith("v0")][0]
    assert stop.get_ydata()[0] == pytest.approx(25 ** 2 / (2 * 0.97))
    service = _trace()
    service.brake_applied_n = np.full((200, 3), 20e3)
    assert figures(service, meta, only="forces")["forces"].axes[0].get_yscale() == "linear"


def test_sweep_deflection_cells_use_the_colour_bar_unit():
    from canbrake.sweep import _short_cm

    assert _short_cm(160.0) == "160" and _short_cm(1.3) == "1.3" and _short_cm(2e4) == "∞"


def test_init_copies_the_data_files_a_scenario_names(tmp_path, monkeypatch):
    import canbrake.builtin as B

    pkg = tmp_path / "pkg"
    (pkg / "data").mkdir(parents=True)
    (pkg / "data" / "wagons.csv").write_text("mass_kg\n25000\n")
    (pkg / "data" / "unused.csv").write_text("x\n")
    (pkg / "heavy.yaml").write_text("name: heavy\ndescription: a heavy train\ntable: data/wagons.csv\n")
    monkeypatch.setattr(B, "builtin_dir", lambda: pkg)
    written = B.init_scenario("heavy", tmp_path / "mine")
    assert sorted(p.relative_to(tmp_path / "mine").as_posix() for p in written) == ["data/wagons.csv", "heavy.yaml"]
    assert (tmp_path / "mine" / "data" / "wagons.csv").read_text() == "mass_kg\n25000\n"


def test_symlog_axes_keep_limits_visible_and_units_right():
    """Extreme first instants switch an axis to symmetric-log: its linear part ends at a decade (no
    decade tick crowds next to 0), never above the decade of the band drawn (jerk comfort ±1 m/s³),
    and is chosen in the plotted unit (coupler force in kN, not N)."""
    meta = PlotMeta(scenario="case1", profile="paper", controller="chen2023", bus="memory", mode="lockstep",
                    ref_decel_mps2=0.97)
    tr = _trace()
    T, n = tr.accel_mps2.shape
    dt = float(tr.t_s[1] - tr.t_s[0])
    tr.accel_mps2 = -0.97 + 0.3 * dt * np.where(np.arange(T) % 2, 1.0, -1.0)[:, None] * np.ones(n) * 1000
    tr.accel_mps2[:2] = 500.0  # jerk ~ 300 m/s³ from the alternation, 1e5+ at the start
    tr.coupler_force_n = np.full((T, n - 1), 2_000.0)  # 2 kN ...
    tr.coupler_force_n[:2] = 5e6                        # ... after a 5 MN spike

    def linthresh(ax):
        assert ax.get_yscale() == "symlog"
        return ax.yaxis.get_transform().linthresh

    figs = figures(tr, meta)
    jerk = linthresh(figs["decel"].axes[1])
    assert jerk <= meta.jerk_limit_mps3 and np.log10(jerk) == np.round(np.log10(jerk))
    force = linthresh(figs["deflections"].axes[1])
    assert force == 1.0  # kN: the decade at or below 1.5 x 2 kN
    brake = linthresh(figs["forces"].axes[0])
    assert brake == 10.0  # kN: the decade at or below 1.5 x 20 kN; 20 kN shows in the first log decade
