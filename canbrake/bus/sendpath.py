"""Per-node send paths for runs: the impairment chain of :mod:`canbrake.bus.impair` adapted to
the nodes' ``can.Message`` protocol, with the lockstep simulation-control frames exempt.

Lockstep timing (simulated time, T = control period, c = ``ecu.lockstep_deadline``):
a frame a node submits in phase 1 of tick k (state, heartbeat) is submitted at t_k and is seen by
the other ECUs in that tick if its impaired latency is at most c·T; a command submitted in phase
2 (at t_k + c·T) reaches the plant in that tick if it arrives by t_k + T. Later frames are held
by the sender and released in the first phase whose horizon reaches their release time, so
"delayed by d" means "used ceil-ish(d/T) periods later", decided deterministically per seed.
"""
from __future__ import annotations

from typing import Any

import can

from canbrake.bus import dbc
from canbrake.bus.impair import MessageSendPath, build_impairments


def exempt_ids(layout: Any) -> set[int]:
    """Frames never impaired: the lockstep barrier frames, and the plant's frames (SYNC,
    reference, sensors), which stand in for the time base and each car's local wiring."""
    if isinstance(layout, int):  # a number of cars: Chen's default placement
        layout = dbc.BusLayout(dbc.default_ecus(layout, coupler_sensors=True))
    return {m.frame_id for m in layout.messages
            if m.kind in ("sync", "reference", "reference_pos", "sensor", "state_done", "cmd_done")
            or (m.kind == "heartbeat" and m.ecu == 0)}


class HorizonSendPath:
    """Node-side send path: ``submit(msg, t_s)`` then ``release(horizon_s)``."""

    def __init__(self, path: MessageSendPath) -> None:
        self.path = path

    def submit(self, msg: can.Message, t_s: float, delay_s: float = 0.0) -> list[can.Message]:
        return self.path.submit(msg, t_s, delay_s)

    def release(self, t_s: float) -> list[can.Message]:
        return self.path.release(t_s)

    def counters(self) -> dict[str, int]:
        return self.path.counters()


def build_send_path(scn: Any, node: str, layout: Any) -> HorizonSendPath:
    """Send path of ``node`` ("ecu3", "plant", or a phantom babbler's name) on the bus ``layout``
    (:func:`canbrake.build.bus_layout`)."""
    path = build_impairments(scn.bus.impairments, scn.seed, node, exempt_ids=exempt_ids(layout))
    return HorizonSendPath(MessageSendPath(path, node))
