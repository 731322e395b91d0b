"""The 1 + 105 ECP train with Chen's consensus controller in every ECU (scenarios/hh106_ecp_consensus.yaml):
the ECP unit's force-to-demand inversion, ``listens: neighbours``, the build's wrapping and a short
closed-loop run."""
from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from canbrake.builtin import find_builtin
from canbrake.physics.heavy_haul import KMH, ecp_fill_for_force, friction_coefficient
from canbrake.scenario import load_scenario

SCN = find_builtin("hh106_ecp_consensus")


def _force_n(fill: float, v_mps: float, k_full_kn: float, n_blocks: float, friction_coef: float, beta_c: float) -> float:
    """Eq. (10) with eqs. (11)-(12) written out with the module's numpy friction law (not the kernel)."""
    k = k_full_kn * fill
    return 1000.0 * beta_c * n_blocks * float(friction_coefficient(k, v_mps / KMH, friction_coef)) * k


@pytest.mark.parametrize("fill", [0.0, 0.01, 0.2, 0.5, 0.93, 1.0])
@pytest.mark.parametrize("v_kmh", [0.0, 3.0, 30.0, 60.0, 120.0])
def test_ecp_fill_inverts_the_brake_force_law(fill: float, v_kmh: float) -> None:
    scn = load_scenario(SCN)
    unit = scn.consist.ecp_unit_params(2)  # a C80 wagon
    f = _force_n(fill, v_kmh * KMH, **unit)
    assert ecp_fill_for_force(f, v_kmh * KMH, **unit) == pytest.approx(fill, abs=1e-9)
    # beyond full service: capped; traction or nothing: released
    assert ecp_fill_for_force(1.5 * _force_n(1.0, v_kmh * KMH, **unit) + 1.0, v_kmh * KMH, **unit) == 1.0
    assert ecp_fill_for_force(-1e4, v_kmh * KMH, **unit) == 0.0


def test_the_wagons_ecus_drive_their_cylinders_and_listen_to_their_neighbours() -> None:
    from canbrake.build import build_controller, ecu_specs
    from canbrake.control.chen import ChenConsensusController
    from canbrake.control.ecp import EcpUnit

    scn = load_scenario(SCN)
    specs = ecu_specs(scn)
    assert specs[0].listens == (2,) and specs[1].listens == (1, 3) and specs[-1].listens == (105,)
    assert specs[0].commands == ("brake_force_n",)  # the locomotive: its electric brake
    assert all(s.commands == ("ecp_demand",) for s in specs[1:])
    loco, wagon = build_controller(scn, 1), build_controller(scn, 2)
    assert isinstance(loco, ChenConsensusController) and isinstance(wagon, EcpUnit)
    # the locomotive-only profile keeps the plain ECP wagon (it commands ecp_demand itself)
    lo = load_scenario(SCN, profile="loco_only")
    assert not isinstance(build_controller(lo, 2), EcpUnit)


def test_consensus_over_ecp_brakes_the_train_along_its_curve(tmp_path: Path) -> None:
    """20 s of the stop in process: every wagon's demand within full service and released never
    below 0, the locomotive within 1 km/h of the braking curve, coupled vehicles within 1 km/h of
    each other, the train's mean deceleration that of the curve within 15 %."""
    import pandas as pd

    from canbrake.run import run_scenario

    scn = load_scenario(SCN, overrides={"duration_s": 20.0})
    s = run_scenario(scn, tmp_path, backend="inprocess", plots=False)
    assert s["status"] == "ok", s.get("message")
    df = pd.read_csv(tmp_path / "signals.csv")
    d = df[[f"cmd_ecp_demand_c{i}" for i in range(2, 107)]].to_numpy()[:-1]  # the last row: no command (NaN)
    assert np.all((d >= 0.0) & (d <= 1.0))
    assert d[-1].mean() > 0.3  # the wagons brake (not the locomotive alone)
    v = df[[f"speed_mps_c{i}" for i in range(1, 107)]].to_numpy()
    ref = df["ref_speed_mps"].to_numpy()
    assert np.max(np.abs(v[:, 0] - ref)) < 1.0 * KMH
    assert np.max(np.abs(np.diff(v, axis=1))) < 1.0 * KMH
    t = df["t_s"].to_numpy()
    a_mean = (v[0, 0] - v[-1, 0]) / (t[-1] - t[0])
    a_ref = float(scn.reference.decel_kmh_per_s) * KMH
    assert a_mean == pytest.approx(a_ref, rel=0.15)
    summary = json.loads((tmp_path / "summary.json").read_text())
    assert summary["frames"]["commands_missed"] == 0


def test_late_state_frames_reach_neighbours_in_the_same_period_on_every_driver(tmp_path: Path) -> None:
    """16 vehicles listening to their neighbours on a bus at ~86 % load (the CAN timing model): STATE
    frames become due after the decision point and are sent after their sender's STATE_DONE. Each
    must be used in the next period on every driver; before the receiving ECU held such a frame
    until it had decided, a peer still waiting for its other neighbour's STATE_DONE took it in the
    same period and one already past its barrier in the next, so one process per ECU gave different
    signals from run to run (and from the in-process engine)."""
    from canbrake.run import run_scenario

    ov = {"duration_s": 2.0, "train.vehicles": [{"type": "hxd1"}, {"type": "c80", "count": 15}],
          "train.disturbance.vehicles": [1], "bus.bitrate_bps": 80000,
          "ecus": [{"name": "loco", "vehicle": 1, "listens": "neighbours"},
                   {"name": "wagon{v}", "vehicles": "2-16", "listens": "neighbours"}]}
    out = {}
    for key, backend, per in (("inprocess", "inprocess", None), ("memory", "memory", 1), ("hosted", "memory", 4)):
        o = dict(ov) if per is None else {**ov, "ecu.per_process": per}
        s = run_scenario(load_scenario(SCN, overrides=o), tmp_path / key, backend=backend, plots=False)
        assert s["status"] == "ok", s.get("message")
        out[key] = ((tmp_path / key / "signals.csv").read_bytes(), (tmp_path / key / "frames.log").read_text())
    load = json.loads((tmp_path / "inprocess" / "summary.json").read_text())["bus_load"]["bus_load_mean"]
    assert load > 0.8  # the bus is loaded enough for late frames
    import re

    blank = lambda t: re.sub(r"canbrake-[A-Za-z0-9_-]+", "CH", t)  # noqa: E731 - the memory channel's name
    for key in ("memory", "hosted"):
        assert out[key][0] == out["inprocess"][0], key
        assert blank(out[key][1]) == blank(out["inprocess"][1]), key


def test_a_force_controller_on_a_pneumatic_wagon_is_refused() -> None:
    """A wagon takes no brake force of its own (no traction, no electric brake): with a pneumatic
    air brake a force-commanding wagon ECU would brake nothing; one line naming the ECU, exit 2
    (the CLI's scenario errors)."""
    from canbrake.scenario import ScenarioError

    with pytest.raises(ScenarioError, match=r"ecus: ECU wagon2 on wagon 2 runs chen2023, which commands a brake "
                                            r"force .*air_brake.mode: pneumatic") as e:
        load_scenario(SCN, overrides={"train.air_brake.mode": "pneumatic"})
    assert "\n" not in str(e.value)
    # the wagons' ECP ECUs of the locomotive-only case are fine on a pneumatic train (li2024_ecp_over_can's profile)
    load_scenario(SCN, profile="loco_only", overrides={"train.air_brake.mode": "pneumatic"})
