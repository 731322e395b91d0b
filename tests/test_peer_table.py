"""The compiled peer table of an ECU (canbrake.bus._codec.PeerTable) and the receivers' origin
check (frame_origin, behind FrameGuard.origin) against the interpreted rules they replaced:
E2E CRC, alive counter (with its extension), origin window, decode into per-signal arrays, pages
of this tick and peers' ages."""
from __future__ import annotations

import functools
import math
from pathlib import Path

import numpy as np
from hypothesis import given, settings
from hypothesis import strategies as st

from canbrake.build import bus_layout
from canbrake.bus._codec import REJECT_CRC, REJECT_COUNTER, PeerTable
from canbrake.bus.e2e import COUNTER_MODULO, counter_modulus, e2e_crc
from canbrake.bus.guard import FrameGuard
from canbrake.bus.codec import FrameCodec
from canbrake.scenario import load_scenario

ROOT = Path(__file__).resolve().parents[1]


@functools.lru_cache(maxsize=None)
def _layout(name: str):
    lay = bus_layout(load_scenario(ROOT / "scenarios" / name))
    return lay, FrameCodec(lay.database())


def extended_counter(payload, ext):
    """The alive counter with its extension ``ext`` = (start bit, bits): the sender's tick mod
    counter_modulus (canbrake.bus.dbc CounterExt), interpreted."""
    c = payload[1] & 0x0F
    if ext is None:
        return c
    start, bits = ext
    return c + COUNTER_MODULO * ((int.from_bytes(bytes(payload), "little") >> start) & ((1 << bits) - 1))


def _origin_oracle(data_id, payload, k, last_origin, same_tick_ok, ext, max_lag):
    """FrameGuard.origin's rules as they were written in Python: origin or the rejection reason."""
    if len(payload) < 2 or payload[0] != e2e_crc(data_id, payload):
        return "crc"
    if payload[1] & 0x0F >= COUNTER_MODULO:
        return "counter"
    modulus = COUNTER_MODULO if ext is None else counter_modulus(ext[1])
    lag = (k - extended_counter(payload, ext)) % modulus
    origin = k - lag
    if lag > max_lag or origin < last_origin or (origin == last_origin and not same_tick_ok):
        return "counter"
    return origin


@settings(max_examples=60, deadline=None)
@given(data=st.data())
def test_peer_table_takes_state_pages_as_the_interpreted_rules(data):
    """Random state pages of several ECUs (valid, corrupted, old, repeated, counter 15) go into a
    PeerTable and into the interpreted oracle: same verdicts, same values, same ages."""
    which = data.draw(st.sampled_from(["emu8_example.yaml", "li2024_ecp_over_can.yaml",
                                       "chen2023_case1_fine_rail.yaml"]))
    lay, fc = _layout(which)
    n = len(lay.ecus)
    states = [m for m in lay.messages if m.kind == "state"]
    senders = sorted({m.ecu for m in states})[:4]
    pages = [m for m in states if m.ecu in senders]
    pages_of = {e: sum(1 for m in pages if m.ecu == e) for e in senders}
    ext_of = lay.counter_ext()
    names = sorted({sig for m in pages for sig, _ in m.signals if sig} | {"speed_mps", "position_m"})
    max_lag = data.draw(st.sampled_from([7, COUNTER_MODULO - 1]))
    table = PeerTable(n, names, [e - 1 for e in senders], max_lag)
    for m in pages:
        table.add_page(m.frame_id, m.ecu - 1, fc.by_id[m.frame_id]._c, [(sig, sp.name) for sig, sp in m.signals if sig],
                       pages_of[m.ecu] > 1, ext_of.get(m.frame_id))
    want = {nm: np.full(n, np.nan) for nm in names}
    origin = [-(10 ** 12)] * n
    fresh = [0] * n
    for k in range(data.draw(st.integers(1, 40))):
        table.new_tick()
        fresh = [0] * n
        for _ in range(data.draw(st.integers(0, 6))):
            m = data.draw(st.sampled_from(pages))
            c = fc.by_id[m.frame_id]
            sent = k - data.draw(st.integers(0, 20))
            vals = {sp.name: data.draw(st.floats(-50, 50)) for sig, sp in m.signals if sig}
            payload = bytearray(c.encode(vals, counter=sent % COUNTER_MODULO, tick=sent))
            how = data.draw(st.sampled_from(["ok", "ok", "flip", "counter15"]))
            if how == "flip":
                payload[data.draw(st.integers(0, len(payload) - 1))] ^= 1 << data.draw(st.integers(0, 7))
            elif how == "counter15":
                payload[1] |= 0x0F
                payload[0] = e2e_crc(m.frame_id, payload)
            j = m.ecu - 1
            ext = ext_of.get(m.frame_id)
            o = _origin_oracle(m.frame_id, payload, k, origin[j], pages_of[m.ecu] > 1, ext, max_lag)
            got = table.take(m.frame_id, payload, k)
            guard = FrameGuard(None, max_lag=max_lag)
            guard.counter_ext = ext_of
            assert guard.origin(m.frame_id, payload, k, origin[j], same_tick_ok=pages_of[m.ecu] > 1) == (
                None if isinstance(o, str) else o)
            if isinstance(o, str):
                assert got == (REJECT_CRC if o == "crc" else REJECT_COUNTER) and guard.last_reason == o
                continue
            d = c.decode(payload)
            for sig, sp in m.signals:
                if sig:
                    want[sig][j] = d[sp.name]
            if o > origin[j]:
                origin[j], fresh[j] = o, 0
            expect = 0
            if o == k:
                fresh[j] += 1
                expect = 2 if fresh[j] == pages_of[m.ecu] else 1
            assert got == expect
            assert table.origin_of(j) == origin[j]
        for nm in names:
            np.testing.assert_array_equal(table.values[nm], want[nm])
        own = data.draw(st.integers(0, n - 1))
        speed = want["speed_mps"].copy()
        speed[own] = 1.0
        age, nfresh, max_age = table.ages(k, 0.01, own, speed)
        o_all = list(origin)
        o_all[own] = k
        ages = [math.inf if o < 0 and v != v else (k - o) * 0.01 for o, v in zip(o_all, speed.tolist())]
        assert age.tolist() == ages
        assert nfresh == 1 + sum(1 for e in senders if origin[e - 1] == k)
        assert max_age == max((a for a in ages if a != math.inf), default=-math.inf)
