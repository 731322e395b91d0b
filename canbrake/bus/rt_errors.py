"""Bus errors in realtime runs: each ECU injects its own (pure state machine, wall-clock times).

In a realtime run the frames travel on a real medium (the in-memory bus, vcan0, an adapter) that
neither corrupts frames nor arbitrates, so the timing model of :mod:`canbrake.bus.faults` cannot
run. What can be done, and is done here, is at the *sender*: before a frame of an ECU goes to
the bus, each transmission attempt is hit with the probability of the scenario's
``bit_error_rate`` (1 − (1 − ber)^n for its n bits, actual stuffing) or of its
``faulty_transceiver`` entry (in its time window, seconds since the run's first SYNC). A failed
attempt puts a python-can error frame (SocketCAN layout, :func:`error_frame`)
on the bus, TEC += 8, and the frame is retried at once; a successful one TEC −= 1. The node is
error-passive from TEC 128 and bus-off above 255: its frames are dropped (its peers' data about
it goes stale, the plant misses its commands) until ``recovery_delay_s`` + 128 × 11 bit times
have passed on the wall clock (an idle bus; a busy one takes longer), or for good without
``auto_recovery``.

Limits, compared with the lockstep model: only ECUs inject (the plant's frames stand in for the
time base); receivers' REC is not counted (no process knows every other's errors); an error
costs no bus time on a medium that has none; retransmissions are immediate.
"""
from __future__ import annotations

import math
import random
from dataclasses import dataclass
from typing import Any

import can

from canbrake.bus.faults import BUS_OFF_LIMIT, PASSIVE_LIMIT, RECESSIVE_SEQUENCE_BITS, RECOVERY_SEQUENCES
from canbrake.bus.timing import frame_bits

__all__ = ["RealtimeErrors", "realtime_errors_of", "error_frame"]

_MAX_ATTEMPTS = 64  # one frame is retried at most this often in one go (bus-off comes after 32 anyway)


# SocketCAN error frame layout (linux/can/error.h)
CAN_ERR_FLAG = 0x20000000
CAN_ERR_CRTL = 0x00000004
CAN_ERR_PROT = 0x00000008
CAN_ERR_BUSOFF = 0x00000040
CAN_ERR_CNT = 0x00000200
CAN_ERR_CRTL_TX_PASSIVE = 0x20
CAN_ERR_PROT_BIT = 0x01


def error_frame(event: Any, t_s: float, channel: str | int, rec: int = 0) -> can.Message:
    """A :class:`canbrake.bus.faults.ErrorEvent` (or anything with ``state`` and ``tec``) as a
    python-can error frame (SocketCAN layout) stamped ``t_s`` (s) on ``channel``: the recorder
    logs it, a realtime ECU's transceiver model (:class:`RealtimeErrors`) puts it on the bus."""
    aid = CAN_ERR_FLAG | CAN_ERR_PROT | CAN_ERR_CNT
    ctrl = 0
    if event.state == "passive":
        aid |= CAN_ERR_CRTL
        ctrl = CAN_ERR_CRTL_TX_PASSIVE
    elif event.state == "bus_off":
        aid |= CAN_ERR_BUSOFF
    data = bytes([0, ctrl, CAN_ERR_PROT_BIT, 0, 0, 0, min(event.tec, 255), min(rec, 255)])
    return can.Message(timestamp=t_s, arbitration_id=aid, is_extended_id=True, is_error_frame=True, dlc=8,
                       data=data, channel=channel, is_rx=True)


@dataclass(frozen=True)
class _Attempt:
    """What :func:`error_frame` needs of an error event."""

    tec: int
    state: str


