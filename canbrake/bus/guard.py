"""Receiver-side checks the nodes call on every protected or simulation-control frame.

One object per receiving node; it owns the rejection counters by reason, which go into the
node's stats and from there into ``summary.json`` (``safety.rejected``):

* ``crc`` — E2E CRC wrong (corruption, or a frame built for another data ID);
* ``counter`` — alive counter invalid (15), too old for the window, or not newer than the last
  accepted frame (repetition, resequencing, delay beyond the window);
* ``freshness`` — authentic frame of an earlier tick whose counter aliases to a newer one (a
  replay that the 4-bit counter alone would have accepted);
* ``authentication`` — MAC wrong (forged frame, masquerade);
* ``unknown_sender`` — a frame on an identifier of the protected ranges that no node of this
  train sends (insertion);
* ``sync`` — a SYNC or barrier frame out of sequence or at a moment the protocol never sends it.

The 4-bit counter (tick mod 15): a frame is placed at ``origin = k - ((k - c) mod 15)``, so a
frame up to 14 periods old is dated right, one 15·m + d periods old is taken for d periods old
(aliasing). The brake unit accepts a lag of at most ``max_lag`` (7) periods and only origins
newer than the last accepted command, so without authentication a verbatim copy of the command
sent 15·m periods earlier passes if it arrives before this period's genuine one.
"""
from __future__ import annotations

from typing import Any

from canbrake.bus._codec import REJECT_CRC, SYNC_END, SYNC_END_IGNORED, SYNC_REJECT, frame_origin, sync_check
from canbrake.bus.e2e import COUNTER_MODULO, counter_modulus
from canbrake.bus.secoc import STALE_ALIASES, SecOC

REASONS = ("crc", "counter", "freshness", "authentication", "unknown_sender", "sync")


class FrameGuard:
    """E2E (+ optional SecOC) checks of the protected frames one node receives."""

    def __init__(self, secoc: SecOC | None = None, *, max_lag: int = COUNTER_MODULO - 1) -> None:
        self.secoc = secoc
        self.max_lag = max_lag
        self.rejected: dict[str, int] = {r: 0 for r in REASONS}
        self.unknown_ids: dict[str, int] = {}
        self.last_reason: str | None = None  # reason of the last rejection
        self.rx_overruns = 0       # receive-queue overflows (flood), see Node.on_rx_overrun
        self.rx_frames_lost = 0    # frames dropped by them
        self.end_ignored = 0       # unauthenticated END frames before the last scheduled tick
        self.state_auth_orphans = 0  # STATE_AUTH frames whose state frame never came (lost)
        #: frames whose counter has an extension (canbrake.bus.dbc CounterExt): id -> (start bit, bits)
        self.counter_ext: dict[int, tuple[int, int]] = {}

    def reject(self, reason: str) -> None:
        self.rejected[reason] += 1
        self.last_reason = reason

    def unknown(self, arbitration_id: int) -> None:
        """Count a frame from a sender this train does not have (by identifier, hex)."""
        self.reject("unknown_sender")
        key = f"{arbitration_id:#05x}"
        self.unknown_ids[key] = self.unknown_ids.get(key, 0) + 1

    def origin(self, data_id: int, payload: bytes | bytearray, k: int, last_origin: int,
               *, authenticated: bool = False, same_tick_ok: bool = False, crc_checked: bool = False) -> int | None:
        """Tick the frame was sent in, or None (rejected and counted). ``k``: the receiver's tick;
        ``last_origin``: tick of the newest frame accepted from this sender (per data ID, or per
        sender with ``same_tick_ok`` when it sends several pages per tick); ``crc_checked``: the
        caller has checked the E2E CRC already (an E2E receiver's check)."""
        ext = self.counter_ext.get(data_id)
        origin, code = frame_origin(data_id, payload, k, last_origin, same_tick_ok, crc_checked, ext, self.max_lag)
        if origin is None:
            self.reject("crc" if code == REJECT_CRC else "counter")
            return None
        if authenticated and not self.authentic(data_id, payload, origin):
            return None
        return origin

    def authentic(self, data_id: int, payload: bytes | bytearray, origin: int) -> bool:
        """SecOC (True without it): the frame's MAC verifies with freshness tick ``origin``; a
        failure is counted: "freshness" if it verifies for an older tick with the same counter
        (a replay), else "authentication"."""
        if self.secoc is None:
            return True
        if self.secoc.verify(data_id, payload, origin, has_crc=True):
            return True
        ext = self.counter_ext.get(data_id)
        modulus = COUNTER_MODULO if ext is None else counter_modulus(ext[1])
        stale = any(self.secoc.verify(data_id, payload, origin - modulus * m, has_crc=True)
                    for m in range(1, STALE_ALIASES + 1))
        self.reject("freshness" if stale else "authentication")
        return False

    def control(self, data_id: int, payload: bytes | bytearray, freshness_tick: int) -> bool:
        """Authenticate a simulation-control frame (SYNC, barrier); True without SecOC."""
        if self.secoc is None:
            return True
        if self.secoc.verify(data_id, payload, freshness_tick, has_crc=False):
            return True
        self.reject("authentication")
        return False

    def overrun(self, frames_lost: int) -> None:
        """Count a receive-queue overflow that dropped ``frames_lost`` frames."""
        self.rx_overruns += 1
        self.rx_frames_lost += int(frames_lost)

    def stats(self) -> dict[str, Any]:
        return {"rejected": dict(self.rejected), "unknown_ids": dict(self.unknown_ids),
                "rx_overruns": self.rx_overruns, "rx_frames_lost": self.rx_frames_lost,
                "end_ignored": self.end_ignored, "state_auth_orphans": self.state_auth_orphans}


