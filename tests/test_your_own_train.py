"""docs/your-own-train.md, executed: an 8-car EMU with a controller from the user's own installed
package (found through the ``canbrake.controllers`` entry point), run on the bus and swept."""
from __future__ import annotations

import json
import os
import shutil
import subprocess
import sys
from pathlib import Path

import pytest

from conftest import ROOT

EXAMPLE = ROOT / "examples" / "my_train"


@pytest.fixture(scope="module")
def site(tmp_path_factory) -> Path:
    """What `pip install examples/my_train` puts on sys.path: the package and its dist-info with the
    entry point (made by hand so the test does not modify the environment)."""
    site = tmp_path_factory.mktemp("site")
    shutil.copytree(EXAMPLE / "mytrain", site / "mytrain")
    info = site / "canbrake_mytrain_example-0.1.0.dist-info"
    info.mkdir()
    (info / "METADATA").write_text("Metadata-Version: 2.1\nName: canbrake-mytrain-example\nVersion: 0.1.0\n")
    lines = (EXAMPLE / "pyproject.toml").read_text().splitlines()
    ctl = [ln for ln in lines if ln.startswith("my_speed_pi")]
    comp = [ln for ln in lines if ln.startswith("davis_kmh")]
    (info / "entry_points.txt").write_text("[canbrake.controllers]\n" + "\n".join(ctl).replace('"', "") + "\n\n"
                                           "[canbrake.components.resistance]\n"
                                           + "\n".join(comp).replace('"', "") + "\n")
    return site


def _canbrake(site: Path | None, *args: str) -> subprocess.CompletedProcess:
    env = dict(os.environ)
    if site is not None:
        env["PYTHONPATH"] = os.pathsep.join([str(site), env.get("PYTHONPATH", "")])
    return subprocess.run([sys.executable, "-m", "canbrake", *args], capture_output=True, text=True, env=env,
                          cwd=ROOT, timeout=600)


def test_own_controller_runs_on_the_bus(site: Path, tmp_path: Path):
    out = tmp_path / "run"
    r = _canbrake(site, "run", str(EXAMPLE / "emu8.yaml"), "--duration", "2", "--out", str(out), "--no-plots")
    assert r.returncode == 0, r.stderr
    s = json.loads((out / "summary.json").read_text())
    assert s["status"] == "ok" and s["n_cars"] == 8 and s["ticks"] == 200
    header = (out / "signals.csv").read_text().splitlines()[0].split(",")
    assert "speed_error_mps_c8" in header  # the controller's own diagnostic, per car
    dbc = (out / "canbrake.dbc").read_text()
    assert "BRAKE_CMD_CAR8" in dbc and "STATE_CAR1" not in dbc  # named ECUs; nobody listens: no STATE
    assert "STATE_DONE_CAR1" not in dbc  # listens: none -> no lockstep state phase


def test_own_controller_parameters_are_checked(site: Path, tmp_path: Path):
    r = _canbrake(site, "run", str(EXAMPLE / "emu8.yaml"), "--set", "controller.params.kq=1", "--out",
                  str(tmp_path / "x"))
    assert r.returncode == 2 and "controller.params.kq" in r.stderr and "Traceback" not in r.stderr
    r = _canbrake(site, "run", str(EXAMPLE / "emu8.yaml"), "--set", "controller.params.kp=fast", "--out",
                  str(tmp_path / "x"))
    assert r.returncode == 2 and "controller.params.kp" in r.stderr
    r = _canbrake(None, "run", str(EXAMPLE / "emu8.yaml"), "--out", str(tmp_path / "x"))
    assert r.returncode == 2 and "unknown controller 'my_speed_pi'" in r.stderr


def test_own_controller_is_swept(site: Path, tmp_path: Path):
    out = tmp_path / "sweep"
    r = _canbrake(site, "sweep", str(EXAMPLE / "emu8.yaml"), "--grid", "delay=0:20ms:2", "--duration", "0.5",
                  "--workers", "0", "--seeds", "1", "--out", str(out), "--no-plots", "-q")
    assert r.returncode == 0, r.stderr
    rows = list(out.glob("**/summary.json"))
    assert len(rows) == 2


def test_a_component_of_the_users_own_package_runs_as_its_si_equivalent(site, tmp_path):
    """resistance: {model: davis_kmh} from the example package (entry point group
    canbrake.components.resistance) is listed by `canbrake components`, and a run with it gives the
    signals of the built-in davis model with the same coefficients in SI, text for text."""
    r = _canbrake(site, "components", "resistance")
    assert r.returncode == 0 and "davis_kmh: Running resistance R = A + B" in r.stdout, r.stderr
    kmh = "{model: davis_kmh, a_n: 1100, b_n_per_kmh: 10, c_n_per_kmh2: 0.39}"
    si = "{model: davis, c0_n: 1100, c1_n_s_per_m: %r, c2_n_s2_per_m2: %r}" % (10 * 3.6, 0.39 * 3.6 * 3.6)
    for name, res in (("kmh", kmh), ("si", si)):
        r = _canbrake(site, "run", str(EXAMPLE / "emu8.yaml"), "--duration", "1", "--bus", "inprocess", "--no-plots",
                      "--set", f"train.vehicle_types.mc.resistance={res}", "--out", str(tmp_path / name))
        assert r.returncode == 0, r.stderr
    assert (tmp_path / "kmh" / "signals.csv").read_bytes() == (tmp_path / "si" / "signals.csv").read_bytes()
    r = _canbrake(site, "run", str(EXAMPLE / "emu8.yaml"), "--duration", "1", "--no-plots", "--set",
                  "train.vehicle_types.mc.resistance={model: davis_kmh, a_n: -5}", "--out", str(tmp_path / "bad"))
    assert r.returncode == 2 and "a_n: Input should be greater than or equal to 0" in r.stderr, r.stderr
