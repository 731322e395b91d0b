"""Parameter sweeps: a grid of impairments (and any scenario field) × seeds, run point by point with
the in-process lockstep engine, collected into ``results.csv`` and drawn as heatmaps.

Grid axes (``--grid NAME=SPEC``), SPEC is ``start:stop[unit]:count`` (``count`` evenly spaced
values, both ends included; a unit on ``stop`` applies to ``start`` as well, or each may carry its
own) or a comma list ``v1,v2,...``:

=================  =========================================================================
``delay``          fixed extra latency (``delay`` impairment) on every ECU's STATE_Ci frames
                   (0x141..) and BRAKE_CMD_Ci frames (0x081..); s, ms, us
``loss``           Bernoulli loss (``loss`` impairment) on the same frames; probability or %
``jitter``         uniform random extra latency in [0, value] on the same frames; s, ms, us
``state_delay``, ``state_loss``, ``state_jitter``, ``cmd_delay``, ``cmd_loss``, ``cmd_jitter``
                   the same on the STATE frames only / the BRAKE_CMD frames only
``bitrate``        ``bus.bitrate_bps``; bit/s, or kbps
``period``         ``control_period_s``; s, ms, us
``set:A.B.C``      any scenario field by dotted path, values parsed as YAML
                   (e.g. ``set:controller.name=chen2023,chen2023_compensated``)
=================  =========================================================================

A value of 0 adds no impairment, so a point at delay 0, loss 0 is exactly the plain run. The
impairments are appended after the scenario's own, in the order loss, jitter, delay.

Seeds: a point whose outcome depends on random draws (loss or jitter > 0 on an axis, or a
random impairment in the scenario itself) is run with ``seeds`` seeds, ``scenario.seed + s``
for s = 0..seeds−1; other points once, with the scenario's seed.

Each run goes into ``OUT/points/<point id>/`` (``run_scenario(..., backend="inprocess",
plots=False)``); by default only ``summary.json``, ``scenario.yaml`` and the ``*_stats.json`` are
kept (``keep="all"`` keeps the traces). The point id is readable (axis values, seed) plus a hash of
the fully resolved scenario, so a point is only reused for exactly the same run. Resume: a point is
skipped if ``results.csv`` already has its row with a final status (``ok``, ``diverged``,
``invalid``) or its ``summary.json`` says ``ok``. The id does not cover canbrake's own code: after
changing a controller, sweep into a new directory. The classification below is reapplied to
reused rows, so changing a threshold only needs a rerun of the same command.

Classification of a run (columns of results.csv, and the safety map):

* ``deflection_violation``: max |coupler deflection| > 1 cm (``DEFLECTION_BOUND_M``, Chen's θ);
* ``tracking_degraded``: the speeds never settle within ±0.5 km/h of v* until the end of the run
  (no convergence), or the RMSE after convergence exceeds 0.5 km/h (``TRACKING_RMSE_KMH``);
* ``unstable``: the plant diverged (``PlantDiverged``: a softening coupler pulled past its peak),
  or max |deflection| ≥ 0.8 m (``UNSTABLE_DEFLECTION_M``; the coupler force peaks at 0.816 m), or the
  worst car's speed error at the end of the run is ≥ 2 km/h (``UNSTABLE_SPEED_ERROR_KMH``, four
  times the band: the loop does not bring the train back to the reference);
* ``safety``: the worst of ``ok`` < ``degraded`` < ``violation`` < ``unstable``.

Engine (``engine``): by default the points the batch engine supports (:mod:`canbrake.batch`: the
coupled kernel (Chen couplers) with chen2023 / chen2023_compensated / pi and delay/loss/jitter axes, lockstep,
ideal timing) run many at once in one process, equal to their per-point runs (signals, metrics,
verdict; no frames.log or bus statistics); the others run one by one, and a line says why.
``engine="batch"`` insists on the batch engine (an error names what it cannot run);
``engine="points"`` runs every point by itself.

Execution: serially in this process (``workers=0`` or ``scheduler="none"``), on a local Dask
cluster of ``workers`` single-threaded worker processes bound to 127.0.0.1 (default), or on an
existing Dask cluster (``scheduler="tcp://host:8786"``; its workers need canbrake installed and
must see ``OUT`` at the same path to keep the point directories — the rows come back to this
process either way).
"""
from __future__ import annotations

import csv
import hashlib
import io
import itertools
import json
import math
import os
import re
import signal
import sys
import threading
import time
import warnings
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Callable, Iterable, Sequence

import numpy as np
import yaml

from canbrake.bus import dbc
from canbrake.scenario import Scenario, ScenarioError, load_scenario, load_yaml, resolve

#: Chen's safety bound on |coupler deflection| (m)
DEFLECTION_BOUND_M = 0.01
#: speed RMSE after convergence beyond which tracking counts as degraded (km/h)
TRACKING_RMSE_KMH = 0.5
#: |deflection| at which the loop counts as unstable (m): about where the Table 2 coupler's force
#: peaks (1/sqrt(-3ε) = 0.816 m for ε = -0.5); beyond it the coupler no longer pulls the cars back
UNSTABLE_DEFLECTION_M = 0.8
#: worst |speed error| at the end of the run at which the loop counts as unstable (km/h)
UNSTABLE_SPEED_ERROR_KMH = 2.0
#: default number of control periods simulated per point (capped by the scenario's duration_s)
DEFAULT_TICKS = 1000

SAFETY_LEVELS = ("ok", "degraded", "violation", "unstable")
#: statuses of a finished point (not retried on resume)
FINAL_STATUSES = ("ok", "diverged", "invalid")
#: impairment types whose effect depends on random draws
RANDOM_IMPAIRMENTS = ("jitter", "loss", "gilbert_elliott", "duplicate", "reorder", "corrupt", "bit_error_rate",
                      "faulty_transceiver")

_UNITS: dict[str, float] = {"s": 1.0, "ms": 1e-3, "us": 1e-6, "%": 0.01, "bps": 1.0, "kbps": 1e3}


class GridError(ValueError):
    """A bad ``--grid`` specification; the message says what is wrong and shows the syntax."""


@dataclass(frozen=True)
class AxisKind:
    """What a grid axis name means: its SI unit, accepted units and value range."""

    column: str                  # results.csv column (SI)
    units: tuple[str, ...]       # accepted unit suffixes ("" = the SI unit itself)
    si: str                      # SI unit shown when no unit was typed
    lo: float = 0.0
    hi: float = math.inf
    integer: bool = False


_TIME = ("", "s", "ms", "us")
AXIS_KINDS: dict[str, AxisKind] = {
    "delay": AxisKind("delay_s", _TIME, "s"),
    "jitter": AxisKind("jitter_s", _TIME, "s"),
    "loss": AxisKind("loss", ("", "%"), "", 0.0, 1.0),
    "state_delay": AxisKind("state_delay_s", _TIME, "s"),
    "state_jitter": AxisKind("state_jitter_s", _TIME, "s"),
    "state_loss": AxisKind("state_loss", ("", "%"), "", 0.0, 1.0),
    "cmd_delay": AxisKind("cmd_delay_s", _TIME, "s"),
    "cmd_jitter": AxisKind("cmd_jitter_s", _TIME, "s"),
    "cmd_loss": AxisKind("cmd_loss", ("", "%"), "", 0.0, 1.0),
    "bitrate": AxisKind("bitrate_bps", ("", "bps", "kbps"), "bps", 1.0, 1e6, integer=True),
    "period": AxisKind("period_s", _TIME, "s", 1e-6, 1.0),
}
_SYNTAX = ("expected NAME=START:STOP[UNIT]:COUNT or NAME=V1,V2,..., e.g. delay=0:50ms:11, "
           "loss=0:0.5:11, loss=0:50%:11, set:controller.params.k=10,20,36")


