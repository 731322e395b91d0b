"""The batch engine (canbrake.batch, issue 13 item 3) against the per-point in-process node engine.

Equality is exact: the batch engine calls the same controller, plant and impairment objects with
the same values in the same order, so every float is the same and signals.csv (plant columns,
merged ECU diagnostics), the ECU traces, the metrics and the verdict are identical, text for text
and value for value. The only documented differences: the batch engine sees no frames, so the
summary has no bus statistics (``frames.on_bus``, ``bus_load``: the sweep rows' frames_on_bus /
bus_load_* columns are empty) and hence no ``overloaded`` finding (the paper profile's 1 ms period
needs about 140 % of a 1 Mbit/s bus: the per-point run says "overloaded" where the batch run says
"ok"); the comparison below leaves exactly those out and nothing else.
"""
from __future__ import annotations

import functools
import math
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from hypothesis import given, settings, strategies as st

from canbrake import sweep as sw
from canbrake.batch import run_batch, unsupported
from canbrake.build import bus_layout
from canbrake.bus.codec import FrameCodec
from canbrake.run import run_scenario
from canbrake.scenario import load_scenario

from conftest import CASE1

#: summary keys that need the frames on the bus (the recorder): not produced by the batch engine
BUS_ONLY_ROW = ("frames_on_bus", "frames_by_kind", "bus_load_", "wall_time_s", "real_time_factor")


def _points(profile: str, duration: float, specs: list[tuple[dict[str, Any], int, dict[str, Any]]]) -> list[Any]:
    """Resolved scenarios of sweep points: (axis values, seed, extra overrides)."""
    base = load_scenario(CASE1, profile=profile, overrides={"duration_s": duration})
    data = base.model_dump(mode="json")
    lay = bus_layout(base)
    out = []
    for params, seed, extra in specs:
        ov = {"duration_s": duration, **extra, **sw.point_overrides(data, params, lay), "seed": seed}
        out.append(load_scenario(CASE1, profile=profile, overrides=ov))
    return out


def _verdict_without_bus(summary: dict[str, Any]) -> tuple[str, list[str]]:
    kinds = [f["kind"] for f in summary.get("findings") or [] if f["kind"] != "overloaded"]
    v = summary["verdict"]
    if v == "overloaded":
        v = "ok" if not kinds else v
    return v, kinds


def _compare(batch_dir: Path, point_dir: Path, sb: dict[str, Any], sp: dict[str, Any]) -> list[str]:
    """Differences between a batch run and a per-point run (empty: equal)."""
    diffs = []
    a = (batch_dir / "signals.csv").read_text()
    b = (point_dir / "signals.csv").read_text()
    if a != b:
        la, lb = a.splitlines(), b.splitlines()
        first = next((i for i, (x, y) in enumerate(zip(la, lb)) if x != y), min(len(la), len(lb)))
        diffs.append(f"signals.csv differs from line {first + 1} ({len(la)} vs {len(lb)} lines)")
    if sb.get("metrics") != sp.get("metrics"):
        diffs.append(f"metrics differ: {sb.get('metrics')} vs {sp.get('metrics')}")
    if sb.get("status") != sp.get("status"):
        diffs.append(f"status {sb.get('status')} vs {sp.get('status')}")
    if _verdict_without_bus(sb) != _verdict_without_bus(sp):
        diffs.append(f"verdict {sb['verdict']} {sb.get('findings')} vs {sp['verdict']} {sp.get('findings')}")
    return diffs


def _run_both(tmp_path: Path, scns: list[Any]) -> tuple[list[dict[str, Any]], list[dict[str, Any]]]:
    sb = run_batch(scns, [tmp_path / f"batch{i}" for i in range(len(scns))])
    sp = [run_scenario(s, tmp_path / f"point{i}", backend="inprocess", plots=False) for i, s in enumerate(scns)]
    return sb, sp


