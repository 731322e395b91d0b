"""External ECUs (``ecus: [{..., external: true}]``, ``--external NAME``): ECUs canbrake does not
start — a foreign program (examples/foreign_ecu.py, examples/foreign_ecu_c/) or a real ECU on the
bus — that follow docs/lockstep-protocol.md. The plant waits for each one's first heartbeat before
the first tick; in lockstep every node waits at most ``ecu.external_timeout_s`` for their frames of
a period (canbrake.nodes.plant / ecu); this module holds what the orchestrator and the summary
say about them."""
from __future__ import annotations

import json
from pathlib import Path
from typing import Any

from canbrake.scenario import Scenario


def missing_message(scn: Scenario, run_dir: Path, channel: str) -> str:
    """One message naming the external ECUs that never sent a heartbeat, and the channel."""
    from canbrake.build import bus_layout

    try:
        missing = json.loads((run_dir / "plant_stats.json").read_text())["extra"]["missing"]
    except (OSError, ValueError, KeyError):
        missing = [p.name for p in scn.placement() if p.external]
    layout = bus_layout(scn)
    names = {e.name: e for e in layout.ecus}
    which = ", ".join(f"{n} (HEARTBEAT {layout.plan.heartbeat(names[n].index):#x})" if n in names else n
                      for n in missing)
    return (f"external ECU {which} not heard on {channel} within {scn.ecu.external_start_timeout_s:g} s "
            f"(ecu.external_start_timeout_s): start it on that channel (it must send its heartbeat until the "
            f"first SYNC, docs/lockstep-protocol.md), or check the channel, bit rate and wiring")


def external_summary(scn: Scenario, plant: dict[str, Any]) -> dict[str, Any] | None:
    """``summary.json``'s ``external_ecus``: per external ECU its first heartbeat (wall s after the
    plant started), the periods the plant went without its commands, lockstep time-outs, late
    frames and its response time (SYNC to its complete commands, wall s). None without any."""
    ext = plant.get("external") or {}
    if not ext:
        return None
    resp = plant.get("response_s") or {}
    return {name: {**figs, "response_s": resp.get(name)} for name, figs in ext.items()}


def external_finding(scn: Scenario, ext: dict[str, Any] | None, ticks: int) -> dict[str, Any] | None:
    """A ``late`` finding when an external ECU missed periods (silent or late), else None."""
    if not ext:
        return None
    bad = {n: f for n, f in ext.items() if f.get("periods_missed")}
    if not bad:
        return None
    parts = [f"{n} missed {f['periods_missed']} of {ticks} periods"
             + (f" ({f['timeouts']} lockstep time-outs of {scn.ecu.external_timeout_s:g} s)" if f.get("timeouts") else "")
             for n, f in bad.items()]
    return {"kind": "late", "external_ecus": {n: f["periods_missed"] for n, f in bad.items()},
            "message": "external ECU silent or late: " + "; ".join(parts)
                       + (" (fail-safe braking applies after safety.command_timeout_s)"
                          if scn.safety.command_timeout_s is not None else
                          " (the plant holds its last command: set safety.command_timeout_s for a fail-safe reaction)")}