@dataclass(frozen=True)
class Axis:
    """One grid axis: ``values`` in SI (or as parsed YAML for ``set:`` axes)."""

    name: str                    # "delay", "loss", ..., or "set:controller.params.k"
    values: tuple[Any, ...]
    unit: str = ""               # unit the user typed (for labels), "" = SI / none

    @property
    def is_set(self) -> bool:
        return self.name.startswith("set:")

    @property
    def path(self) -> str:
        """Dotted scenario path of a ``set:`` axis."""
        return self.name[4:]

    @property
    def column(self) -> str:
        return self.path if self.is_set else AXIS_KINDS[self.name].column

    def label(self) -> str:
        """Axis label for plots, in the unit the user typed."""
        if self.is_set:
            return self.path
        kind = AXIS_KINDS[self.name]
        unit = self.unit or kind.si
        return f"{self.name} ({unit})" if unit else self.name

    def display(self, value: Any) -> str:
        """``value`` in the typed unit, short (for tick labels and point ids)."""
        if self.is_set or not isinstance(value, (int, float)):
            return str(value)
        scale = _UNITS.get(self.unit, 1.0)
        return f"{value / scale:.6g}"


def _number(text: str, axis: str, spec: str) -> tuple[float, str]:
    m = re.fullmatch(r"\s*([-+]?(?:\d+\.?\d*|\.\d+)(?:[eE][-+]?\d+)?)\s*([a-zA-Z%]*)\s*", text)
    if not m:
        raise GridError(f"--grid {spec!r}: {text!r} is not a number (with an optional unit); {_SYNTAX}")
    return float(m.group(1)), m.group(2)


def parse_grid(spec: str) -> Axis:
    """Parse one ``--grid`` argument into an :class:`Axis` (values in SI)."""
    if "=" not in spec:
        raise GridError(f"--grid {spec!r}: missing '='; {_SYNTAX}")
    name, body = (s.strip() for s in spec.split("=", 1))
    if not body:
        raise GridError(f"--grid {spec!r}: no values after '='; {_SYNTAX}")
    if name.startswith("set:"):
        path = name[4:]
        if not re.fullmatch(r"[A-Za-z0-9_]+(\.[A-Za-z0-9_]+)*", path):
            raise GridError(f"--grid {spec!r}: {path!r} is not a dotted scenario path "
                            f"(e.g. set:controller.params.k=10,20)")
        if ":" in body and "," not in body:
            return _parse_range(name, body, spec, AxisKind(path, ("",), "", -math.inf, math.inf))
        try:
            values = tuple(load_yaml(v) for v in body.split(","))
        except yaml.YAMLError:
            raise GridError(f"--grid {spec!r}: a value is not valid YAML") from None
        if any(isinstance(v, (dict, list)) for v in values) or "" in [v.strip() for v in body.split(",")]:
            raise GridError(f"--grid {spec!r}: values must be plain scalars separated by commas")
        if len(set(map(str, values))) != len(values):
            raise GridError(f"--grid {spec!r}: repeated values")
        return Axis(name, values)
    if name not in AXIS_KINDS:
        raise GridError(f"--grid {spec!r}: unknown axis {name!r} (known: {', '.join(AXIS_KINDS)}, "
                        f"or set:DOTTED.PATH)")
    kind = AXIS_KINDS[name]
    if ":" in body:
        return _parse_range(name, body, spec, kind)
    parsed = [_number(item, name, spec) for item in body.split(",")]
    units = {u for _, u in parsed if u}
    if len(units) > 1:
        raise GridError(f"--grid {spec!r}: values in different units ({', '.join(sorted(units))}); use one")
    unit = units.pop() if units else ""
    values = tuple(float(f"{_to_si(v, unit, name, kind, spec):.12g}") for v, _ in parsed)
    if len(set(values)) != len(values):
        raise GridError(f"--grid {spec!r}: repeated values")
    return Axis(name, values, unit)


def _to_si(value: float, unit: str, name: str, kind: AxisKind, spec: str) -> float:
    if unit not in kind.units:
        ok = ", ".join(u for u in kind.units if u) or "none"
        raise GridError(f"--grid {spec!r}: unit {unit!r} does not fit axis {name!r} (units: {ok})")
    si = value * _UNITS.get(unit, 1.0)
    if kind.units == _TIME and unit == "" and si > 1.0:
        raise GridError(f"--grid {spec!r}: {value:g} s is more than a second; did you mean {value:g}ms?")
    if not kind.lo <= si <= kind.hi:
        lo = kind.lo / _UNITS.get(unit, 1.0)
        hi = kind.hi / _UNITS.get(unit, 1.0)
        raise GridError(f"--grid {spec!r}: {name} must be between {lo:g} and {hi:g}{unit}, got {value:g}{unit}")
    if kind.integer:
        si = float(round(si))
    return si


def _parse_range(name: str, body: str, spec: str, kind: AxisKind) -> Axis:
    parts = body.split(":")
    if len(parts) != 3:
        raise GridError(f"--grid {spec!r}: a range has three parts START:STOP:COUNT; {_SYNTAX}")
    start, u0 = _number(parts[0], name, spec)
    stop, u1 = _number(parts[1], name, spec)
    try:
        count = int(parts[2])
    except ValueError:
        raise GridError(f"--grid {spec!r}: COUNT {parts[2]!r} is not a whole number; {_SYNTAX}") from None
    if count < 1:
        raise GridError(f"--grid {spec!r}: COUNT must be at least 1, got {count}")
    if u0 and u1 and u0 != u1:
        raise GridError(f"--grid {spec!r}: START and STOP have different units ({u0!r}, {u1!r})")
    unit = u1 or u0
    if count == 1 and start != stop:
        raise GridError(f"--grid {spec!r}: COUNT 1 needs START == STOP (or give a list)")
    if count > 1 and stop <= start:
        raise GridError(f"--grid {spec!r}: STOP must be greater than START")
    raw = np.linspace(start, stop, count) if count > 1 else np.array([start])
    if name.startswith("set:"):
        if unit:
            raise GridError(f"--grid {spec!r}: set: axes take plain numbers (SI, as in the scenario)")
        return Axis(name, tuple(float(f"{v:.12g}") for v in raw))
    _to_si(stop, unit, name, kind, spec)  # the ends first: errors name the values typed
    _to_si(start, unit, name, kind, spec)
    values = tuple(float(f"{_to_si(float(v), unit, name, kind, spec):.12g}") for v in raw)
    if len(set(values)) != len(values):
        raise GridError(f"--grid {spec!r}: repeated values after rounding")
    return Axis(name, values, unit)


def check_axes(axes: Sequence[Axis]) -> None:
    """No axis twice, and no two axes that set the same thing."""
    names = [a.name for a in axes]
    dup = sorted({n for n in names if names.count(n) > 1})
    if dup:
        raise GridError(f"--grid: axis {dup[0]!r} given twice")
    for a in axes:
        for b in axes:
            if a is not b and a.name in ("delay", "loss", "jitter") and b.name in (f"state_{a.name}", f"cmd_{a.name}"):
                raise GridError(f"--grid: {a.name!r} already acts on STATE and BRAKE_CMD frames; "
                                f"do not combine it with {b.name!r}")


# ----------------------------------------------------------------------------- overrides
def frame_ids(layout: Any, which: str) -> list[int]:
    """Arbitration ids the impairment axes act on: "state", "cmd" or "both" (``layout``: the
    run's :class:`~canbrake.bus.dbc.BusLayout`, or a number of cars for Chen's placement)."""
    if isinstance(layout, int):
        layout = dbc.BusLayout(dbc.default_ecus(layout, coupler_sensors=True))
    state, cmd = layout.ids("state"), layout.ids("cmd")
    return {"state": state, "cmd": cmd, "both": state + cmd}[which]


