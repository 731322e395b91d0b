"""pytest plugin for testing your own controllers and trains with canbrake
(docs/testing-your-controller.md).

Installed with canbrake (entry point ``pytest11``), so its fixtures are available in any pytest
suite with nothing to import:

``canbrake_scenario(name_or_path, profile=None, **overrides)``
    load a scenario (a file, or a built-in by name) -> :class:`canbrake.scenario.Scenario`
``canbrake_run(scenario, bus="inprocess", **overrides)``
    run it in this process (``inprocess``: direct delivery; ``virtual``: python-can's virtual bus);
    fast and deterministic -> :class:`canbrake.api.RunResult`, in a fresh folder under ``tmp_path``
``canbrake_memory_run(scenario, **overrides)``
    the same on the in-memory CAN bus with one OS process per node (as ``canbrake run``); a
    controller must then live in an importable module, not in the test file
``canbrake_rogue(scenario, arbitration_id, data, rate_hz=1000, start_s=0, stop_s=inf)``
    the scenario with a rogue node that injects ``data`` as frame ``arbitration_id`` (python-can's
    and the bus's send path: deterministic on every bus) -> Scenario

and the assertion helpers below (also as the ``railway`` fixture), which fail with a message in
railway terms: which coupler or car, how much, when, against which limit.
"""
from __future__ import annotations

import itertools
import math
import re
from pathlib import Path
from typing import TYPE_CHECKING, Any, Callable

import pytest

if TYPE_CHECKING:  # canbrake itself is imported when a fixture is used, not when pytest starts
    from canbrake.api import RunResult
    from canbrake.scenario import Scenario


def load_scenario(*args: Any, **kwargs: Any) -> "Scenario":
    """canbrake.load_scenario (imported on first use)."""
    from canbrake.api import load_scenario as _load

    return _load(*args, **kwargs)


def run(*args: Any, **kwargs: Any) -> "RunResult":
    """canbrake.run (imported on first use)."""
    from canbrake.api import run as _run

    return _run(*args, **kwargs)

KMH = 3.6  # km/h per m/s

__all__ = ["assert_deflection_within", "assert_speed_band", "assert_stopping_distance",
           "assert_no_deadline_misses", "assert_e2e_rejections", "with_rogue"]


# ----------------------------------------------------------------------------- assertions
def _columns(df: Any, pattern: str) -> list[str]:
    rx = re.compile(pattern)
    return sorted((c for c in df.columns if rx.fullmatch(c)), key=lambda c: int(re.findall(r"\d+$", c)[0]))


def assert_deflection_within(result: RunResult, bound_m: float = 0.01, *, after_s: float = 0.0) -> None:
    """Every coupler's deflection |Δl| stays within ``bound_m`` (m) from ``after_s`` (s) on."""
    sig = result.signals
    sig = sig[sig.index >= after_s]
    worst: tuple[float, str, float] | None = None
    for col in _columns(sig, r"deflection_m_k\d+"):
        a = sig[col].abs()
        if not a.empty and (worst is None or a.max() > worst[0]):
            worst = (float(a.max()), col, float(a.idxmax()))
    if worst is not None and not worst[0] <= bound_m:  # NaN (a diverged run) fails too
        j = int(col_num(worst[1]))
        raise AssertionError(f"coupler {j}–{j + 1} deflected {worst[0] * 100:.3g} cm at t = {worst[2]:.3f} s, beyond "
                             f"the ±{bound_m * 100:g} cm bound (from t = {after_s:g} s)")


def col_num(col: str) -> int:
    """The car or coupler number at the end of a column name (``speed_mps_c3`` -> 3)."""
    return int(re.findall(r"\d+$", col)[0])


def assert_speed_band(result: RunResult, band_kmh: float = 0.5, *, after_s: float = 0.0,
                      cars: list[int] | None = None) -> None:
    """Every car (or the 1-based ``cars``) keeps |v − v*| within ``band_kmh`` (km/h) from ``after_s`` on."""
    sig = result.signals
    sig = sig[sig.index >= after_s]
    for col in _columns(sig, r"speed_mps_c\d+"):
        car = col_num(col)
        if cars is not None and car not in cars:
            continue
        err = (sig[col] - sig["ref_speed_mps"]) * KMH
        if err.empty:
            continue
        a = err.abs()
        if not a.max() <= band_kmh:
            t = float(a.idxmax())
            raise AssertionError(f"car {car} ran {err[t]:+.3g} km/h off the reference speed v* = "
                                 f"{sig['ref_speed_mps'][t] * KMH:.2f} km/h at t = {t:.3f} s, outside the "
                                 f"±{band_kmh:g} km/h band (from t = {after_s:g} s)")


def assert_stopping_distance(result: RunResult, max_m: float | None = None, *, tolerance_m: float = 1.0) -> None:
    """Each car stops within ``max_m`` (m) of where it started braking. Default limit: the
    reference's v0*²/(2a*) + ``tolerance_m``. A car still moving at the end of the run is judged by
    its predicted stopping distance: travelled + v²/(2a*), braking at a* from the last instant."""
    scn = result.scenario or load_scenario(result.run_dir / "scenario.yaml")
    a = float(scn.reference.decel_mps2)
    if not a > 0:
        raise ValueError("assert_stopping_distance: the scenario's reference does not decelerate (a* <= 0)")
    sig = result.signals
    v0 = float(sig["ref_speed_mps"].iloc[0])
    limit = v0 ** 2 / (2 * a) + tolerance_m if max_m is None else max_m
    for col in _columns(sig, r"position_m_c\d+"):
        car = col_num(col)
        x = sig[col]
        v = float(sig[f"speed_mps_c{car}"].iloc[-1])
        travelled = float(x.iloc[-1] - x.iloc[0])
        predicted = travelled + max(v, 0.0) ** 2 / (2 * a)
        if not predicted <= limit:
            how = "stopped after" if v < 0.01 else f"still at {v * KMH:.1f} km/h, would stop after"
            raise AssertionError(f"car {car} {how} {predicted:.2f} m, more than the allowed {limit:.2f} m "
                                 f"(reference v0*²/2a* = {v0 ** 2 / (2 * a):.2f} m at a* = {a:.3g} m/s²)")


