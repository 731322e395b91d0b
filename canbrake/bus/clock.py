"""ECU clock drift and timer jitter in simulated time (pure).

A real ECU sends its periodic frames on its own timer, not on the plant's time base. A crystal
off by ``ppm`` parts per million makes the timer's period ``T·(1 + ppm·1e-6)``; relative to the
plant's grid t_k = k·T the send instant of period k then slides by ``−k·T·ppm·1e-6`` and wraps
around every ``1/|ppm·1e-6|`` periods (the timer fires twice in one plant period, or not at all:
a sample slip). Timer jitter adds a random delay uniform in ``[0, jitter_s)`` to every instant.

Model used by the lockstep timing replica (:mod:`canbrake.bus.schedule`): the frames of ECU i
for tick k are queued at ``t_k + offset_i(k)`` with
``offset_i(k) = (phase_s − k·T·ppm·1e-6) mod T + U[0, jitter_s)``, the controller's data still
sampled at t_k. The extra queueing shows up as latency: a state frame whose offset passes the
lockstep deadline c·T is used one tick late, so periodic frames of different ECUs slide against
each other, in and out of the deadline window and of each other's arbitration. A fast clock
(``ppm > 0``) with ``phase_s = 0`` starts just below a whole period late and slides earlier.

Limits: the data are not resampled at the ECU's own instant, slips do not skip or double a
control step (the ECU still computes once per plant tick), and realtime runs use the host clock.
"""
from __future__ import annotations

import math
import random

from pydantic import BaseModel, ConfigDict, Field

__all__ = ["ClockConfig", "EcuClock"]


class ClockConfig(BaseModel):
    """Scenario entry ``ecu.clocks[i]``: the clock of one ECU."""

    model_config = ConfigDict(extra="forbid", frozen=True, allow_inf_nan=False)

    car: int = Field(ge=1, description="the car whose ECU has this clock")
    ppm: float = Field(0.0, ge=-100_000, le=100_000, description="frequency error in parts per million "
                                                                 "(positive: the ECU's timer runs fast)")
    jitter_s: float = Field(0.0, ge=0.0, description="timer jitter: extra delay uniform in [0, jitter_s) (s)")
    phase_s: float = Field(0.0, ge=0.0, description="offset of the ECU's timer from the plant's grid at t = 0 (s)")


class EcuClock:
    """Offsets (s) of one ECU's send instants from the plant's grid, tick by tick (call in order)."""

    def __init__(self, cfg: ClockConfig, period_s: float, seed: int = 0) -> None:
        self.cfg = cfg
        self.period_s = float(period_s)
        self._rng = random.Random(seed)

    def offset_s(self, k: int) -> float:
        """Offset of tick ``k`` (s): drift phase in [0, T) plus jitter. Draws one jitter value per
        call, so call once per tick in increasing k."""
        T = self.period_s
        drift = math.fmod(self.cfg.phase_s - k * T * self.cfg.ppm * 1e-6, T)
        if drift < 0:
            drift += T
        if drift > T * (1 - 1e-12):
            drift = 0.0
        jit = self.cfg.jitter_s * self._rng.random() if self.cfg.jitter_s > 0 else 0.0
        return drift + jit