def impairments_for(params: dict[str, Any], n_cars: Any) -> list[dict[str, Any]]:
    """Impairment specs (dicts for ``bus.impairments``) for the impairment axes in ``params``
    (axis name -> SI value); order: loss, jitter, delay; a value of 0 adds nothing."""
    out: list[dict[str, Any]] = []
    for kind in ("loss", "jitter", "delay"):
        for prefix, which in (("", "both"), ("state_", "state"), ("cmd_", "cmd")):
            v = params.get(prefix + kind)
            if v is None or v == 0:
                continue
            ids = frame_ids(n_cars, which)
            if kind == "loss":
                out.append({"type": "loss", "probability": float(v), "ids": ids})
            elif kind == "jitter":
                out.append({"type": "jitter", "distribution": "uniform", "low_s": 0.0, "high_s": float(v), "ids": ids})
            else:
                out.append({"type": "delay", "delay_s": float(v), "ids": ids})
    return out


def point_overrides(base: dict[str, Any], params: dict[str, Any], n_cars: Any) -> dict[str, Any]:
    """Dotted-path overrides of one grid point (``params``: axis name -> value).

    ``base`` is the scenario mapping after profile and ``--set`` (its ``bus.impairments`` are kept
    and the axes' impairments appended)."""
    ov: dict[str, Any] = {}
    for name, v in params.items():
        if name.startswith("set:"):
            ov[name[4:]] = v
        elif name == "bitrate":
            ov["bus.bitrate_bps"] = int(v)
        elif name == "period":
            ov["control_period_s"] = float(v)
    extra = impairments_for(params, n_cars)
    if extra:
        own = list(((base.get("bus") or {}).get("impairments")) or [])
        ov["bus.impairments"] = own + extra
    return ov


def is_random(params: dict[str, Any], base_impairments: Iterable[Any] = ()) -> bool:
    """Does the outcome of this point depend on the seed?"""
    if any(v for k, v in params.items() if not k.startswith("set:") and (k.endswith("loss") or k.endswith("jitter"))):
        return True
    for spec in base_impairments:
        t = spec.get("type") if isinstance(spec, dict) else getattr(spec, "type", None)
        if t in RANDOM_IMPAIRMENTS:
            return True
    return False


# ----------------------------------------------------------------------------- plan
@dataclass
class PointTask:
    """One run of the sweep (picklable; what a worker gets)."""

    point_id: str
    params: dict[str, Any]       # axis name -> value (SI)
    seed: int
    scenario: dict[str, Any]     # resolved scenario (model_dump, JSON mode)
    run_dir: str
    keep: str = "summary"
    base_impairments: int = 0    # how many of scenario.bus.impairments are the scenario's own (not the axes')


@dataclass
class SweepPlan:
    scenario_path: str
    profile: str | None
    axes: list[Axis]
    tasks: list[PointTask]
    base: Scenario
    out: Path
    seeds: int
    duration_s: float
    sets: dict[str, Any] = field(default_factory=dict)


def _slug(text: str) -> str:
    return re.sub(r"[^A-Za-z0-9.=_+-]", "_", text)


def _point_id(axes: Sequence[Axis], params: dict[str, Any], seed: int, resolved: dict[str, Any]) -> str:
    readable = "_".join(f"{a.path if a.is_set else a.name}={a.display(params[a.name])}{a.unit}" for a in axes)
    digest = hashlib.sha1(json.dumps(resolved, sort_keys=True).encode()).hexdigest()[:8]
    head = _slug(f"{readable}_seed={seed}" if readable else f"seed={seed}")
    if len(head) > 120:
        head = head[:120]
    return f"{head}-{digest}"


def default_duration_s(scn: Scenario) -> float:
    """``DEFAULT_TICKS`` control periods, at most the scenario's own duration."""
    return min(scn.duration_s, DEFAULT_TICKS * scn.control_period_s)


def plan_sweep(scenario: str | Path, axes: Sequence[Axis], out: str | Path, *, profile: str | None = None,
               sets: dict[str, Any] | None = None, duration_s: float | None = None, seeds: int = 3,
               keep: str = "summary") -> SweepPlan:
    """Every (point, seed) run of the sweep, resolved and validated (raises ScenarioError/GridError)."""
    axes = list(axes)
    check_axes(axes)
    if seeds < 1:
        raise GridError(f"--seeds must be at least 1, got {seeds}")
    if keep not in ("summary", "all"):
        raise GridError(f"--keep must be summary or all, got {keep!r}")
    sets = dict(sets or {})
    base = load_scenario(scenario, profile=profile, overrides=sets)
    if base.mode != "lockstep":
        raise ScenarioError(f"{scenario}: sweeps run the in-process lockstep engine; mode is {base.mode!r}")
    from canbrake.run import check_buildable, check_controller_params
    from canbrake.scenario import blame_overrides

    try:  # controller parameters and data files, as `canbrake run` checks them (exit 2, not a traceback)
        check_buildable(base)
    except ScenarioError as e:
        raise ScenarioError(blame_overrides(f"{scenario}: {e}", str(scenario), sets)) from None
    dur = float(duration_s) if duration_s is not None else default_duration_s(base)
    if not dur > 0:
        raise GridError(f"--duration must be > 0, got {dur:g}")
    base_data = base.model_dump(mode="json")
    base_data["duration_s"] = dur
    out = Path(out)
    tasks: list[PointTask] = []
    combos = list(itertools.product(*[a.values for a in axes])) if axes else [()]
    from canbrake.build import bus_layout

    layout = bus_layout(base)
    for combo in combos:
        params = {a.name: v for a, v in zip(axes, combo)}
        ov = point_overrides(base_data, params, layout)
        random = is_random(params, ov.get("bus.impairments", base_data["bus"]["impairments"]))
        seed_list = [base.seed + s for s in range(seeds)] if random else [base.seed]
        for seed in seed_list:
            o = dict(ov)
            o["seed"] = seed
            where = ", ".join(f"{a.name}={a.display(params[a.name])}{a.unit}" for a in axes) or "the base point"
            pscn = resolve(base_data, f"{scenario} ({where})", None, o)
            if any(k.startswith(("controller", "ecus")) for k in ov):  # a grid axis over controller parameters
                try:
                    check_controller_params(pscn)
                except ScenarioError as e:  # an input error before any run, not a worker's traceback
                    raise ScenarioError(f"--grid ({where}): {e}") from None
            resolved = pscn.model_dump(mode="json")
            pid = _point_id(axes, params, seed, resolved)
            tasks.append(PointTask(pid, params, seed, resolved, str(out / "points" / pid), keep,
                                   len(base_data["bus"]["impairments"] or [])))
    return SweepPlan(str(scenario), base.profile, axes, tasks, base, out, seeds, dur, sets)


# ----------------------------------------------------------------------------- one point
_BULKY = ("frames.log", "signals.csv", "canbrake.dbc")


