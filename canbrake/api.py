"""canbrake's Python API: load a scenario, run it, sweep it, read the results (docs/python-api.md).

Works from a plain script (no ``if __name__ == "__main__":`` guard needed, on every bus), from a
Jupyter kernel and from pytest. Units are SI throughout (m, s, m/s, N, kg), in every column name.

    import canbrake
    r = canbrake.run("chen2023_case1_fine_rail", duration_s=1.0)
    r.summary["metrics"]["max_abs_deflection_m"]     # m
    r.signals["speed_mps_c3"]                          # pandas Series indexed by time (s)
"""
from __future__ import annotations

import json
import tempfile
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING, Any, Iterator, Mapping, Sequence

from canbrake.scenario import Scenario, ScenarioError, resolve

if TYPE_CHECKING:  # imported lazily: pandas, cantools and matplotlib cost start-up time
    import can
    import cantools
    import pandas as pd
    from matplotlib.figure import Figure

__all__ = ["RunResult", "RunFailure", "load_scenario", "run", "sweep", "open_run"]


class RunFailure(RuntimeError):
    """A run failed after it started (a node process died, the run stalled); ``run_dir`` keeps
    every log written so far, ``summary`` is its summary.json."""

    def __init__(self, message: str, run_dir: Path, summary: dict[str, Any]) -> None:
        super().__init__(message)
        self.run_dir = run_dir
        self.summary = summary


def _dotted(overrides: Mapping[str, Any]) -> dict[str, Any]:
    """Keyword overrides to dotted scenario paths: ``controller__params__k`` -> ``controller.params.k``
    (a key may also be given dotted already, ``**{"controller.params.k": 20}``)."""
    return {k.replace("__", "."): v for k, v in overrides.items()}


def _keyword_labels(overrides: Mapping[str, Any], renamed: Mapping[str, str] | None = None) -> dict[str, str]:
    """How messages name each override: by the keyword argument it came from
    (``keyword argument duration_s``), not ``--set``; ``renamed``: dotted key -> keyword for
    arguments that are not the field's own name (``log_format`` sets ``bus.log_format``)."""
    out = {k.replace("__", "."): f"keyword argument {k}" for k in overrides}
    out.update({k: f"keyword argument {kw}" for k, kw in (renamed or {}).items()})
    return out


def load_scenario(path: str | Path | Scenario, profile: str | None = None, *,
                  external: Sequence[str] | None = None, **overrides: Any) -> Scenario:
    """Read and validate a scenario.

    ``path``: a YAML file, or the name of a built-in scenario (``canbrake scenarios`` lists them),
    or a :class:`Scenario` to derive from. ``profile``: one of the scenario's ``profiles:``.
    ``overrides``: scenario fields, nested with ``__`` (``duration_s=1.0``, ``seed=3``,
    ``controller__params__k=20``, ``bus__bitrate_bps=500000``), values in the units of the field
    names. ``external``: ECU names that run outside canbrake (as ``canbrake run --external``; see
    docs/lockstep-protocol.md). Raises :class:`canbrake.ScenarioError` naming the file and field on
    bad input.
    """
    return _load(path, profile, external, overrides, _keyword_labels(overrides))


def _load(path: str | Path | Scenario, profile: str | None, external: Sequence[str] | None,
          overrides: Mapping[str, Any], labels: Mapping[str, str]) -> Scenario:
    from canbrake.scenario import load_scenario as _load_file

    if isinstance(path, Scenario):
        data = path.model_dump(mode="json")
        if profile is not None:
            data.pop("profile", None)
        return resolve(data, f"<scenario {path.name}>", profile, _dotted(overrides),
                       list(external) if external else None, labels)
    return _load_file(path, profile=profile, overrides=_dotted(overrides),
                      external=list(external) if external else None, labels=labels)


