"""canbrake: CAN-bus-in-the-loop emulator for distributed train braking control.

The Python API (docs/python-api.md): :func:`load_scenario`, :func:`run` (-> :class:`RunResult`),
:func:`sweep` (-> pandas DataFrame), :func:`open_run`. Imported lazily, so ``import canbrake``
stays cheap for node processes and the command line.
"""
from __future__ import annotations

from typing import Any

__version__ = "0.1.0"

__all__ = ["load_scenario", "run", "sweep", "open_run", "RunResult", "RunFailure", "ScenarioError",
           "Scenario", "scenarios"]


def __getattr__(name: str) -> Any:
    if name in ("run", "sweep"):  # the modules, made callable as the API's run() and sweep()
        import importlib

        return importlib.import_module(f"canbrake.{name}")
    if name in ("load_scenario", "open_run", "RunResult", "RunFailure"):
        from canbrake import api

        return getattr(api, name)
    if name in ("ScenarioError", "Scenario"):
        from canbrake import scenario

        return getattr(scenario, name)
    if name == "scenarios":
        from canbrake.builtin import builtin_scenarios

        return builtin_scenarios
    raise AttributeError(f"module 'canbrake' has no attribute {name!r}")