def run_point(task: PointTask | dict[str, Any]) -> dict[str, Any]:
    """Run one point (in a worker); returns its results row. Never raises for a failed run."""
    if isinstance(task, dict):
        task = PointTask(**task)
    from canbrake.analysis.summary import finalize_run
    from canbrake.run import choose_bus, run_scenario

    import canbrake.control.chen_compensated  # noqa: F401  (registers chen2023_compensated)

    run_dir = Path(task.run_dir)
    t0 = time.time()
    summary: dict[str, Any]
    try:
        scn = Scenario.model_validate(task.scenario)
        with warnings.catch_warnings(), np.errstate(all="ignore"):
            warnings.simplefilter("ignore", RuntimeWarning)
            try:
                summary = run_scenario(scn, run_dir, backend="inprocess", plots=False)
            except ScenarioError:
                raise
            except Exception as e:  # noqa: BLE001 - e.g. PlantDiverged: the run's outcome, not a sweep error
                diverged = type(e).__name__ == "PlantDiverged" or "not finite" in str(e)
                outcome = {"status": "diverged" if diverged else "failed",
                           "message": f"{type(e).__name__}: {str(e).splitlines()[0] if str(e) else ''}",
                           "wall_time_s": time.time() - t0}
                summary = finalize_run(scn, run_dir, choose_bus(scn, "inprocess").describe(), outcome, plots=False)
    except ScenarioError as e:
        summary = {"status": "invalid", "message": str(e).splitlines()[0], "seed": task.seed}
        run_dir.mkdir(parents=True, exist_ok=True)
        (run_dir / "summary.json").write_text(json.dumps(summary, indent=1))
    except Exception as e:  # noqa: BLE001 - a bug in a point must not end the sweep; recorded, retried on resume
        summary = {"status": "error", "message": f"{type(e).__name__}: {e}", "seed": task.seed}
    if summary.get("status") not in ("ok",) and "message" in summary:
        summary["message"] = _normalise_message(summary)
    if task.keep != "all" and run_dir.exists():
        _trim_run_dir(run_dir)
    return make_row(task, summary)


def _normalise_message(summary: dict[str, Any]) -> str:
    msg = str(summary.get("message") or "")
    if summary.get("status") == "failed" and ("PlantDiverged" in msg or "not finite" in msg):
        summary["status"] = "diverged"
    return msg.splitlines()[0] if msg else ""


def _trim_run_dir(run_dir: Path) -> None:
    for name in _BULKY:
        p = run_dir / name
        if p.exists():
            p.unlink()
    for p in run_dir.glob("ecu_c*.csv"):
        p.unlink()
    plots = run_dir / "plots"
    if plots.is_dir() and not any(plots.iterdir()):
        plots.rmdir()


def _flatten(prefix: str, d: dict[str, Any], out: dict[str, Any]) -> None:
    for k, v in d.items():
        name = f"{prefix}{k}"
        if isinstance(v, dict):
            _flatten(f"{name}_", v, out)
        elif isinstance(v, (list, tuple)):
            nums = [x for x in v if isinstance(x, (int, float)) and not isinstance(x, bool)]
            for i, x in enumerate(v, start=1):
                out[f"{name}_c{i}"] = x
            if nums and len(nums) == len(v):
                out[f"{name}_max"] = max(abs(x) for x in nums) if "error" in k else max(nums)
        else:
            out[name] = v


def make_row(task: PointTask, summary: dict[str, Any]) -> dict[str, Any]:
    """The results.csv row of one run: parameters, seed, status, every summary metric, classification."""
    row: dict[str, Any] = {"point_id": task.point_id}
    for name, v in task.params.items():
        col = name[4:] if name.startswith("set:") else AXIS_KINDS[name].column
        row[col] = v
    row["seed"] = task.seed
    sc = task.scenario
    row["profile"] = sc.get("profile")
    row["controller"] = (sc.get("controller") or {}).get("name")
    row["duration_s"] = sc.get("duration_s")
    row["control_period_s"] = sc.get("control_period_s")
    # a run that executed but diverged is a "diverged" point of the map (summary: verdict)
    row["status"] = "diverged" if summary.get("verdict") == "diverged" else summary.get("status", "error")
    row["message"] = summary.get("message", "")
    for k in ("ticks", "wall_time_s", "real_time_factor"):
        row[k] = summary.get(k)
    metrics: dict[str, Any] = {}
    _flatten("", summary.get("metrics") or {}, metrics)
    row.update(metrics)
    for group in ("frames", "bus_load", "deadline_misses"):
        if isinstance(summary.get(group), dict):
            flat: dict[str, Any] = {}
            _flatten(f"{group}_", {k: v for k, v in summary[group].items() if not isinstance(v, dict)}, flat)
            row.update(flat)
    row.update(classify(row))
    return row


def _num(v: Any) -> float:
    try:
        x = float(v)
    except (TypeError, ValueError):
        return math.nan
    return x


def classify(row: dict[str, Any]) -> dict[str, Any]:
    """Safety classification of one row (see the module docstring)."""
    status = row.get("status")
    if status not in ("ok", "diverged", "failed"):
        return {"deflection_violation": None, "tracking_degraded": None, "unstable": None, "safety": None,
                "safety_level": None}
    defl = _num(row.get("max_abs_deflection_m"))
    tc = row.get("convergence_time_s")
    rmse_after = _num(row.get("speed_rmse_after_convergence_kmh_max"))
    final_err = _num(row.get("final_speed_error_kmh_max"))
    finite = math.isfinite(defl)
    violation = (not finite) or defl > DEFLECTION_BOUND_M
    degraded = (tc in (None, "") or not math.isfinite(_num(tc))
                or (math.isfinite(rmse_after) and rmse_after > TRACKING_RMSE_KMH))
    unstable = (status != "ok" or not finite or defl >= UNSTABLE_DEFLECTION_M
                or not math.isfinite(final_err) or final_err >= UNSTABLE_SPEED_ERROR_KMH)
    level = 3 if unstable else 2 if violation else 1 if degraded else 0
    return {"deflection_violation": bool(violation), "tracking_degraded": bool(degraded), "unstable": bool(unstable),
            "safety": SAFETY_LEVELS[level], "safety_level": level}


# ----------------------------------------------------------------------------- results.csv
_LEAD = ("point_id",)
_TAIL_FIRST = ("seed", "profile", "controller", "duration_s", "control_period_s", "status", "message",
               "safety", "safety_level", "deflection_violation", "tracking_degraded", "unstable")


def _fmt(v: Any) -> str:
    if v is None:
        return ""
    if isinstance(v, bool):
        return "true" if v else "false"
    if isinstance(v, float):
        return repr(v) if math.isfinite(v) else ("inf" if v > 0 else "-inf" if v < 0 else "nan")
    return str(v)


def _parse(v: str) -> Any:
    if v == "":
        return None
    if v in ("true", "false"):
        return v == "true"
    try:
        if re.fullmatch(r"[-+]?\d+", v):
            return int(v)
        return float(v)
    except ValueError:
        return v


def read_results(path: str | Path) -> list[dict[str, Any]]:
    """results.csv as rows of typed values (numbers, booleans, None for empty cells)."""
    p = Path(path)
    if not p.exists():
        return []
    with open(p, newline="") as f:
        return [{k: _parse(v) for k, v in r.items()} for r in csv.DictReader(f)]


def write_results(path: str | Path, rows: Sequence[dict[str, Any]], axis_columns: Sequence[str] = ()) -> None:
    """Write rows atomically; columns: point_id, the axes, seed/status/classification, then metrics."""
    cols: list[str] = list(_LEAD) + [c for c in axis_columns if c not in _LEAD]
    for c in _TAIL_FIRST:
        if c not in cols:
            cols.append(c)
    for r in rows:
        for k in r:
            if k not in cols:
                cols.append(k)
    p = Path(path)
    tmp = p.with_suffix(".csv.tmp")
    buf = io.StringIO()
    w = csv.writer(buf)
    w.writerow(cols)
    for r in rows:
        w.writerow([_fmt(r.get(c)) for c in cols])
    tmp.write_text(buf.getvalue())
    os.replace(tmp, p)


# ----------------------------------------------------------------------------- execution
@dataclass
class SweepResult:
    out: Path
    results_csv: Path
    rows: list[dict[str, Any]]          # this sweep's rows, in plan order
    ran: int                            # points run now
    skipped: int                        # points found done
    heatmaps: list[Path]
    interrupted: bool = False
    errors: int = 0


def _done_summary(task: PointTask) -> dict[str, Any] | None:
    p = Path(task.run_dir) / "summary.json"
    if not p.exists():
        return None
    try:
        s = json.loads(p.read_text())
    except (OSError, ValueError):
        return None
    return s if s.get("status") == "ok" else None