@dataclass
class RunResult:
    """The results of one run, read lazily from its run directory ``run_dir``."""

    run_dir: Path
    summary: dict[str, Any]
    scenario: Scenario | None = None
    _signals: Any = field(default=None, repr=False)

    @property
    def status(self) -> str:
        """How the run executed: ok, diverged, failed or interrupted."""
        return str(self.summary.get("status", "failed"))

    @property
    def verdict(self) -> Any:
        """The judgement of the physics and the bus: ``summary["verdict"]`` when the run wrote one;
        otherwise ``"diverged"``, ``"deflection_bound_exceeded"`` (|Δl| > 1 cm) or ``"ok"``."""
        if "verdict" in self.summary:
            return self.summary["verdict"]
        if self.status == "diverged":
            return "diverged"
        m = self.summary.get("metrics") or {}
        if m.get("max_abs_deflection_m", 0.0) > 0.01:
            return "deflection_bound_exceeded"
        return "ok" if self.status == "ok" else self.status

    @property
    def metrics(self) -> dict[str, Any]:
        """``summary["metrics"]``: convergence time (s), speed RMSE per car (km/h), max |deflection| (m), ..."""
        return dict(self.summary.get("metrics") or {})

    @property
    def signals(self) -> "pd.DataFrame":
        """signals.csv as a DataFrame indexed by simulated time ``t_s`` (s); every column name ends
        in its unit (``speed_mps_c3``, ``brake_applied_n_c1``, ``deflection_m_k2``; ``_c<i>`` car,
        ``_k<j>`` coupler between cars j and j+1); ECU diagnostics are joined on the tick."""
        if self._signals is None:
            import pandas as pd

            self._signals = pd.read_csv(self.run_dir / "signals.csv", index_col="t_s")
        return self._signals

    @property
    def log_path(self) -> Path:
        """The run's frame log (``frames.log`` or ``frames.<asc|blf|trc|mf4>``)."""
        for p in sorted(self.run_dir.glob("frames.*")):
            if p.suffix in (".log", ".asc", ".blf", ".trc", ".mf4"):
                return p
        return self.run_dir / "frames.log"

    def frames(self) -> Iterator["can.Message"]:
        """Every frame on the bus, in log order, as python-can ``can.Message`` (timestamps: see
        docs/architecture.md, "Frame timestamps")."""
        import can

        yield from can.LogReader(str(self.log_path))

    @property
    def database(self) -> "cantools.database.can.Database":
        """The cantools database the run used (its ``canbrake.dbc``)."""
        import cantools

        return cantools.database.load_file(str(self.run_dir / "canbrake.dbc"))

    def decoded(self, message: str) -> "pd.DataFrame":
        """The frames of one DBC message (e.g. ``"BRAKE_CMD_C3"``) decoded with the run's
        database: one row per frame, indexed by the frame's timestamp (s), signals in DBC units."""
        import pandas as pd

        db = self.database
        m = db.get_message_by_name(message)
        rows, times = [], []
        for f in self.frames():
            if f.arbitration_id == m.frame_id and not f.is_error_frame:
                rows.append(m.decode(bytes(f.data), decode_choices=False))
                times.append(f.timestamp)
        return pd.DataFrame(rows, index=pd.Index(times, name="timestamp_s"))

    def plot(self, which: str = "overview") -> "Figure":
        """A matplotlib Figure of this run: ``overview`` (one page) or one of ``speeds``,
        ``errors``, ``decel``, ``deflections``, ``forces``, ``stopping``. Nothing is written."""
        from canbrake.analysis.plots import run_figures

        figs = run_figures(self.run_dir, only=which)
        if which not in figs:
            raise ValueError(f"plot {which!r}: not available for this run (available: {', '.join(figs) or 'none'})")
        return figs[which]

    def __repr__(self) -> str:
        m = self.metrics
        extra = ""
        if m:
            extra = (f", max |deflection| {m.get('max_abs_deflection_m', float('nan')) * 100:.3g} cm, "
                     f"worst speed RMSE {max(m.get('speed_rmse_kmh') or [float('nan')]):.3g} km/h")
        return f"RunResult({self.summary.get('scenario')!r}, status={self.status!r}{extra}, run_dir='{self.run_dir}')"


def open_run(run_dir: str | Path) -> RunResult:
    """A :class:`RunResult` for an existing run directory (written by ``canbrake run`` or :func:`run`)."""
    d = Path(run_dir)
    try:
        summary = json.loads((d / "summary.json").read_text())
    except FileNotFoundError:
        raise ScenarioError(f"{d}: not a run directory (no summary.json)") from None
    return RunResult(d, summary)


