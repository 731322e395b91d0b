"""Chen 2023's Table 2 lives in the scenario files only: the three cases must carry the same one,
and scenario checks that guard its form."""
from __future__ import annotations

import pytest

from canbrake.scenario import ScenarioError, resolve

from chen_runs import CASES, chen_scenario


def _table2(case: int) -> dict:
    scn = chen_scenario(case, duration_s=1.0, profile="paper")
    t = scn.train.model_dump()
    table2 = {k: t[k] for k in ("vehicles", "track")}  # the rail conditions (train.wheel_rail) are the cases'
    table2["coupler"] = t["vehicle_types"]["metro_car"]["coupler"]
    return {"train": table2, "initial": scn.initial.model_dump(),
            "reference": scn.reference.model_dump(), "controller": scn.controller.model_dump(),
            "control_period_s": scn.control_period_s}


def test_the_three_cases_carry_the_same_table2():
    t1 = _table2(1)
    assert _table2(2) == t1 and _table2(3) == t1
    assert set(CASES) == {1, 2, 3}


def test_positions_in_the_other_order_than_the_spacing_are_an_error():
    # Table 2 lists the cars with car 6 in front (x_i - x_{i+1} = -10 m); vehicle types with a
    # length put car 1 in front (+10 m): that is a 20 m deflection
    scn = chen_scenario(1, duration_s=1.0)
    data = {"name": "t", "duration_s": 0.1, "initial": scn.initial.model_dump(), "reference": {
        "speed_kmh": 90, "decel_kmh_per_s": 3.5}, "controller": {"name": "pi"},
        "train": {"vehicle_types": {f"car{i + 1}": {"mass_kg": m, "length_m": 10.0}
                                    for i, m in enumerate(scn.consist.mass_kg)},
                  "vehicles": [{"type": f"car{i + 1}"} for i in range(scn.n_cars)]}}
    with pytest.raises(ScenarioError, match=r"t.yaml: initial.position_m: coupler 1 .* deflected by -20 m"):
        resolve(data, "t.yaml")
    # without lengths (Table 2's form) the initial positions space the cars
    data["train"]["vehicle_types"] = {"car": {}}
    data["train"]["vehicles"] = [{"type": "car", "mass_kg": list(scn.consist.mass_kg)}]
    assert resolve(data, "t.yaml").consist.coupler.spacing_m is None