#: at most this many points per batch (a Dask task); more points per batch amortise more (a tick of
#: the batch engine costs about the same for 8 points as for 64: numpy per-call overhead), fewer
#: balance the workers and report progress more often
BATCH_MAX_POINTS = 64
#: a batch holds its points' traces in memory until they end (canbrake.batch.point_bytes): at most
#: this much per batch, i.e. per worker (64 points of Chen case 1 x 10 s: ~0.9 GB)
BATCH_MEMORY_BYTES = 1 << 30
ENGINES = ("auto", "batch", "points")


def batch_unsupported(task: PointTask) -> str | None:
    """Why the batch engine (:mod:`canbrake.batch`) cannot run this point, or None."""
    from canbrake.batch import unsupported

    try:
        scn = Scenario.model_validate(task.scenario)
    except Exception:  # noqa: BLE001 - an invalid point is reported by its per-point run
        return "not for an invalid scenario"
    return unsupported(scn, task.base_impairments)


def plan_batches(tasks: Sequence[PointTask], workers: int) -> tuple[list[list[PointTask]], list[PointTask], dict[str, int]]:
    """(batches for the batch engine, tasks to run one by one, fallback reasons -> count)."""
    from canbrake.batch import batch_key, point_bytes

    reasons: dict[str, int] = {}
    groups: dict[tuple, list[PointTask]] = {}
    size: dict[tuple, int] = {}
    single: list[PointTask] = []
    for t in tasks:
        why = batch_unsupported(t)
        if why is not None:
            reasons[why] = reasons.get(why, 0) + 1
            single.append(t)
            continue
        scn = Scenario.model_validate(t.scenario)
        key = batch_key(scn)
        groups.setdefault(key, []).append(t)
        size.setdefault(key, point_bytes(scn))
    batches: list[list[PointTask]] = []
    w = max(1, workers)
    for key, g in groups.items():
        # a multiple of the workers' number of batches of at most BATCH_MAX_POINTS points (fewer
        # where a batch would hold more than BATCH_MEMORY_BYTES of traces), dealt round robin
        # (neighbouring grid points cost alike: e.g. a row of early divergences)
        most = max(1, min(BATCH_MAX_POINTS, BATCH_MEMORY_BYTES // size[key]))
        nb = w * -(-(-(-len(g) // most)) // w) if len(g) > w else len(g)
        batches += [b for b in (g[i::nb] for i in range(nb)) if b]
    return batches, single, reasons


def run_batch_points(tasks: Sequence[PointTask | dict[str, Any]]) -> list[dict[str, Any]]:
    """Run several points at once with the batch engine (in a worker); returns their rows. If the
    batch cannot be set up or fails, its points are run one by one (never raises)."""
    from canbrake.batch import run_batch

    import canbrake.control.chen_compensated  # noqa: F401  (registers chen2023_compensated)

    from canbrake.run import preflight

    tasks = [PointTask(**t) if isinstance(t, dict) else t for t in tasks]
    rows: list[dict[str, Any]] = []
    ok: list[PointTask] = []
    scns: list[Scenario] = []
    for t in tasks:  # what run_scenario checks before it runs (an invalid point is reported by run_point)
        try:
            scn = Scenario.model_validate(t.scenario)
            preflight(scn, "inprocess")
        except Exception:  # noqa: BLE001
            rows.append(run_point(t))
            continue
        ok.append(t)
        scns.append(scn)
    tasks = ok
    if not tasks:
        return rows
    try:
        summaries = run_batch(scns, [Path(t.run_dir) for t in tasks])
    except Exception:  # noqa: BLE001 - the per-point runs say what is wrong with which point
        return rows + [run_point(t) for t in tasks]
    for t, summary in zip(tasks, summaries):
        if summary.get("status") not in ("ok",) and "message" in summary:
            summary["message"] = _normalise_message(summary)
        if t.keep != "all":
            _trim_run_dir(Path(t.run_dir))
        rows.append(make_row(t, summary))
    return rows


def execute(tasks: Sequence[PointTask], on_row: Callable[[dict[str, Any]], None], *, workers: int = 2,
            scheduler: str | None = None, progress: bool = True, engine: str = "auto",
            log: Callable[[str], None] | None = None) -> None:
    """Run ``tasks``; call ``on_row`` in this process for each finished one (any order).

    ``scheduler`` None: a LocalCluster of ``workers`` processes (serial here if ``workers`` is 0);
    "none": serial here; anything else: the address of a Dask scheduler. ``engine``: "auto" runs the
    points the batch engine supports in batches (one Dask task per batch) and the others one by
    one, saying why on ``log``; "batch" only the batch engine (GridError if a point needs the
    per-point engine); "points" every point by itself.
    """
    if engine not in ENGINES:
        raise GridError(f"--engine must be one of {', '.join(ENGINES)}, got {engine!r}")
    serial = scheduler == "none" or (scheduler is None and workers <= 0)
    if engine == "points":
        batches, single = [], list(tasks)
    else:
        batches, single, reasons = plan_batches(tasks, 1 if serial else workers)
        if engine == "batch" and reasons:
            why, n = next(iter(reasons.items()))
            raise GridError(f"--engine batch: the batch engine cannot run {n} point(s): {why}; "
                            f"use --engine auto (those points one by one) or --engine points")
        if log is not None:
            for why, n in reasons.items():
                log(f"batch engine: {why}; running {n} point(s) one by one")
            if batches:
                log(f"batch engine: {sum(map(len, batches))} point(s) in {len(batches)} batch(es)")
    bar = _progress_bar(len(tasks), progress)
    try:
        if serial:
            for b in batches:
                for row in run_batch_points(b):
                    on_row(row)
                    bar.update(1)
            for t in single:
                on_row(run_point(t))
                bar.update(1)
            return
        _execute_dask(single, on_row, bar, workers=workers, scheduler=scheduler, batches=batches)
    finally:
        bar.close()


def _progress_bar(total: int, enabled: bool) -> Any:
    try:
        from tqdm import tqdm
    except ImportError:  # pragma: no cover - tqdm is a dependency; degrade to no bar
        enabled = False
    if not enabled:
        class _NoBar:
            def update(self, n: int = 1) -> None:
                pass

            def close(self) -> None:
                pass

        return _NoBar()
    tty = sys.stderr.isatty()
    return tqdm(total=total, desc="sweep", unit="run", file=sys.stderr, dynamic_ncols=True,
                mininterval=0.5 if tty else 15.0, smoothing=0.05)


def _probe_scheduler(address: str) -> None:
    """Fail at once, with a clear message, when nothing listens at a tcp:// scheduler address
    (the Dask client would retry for its whole timeout)."""
    import socket

    m = re.fullmatch(r"(?:tcp://)?\[?([^\]/]+?)\]?:(\d+)", address.strip())
    if not m:
        return
    try:
        socket.create_connection((m.group(1), int(m.group(2))), timeout=5).close()
    except OSError as e:
        raise GridError(f"--scheduler {address}: cannot connect to a Dask scheduler: "
                        f"{e.strerror or e}") from None


def _execute_dask(tasks: Sequence[PointTask], on_row: Callable[[dict[str, Any]], None], bar: Any, *,
                  workers: int, scheduler: str | None, batches: Sequence[Sequence[PointTask]] = ()) -> None:
    try:
        from distributed import Client, LocalCluster, as_completed
    except ImportError:
        raise GridError("Dask is not installed: pip install 'dask[distributed]' "
                        "(or run serially with --workers 0)") from None
    cluster = None
    client = None
    futures: list[Any] = []
    # Ctrl-C while the cluster starts would leave half-started workers to atexit hooks: hold SIGINT
    # and SIGTERM until the cluster object exists (it is then delivered and closes the cluster below).
    # The workers ignore SIGINT (dask_setup below): on a terminal's Ctrl-C, sent to the whole process
    # group, they are shut down by this process instead of dying mid-point with tracebacks.
    hold = {signal.SIGINT, signal.SIGTERM}
    masked = threading.current_thread() is threading.main_thread() and hasattr(signal, "pthread_sigmask")
    if masked:
        signal.pthread_sigmask(signal.SIG_BLOCK, hold)
    try:
        if scheduler is None:
            # loopback only, no dashboard; the scheduler's small HTTP endpoint (health, metrics) on a
            # free loopback port rather than 8787, which another cluster may hold
            cluster = LocalCluster(n_workers=workers, threads_per_worker=1, processes=True, host="127.0.0.1",
                                   dashboard_address=None, silence_logs=50, preload=["canbrake.sweep"],
                                   scheduler_kwargs={"dashboard_address": "127.0.0.1:0"})
            client = Client(cluster)
        else:
            _probe_scheduler(scheduler)
            try:
                client = Client(scheduler, timeout="20s")
            except (OSError, TimeoutError) as e:
                raise GridError(f"--scheduler {scheduler}: cannot connect to a Dask scheduler: {e}") from None
        if masked:
            masked = False
            signal.pthread_sigmask(signal.SIG_UNBLOCK, hold)
        # a batch of points is one task (canbrake.batch); the batches go first, they are the long ones
        work: list[list[PointTask]] = [list(b) for b in batches]
        futures = [client.submit(run_batch_points, [t.__dict__ for t in b],
                                 key=f"canbrake-batch-{b[0].point_id}-{len(b)}", pure=False, retries=1)
                   for b in work]
        work += [[t] for t in tasks]
        futures += [client.submit(run_point, t.__dict__, key=f"canbrake-point-{t.point_id}", pure=False,
                                  retries=1) for t in tasks]
        for fut in as_completed(futures):
            group = work[futures.index(fut)]
            try:
                res = fut.result()
                rows = res if isinstance(res, list) else [res]
            except Exception as e:  # noqa: BLE001 - e.g. a worker died twice on this point
                rows = [make_row(t, {"status": "error", "message": f"{type(e).__name__}: {e}"}) for t in group]
            for row in rows:
                on_row(row)
                bar.update(1)
    finally:
        if masked:
            signal.pthread_sigmask(signal.SIG_UNBLOCK, hold)
        if client is not None:
            try:
                if futures:
                    client.cancel(futures, force=True)
            except Exception:  # noqa: BLE001 - best effort while shutting down
                pass
            client.close(timeout=10)
        if cluster is not None:
            cluster.close(timeout=20)


def dask_setup(worker: Any) -> None:
    """Dask preload hook (``preload=["canbrake.sweep"]``): a local worker leaves Ctrl-C to the sweep
    process, which shuts it down."""
    if threading.current_thread() is threading.main_thread():
        signal.signal(signal.SIGINT, signal.SIG_IGN)


def run_sweep(scenario: str | Path, axes: Sequence[Axis], out: str | Path, *, profile: str | None = None,
              sets: dict[str, Any] | None = None, duration_s: float | None = None, seeds: int = 3,
              workers: int = 2, scheduler: str | None = None, keep: str = "summary", plots: bool = True,
              progress: bool = True, log: Callable[[str], None] | None = None, engine: str = "auto") -> SweepResult:
    """Plan, resume, run and plot a sweep. Ctrl-C (or SIGTERM) stops it cleanly: every finished point
    is in results.csv and the same call resumes."""
    log = log or (lambda s: None)
    plan = plan_sweep(scenario, axes, out, profile=profile, sets=sets, duration_s=duration_s, seeds=seeds, keep=keep)
    out = plan.out
    out.mkdir(parents=True, exist_ok=True)
    (out / "points").mkdir(exist_ok=True)
    csv_path = out / "results.csv"
    existing = read_results(csv_path)
    ids = {t.point_id for t in plan.tasks}
    by_id: dict[str, dict[str, Any]] = {}
    foreign: list[dict[str, Any]] = []
    for r in existing:
        if r.get("point_id") in ids:
            if r.get("status") in FINAL_STATUSES:
                r.update(classify(r))  # the thresholds of this version
                by_id[str(r["point_id"])] = r
        else:
            foreign.append(r)
    if foreign:
        log(f"results.csv keeps {len(foreign)} row(s) of other sweep configurations; the maps use this sweep's only")
    todo: list[PointTask] = []
    for t in plan.tasks:
        if t.point_id in by_id:
            continue
        s = _done_summary(t)
        if s is not None:
            by_id[t.point_id] = make_row(t, s)
        else:
            todo.append(t)
    skipped = len(plan.tasks) - len(todo)
    axis_cols = [a.column for a in plan.axes]
    _write_manifest(plan)
    log(f"{len(plan.tasks)} runs ({len({tuple(sorted(map(str, t.params.items()))) for t in plan.tasks})} points), "
        f"{skipped} already done, {len(todo)} to run; {plan.duration_s:g} s simulated each -> {out}")

    lock = threading.Lock()
    last_write = [0.0]

    def flush() -> None:
        order = {t.point_id: i for i, t in enumerate(plan.tasks)}
        mine = sorted(by_id.values(), key=lambda r: order.get(str(r["point_id"]), 0))
        write_results(csv_path, foreign + mine, axis_cols)

    def on_row(row: dict[str, Any]) -> None:
        with lock:
            by_id[str(row["point_id"])] = row
            now = time.time()
            if now - last_write[0] > 2.0:
                flush()
                last_write[0] = now

    interrupted = False
    old_term = None
    if threading.current_thread() is threading.main_thread():
        def _on_term(signum: int, frame: Any) -> None:
            raise KeyboardInterrupt

        old_term = signal.signal(signal.SIGTERM, _on_term)
    try:
        if todo:
            execute(todo, on_row, workers=workers, scheduler=scheduler, progress=progress, engine=engine, log=log)
    except KeyboardInterrupt:
        interrupted = True
    finally:
        if old_term is not None:
            signal.signal(signal.SIGTERM, old_term)
        flush()
    rows = [by_id[t.point_id] for t in plan.tasks if t.point_id in by_id]
    errors = sum(1 for r in rows if r.get("status") not in FINAL_STATUSES)
    heatmaps: list[Path] = []
    if rows and not interrupted:
        (out / "thresholds.md").write_text(threshold_table(rows, plan.axes))
        if plots:
            heatmaps = plot_heatmaps(rows, plan.axes, out, title=_title(plan))
    return SweepResult(out, csv_path, rows, len(todo), skipped, heatmaps, interrupted, errors)


def _title(plan: SweepPlan) -> str:
    b = plan.base
    prof = f", profile {b.profile}" if b.profile else ""
    ctrl = "" if any(a.name == "set:controller.name" for a in plan.axes) else f", {b.controller.name}"
    return f"{b.name}{prof}{ctrl}, {plan.duration_s:g} s"


def _write_manifest(plan: SweepPlan) -> None:
    data = {"scenario": plan.scenario_path, "profile": plan.profile, "set": plan.sets,
            "axes": [{"name": a.name, "values": list(a.values), "unit": a.unit} for a in plan.axes],
            "seeds": plan.seeds, "duration_s": plan.duration_s, "runs": len(plan.tasks),
            "classification": {"deflection_bound_m": DEFLECTION_BOUND_M, "tracking_rmse_kmh": TRACKING_RMSE_KMH,
                               "unstable_deflection_m": UNSTABLE_DEFLECTION_M,
                               "unstable_speed_error_kmh": UNSTABLE_SPEED_ERROR_KMH}}
    (plan.out / "sweep.json").write_text(json.dumps(data, indent=1))


# ----------------------------------------------------------------------------- heatmaps
def aggregate(rows: Sequence[dict[str, Any]], axes: Sequence[Axis]) -> dict[tuple, dict[str, Any]]:
    """Per point (tuple of axis values), over its seeds: worst max |deflection| (m), mean worst-car
    speed RMSE (km/h), latest convergence time (s, inf = never), worst safety level and the share of
    seeds at that level."""
    cols = [a.column for a in axes]
    groups: dict[tuple, list[dict[str, Any]]] = {}
    for r in rows:
        if r.get("status") not in FINAL_STATUSES or r.get("status") == "invalid":
            continue
        key = tuple(_key(r.get(c)) for c in cols)
        groups.setdefault(key, []).append(r)
    out: dict[tuple, dict[str, Any]] = {}
    for key, rs in groups.items():
        defl = [_num(r.get("max_abs_deflection_m")) for r in rs]
        defl = [d if not math.isnan(d) else math.inf for d in defl]
        rmse = [_num(r.get("speed_rmse_kmh_max")) for r in rs]
        rmse_f = [x for x in rmse if math.isfinite(x)]
        conv = [_num(r.get("convergence_time_s")) for r in rs]
        conv = [c if math.isfinite(c) else math.inf for c in conv]
        levels = [int(r["safety_level"]) for r in rs if r.get("safety_level") is not None]
        worst = max(levels) if levels else None
        out[key] = {"deflection_m": max(defl), "rmse_kmh": float(np.mean(rmse_f)) if rmse_f else math.inf,
                    "level": worst, "convergence_s": max(conv) if conv else math.inf,
                    "share": (levels.count(worst) / len(levels)) if levels else 0.0,
                    "seeds": len(rs), "diverged": sum(1 for r in rs if r.get("status") == "diverged")}
    return out


def _key(v: Any) -> Any:
    if isinstance(v, float):
        return float(f"{v:.12g}")
    return v


def plot_heatmaps(rows: Sequence[dict[str, Any]], axes: Sequence[Axis], out_dir: str | Path, *,
                  title: str = "", prefix: str = "heatmap_") -> list[Path]:
    """heatmap_deflection.png, heatmap_speed_rmse.png, heatmap_convergence.png, heatmap_safety.png in
    ``out_dir``.

    x = first axis, y = second axis (one row if there is one axis); further axes give one panel
    each, side by side."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    from matplotlib.colors import BoundaryNorm, ListedColormap, LogNorm, Normalize

    axes = list(axes)
    if not axes:
        return []
    agg = aggregate(rows, axes)
    xa = axes[0]
    ya = axes[1] if len(axes) > 1 else None
    facet_axes = axes[2:]
    facets = list(itertools.product(*[a.values for a in facet_axes])) or [()]
    nx, ny = len(xa.values), (len(ya.values) if ya else 1)
    out_dir = Path(out_dir)
    paths: list[Path] = []

    def cell(fv: tuple, ix: int, iy: int) -> dict[str, Any] | None:
        xv = xa.values[ix]
        yv = ya.values[iy] if ya else None
        key = tuple(_key(v) for v in ((xv,) + ((yv,) if ya else ()) + tuple(fv)))
        return agg.get(key)

    def grid(field_: str) -> list[np.ndarray]:
        gs = []
        for fv in facets:
            g = np.full((ny, nx), np.nan)
            for iy in range(ny):
                for ix in range(nx):
                    a = cell(fv, ix, iy)
                    if a is not None and a[field_] is not None:
                        g[iy, ix] = a[field_]
            gs.append(g)
        return gs

    fs = 6 if max(nx, ny) > 8 else 8

    def annotate(ax: Any, fv: tuple, label: Callable[[dict[str, Any]], tuple[str, str] | None]) -> None:
        """Write ``label(cell) -> (text, colour)`` into every cell that has results (None: leave empty)."""
        for iy in range(ny):
            for ix in range(nx):
                c = cell(fv, ix, iy)
                t = None if c is None else label(c)
                if t is not None:
                    ax.text(ix, iy, t[0], ha="center", va="center", fontsize=fs - 1, color=t[1])

    def deflection_label(c: dict[str, Any]) -> tuple[str, str]:
        v = c["deflection_m"] * 100.0
        txt = "div" if c["diverged"] and c["diverged"] == c["seeds"] else _short_cm(v)
        return txt, "white" if not math.isfinite(v) or v < 3 or v > 100 else "black"

    def rmse_label(c: dict[str, Any]) -> tuple[str, str]:
        v = c["rmse_kmh"]
        txt = "∞" if not math.isfinite(v) or v >= 1e4 else f"{v:.2g}" if v < 100 else f"{v:.0f}"
        return txt, "white" if not math.isfinite(v) or v < 0.3 or v > 100 else "black"

    def safety_label(c: dict[str, Any]) -> tuple[str, str] | None:
        if c["seeds"] <= 1 or c["share"] >= 1.0:
            return None
        k = int(round(c["share"] * c["seeds"]))
        return f"{k}/{c['seeds']}", "white" if c["level"] == 3 else "black"

    panel_w = max(3.0, 0.36 * nx + 1.0)
    panel_h = max(2.4, 0.3 * ny + 1.4)

    def figure() -> tuple[Any, list[Any]]:
        fig, axs = plt.subplots(1, len(facets), figsize=(panel_w * len(facets) + 1.3, panel_h + 0.6),
                                squeeze=False, constrained_layout=True)
        return fig, list(axs[0])

    def decorate(ax: Any, fv: tuple) -> None:
        ax.set_xticks(range(nx))
        ax.set_xticklabels([xa.display(v) for v in xa.values], fontsize=fs, rotation=90 if nx > 8 else 0)
        ax.set_xlabel(xa.label(), fontsize=8)
        if ya:
            ax.set_yticks(range(ny))
            ax.set_yticklabels([ya.display(v) for v in ya.values], fontsize=fs)
            ax.set_ylabel(ya.label(), fontsize=8)
        else:
            ax.set_yticks([])
        if facet_axes:
            ax.set_title(", ".join(f"{a.path if a.is_set else a.name}={a.display(v)}{a.unit}"
                                   for a, v in zip(facet_axes, fv)), fontsize=8)

    # max |deflection|
    fig, axs = figure()
    norm = LogNorm(vmin=0.01, vmax=100.0)
    cmap = matplotlib.colormaps["viridis"].with_extremes(over="#7f0000", bad="#dddddd")
    im = None
    for ax, fv, g in zip(axs, facets, grid("deflection_m")):
        cm = np.where(np.isfinite(g), np.clip(g * 100.0, 0.01, None), np.where(np.isnan(g), np.nan, 1e9))
        im = ax.imshow(np.ma.masked_invalid(cm), origin="lower", aspect="auto", cmap=cmap, norm=norm)
        annotate(ax, fv, deflection_label)
        _bound_outline(ax, g, DEFLECTION_BOUND_M)
        decorate(ax, fv)
    cb = fig.colorbar(im, ax=axs, extend="max", shrink=0.9)
    cb.set_label("max |Δl| (cm), worst seed", fontsize=7)
    cb.ax.tick_params(labelsize=7)
    _fit_suptitle(fig, f"max coupler deflection (white outline: within ±1 cm) — {title}")
    paths.append(_save(fig, out_dir / f"{prefix}deflection.png"))

    # speed RMSE
    fig, axs = figure()
    norm = LogNorm(vmin=0.01, vmax=100.0)
    for ax, fv, g in zip(axs, facets, grid("rmse_kmh")):
        gm = np.where(np.isfinite(g), np.clip(g, 0.01, None), np.where(np.isnan(g), np.nan, 1e9))
        im = ax.imshow(np.ma.masked_invalid(gm), origin="lower", aspect="auto", cmap=cmap, norm=norm)
        annotate(ax, fv, rmse_label)
        decorate(ax, fv)
    cb = fig.colorbar(im, ax=axs, extend="max", shrink=0.9)
    cb.set_label("speed RMSE (km/h), worst car, mean of seeds", fontsize=7)
    cb.ax.tick_params(labelsize=7)
    _fit_suptitle(fig, f"speed tracking RMSE — {title}")
    paths.append(_save(fig, out_dir / f"{prefix}speed_rmse.png"))

    # convergence time
    fig, axs = figure()
    ccmap = matplotlib.colormaps["viridis"].with_extremes(over="#7f0000", bad="#dddddd")
    for ax, fv, g in zip(axs, facets, grid("convergence_s")):
        finite = g[np.isfinite(g)]
        top = float(finite.max()) if finite.size else 1.0
        im = ax.imshow(np.ma.masked_invalid(np.where(np.isinf(g), 1e9, g)), origin="lower", aspect="auto",
                       cmap=ccmap, norm=Normalize(vmin=0.0, vmax=max(top, 1e-3)))
        def convergence_label(c: dict[str, Any], top: float = top) -> tuple[str, str]:
            v = c["convergence_s"]
            return ("never" if not math.isfinite(v) else f"{v:.2g}",
                    "white" if not math.isfinite(v) or v < 0.5 * top else "black")

        annotate(ax, fv, convergence_label)
        decorate(ax, fv)
    cb = fig.colorbar(im, ax=axs, extend="max", shrink=0.9)
    cb.set_label("convergence to ±0.5 km/h (s), latest seed", fontsize=7)
    cb.ax.tick_params(labelsize=7)
    _fit_suptitle(fig, f"convergence time (never = not within the band at the end) — {title}")
    paths.append(_save(fig, out_dir / f"{prefix}convergence.png"))

    # safety
    fig, axs = figure()
    colors = ["#2ca02c", "#f2d21b", "#ff7f0e", "#b10026"]
    scmap = ListedColormap(colors).with_extremes(bad="#dddddd")
    snorm = BoundaryNorm([-0.5, 0.5, 1.5, 2.5, 3.5], 4)
    for ax, fv, g in zip(axs, facets, grid("level")):
        im = ax.imshow(np.ma.masked_invalid(g), origin="lower", aspect="auto", cmap=scmap, norm=snorm)
        annotate(ax, fv, safety_label)
        decorate(ax, fv)
    cb = fig.colorbar(im, ax=axs, ticks=[0, 1, 2, 3], shrink=0.9)
    cb.ax.set_yticklabels(["ok", "tracking\ndegraded", "|Δl| > 1 cm", "unstable"], fontsize=7)
    _fit_suptitle(fig, f"safety (worst seed; k/n = seeds at that level) — {title}")
    paths.append(_save(fig, out_dir / f"{prefix}safety.png"))
    return paths


def _short_cm(v: float) -> str:
    """A deflection in cm for a cell, in the colour bar's unit: 0.052, 1.3, 58, 160, 2400; ∞ beyond
    100 m (the plant ran away)."""
    if not math.isfinite(v) or v >= 1e4:
        return "∞"
    if v >= 100:
        return f"{v:.0f}"
    return f"{v:.2g}"


def _fit_suptitle(fig: Any, text: str, fontsize: float = 8) -> None:
    """A figure title wrapped to the figure's width (≈ 0.6 em per character), never cut off."""
    import textwrap

    width_in = float(fig.get_size_inches()[0])
    fig.suptitle(textwrap.fill(text, max(24, int(width_in * 72 / (fontsize * 0.6)))), fontsize=fontsize)


def _bound_outline(ax: Any, g: np.ndarray, bound_m: float) -> None:
    """Outline the cells within the bound."""
    inside = np.isfinite(g) & (g <= bound_m)
    ny, nx = g.shape
    for iy in range(ny):
        for ix in range(nx):
            if not inside[iy, ix]:
                continue
            for dx, dy, seg in ((1, 0, ([ix + .5, ix + .5], [iy - .5, iy + .5])),
                                (-1, 0, ([ix - .5, ix - .5], [iy - .5, iy + .5])),
                                (0, 1, ([ix - .5, ix + .5], [iy + .5, iy + .5])),
                                (0, -1, ([ix - .5, ix + .5], [iy - .5, iy - .5]))):
                jx, jy = ix + dx, iy + dy
                if not (0 <= jx < nx and 0 <= jy < ny) or not inside[jy, jx]:
                    ax.plot(*seg, color="white", lw=1.2)


def _save(fig: Any, path: Path) -> Path:
    import matplotlib.pyplot as plt

    fig.savefig(path, dpi=90)
    plt.close(fig)
    return path


# ----------------------------------------------------------------------------- thresholds
def thresholds(rows: Sequence[dict[str, Any]], axis: Axis, other: dict[str, Any] | None = None) -> dict[str, Any]:
    """Along ``axis`` (other axes fixed at ``other``, column -> value): the first value at which the
    worst seed violates the deflection bound, degrades tracking and goes unstable (None: never on the grid)."""
    other = other or {}
    out: dict[str, Any] = {}
    for flag in ("deflection_violation", "tracking_degraded", "unstable"):
        first = None
        for v in axis.values:
            sel = [r for r in rows if _key(r.get(axis.column)) == _key(v)
                   and all(_key(r.get(c)) == _key(w) for c, w in other.items())
                   and r.get("status") in ("ok", "diverged", "failed")]
            if sel and any(r.get(flag) for r in sel):
                first = v
                break
        out[flag] = first
    return out


def threshold_table(rows: Sequence[dict[str, Any]], axes: Sequence[Axis]) -> str:
    """Markdown: along each of the first two numeric axes, with the other one at its first value (and
    per combination of the remaining axes), the first grid value at which the worst seed leaves ±1 cm,
    degrades tracking and goes unstable ("> last" = not on the grid)."""
    axes = list(axes)
    numeric = [a for a in axes if all(isinstance(v, (int, float)) and not isinstance(v, bool) for v in a.values)]
    main = numeric[:2]
    facet_axes = [a for a in axes if a not in main]
    if not main:
        return ""
    lines = ["| " + " | ".join([a.path if a.is_set else a.name for a in facet_axes] + ["along", "others at",
             "leaves ±1 cm from", "tracking degraded from", "unstable from"]) + " |"]
    lines.append("|" + "---|" * (len(facet_axes) + 5))
    for fv in itertools.product(*[a.values for a in facet_axes]) or [()]:
        fixed = {a.column: v for a, v in zip(facet_axes, fv)}
        for ax in main:
            rest = {b.column: b.values[0] for b in main if b is not ax}
            th = thresholds(rows, ax, {**fixed, **rest})
            have = any(all(_key(r.get(c)) == _key(w) for c, w in {**fixed, **rest}.items()) for r in rows)
            shown = [f"{a.display(v)}{a.unit}" for a, v in zip(facet_axes, fv)]
            at = ", ".join(f"{b.name if not b.is_set else b.path}={b.display(b.values[0])}{b.unit}"
                           for b in main if b is not ax) or "-"

            def fmt(v: Any) -> str:
                if not have:
                    return "–"
                return f"> {ax.display(ax.values[-1])}{ax.unit}" if v is None else f"{ax.display(v)}{ax.unit}"

            lines.append("| " + " | ".join(shown + [ax.name if not ax.is_set else ax.path, at,
                                                    fmt(th["deflection_violation"]), fmt(th["tracking_degraded"]),
                                                    fmt(th["unstable"])]) + " |")
    return "\n".join(lines) + "\n"


from canbrake.startup import make_module_callable  # noqa: E402

make_module_callable(__name__)  # canbrake.sweep(...) is the API's sweep (canbrake/api.py)
