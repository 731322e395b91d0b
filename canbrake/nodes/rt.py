"""Realtime scheduling of a node process (``mode: realtime`` with one process per node).

What Linux offers, applied where permitted and reported either way:

- ``SCHED_FIFO`` (``os.sched_setscheduler``): the plant (time master) at priority 60, ECUs at 50,
  the recorder at 40 (writers wait for it: a starved recorder would stall the bus),
  so a node that a frame makes runnable preempts the ordinary (``SCHED_OTHER``) processes of the
  machine at once. Needs CAP_SYS_NICE (root or an rtprio limit); without it the node stays
  ``SCHED_OTHER`` and tries ``nice -10``; the description says which was obtained. The kernel's RT
  throttling (``/proc/sys/kernel/sched_rt_runtime_us``, 95 % by default) keeps a runaway FIFO node
  from locking the machine; the nodes block on the bus between frames and spin only for the last
  ``spin_s`` before a deadline.
- CPU affinity (``os.sched_setaffinity``), policy ``CANBRAKE_RT_AFFINITY``: ``plant`` (default)
  pins the plant to the last CPU and leaves the others free; ``split`` also keeps every other
  node off that CPU; ``none`` pins nothing.

- Python's garbage collector: every node process, in any mode, freezes what it holds after
  setting up (:func:`canbrake.nodes.driver.freeze_heap`, ``CANBRAKE_GC``): a full collection
  would otherwise walk it, long enough to miss a 10 ms deadline.

``CANBRAKE_RT_SCHED=off`` turns all of it off (the fallback path, for comparison).
"""
from __future__ import annotations

import os

PRIORITY = {"plant": 60, "ecu": 50, "recorder": 40}


def spin_s(period_s: float) -> float:
    """How long before a deadline a realtime node polls and yields instead of sleeping (s):
    ``CANBRAKE_RT_SPIN_US`` (default 100 us), at most 20 % of the period ``period_s`` (s)."""
    return min(float(os.environ.get("CANBRAKE_RT_SPIN_US", "100")) * 1e-6, 0.2 * period_s)


def setup_realtime(role: str) -> str:
    """Apply realtime scheduling and affinity to this process (a node of ``role``: plant, ecu,
    recorder, ...); returns what was obtained, e.g. ``"SCHED_FIFO 60, CPUs [1]"``."""
    if os.environ.get("CANBRAKE_RT_SCHED", "fifo") == "off":
        return "SCHED_OTHER (CANBRAKE_RT_SCHED=off)"
    return _schedule(role)


def _schedule(role: str) -> str:
    """SCHED_FIFO (or nice) and affinity for a node of ``role``; what was obtained."""
    parts = []
    prio = PRIORITY.get(role)
    if prio is None:
        parts.append("SCHED_OTHER (not a realtime role)")
    elif not hasattr(os, "sched_setscheduler"):
        parts.append("SCHED_OTHER (no sched_setscheduler on this platform)")
    else:
        try:
            os.sched_setscheduler(0, os.SCHED_FIFO, os.sched_param(prio))
            parts.append(f"SCHED_FIFO {prio}")
        except OSError as e:
            try:
                os.nice(-10)
                parts.append(f"SCHED_OTHER nice -10 (SCHED_FIFO not permitted: {e.strerror})")
            except OSError:
                parts.append(f"SCHED_OTHER (SCHED_FIFO and nice not permitted: {e.strerror})")
    policy = os.environ.get("CANBRAKE_RT_AFFINITY", "plant")
    try:
        cpus = sorted(os.sched_getaffinity(0))
    except (AttributeError, OSError):
        return ", ".join(parts)
    if policy in ("plant", "split") and len(cpus) >= 2:
        want = [cpus[-1]] if role == "plant" else (cpus[:-1] if policy == "split" else cpus)
        try:
            os.sched_setaffinity(0, want)
            cpus = want
        except OSError as e:
            parts.append(f"affinity not set: {e.strerror}")
    parts.append(f"CPUs {cpus}")
    return ", ".join(parts)
