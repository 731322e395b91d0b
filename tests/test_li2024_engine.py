"""Li 2024 through the node engine: the scenarios load, run on every backend with identical frames
and signals, track the reference, and the report regenerates (short runs; the full 2600 s runs are
in docs/reproduction/li2024.md)."""
from __future__ import annotations

import shutil
from pathlib import Path

import numpy as np
import pytest

from canbrake.run import run_scenario
from canbrake.scenario import load_scenario

SCENARIOS = Path(__file__).resolve().parents[1] / "scenarios"
TRACKING = ("li2024_pid", "li2024_smc", "li2024_rbfnn_smc", "li2024_rbfnn_smc_ndo")


def _scn(name: str, profile: str | None = None, **over):
    return load_scenario(SCENARIOS / f"{name}.yaml", profile=profile, overrides=over)


def _signals(run_dir: Path, cols: tuple[str, ...]) -> dict[str, np.ndarray]:
    import pandas as pd
    df = pd.read_csv(run_dir / "signals.csv", usecols=list(cols))
    return {c: df[c].to_numpy() for c in cols}


@pytest.mark.parametrize("name", ("li2024_driver",) + TRACKING)
def test_scenarios_load_with_one_locomotive_ecu(name):
    scn = _scn(name)
    placed = scn.placement()
    assert [(p.name, p.vehicle) for p in placed] == [("loco", 1)]
    assert scn.n_cars == 106 and scn.control_period_s == 0.01
    assert _scn(name, "disturbance").consist.disturbance.enabled


def test_the_li2024_scenarios_share_one_train():
    """The train is repeated in each scenario file; only the driver run's plant is nominal (δ = 0)."""
    trains = {n: _scn(n).train.model_dump() for n in ("li2024_driver",) + TRACKING}
    base = trains["li2024_smc"]
    for n, t in trains.items():
        if n == "li2024_driver":
            assert t["uncertainty"] == 0.0
            t = {**t, "uncertainty": base["uncertainty"]}
        assert t == base, n


@pytest.mark.slow
def test_rbfnn_smc_ndo_is_identical_on_every_backend(tmp_path):
    scn = _scn("li2024_rbfnn_smc_ndo", "disturbance", duration_s=2.0)
    runs = {}
    for backend in ("inprocess", "virtual", "memory"):
        s = run_scenario(scn, tmp_path / backend, backend=backend, plots=False)
        assert s["status"] == "ok", s.get("message")
        runs[backend] = tmp_path / backend
    for f in ("signals.csv", "frames.log"):
        ref = (runs["inprocess"] / f).read_bytes()
        for b in ("virtual", "memory"):
            assert (runs[b] / f).read_bytes() == ref, (b, f)
    import can
    import cantools
    db = cantools.database.load_file(str(runs["memory"] / "canbrake.dbc"))
    decoded = [db.decode_message(m.arbitration_id, m.data) for m in can.LogReader(str(runs["memory"] / "frames.log"))]
    assert len(decoded) > 200 and any("PassiveForce" in d for d in decoded)
    cols = _signals(runs["inprocess"], ("t_s", "speed_mps_c1", "ref_speed_mps", "passive_force_n_c1"))
    assert cols["t_s"][-1] == pytest.approx(2.0)
    assert np.all(np.isfinite(cols["passive_force_n_c1"]))


@pytest.mark.slow
def test_tracking_through_the_engine(tmp_path):
    """20 s of the reference's traction segment: every controller tracks within 0.3 km/h RMSE, and
    the paper's order RBFNN-SMC + NDO < SMC < PID holds (the report measures it over 2600 s)."""
    rmse = {}
    for name in ("li2024_pid", "li2024_smc", "li2024_rbfnn_smc_ndo"):
        s = run_scenario(_scn(name, duration_s=20.0), tmp_path / name, backend="inprocess", plots=False)
        assert s["status"] == "ok"
        c = _signals(tmp_path / name, ("speed_mps_c1", "ref_speed_mps"))
        rmse[name] = float(np.sqrt(np.mean(((c["speed_mps_c1"] - c["ref_speed_mps"]) * 3.6) ** 2)))
    assert max(rmse.values()) < 0.3
    assert rmse["li2024_rbfnn_smc_ndo"] < rmse["li2024_smc"] < rmse["li2024_pid"]