def assert_no_deadline_misses(result: RunResult, allowed: int = 0) -> None:
    """At most ``allowed`` control periods in which a command or a peer value was late (realtime)."""
    d = result.summary.get("deadline_misses") or {}
    plant, ecus = int(d.get("plant") or 0), int(d.get("ecus") or 0)
    if plant + ecus > allowed:
        ticks = result.summary.get("ticks") or 0
        rate = f" ({plant / ticks:.1%} of {ticks} periods)" if ticks else ""
        raise AssertionError(f"{plant} plant deadline misses{rate} and {ecus} ECU deadline misses, more than the "
                             f"{allowed} allowed (max lateness {d.get('max_lateness_s', 0.0) * 1000:.3g} ms)")


def assert_e2e_rejections(result: RunResult, *, at_least: int | None = None, at_most: int | None = None) -> None:
    """The count of frames rejected by the E2E check (bad CRC: brake commands at the plant's brake
    units plus peer STATE frames at the ECUs) is within [``at_least``, ``at_most``]; with neither
    given, none may have been rejected."""
    f = result.summary.get("frames") or {}
    cmd, peer = int(f.get("commands_corrupted") or 0), int(f.get("peer_frames_corrupted") or 0)
    n = cmd + peer
    lo = at_least if at_least is not None else 0
    hi = at_most if at_most is not None else (math.inf if at_least is not None else 0)
    if not lo <= n <= hi:
        want = f"at least {lo}" if hi == math.inf else f"between {lo} and {hi}" if lo else f"at most {hi}"
        raise AssertionError(f"{n} frames failed the E2E check ({cmd} brake commands rejected by the brake units, "
                             f"{peer} peer STATE frames by the ECUs); expected {want}")


def with_rogue(scenario: "Scenario", arbitration_id: int, data: bytes, *, rate_hz: float = 1000.0,
               start_s: float = 0.0, stop_s: float | None = None, sender: str | None = None) -> "Scenario":
    """``scenario`` with a rogue device that sends frame ``arbitration_id`` with payload ``data``
    at ``rate_hz`` (Hz) in [``start_s``, ``stop_s``) s of simulated time: a ``babble`` impairment,
    deterministic on every bus. The frames enter the bus through the send path of ``sender``
    (default: the last car's ECU, ``ecu<n>``); a node never hears its own frames, so the rogue
    device must not sit on the node it attacks (a name that is no node is hosted by the plant)."""
    if sender is None:
        sender = f"ecu{scenario.n_cars}"
    spec: dict[str, Any] = {"type": "babble", "sender": sender, "arbitration_id": int(arbitration_id),
                            "rate_hz": float(rate_hz), "dlc": len(data), "data_hex": bytes(data).hex(),
                            "start_s": float(start_s)}
    if stop_s is not None:
        spec["stop_s"] = float(stop_s)
    imps = [i.model_dump(mode="json") if hasattr(i, "model_dump") else i for i in scenario.bus.impairments]
    return load_scenario(scenario, bus__impairments=imps + [spec])


class Railway:
    """The assertion helpers as one fixture: ``railway.deflection_within(r, 0.01)``, ..."""

    deflection_within = staticmethod(assert_deflection_within)
    speed_band = staticmethod(assert_speed_band)
    stopping_distance = staticmethod(assert_stopping_distance)
    no_deadline_misses = staticmethod(assert_no_deadline_misses)
    e2e_rejections = staticmethod(assert_e2e_rejections)


# ----------------------------------------------------------------------------- fixtures
@pytest.fixture
def canbrake_scenario() -> Callable[..., "Scenario"]:
    """``load(name_or_path, profile=None, **overrides) -> Scenario`` (see canbrake.load_scenario)."""
    return load_scenario


def _runner(tmp_path: Path, default_bus: str) -> Callable[..., RunResult]:
    counter = itertools.count(1)

    def _run(scenario: Any, bus: str = default_bus, plots: bool = False, **kwargs: Any) -> RunResult:
        out = kwargs.pop("out", None) or tmp_path / f"canbrake-run-{next(counter)}"
        return run(scenario, out=out, bus=bus, plots=plots, **kwargs)

    return _run


@pytest.fixture
def canbrake_run(tmp_path: Path) -> Callable[..., RunResult]:
    """``run(scenario, bus="inprocess", **overrides) -> RunResult``: all nodes in this process
    (``inprocess`` direct delivery or python-can ``virtual``); lockstep, deterministic."""
    return _runner(tmp_path, "inprocess")


@pytest.fixture
def canbrake_memory_run(tmp_path: Path) -> Callable[..., RunResult]:
    """``run(scenario, **overrides) -> RunResult`` on the in-memory CAN bus, one OS process per node."""
    return _runner(tmp_path, "memory")


@pytest.fixture
def canbrake_rogue() -> Callable[..., "Scenario"]:
    """``rogue(scenario, arbitration_id, data, rate_hz=1000, start_s=0, stop_s=None) -> Scenario``."""
    return with_rogue


@pytest.fixture
def railway() -> Railway:
    """Assertion helpers in railway terms (see :class:`Railway`)."""
    return Railway()