# Paper profile, 1 ms: delays of 0, 2, 9 (beyond the brake unit's 7-period window: every command
# rejected) and 20 periods (past the 4-bit counter: frames dated 5 periods old), loss with
# several seeds, jitter; 60 ticks each (most points diverge within them, which is compared too).
PAPER = [({"delay": 0.0, "loss": 0.0}, 1, {}),
         ({"delay": 0.002, "loss": 0.0}, 1, {}),
         ({"delay": 0.009, "loss": 0.0}, 1, {}),
         ({"delay": 0.02, "loss": 0.0}, 1, {}),
         ({"delay": 0.0, "loss": 0.3}, 1, {}),
         ({"delay": 0.0, "loss": 0.3}, 2, {}),
         ({"delay": 0.005, "loss": 0.5}, 3, {}),
         ({"jitter": 0.003}, 4, {})]
# Realistic profile, 10 ms (brake functions, blending, a 0.3 s lag): converging runs over 1.5 s,
# and the other two controllers.
REALISTIC = [({"delay": 0.0, "loss": 0.0}, 1, {}),
             ({"delay": 0.03, "loss": 0.2}, 1, {}),
             ({"delay": 0.05, "loss": 0.5}, 2, {}),
             ({"delay": 0.02, "loss": 0.1}, 1, {"controller.name": "chen2023_compensated"}),
             ({"delay": 0.02, "loss": 0.1}, 1, {"controller": {"name": "pi", "params": {"kp": 2.0}}})]


@pytest.mark.slow
@pytest.mark.parametrize("profile,duration,specs", [("paper", 0.06, PAPER), ("realistic", 1.5, REALISTIC)],
                         ids=["paper", "realistic"])
def test_batch_equals_per_point_runs(tmp_path, profile, duration, specs):
    scns = _points(profile, duration, specs)
    assert all(unsupported(s, 0) is None for s in scns)
    sb, sp = _run_both(tmp_path, scns)
    for i, (params, seed, extra) in enumerate(specs):
        assert _compare(tmp_path / f"batch{i}", tmp_path / f"point{i}", sb[i], sp[i]) == [], (params, seed, extra)
    # the comparison sees something: runs that differ (the points differ) are told apart
    assert _compare(tmp_path / "batch0", tmp_path / "point1", sb[0], sp[1])


def test_a_perturbed_point_is_caught(tmp_path):
    """The equality check can fail: the batch runs one point with a delay one period longer."""
    specs = [({"delay": 0.03, "loss": 0.2}, 1, {})]
    good = _points("realistic", 1.0, specs)
    bad = _points("realistic", 1.0, [({"delay": 0.04, "loss": 0.2}, 1, {})])
    sb = run_batch(bad, [tmp_path / "batch0"])
    sp = [run_scenario(good[0], tmp_path / "point0", backend="inprocess", plots=False)]
    assert _compare(tmp_path / "batch0", tmp_path / "point0", sb[0], sp[0])


@pytest.mark.slow
def test_sweep_rows_equal_per_point_rows(tmp_path):
    """`canbrake sweep` with the batch engine (default) and with --engine points: the same rows
    except the bus statistics and wall times."""
    axes = [sw.parse_grid("delay=0,20ms"), sw.parse_grid("loss=0,0.3")]
    kw = dict(profile="realistic", duration_s=1.0, seeds=2, workers=0, plots=False, progress=False)
    logs: list[str] = []
    rb = sw.run_sweep(CASE1, axes, tmp_path / "b", log=logs.append, **kw).rows
    rp = sw.run_sweep(CASE1, axes, tmp_path / "p", engine="points", **kw).rows
    assert any("batch engine: 6 point(s) in 1 batch(es)" in m for m in logs), logs
    assert len(rb) == len(rp) == 6
    for a, b in zip(rb, rp):
        keys = {k for k in a.keys() | b.keys() if not k.startswith(BUS_ONLY_ROW)}
        assert {k: a.get(k) for k in keys} == {k: b.get(k) for k in keys}
    assert {r["safety"] for r in rb} == {r["safety"] for r in rp}


