"""TrainPlant's period with brake equipment, compiled (EquippedKernel, issue 27): bit for bit what
main's Python sub-step loop gave on the plants of tests/equipped_cases.py (gears on a subset of
couplers, the pneumatic and ECP air brake, the route, the locomotive's limits, δ, eq. 40,
resistance tables, traction envelopes, end stops; blending, dump valves and wheelsets, rail
events, disturbances; a stack with a parked diverged row; a grade function; a diverging plant's
message), recorded in tests/data/equipped_ref.npz before the loop was replaced."""
from __future__ import annotations

import numpy as np
import pytest

import equipped_cases as E


def _bits(a: np.ndarray) -> np.ndarray:
    return np.ascontiguousarray(a, dtype=float).view(np.int64)


@pytest.fixture(scope="module")
def ref() -> dict[str, np.ndarray]:
    with np.load(E.REF) as z:
        return {k: z[k] for k in z.files}


@pytest.mark.parametrize("name", list(E.CASES))
def test_the_compiled_period_gives_the_python_loops_values_bit_for_bit(name: str, ref) -> None:
    got = E.run(name)
    want = {k.split("/", 1)[1]: v for k, v in ref.items() if k.startswith(name + "/")}
    assert sorted(got) == sorted(want)
    for key, w in want.items():
        g = got[key]
        assert g.shape == w.shape, key
        if w.dtype.kind == "U":  # the divergence message
            assert str(g[0]) == str(w[0])
            continue
        bad = np.flatnonzero((_bits(g) != _bits(w)).reshape(-1))
        assert bad.size == 0, f"{key}: {bad.size} values differ, first at {bad[0]}: {g.reshape(-1)[bad[0]]!r} != " \
                              f"{w.reshape(-1)[bad[0]]!r}"


def test_the_cases_cover_what_they_claim(ref) -> None:
    """The recorded runs do what the cases are for: the air brake applied, gears loaded on both
    sides, the valves vented, a stack row parked, a plant diverged."""
    assert ref["li_pneumatic/air_brake_n"].max() > 1e4 and ref["li_ecp/air_brake_n"].max() > 1e4
    assert ref["li_pneumatic/pipe_pa"].min() < 5e5
    for name in ("li_pneumatic", "li_ecp"):
        fs = ref[f"{name}/gear_force_state"]
        assert fs.max() > 1e4 and fs.min() < -1e4 or abs(fs).max() > 1e4
    assert np.nanmax(ref["equipped/wsp_valve"]) > 0.5 and np.nanmax(ref["equipped_stack/wsp_valve"]) > 0.5
    assert ref["equipped_stack/diverged_rows"][-1].tolist() == [0.0, 0.0, 1.0]
    assert "not finite" in str(ref["diverging/diverged_message"][0])