@pytest.mark.slow
def test_report_regenerates_through_the_engine(tmp_path):
    from canbrake.report import li2024

    sd = tmp_path / "scenarios"
    shutil.copytree(SCENARIOS, sd)
    specs = [li2024.RunSpec("pid", False), li2024.RunSpec("smc", False), li2024.RunSpec("rbfnn-smc+ndo", True),
             li2024.RunSpec("rbfnn-smc+ndo", False), li2024.RunSpec("rbfnn-smc+ndo", False, "listed", "printed"),
             li2024.RunSpec("rbfnn-smc+ndo", False, "listed", "nominal", 0.005)]
    md = li2024.generate(tmp_path / "out", tmp_path / "runs", jobs=1, log=lambda s: None, duration_s=5.0,
                         specs=specs, scen_dir=sd, driver_duration_s=5.0)
    text = md.read_text()
    assert "Table 2" in text and "| PID |" in text and "canbrake run scenarios/li2024_smc.yaml" in text
    assert "## Table 2 in each reading" in text and "## Step size" in text
    assert "--set ecus.0.controller.params.ndo_model=printed" in text
    assert "--set train.integration_step_s=0.005" in text
    assert (tmp_path / "out" / "figures" / "li2024_errors.png").exists()
    assert (tmp_path / "runs" / "pid-nodist" / "report.npz").exists()
    # the driver run made the reference table the tracking runs read
    assert (sd / "data" / "li2024_reference.csv").read_text().splitlines()[2] == "time_s,speed_kmh"


@pytest.mark.slow
def test_ecp_over_can_wagons_apply_the_locomotive_demand(tmp_path):
    """The locomotive ECU broadcasts the demand at 0.1 s; each wagon ECU receives it in the next
    period and commands its cylinder: the last wagon brakes within 0.1 s over CAN (the pneumatic
    signal needs 1271 m / 200 m/s = 6.4 s to get there; tests/test_li2024.py checks the wave)."""
    scn = load_scenario(SCENARIOS / "li2024_ecp_over_can.yaml",
                        overrides={"duration_s": 0.3, "ecus.0.controller.params.brake_at_s": 0.1,
                                   "bus.timing": "ideal"})  # with the timing model, late wagons lose a tick
    assert len(scn.placement()) == 106
    s = run_scenario(scn, tmp_path / "r", backend="inprocess", plots=False)
    assert s["status"] == "ok", s.get("message")
    import pandas as pd
    df = pd.read_csv(tmp_path / "r" / "signals.csv")
    last = df["brake_cylinder_pressure_pa_c106"].to_numpy()
    assert list(df["cmd_ecp_demand_c106"].to_numpy()[:4]) == [0.0, 0.0, 0.0, 1.0]  # t = 0, .05, .1, .15
    assert last[-1] > 0.0


@pytest.mark.slow
def test_a_silent_ecp_wagon_brakes_on_its_own_with_the_failsafe(tmp_path):
    """Wagon 53's ECU goes silent at 0.05 s. Without a fail-safe its cylinder holds the last command
    (released); with ``safety.failsafe_commands: {ecp_demand: 1}`` the brake unit applies a full
    application after ``command_timeout_s`` (0.1 s = 2 periods) while its neighbours stay released
    (no demand yet)."""
    base = {"duration_s": 0.5, "ecus.0.controller.params.brake_at_s": 10.0, "bus.timing": "ideal",
            "bus.impairments": [{"type": "silent", "senders": ["wagon53"], "start_s": 0.05}]}
    out = {}
    for key, extra in (("hold", {}), ("failsafe", {"safety": {"command_timeout_s": 0.1,
                                                              "failsafe_commands": {"ecp_demand": 1.0}}})):
        scn = load_scenario(SCENARIOS / "li2024_ecp_over_can.yaml", overrides={**base, **extra})
        s = run_scenario(scn, tmp_path / key, backend="inprocess", plots=False)
        assert s["status"] == "ok", s.get("message")
        out[key] = (s, _signals(tmp_path / key, ("brake_cylinder_pressure_pa_c53", "brake_cylinder_pressure_pa_c52")))
    s_hold, hold = out["hold"]
    s_fs, fs = out["failsafe"]
    assert hold["brake_cylinder_pressure_pa_c53"].max() == 0.0
    assert fs["brake_cylinder_pressure_pa_c53"][-1] > 0.0 and fs["brake_cylinder_pressure_pa_c52"].max() == 0.0
    assert s_fs["failsafe"]["activations"] == 1 and list(s_fs["failsafe"]["first_activation_s"]) == ["c53"]


@pytest.mark.slow
def test_ecp_report_runs_the_step_check(tmp_path):
    """`canbrake report ecp` on a short run: the step-size runs are the same run with the plant step
    halved twice, and the table shows each with the change to the next finer step."""
    from canbrake.report import ecp
    sets = (("ecus.0.controller.params.brake_at_s", 0.1), ("bus.timing", "ideal"), ("train.integration_step_s", 0.01))
    spec = ecp.Spec("ecp-250k", None, "ECP test", sets)
    md = ecp.generate(tmp_path / "out", tmp_path / "runs", jobs=1, duration_s=0.4, specs=(spec,),
                      log=lambda m: None)
    text = md.read_text()
    assert "## Integration step" in text
    for h in ("10 ms", "5 ms", "2.5 ms"):
        assert f"| ECP test | {h} |" in text
    assert "--set train.integration_step_s=0.0025" in text
    import json
    r5 = json.loads((tmp_path / "runs" / "ecp-250k-h5ms" / "report.json").read_text())
    r10 = json.loads((tmp_path / "runs" / "ecp-250k" / "report.json").read_text())
    assert r5["max_compression_n"] != r10["max_compression_n"]  # a different step is a different run
