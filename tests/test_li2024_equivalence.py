"""Transition check (issue 10): the heavy-haul PlantModel built from the scenario data and the
engine controllers give the same numbers as the closed loop of canbrake.li2024_sim they replace.
Removed together with li2024_sim once the scenarios run through the node engine."""
from __future__ import annotations

from pathlib import Path
from types import SimpleNamespace

import numpy as np
import pytest
import yaml

from canbrake.consist.heavy_haul import HeavyHaulTrain
from canbrake.control.base import Observation, make_controller
from canbrake.li2024_sim import HeavyHaulPlant, Reference, driver_reference, simulate

ROOT = Path(__file__).resolve().parents[1]
TRAIN = ROOT / "tests" / "data" / "li2024_train.yaml"


#: what build_plant takes from the scenario
SCN = SimpleNamespace(initial=SimpleNamespace(speed_kmh=50.0, position_m=None))


def _plant_time(k: int) -> float:
    """The plant's clock after k steps of 10 ms (accumulated, as both plants keep it)."""
    t = 0.0
    for _ in range(k):
        t += 0.01
    return t


def _train(**over) -> HeavyHaulTrain:
    d = yaml.safe_load(TRAIN.read_text())["train"]
    d.update(over)
    return HeavyHaulTrain.model_validate(d)


def _loop(name: str, params: dict, n: int, train: HeavyHaulTrain, ref: Reference | None = None):
    m = train.build_plant(SCN, ROOT / "scenarios")
    ctl = make_controller(name, params, car_index=0, n_cars=1, mass_kg=float(m.mass_kg[0]), dt_s=0.01)
    nan = np.full(m.n_vehicles, np.nan)
    v = []
    for k in range(n):
        me = m.measurements()
        sens = {s: float(me[s][0]) for s in ctl.sensor_names}
        rk = {} if ref is None else dict(ref_speed_mps=float(ref.v_mps[k]), ref_decel_mps2=-float(ref.a_mps2[k]),
                                         ref_position_m=float(ref.x_m[k]))
        obs = Observation(tick=k, time_s=m.t, speed_mps=sens["speed_mps"], position_m=sens["position_m"],
                          ref_speed_mps=rk.pop("ref_speed_mps", 0.0), ref_decel_mps2=rk.pop("ref_decel_mps2", 0.0),
                          peer_speed_mps=np.zeros(1), peer_position_m=np.zeros(1), peer_age_s=np.zeros(1),
                          sensors=sens, **rk)
        out = ctl.step(obs)
        v.append(me["speed_mps"][0])
        cmd = {"brake_force_n": nan.copy(), "airbrake_apply": nan.copy()}
        cmd["brake_force_n"][0] = out.brake_force_n
        cmd["airbrake_apply"][0] = out.commands["airbrake_apply"]
        m.step(0.01, cmd)
    return np.array(v), m


def test_plant_model_reproduces_heavy_haul_plant():
    sched = [(_plant_time(100), True), (_plant_time(1200), False)]
    old = HeavyHaulPlant(uncertainty=0.01, disturbance=True, airbrake_schedule=sched, x0_m=17000.0)
    new = _train(uncertainty=0.01, start_position_m=17000.0,
                 disturbance={"enabled": True, "vehicles": [1] + list(range(11, 102, 10))}).build_plant(SCN, ROOT / "scenarios")
    state = 0.0
    for k in range(2000):
        t = k * 0.01
        if k not in (100, 1200):  # the ECU sees the brake before its own command of the tick
            assert new.measurements()["passive_force_n"][0] / new.mass_kg[0] == pytest.approx(old.loco_f_nominal(), rel=1e-12)
        state = next((float(a) for ts, a in sched if abs(ts - t) < 1e-9), state)
        u = 2e5 * np.sin(t / 5)
        old.step(u)
        new.step(0.01, {"brake_force_n": np.r_[-u, np.full(105, np.nan)], "airbrake_apply": np.r_[state, np.full(105, np.nan)]})
    assert np.array_equal(old.v, new.v) and np.array_equal(old.x, new.x) and np.array_equal(old.fc, new.fc)
    assert np.array_equal(old.ab.fill, new.ab.fill) and new.ab.fill[-1] > 0


def test_driver_controller_reproduces_driver_reference():
    ref, raw = driver_reference(duration_s=10.0)
    v, _ = _loop("li2024_driver", {}, ref.t_s.size, _train(uncertainty=0.0))
    assert np.array_equal(v, raw["v_mps"])


@pytest.mark.parametrize("old_name, new_name", [("pid", "li2024_pid"), ("smc", "li2024_smc"),
                                                ("rbfnn-smc+ndo", "li2024_rbfnn_smc_ndo")])
def test_tracking_controllers_reproduce_simulate(old_name, new_name):
    ref, _ = driver_reference(duration_s=10.0)
    ref.airbrake_events[:] = [(_plant_time(200), True), (_plant_time(600), False)]
    r = simulate(old_name, ref, record_every_s=0.01)
    v, m = _loop(new_name, {"airbrake_schedule": [[t, int(a)] for t, a in ref.airbrake_events]}, ref.t_s.size,
                 _train(), ref)
    if old_name == "pid":
        assert np.array_equal(v, r["v_mps"])
    else:
        # the model term sees the air brake before the ECU's own command of the tick: for one tick it
        # misses the locomotive's first fill increment, ~77 N, i.e. 77 N * 10 ms / 184 t = 4.2e-6 m/s
        assert np.max(np.abs(v - r["v_mps"])) < 1e-5
        assert np.array_equal(v[:200], r["v_mps"][:200])
    assert m.ab.fill[-1] > 0
