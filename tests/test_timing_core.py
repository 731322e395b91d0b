"""The compiled discrete-event core of the timing model (canbrake.bus._timing) against a brute-force
oracle: at each instant the bus is idle, scan every frame queued so far, take each node's head
(priority: lowest arbitration field; FIFO: oldest) and let the lowest arbitration field win
(``_arbitration_key``, the bit-by-bit order on the wire). No heaps, no packed keys."""
from __future__ import annotations

import math

from hypothesis import given, settings
from hypothesis import strategies as st

from canbrake.bus._timing import arb_key
from canbrake.bus.timing import TIME_EPS_S, BusTimingModel, _arbitration_key, frame_bits

NODES = ("plant", "ecu1", "ecu2", "ecu3")

frame = st.tuples(
    st.sampled_from(NODES),
    st.booleans(),                      # extended
    st.integers(0, 0x1FFF_FFFF),        # identifier (masked to 11 bits when standard)
    st.booleans(),                      # remote
    st.integers(0, 8),                  # dlc
    st.integers(0, 400),                # queue time in 10 us steps (ties on purpose)
)


def _oracle(frames: list[tuple], bitrate: float, fifo: bool) -> list[tuple[int, float, float]]:
    """(submission number, start, end) of every frame in bus order, by exhaustive scan."""
    pend = [dict(seq=i, node=n, key=_arbitration_key(a, e, r), tq=t, bits=b) for i, (n, a, e, r, t, b) in
            enumerate(frames)]
    out = []
    free = -math.inf
    while pend:
        t = max(free, min(p["tq"] for p in pend))
        # queued by t within rounding (the model's rule: a frame queued at the instant the bus
        # goes free, computed as a sum of frame times, competes in that arbitration)
        due = [p for p in pend if p["tq"] <= t + TIME_EPS_S]
        heads = []
        for node in NODES:
            mine = [p for p in due if p["node"] == node]
            if mine:
                order = (lambda p: (p["tq"], p["seq"])) if fifo else (lambda p: (p["key"], p["tq"], p["seq"]))
                heads.append(min(mine, key=order))
        win = min(heads, key=lambda p: (p["key"], p["tq"], p["seq"]))
        end = t + win["bits"] / bitrate
        out.append((win["seq"], t, end))
        free = end
        pend.remove(win)
    return out


@settings(max_examples=150, deadline=None)
@given(st.lists(frame, min_size=1, max_size=40), st.sampled_from([125_000, 500_000, 1_000_000]),
       st.booleans(), st.integers(1, 5))
def test_core_matches_brute_force_arbitration(raw, bitrate, fifo, n_steps) -> None:
    frames = []
    for node, ext, aid, remote, dlc, tq in raw:
        aid = aid if ext else aid & 0x7FF
        frames.append((node, aid, ext, remote, tq * 1e-5, frame_bits(aid, ext, dlc, None, "worst", is_remote=remote)))
    m = BusTimingModel(bitrate, queue_policy="fifo" if fifo else "priority", record_history=False)
    for (node, aid, ext, remote, tq, _bits), (_n, _e, _a, _r, dlc, _t) in zip(frames, raw):
        m.submit(node, aid, ext, dlc, None, tq, is_remote=remote)
    got = []
    horizon = 1.0  # every frame ends by then (40 frames x 160 bits at 125 kbit/s < 52 ms after 4 ms)
    for j in range(1, n_steps + 1):  # advancing in steps changes nothing
        got += [(d.ticket.seq, d.t_start_s, d.t_end_s) for d in m.advance(horizon * j / n_steps)]
    assert got == _oracle(frames, float(bitrate), fifo)


@given(st.integers(0, 0x1FFF_FFFF), st.booleans(), st.booleans(),
       st.integers(0, 0x1FFF_FFFF), st.booleans(), st.booleans())
def test_packed_arbitration_key_orders_as_the_wire(a, ea, ra, b, eb, rb) -> None:
    a = a if ea else a & 0x7FF
    b = b if eb else b & 0x7FF
    ka, kb = _arbitration_key(a, ea, ra), _arbitration_key(b, eb, rb)
    pa, pb = arb_key(a, ea, ra), arb_key(b, eb, rb)
    assert (pa < pb) == (ka < kb) and (pa == pb) == (ka == kb)
