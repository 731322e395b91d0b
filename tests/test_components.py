"""The component schema of ``train:`` (issue 27 items 1-2): registries, a user's component through
an entry point, the assembler's kernel choice and its one-line refusals, the moved keys, and every
shipped scenario loading in it."""
from __future__ import annotations

import subprocess
import sys
import textwrap
from pathlib import Path

import numpy as np
import pytest

from canbrake.consist import components as C
from canbrake.errors import ScenarioError
from canbrake.scenario import load_scenario

ROOT = Path(__file__).resolve().parents[1]
SCENARIOS = sorted((ROOT / "scenarios").glob("*.yaml"))


@pytest.mark.parametrize("path", SCENARIOS, ids=lambda p: p.stem)
def test_every_shipped_scenario_loads_with_every_profile(path: Path) -> None:
    scn = load_scenario(path)
    assert scn.train.kernel_name in C.KERNELS
    for prof in scn.profiles:
        assert load_scenario(path, profile=prof).n_cars >= 1


def test_kernel_follows_the_components() -> None:
    assert load_scenario("chen2023_case1_fine_rail").train.kernel_name == "coupled"
    assert load_scenario("li2024_pid").train.kernel_name == "coupled"  # one plant for every train (issue 27)
    cai = load_scenario("cai2014_case1")
    assert cai.train.kernel_name == "coupled" and cai.consist.rigid  # TrainPlant's rigid coupling


@pytest.mark.parametrize("kind", C.KINDS)
def test_unknown_model_lists_the_known_ones(kind: str) -> None:
    with pytest.raises(ScenarioError) as e:
        load_scenario("chen2023_case1_fine_rail", overrides={f"train.every_vehicle.{kind}": {"model": "no_such"}})
    msg = str(e.value)
    assert "\n" not in msg
    assert msg.startswith(f"--set train.every_vehicle.{kind}: unknown {kind} model 'no_such' (models: ")
    for name in C.available_components(kind):
        assert name in msg


def test_a_component_parameter_is_checked_by_its_schema() -> None:
    with pytest.raises(ScenarioError, match=r"--set train.every_vehicle.coupler.stiffness_n_per_m: "
                                            r"Input should be greater than 0"):
        load_scenario("chen2023_case1_fine_rail", overrides={"train.every_vehicle.coupler.stiffness_n_per_m": -1})
    with pytest.raises(ScenarioError, match=r"--set train.every_vehicle.brake.lag: unknown key"):
        load_scenario("chen2023_case1_fine_rail", overrides={"train.every_vehicle.brake.lag": 0.3})


def test_a_profile_overrides_a_component_for_every_vehicle() -> None:
    scn = load_scenario("chen2023_case1_fine_rail", profile="realistic")
    assert scn.consist.coupler.end_stop_m == 0.08
    assert scn.actuator.model == "realistic" and scn.actuator.lag_s == 0.3
    assert scn.consist.brakes.blending is not None
    emu = load_scenario("emu8_low_adhesion", profile="li_envelope")
    per_car = emu.consist.brakes.blending.per_car
    assert [None if c is None else c.model for c in per_car] == ["none", "envelope", "envelope", "none", "none",
                                                                  "envelope", "envelope", "none"]
    assert emu.consist.brakes.wsp.enabled


def test_per_car_masses_as_one_list() -> None:
    scn = load_scenario("chen2023_case1_fine_rail")
    np.testing.assert_array_equal(scn.vehicle_masses_kg(), [18000, 21000, 19500, 20000, 19700, 22000])
    with pytest.raises(ScenarioError, match=r"train.vehicles.0.count: 3, but mass_kg lists 6 vehicles"):
        load_scenario("chen2023_case1_fine_rail", overrides={"train.vehicles.0.count": 3})


def test_per_coupler_stiffness_with_one_type_per_car() -> None:
    kappas = [80000.0, 90000.0, 100000.0]
    data = {
        "name": "t", "duration_s": 1.0,
        "train": {"vehicle_types": {f"car{i}": {"mass_kg": 20000.0, "coupler": {"model": "chen", "stiffness_n_per_m": k}}
                                    for i, k in enumerate(kappas + [1.0])},
                  "vehicles": [{"type": f"car{i}"} for i in range(4)]},
        "initial": {"speed_kmh": 50}, "reference": {"speed_kmh": 50, "decel_kmh_per_s": 1.0},
    }
    from canbrake.scenario import resolve

    assert resolve(data, "t.yaml").consist.coupler.stiffness_n_per_m == kappas  # the last car's rear coupler: unused