class RealtimeErrors:
    """One ECU's transmit errors and fault confinement in a realtime run."""

    def __init__(self, node: str, *, bers: list[tuple[float, float, float]], faulty: list[tuple[float, float, float]],
                 seed: int, bitrate_bps: float, auto_recovery: bool = True, recovery_delay_s: float = 0.0) -> None:
        self.node = node
        self.bers = bers            # (ber, start_s, stop_s)
        self.faulty = faulty        # (probability, start_s, stop_s) of this node's transceiver
        self.rng = random.Random(seed)
        self.bitrate = float(bitrate_bps)
        self.auto_recovery = auto_recovery
        self.recovery_delay_s = recovery_delay_s
        self.tec = 0
        self.state = "active"
        self.error_frames = 0
        self.bus_off_episodes = 0
        self.frames_dropped = 0
        self._recover_at = math.inf
        self.changes: list[dict] = []

    def _p_error(self, t_s: float, bits: int) -> float:
        ok = 1.0
        for ber, a, b in self.bers:
            if a <= t_s < b:
                ok *= (1.0 - ber) ** bits
        for p, a, b in self.faulty:
            if a <= t_s < b:
                ok *= 1.0 - p
        return 1.0 - ok

    def _set_state(self, t_s: float) -> None:
        new = "bus_off" if self.tec > BUS_OFF_LIMIT else ("passive" if self.tec >= PASSIVE_LIMIT else "active")
        if new != self.state:
            self.changes.append({"t_s": t_s, "from": self.state, "to": new, "tec": self.tec})
            self.state = new

    def attempt(self, msg: can.Message, t_s: float) -> tuple[list[can.Message], bool]:
        """Send ``msg`` at ``t_s`` (s since the run's start): the error frames that precede it on
        the bus and whether it goes out at all (False: the node is or went bus-off)."""
        if self.state == "bus_off":
            if t_s < self._recover_at:
                self.frames_dropped += 1
                return [], False
            self.tec = 0
            self._set_state(t_s)
        bits = frame_bits(msg.arbitration_id, msg.is_extended_id, msg.dlc, bytes(msg.data), stuffing="actual")
        p = self._p_error(t_s, bits)
        errors: list[can.Message] = []
        for _ in range(_MAX_ATTEMPTS):
            if p <= 0.0 or self.rng.random() >= p:
                self.tec = max(0, self.tec - 1)
                self._set_state(t_s)
                return errors, True
            self.tec += 8
            self._set_state(t_s)
            self.error_frames += 1
            err = error_frame(_Attempt(min(self.tec, 255), self.state), 0.0, "")
            err.arbitration_id &= 0x1FFFFFFF  # the error class bits; the flag is is_error_frame (python-can)
            errors.append(err)
            if self.state == "bus_off":
                self.bus_off_episodes += 1
                self.frames_dropped += 1
                self._recover_at = (t_s + self.recovery_delay_s + RECOVERY_SEQUENCES * RECESSIVE_SEQUENCE_BITS
                                    / self.bitrate) if self.auto_recovery else math.inf
                return errors, False
        self.frames_dropped += 1
        return errors, False

    def summary(self) -> dict[str, Any]:
        return {"state": self.state, "tec": self.tec, "error_frames": self.error_frames,
                "bus_off_episodes": self.bus_off_episodes, "frames_dropped": self.frames_dropped,
                "changes": self.changes[:200]}


def realtime_errors_of(scn: Any, node: str) -> RealtimeErrors | None:
    """The injector of ECU ``node`` for a realtime run of ``scn`` (None if it has no
    ``bit_error_rate`` / ``faulty_transceiver`` impairment for it, or the run is lockstep)."""
    from canbrake.bus.impair import BitErrorRateSpec, FaultyTransceiverSpec, derive_seed

    if scn.mode != "realtime":
        return None
    specs = [s for s in scn.bus.impairments if isinstance(s, (BitErrorRateSpec, FaultyTransceiverSpec))]
    stop = [math.inf if s.stop_s is None else s.stop_s for s in specs]
    bers = [(s.ber, s.start_s, e) for s, e in zip(specs, stop) if isinstance(s, BitErrorRateSpec)]
    faulty = [(s.probability, s.start_s, e) for s, e in zip(specs, stop)
              if isinstance(s, FaultyTransceiverSpec) and s.node == node]
    if not bers and not faulty:
        return None
    return RealtimeErrors(node, bers=bers, faulty=faulty,
                          seed=int(derive_seed(scn.seed, "rt_errors", node).generate_state(1)[0]),
                          bitrate_bps=float(scn.bus.bitrate_bps), auto_recovery=all(s.auto_recovery for s in specs),
                          recovery_delay_s=max(s.recovery_delay_s for s in specs))