def test_sweep_falls_back_and_says_why(tmp_path):
    axes = [sw.parse_grid("delay=0,20ms")]
    logs: list[str] = []
    res = sw.run_sweep(CASE1, axes, tmp_path / "s", profile="realistic", duration_s=0.05, seeds=1, workers=0,
                       plots=False, progress=False, sets={"bus.timing": "model"}, log=logs.append)
    assert [m for m in logs if m.startswith("batch engine:")] == [
        "batch engine: not with the bus timing model (bus.timing: model); running 2 point(s) one by one"]
    assert [r["status"] for r in res.rows] == ["ok", "ok"]
    assert res.rows[0]["frames_on_bus"]  # per-point runs: the recorder's figures are there


def test_engine_batch_refuses_what_it_cannot_run(tmp_path, capsys):
    from canbrake.cli import main

    code = main(["sweep", str(CASE1), "--grid", "delay=0,20ms", "--duration", "0.02", "--seeds", "1",
                 "--workers", "0", "--out", str(tmp_path / "s"), "--no-plots", "-q", "--engine", "batch",
                 "--set", "bus.timing=model"])
    err = capsys.readouterr().err
    assert code == 2
    assert "--engine batch: the batch engine cannot run 2 point(s): not with the bus timing model" in err
    assert "Traceback" not in err


@pytest.mark.parametrize("overrides,reason", [
    ({"bus.timing": "model"}, "bus timing model"),
    ({"mode": "realtime"}, "realtime"),
    ({"safety.command_timeout_s": 0.1}, "fail-safe"),
    ({"controller": {"name": "li2024_pid", "params": {}}}, "controller(s) li2024_pid"),
])
def test_unsupported_configurations_are_named(overrides, reason):
    scn = load_scenario(CASE1, profile="realistic", overrides=overrides)
    why = unsupported(scn)
    assert why is not None and reason in why


def test_scenario_impairments_are_not_batched():
    scn = load_scenario(CASE1, profile="realistic",
                        overrides={"bus.impairments": [{"type": "delay", "delay_s": 0.01}]})
    assert unsupported(scn, 0) is None
    assert "own bus.impairments" in unsupported(scn, 1)


@functools.lru_cache(maxsize=1)
def _codec() -> FrameCodec:
    return FrameCodec(bus_layout(load_scenario(CASE1)).database())


@settings(max_examples=300, deadline=None)
@given(st.floats(allow_nan=True, allow_infinity=True, width=64), st.sampled_from(range(5)))
def test_quantiser_is_decode_of_encode(x, which):
    """The vectorised quantiser gives what an ECU decodes, for every signal the batch engine moves."""
    codec = _codec()
    msg, sig, name = [("SENSOR_C1", "Speed", "speed_mps"), ("SENSOR_C1", "Position", "position_m"),
                      ("STATE_C2", "Position", "position_m"), ("BRAKE_CMD_C3", "BrakeForce", "brake_force_n"),
                      ("REFERENCE", "RefDecel", "ref_decel_mps2")][which]
    mc = codec[msg]
    vals = {sig: x} if math.isfinite(x) else {}
    try:
        want = mc.decode(mc.encode(vals, counter=0, tick=0) if mc.protected else mc.encode(vals))[sig]
    except OverflowError:
        with pytest.raises(OverflowError):
            mc.quantiser(sig)(np.array([x]))
        return
    got = mc.quantiser(sig)(np.array([x]))[0]
    assert got == want and math.copysign(1.0, got) == math.copysign(1.0, want)