class _Fake:
    """An entry point of a user's package (importlib.metadata.EntryPoint's interface)."""

    def __init__(self, name: str, obj: object, value: str = "userpkg:Quadratic") -> None:
        self.name, self._obj, self.value = name, obj, value

    def load(self) -> object:
        return self._obj


def test_a_users_component_from_an_entry_point(tmp_path: Path) -> None:
    """A resistance model of a user's package, found through ``canbrake.components.resistance`` in a
    real installed distribution: it runs on the coupled kernel (it gives Davis coefficients)."""
    pkg = tmp_path / "site"
    pkg.mkdir()
    (pkg / "userres.py").write_text(textwrap.dedent('''
        from pydantic import BaseModel, ConfigDict, Field

        class KnQuadratic(BaseModel):
            """c0 + c2 v^2 in kN (v in m/s)."""
            model_config = ConfigDict(extra="forbid")
            model: str = "kn_quadratic"
            c0_kn: float = Field(ge=0)
            c2_kn_s2_per_m2: float = Field(0.0, ge=0)

            def davis_n(self):
                return 1000.0 * self.c0_kn, 0.0, 1000.0 * self.c2_kn_s2_per_m2
    '''))
    dist = pkg / "userres-0.1.dist-info"
    dist.mkdir()
    (dist / "METADATA").write_text("Metadata-Version: 2.1\nName: userres\nVersion: 0.1\n")
    (dist / "entry_points.txt").write_text("[canbrake.components.resistance]\nkn_quadratic = userres:KnQuadratic\n")
    code = textwrap.dedent(f'''
        import sys
        sys.path.insert(0, {str(pkg)!r})
        from canbrake.consist.components import available_components
        from canbrake.errors import ScenarioError
        from canbrake.scenario import load_scenario
        assert "kn_quadratic" in available_components("resistance"), available_components("resistance")
        scn = load_scenario("chen2023_case1_fine_rail", overrides={{"train.every_vehicle.resistance":
                            {{"model": "kn_quadratic", "c0_kn": 0.5, "c2_kn_s2_per_m2": 0.002}}}})
        d = scn.consist.davis
        assert d.c0_n == [500.0] * 6 and d.c2_n_s2_per_m2 == [2.0] * 6, d
        try:
            load_scenario("chen2023_case1_fine_rail", overrides={{"train.every_vehicle.resistance":
                          {{"model": "kn_quadratic", "c0_kn": -1}}}})
        except ScenarioError as e:
            assert "train.every_vehicle.resistance.c0_kn: Input should be greater than or equal to 0" in str(e), e
        else:
            raise AssertionError("accepted")
        print("ok")
    ''')
    r = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, cwd=ROOT, timeout=120)
    assert r.returncode == 0 and r.stdout.strip() == "ok", r.stderr