def sign_control(secoc: SecOC | None, data_id: int, payload: bytes, freshness_tick: int) -> bytes:
    """Sign a simulation-control frame (no-op without SecOC)."""
    if secoc is None:
        return payload
    return secoc.sign(data_id, payload, freshness_tick, has_crc=False)


def sign_protected(secoc: SecOC | None, data_id: int, payload: bytes, tick: int) -> bytes:
    """Sign an E2E-protected frame (MAC, then CRC over it); no-op without SecOC."""
    if secoc is None:
        return payload
    return secoc.sign(data_id, payload, tick, has_crc=True)



def sync_verdict(guard: FrameGuard, data_id: int, payload: bytes | bytearray, own_k: int, *,
                 tick_complete: bool, lockstep: bool, final_tick: int | None = None) -> str | None:
    """Check a SYNC frame at a receiver whose last accepted tick is ``own_k``: "tick" (start the
    next period), "end" (end of the run) or None (rejected and counted).

    Lockstep: the time master sends SYNC(k+1), and the END frame, only once every node has
    finished tick k, so a SYNC is accepted only if it is the next tick and the receiver has
    finished its tick (``tick_complete``). With SecOC the frame's MAC must match (freshness = its
    tick, for END the receiver's last tick), and an authentic END may come early (the closed loop
    diverged). Without SecOC an END is accepted only after ``final_tick``, the last scheduled tick
    (when given): a forged one cannot be told from the plant's early END, so an early end of the
    run is left to the driver, which ends the other nodes once the time master has finished.
    Realtime: any newer tick is accepted. The sequence rules are compiled
    (:func:`canbrake.bus._codec.sync_check`, which the ECU's peer table applies itself).
    """
    code, tick = sync_check(payload, own_k, tick_complete, lockstep, final_tick, guard.secoc is not None)
    if code == SYNC_REJECT:
        guard.reject("sync")
        return None
    if code == SYNC_END_IGNORED:
        guard.end_ignored += 1  # forged, or the plant's own early END (diverged): not a rejection reason
        return None
    end = code == SYNC_END
    if not guard.control(data_id, payload, own_k if end else tick):
        return None
    return "end" if end else "tick"