@pytest.mark.slow
def test_paper_points_run_vectorised_and_equal_per_point_runs_over_half_a_second(tmp_path):
    """Chen's paper profile (the default sweep's): every ECU slot runs the controller's batch form
    (ChenConsensusController.step_batch) and the plants run as one stack (stack_plants), and each
    point still equals its per-point run over 500 ticks (spacing latch, loss, delay, jitter)."""
    from canbrake.batch import BatchEngine

    specs = [({"delay": 0.0, "loss": 0.0}, 1, {}), ({"delay": 0.0, "loss": 0.05}, 5, {}),
             ({"jitter": 0.0004}, 2, {})]
    scns = _points("paper", 0.5, specs)
    eng = BatchEngine(scns, [None] * len(scns))
    assert eng.stack is not None and all(c is not None for c in eng.batch_ctrl)
    assert eng.grouped == set(range(eng.n_ecus)) and len(eng.slot_groups) == 1  # one call per tick
    sb, sp = _run_both(tmp_path, scns)
    for i, spec in enumerate(specs):
        assert _compare(tmp_path / f"batch{i}", tmp_path / f"point{i}", sb[i], sp[i]) == [], spec


def test_batches_hold_at_most_their_memory_budget(tmp_path):
    """Long points make smaller batches: a batch keeps its points' traces until they end, so
    plan_batches caps it at BATCH_MEMORY_BYTES (10 s points of Chen case 1: the full 64)."""
    from canbrake.batch import point_bytes

    axes = [sw.parse_grid("delay=0:20ms:9"), sw.parse_grid("loss=0:0.2:9")]
    caps = {}
    for dur in (10.0, 120.0):
        plan = sw.plan_sweep(CASE1, axes, tmp_path / f"p{dur:g}", duration_s=dur, seeds=1)
        batches, single, _ = sw.plan_batches(plan.tasks, 1)
        assert not single and sum(map(len, batches)) == 81
        caps[dur] = sw.BATCH_MEMORY_BYTES // point_bytes(plan.base.model_copy(update={"duration_s": dur}))
        assert max(map(len, batches)) <= min(sw.BATCH_MAX_POINTS, caps[dur])
        if dur == 120.0:
            assert len(batches) >= 81 / caps[dur]
    assert caps[10.0] >= sw.BATCH_MAX_POINTS > caps[120.0] * 8


def test_points_with_different_controllers_batch_apart(tmp_path):
    """A grid over the controller makes one batch per controller, so each ECU slot of a batch runs
    one controller (chen2023's batch form for all its points at once)."""
    axes = [sw.parse_grid("delay=0,1ms"), sw.parse_grid("set:controller.name=chen2023,chen2023_compensated")]
    plan = sw.plan_sweep(CASE1, axes, tmp_path / "p", duration_s=0.01, seeds=1)
    batches, single, _ = sw.plan_batches(plan.tasks, 1)
    assert not single and len(batches) == 2
    names = sorted(tuple(sorted({t.scenario["controller"]["name"] for t in b})) for b in batches)
    assert names == [("chen2023",), ("chen2023_compensated",)]


@pytest.mark.slow
@pytest.mark.parametrize("profile,duration,extra", [
    ("realistic", 1.5, {"controller.name": "chen2023_compensated"}),
    ("paper", 0.3, {"controller.name": "chen2023_compensated"}),
    ("realistic", 1.5, {"controller": {"name": "pi", "params": {"kp": 2.0, "ki": 0.5}}}),
], ids=["compensated-realistic", "compensated-paper", "pi-realistic"])
def test_other_controllers_run_their_batch_forms_and_equal_per_point_runs(tmp_path, profile, duration, extra):
    """Points that all run chen2023_compensated (or pi) step each ECU slot with the controller's
    batch form, and still equal their per-point runs: delays past the counter's window, loss."""
    from canbrake.batch import BatchEngine

    specs = [({"delay": 0.0, "loss": 0.0}, 1, extra), ({"delay": 0.02, "loss": 0.2}, 3, extra),
             ({"delay": 0.004, "loss": 0.5}, 2, extra)]
    scns = _points(profile, duration, specs)
    assert all(c is not None for c in BatchEngine(scns, [None] * len(scns)).batch_ctrl)
    sb, sp = _run_both(tmp_path, scns)
    for i, spec in enumerate(specs):
        assert _compare(tmp_path / f"batch{i}", tmp_path / f"point{i}", sb[i], sp[i]) == [], spec