def test_a_broken_entry_point_is_one_line(monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setattr(C, "_entry_points", lambda kind: [_Fake("bad_one", object())] if kind == "brake" else [])
    with pytest.raises(C.ComponentError, match=r"^brake model 'bad_one' \(entry point userpkg:Quadratic\) is not a "
                                               r"pydantic model class$"):
        C.component_class("brake", "bad_one")
    assert "bad_one" in C.available_components("brake")


def test_register_component_in_code() -> None:
    from pydantic import BaseModel

    @C.register_component("traction", "test_rating")
    class Rating(BaseModel):
        model: str = "test_rating"
        max_accel_mps2: float = 1.0

    try:
        assert C.component_class("traction", "test_rating") is Rating
        # registered, but no kernel takes it yet: one line naming the vehicle type and what each kernel takes
        with pytest.raises(ScenarioError) as e:
            load_scenario("chen2023_case1_fine_rail", overrides={"train.every_vehicle.traction": {"model": "test_rating"}})
        assert "\n" not in str(e.value)
        assert "no physics kernel implements this train yet: vehicle type metro_car has resistance=none, " \
               "coupler=chen, brake=ideal, traction=test_rating, wheels=none" in str(e.value)
    finally:
        C._REGISTRY["traction"].pop("test_rating")


def test_a_combination_no_kernel_implements_is_one_line() -> None:
    from pydantic import BaseModel

    @C.register_component("coupler", "test_spring")
    class Spring(BaseModel):
        model: str = "test_spring"
        stiffness_n_per_m: float = 1e6

    try:
        with pytest.raises(ScenarioError) as e:
            load_scenario("chen2023_case1_fine_rail", overrides={"train.every_vehicle.coupler": {"model": "test_spring"}})
    finally:
        C._REGISTRY["coupler"].pop("test_spring")
    msg = str(e.value)
    assert "\n" not in msg
    assert "train.vehicle_types.metro_car: no physics kernel implements this train yet: vehicle type metro_car has " \
           "resistance=none, coupler=test_spring, brake=ideal, traction=none, wheels=none" in msg
    assert "coupled (TrainPlant) takes coupler chen|draft_gear|linear|none|rigid, brake air|electro_pneumatic|ideal|none" \
        in msg
    assert "heavy_haul" not in msg and "HeavyHaulModel" not in msg  # one plant for every train (issue 27)
    assert "AdhesionTrain" not in msg  # one plant for the elastic and the rigid trains


def test_adhesion_limit_on_a_wagon_is_one_line() -> None:
    with pytest.raises(ScenarioError) as e:
        load_scenario("chen2023_case1_fine_rail",
                      overrides={"train.every_vehicle.wheels": {"model": "adhesion_limit", "mu": 0.3}})
    assert str(e.value) == ("--set train.every_vehicle.wheels: adhesion on vehicle type metro_car, which has no driven "
                            "axles (no traction: a wagon); give it a traction envelope or leave wheels out")


def test_rigid_and_elastic_couplers_do_not_mix_yet() -> None:
    with pytest.raises(ScenarioError, match=r"train.vehicle_types.c80.coupler: vehicle type c80 is "
                                            r"rigidly coupled and hxd1 has a draft_gear coupler: a train mixing rigid "
                                            r"and elastic couplers is not implemented yet"):
        load_scenario("li2024_pid", overrides={"train.vehicle_types.c80.coupler": {"model": "rigid"}})
    with pytest.raises(ScenarioError, match=r"train.vehicle_types.locomotive.wheels: driven axles \(Cai 2014, per-axle "
                                            r"torque commands\) run on a rigidly coupled train only yet"):
        load_scenario("cai2014_case1", overrides={"train.every_vehicle.coupler": {"model": "chen"}})
    with pytest.raises(ScenarioError, match=r"train.vehicle_types.carriage.brake: a rigidly coupled train "
                                            r"\(coupler: \{model: rigid\}\) takes mass, resistance and driven axles"):
        load_scenario("cai2014_case1", overrides={"train.vehicle_types.carriage.brake": {"model": "ideal"}})
    with pytest.raises(ScenarioError, match=r"events.0: a rigidly coupled train \(coupler: \{model: rigid\}\) takes "
                                            r"no events yet"):
        load_scenario("cai2014_case1", overrides={"events": [{"type": "rail", "start_s": 1.0, "brake_factor": 0.5}]})


def test_brake_pipe_without_a_locomotive() -> None:
    with pytest.raises(ScenarioError, match=r"train.vehicles.0.type: vehicle type c80 has an air brake, but nothing "
                                            r"feeds the brake pipe: the leading vehicle \(c80\) is not a locomotive "
                                            r"\(no traction\)"):
        load_scenario("li2024_pid", overrides={"train.vehicles": [{"type": "c80", "count": 10}],
                                               "train.disturbance.enabled": False})
    with pytest.raises(ScenarioError, match=r"train.air_brake: vehicle type hxd1 has an air brake, which needs the "
                                            r"train's brake pipe"):
        load_scenario("li2024_pid", overrides={"train.air_brake": None})


def test_adhesion_on_a_vehicle_without_axles() -> None:
    with pytest.raises(ScenarioError, match=r"train.vehicle_types.c80.wheels: adhesion on vehicle type c80, which has "
                                            r"no driven axles \(no traction: a wagon\)"):
        load_scenario("li2024_pid", overrides={"train.vehicle_types.c80.wheels": {"model": "adhesion_limit", "mu": 0.3}})
    with pytest.raises(ScenarioError, match=r"train.vehicle_types.metro_car.brake.wsp: wheel-slide protection needs "
                                            r"axles, and vehicle type metro_car has no wheels"):
        load_scenario("chen2023_case2_low_adhesion", profile="wsp",
                      overrides={"train.vehicle_types.metro_car.wheels": None})
    with pytest.raises(ScenarioError, match=r"ecus: ECU traction on vehicle 2 \(carriage\) runs cai2014 for 4 driven "
                                            r"axles, but vehicle 2 has no driven axles "
                                            r"\(train.vehicle_types.carriage.wheels\)"):
        load_scenario("cai2014_case1", overrides={"ecus.0.vehicle": 2})


def test_the_coupled_kernel_takes_brake_models_lags_and_functions_per_vehicle() -> None:
    """Brake models and lags may differ per vehicle (an ideal one is lag 0), and so may the brake
    functions (here easing on one vehicle type only: tests/test_per_vehicle_brakes.py)."""
    from canbrake.scenario import resolve

    data = {
        "name": "t", "duration_s": 1.0,
        "train": {"vehicle_types": {"a": {"mass_kg": 20000.0, "brake": {"model": "ideal"}},
                                    "b": {"mass_kg": 20000.0, "brake": {"model": "electro_pneumatic"}}},
                  "vehicles": [{"type": "a"}, {"type": "b"}]},
        "initial": {"speed_kmh": 50}, "reference": {"speed_kmh": 50, "decel_kmh_per_s": 1.0},
    }
    act = resolve(data, "t.yaml").actuator
    assert act.model == "realistic" and act.lag_s == [0.0, 0.3] and act.jerk_limit_mps3 == [None, 1.0]
    data["train"]["vehicle_types"]["b"]["brake"]["easing"] = {}
    cars = resolve(data, "t.yaml").consist.brakes.cars
    assert [c.vehicle_type for c in cars] == ["a", "b"] and cars[0].easing is None and cars[1].easing is not None


def test_heavy_haul_only_fields_on_another_train() -> None:
    with pytest.raises(ScenarioError, match=r"train.integration_step_s: used by draft-gear trains"):
        load_scenario("chen2023_case1_fine_rail", overrides={"train.integration_step_s": 0.001})


@pytest.mark.parametrize("key,value,where", [
    ("train.model", "coupled", "train.model: there are no train families any more"),
    ("train.mass_kg", [1.0, 2.0], "train.mass_kg: moved to train.vehicles"),
    ("train.coupler", {"end_stop_m": 0.08}, "train.coupler: moved to the coupler component"),
    ("train.davis", {"c0_n": 1.0}, "train.davis: moved to the resistance component"),
    ("train.grade_permille", 1.0, "train.grade_permille: moved to train.track.grade_permille"),
    ("train.brakes", {"wsp": {"enabled": True}}, "train.brakes: moved to the components"),
    ("train.route", {"file": "x.csv"}, "train.route: moved to train.track.route"),
    ("train.vehicle_types.metro_car.davis", {"c0_n": 1.0}, "train.vehicle_types.metro_car.davis: moved to resistance"),
    ("actuator", {"model": "realistic"}, "actuator: moved to train: each vehicle type's brake component"),
])
def test_old_keys_say_where_they_moved(key: str, value: object, where: str) -> None:
    with pytest.raises(ScenarioError) as e:
        load_scenario("chen2023_case1_fine_rail", overrides={key: value})
    assert "\n" not in str(e.value)
    assert where in str(e.value)


def test_old_keys_exit_2_on_the_command_line(tmp_path: Path) -> None:
    old = (ROOT / "scenarios" / "chen2023_case1_fine_rail.yaml").read_text().replace(
        "  track: {grade_permille: 0}\n", "  track: {grade_permille: 0}\n  model: coupled\n")
    p = tmp_path / "old.yaml"
    p.write_text(old)
    r = subprocess.run([sys.executable, "-m", "canbrake", "dbc", str(p), "-o", str(tmp_path / "x.dbc")], capture_output=True, text=True, cwd=ROOT,
                       timeout=120)
    assert r.returncode == 2, (r.stdout, r.stderr)
    assert "Traceback" not in r.stderr
    assert "train.model: there are no train families any more" in r.stderr + r.stdout


@pytest.mark.parametrize("key, value, says", [
    ("train.air_brake.cylinder_tau_s", "nan", "must be a finite number, got nan"),
    ("train.air_brake.cylinder_tau_s", True, "expected a number, got true"),
    ("train.draft_gears.MT-2.slack_mm", "inf", "must be a finite number, got inf"),
])
def test_nan_and_bools_in_every_part_of_the_train_are_named_as_such(key, value, says):
    """Every part of the schema (the components' sub-models too: the air brake, the draft gears)
    refuses NaN, infinity and a YAML bool as a number with that reason, not with its bound
    ("Input should be greater than 0" for a NaN)."""
    from canbrake.scenario import ScenarioError

    with pytest.raises(ScenarioError, match=f"--set {key}: {says}"):
        load_scenario("li2024_pid", overrides={key: value})


def test_a_linear_coupler_is_chens_with_epsilon_zero(tmp_path):
    """coupler: {model: linear} gives the signals of Chen's coupler with ε = 0, text for text; it
    takes no ε (a mistyped nonlinear coupler is refused, not silently linearised)."""
    import canbrake

    chen = canbrake.run("emu8_example", duration_s=0.5, bus="inprocess", out=tmp_path / "chen", plots=False)
    lin = canbrake.run("emu8_example", duration_s=0.5, bus="inprocess", out=tmp_path / "lin", plots=False,
                       train__every_vehicle__coupler={"model": "linear", "stiffness_n_per_m": 2.0e6, "end_stop_m": 0.08,
                                                      "end_stop_stiffness_n_per_m": 5.0e6, "end_stop_absorption": 0.5})
    assert (tmp_path / "lin" / "signals.csv").read_bytes() == (tmp_path / "chen" / "signals.csv").read_bytes()
    assert chen.summary["status"] == lin.summary["status"] == "ok"
    with pytest.raises(ScenarioError, match="epsilon_per_m2: unknown key"):
        load_scenario("emu8_example", overrides={"train.every_vehicle.coupler": {
            "model": "linear", "stiffness_n_per_m": 2.0e6, "epsilon_per_m2": -0.5}})


def test_a_bad_every_vehicle_override_is_one_line_naming_it():
    """train.every_vehicle is merged over every vehicle type; a bad value set there is reported once,
    against the --set that gave it (not once per vehicle type against the file), and an ed_brake's
    path has no discriminator tag in it."""
    for key, value, says in (("train.every_vehicle.brake.lag_s", -1, "Input should be greater than 0"),
                             ("train.every_vehicle.brake.blending.friction_lag_s", "nan",
                              "must be a finite number, got nan")):
        with pytest.raises(ScenarioError) as e:
            load_scenario("emu8_low_adhesion", overrides={key: value})
        assert str(e.value) == f"--set {key}: {says}"
    with pytest.raises(ScenarioError, match=r"train.vehicle_types.motor.brake.ed_brake.max_decel_mps2: Field required"):
        load_scenario("emu8_low_adhesion", overrides={"train.vehicle_types.motor.brake.ed_brake": {"model": "per_mass"}})


def test_canbrake_components_lists_every_model_with_its_parameters():
    r = subprocess.run([sys.executable, "-m", "canbrake", "components"], capture_output=True, text=True)
    assert r.returncode == 0, r.stderr
    for kind in C.KINDS:
        assert f"{kind}:\n" in r.stdout
        for name in C.available_components(kind):
            assert f"\n  {name}: " in r.stdout or f"\n  {name}\n" in r.stdout
    assert "stiffness_n_per_m*, end_stop_m=None" in r.stdout  # linear: κ required, the end stop optional
    bad = subprocess.run([sys.executable, "-m", "canbrake", "components", "brakes"], capture_output=True, text=True)
    assert bad.returncode == 2 and "Traceback" not in bad.stderr and "unknown component kind 'brakes'" in bad.stderr