def run(scenario: str | Path | Scenario, *, out: str | Path | None = None, bus: str = "memory",
        mode: str | None = None, profile: str | None = None, channel: str | None = None,
        interface: str | None = None, log_format: str | None = None, plots: bool = True,
        external: Sequence[str] | None = None, **overrides: Any) -> RunResult:
    """Run a scenario and return its results.

    ``scenario``: a YAML file, a built-in scenario's name, or a :class:`Scenario`.
    ``out``: the run directory (default: a new temporary directory, kept). ``bus``: ``memory``
    (one OS process per node over the in-memory bus), ``socketcan`` (``channel`` e.g. vcan0),
    ``virtual`` (python-can virtual bus, one process) or ``inprocess`` (fastest).
    ``mode``: ``lockstep`` or ``realtime``. ``log_format``: ``log`` (candump -L, default),
    ``asc``, ``blf``, ``trc`` or ``mf4``. ``external``: ECU names the run does not start but waits
    for on the bus (their heartbeat within ``ecu.external_start_timeout_s``; the user's own program
    or a real ECU). ``overrides``: scenario fields as in
    :func:`load_scenario` (``duration_s=0.5``, ``seed=2``, ``controller__params__k=20``).

    Bad input raises :class:`canbrake.ScenarioError` before anything runs. A run that fails while
    running (a node process dies, the run stalls) raises :class:`RunFailure`; Ctrl-C raises
    KeyboardInterrupt. A diverged closed loop is a result, not an error: see ``.verdict``.
    """
    from canbrake.run import preflight, run_scenario

    labels = _keyword_labels(overrides, {"mode": "mode", "bus.log_format": "log_format"})
    if mode is not None:
        overrides["mode"] = mode
    if log_format is not None:
        overrides["bus__log_format"] = log_format
    scn = _load(scenario, profile, external, overrides, labels)
    backend = None if bus == "memory" and scn.bus.backend != "memory" else bus
    try:
        preflight(scn, backend, channel, interface)
    except ScenarioError as e:  # a controller parameter given as a keyword: name the keyword
        from canbrake.scenario import blame_overrides

        raise ScenarioError(blame_overrides(str(e), "", _dotted(overrides), labels)) from None
    run_dir = Path(out) if out is not None else Path(tempfile.mkdtemp(prefix=f"canbrake-{scn.name}-"))
    summary = run_scenario(scn, run_dir, backend=backend, channel=channel, interface=interface, plots=plots)
    if summary.get("status") == "interrupted":
        raise KeyboardInterrupt(summary.get("message", "interrupted"))
    if summary.get("status") not in ("ok", "diverged"):
        raise RunFailure(f"run failed: {summary.get('message')} (logs kept in {run_dir})", run_dir, summary)
    return RunResult(run_dir, summary, scn)


def sweep(scenario: str | Path | Scenario, grid: Sequence[str] | Mapping[str, Sequence[Any]], *,
          out: str | Path | None = None, seeds: int = 1, duration_s: float | None = None,
          profile: str | None = None, workers: int = 0, plots: bool = True, **overrides: Any) -> "pd.DataFrame":
    """Run ``scenario`` over a grid of impairments or scenario fields × ``seeds``; one row per run.

    ``grid``: ``canbrake sweep --grid`` specs (``["delay=0:20ms:3", "loss=0,0.1"]``) or a mapping
    from axis name to values in SI (``{"delay": [0, 0.01], "set:controller.params.k": [10, 36]}``;
    axes: delay, loss, jitter (s or probability), state_/cmd_ variants, bitrate (bit/s), period (s),
    ``set:DOTTED.PATH``). ``workers``: 0 runs the points one after another in this process (no
    worker processes); n > 0 uses n local Dask workers. ``out``: where results.csv, the heatmaps
    and thresholds.md go (default: a new temporary directory). Columns: the axes, ``seed``,
    ``status``, the metrics (``max_abs_deflection_m``, ``speed_rmse_kmh_worst``, ...) and the
    classification flags (docs/delay-robustness.md). The DataFrame's ``attrs["out"]`` is the folder.
    """
    import pandas as pd

    from canbrake.startup import children_skip_main
    from canbrake.sweep import GridError, check_axes, parse_grid, run_sweep

    specs = list(grid) if not isinstance(grid, Mapping) else [
        f"{name}={','.join(_grid_value(v) for v in values)}" for name, values in grid.items()]
    try:
        axes = [parse_grid(s) for s in specs]
        check_axes(axes)
    except GridError as e:
        raise ScenarioError(str(e)) from None
    base = load_scenario(scenario, profile=profile)
    out_dir = Path(out) if out is not None else Path(tempfile.mkdtemp(prefix=f"canbrake-sweep-{base.name}-"))
    out_dir.mkdir(parents=True, exist_ok=True)
    if isinstance(scenario, Scenario) or not Path(scenario).exists():
        src = out_dir / f"{base.name}.yaml"  # a Scenario object or a built-in: a file the sweep can record
        src.write_text(base.to_yaml())
        scenario, profile = src, None
    with children_skip_main():
        res = run_sweep(scenario, axes, out_dir, profile=profile, sets=_dotted(overrides), duration_s=duration_s,
                        seeds=seeds, workers=workers, scheduler="none" if workers == 0 else None, plots=plots,
                        progress=False)
    if res.interrupted:
        raise KeyboardInterrupt("sweep interrupted; finished points are in " + str(res.results_csv))
    df = pd.DataFrame(res.rows)
    df.attrs["out"] = str(out_dir)
    return df


def _grid_value(v: Any) -> str:
    if isinstance(v, bool):
        return "true" if v else "false"
    if isinstance(v, float):
        return f"{v:.12g}"
    return str(v)
