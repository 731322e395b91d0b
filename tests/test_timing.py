"""CAN wire timing: frame lengths by hand, arbitration, and the 6-car load example."""
from __future__ import annotations

import math
import random

import pytest

from canbrake.bus.timing import (
    IFS_BITS,
    BusTimingModel,
    crc15,
    frame_bits,
    frame_bitstream,
    frame_time_s,
    stuff_bit_count,
)

US = 1e-6


# --------------------------------------------------------------------------------------------
# frame_bits


def test_hand_check_8_byte_standard_frame_at_500k() -> None:
    # 1 SOF + 11 ID + 3 (RTR, IDE, r0) + 4 DLC + 64 data + 15 CRC = 98 stuffable bits,
    # + 10 (CRC delim, ACK, ACK delim, 7 EOF) + 3 IFS = 111; worst stuffing (98 - 1)//4 = 24.
    assert frame_bits(0x123, False, 8, stuffing="none") == 111
    assert frame_bits(0x123, False, 8, stuffing="worst") == 135
    assert frame_time_s(135, 500_000) == pytest.approx(270 * US)
    assert frame_bits(0x123, False, 8, include_ifs=False) == 135 - IFS_BITS


def test_other_frame_lengths_by_hand() -> None:
    # extended 8 bytes: 54 + 64 = 118 stuffable, + 13 = 131, + (117)//4 = 29 -> 160
    assert frame_bits(0x1ABCDEF, True, 8, stuffing="none") == 131
    assert frame_bits(0x1ABCDEF, True, 8) == 160
    # standard 0 bytes: 34 + 13 = 47, + 33//4 = 8 -> 55; a remote frame has no data field
    assert frame_bits(0x10, False, 0) == 55
    assert frame_bits(0x10, False, 8, is_remote=True) == 55
    # 5-byte and 4-byte standard frames (the brake command and SYNC of the example below)
    assert frame_bits(0x100, False, 5) == 47 + 40 + 18 == 105
    assert frame_bits(0x080, False, 4) == 47 + 32 + 16 == 95


def test_crc15_catalogue_check_value() -> None:
    # CRC-15/CAN (poly 0x4599, init 0, no reflection): check("123456789") = 0x059E
    bits = [int(c) for byte in b"123456789" for c in format(byte, "08b")]
    assert crc15(bits) == 0x059E


def test_stuffing_rule_by_hand() -> None:
    assert stuff_bit_count([0] * 4) == 0
    assert stuff_bit_count([0] * 5) == 1  # inserted even after the last bit
    assert stuff_bit_count([0] * 5 + [1] * 4) == 2  # the stuff bit (1) starts the next run
    assert stuff_bit_count([0] * 10) == 2
    assert stuff_bit_count([0, 1] * 20) == 0


def test_actual_stuffing_all_zero_frame() -> None:
    # ID 0, DLC 0: SOF..DLC are 19 zeros and the CRC of zeros is 0 -> 34 zeros -> runs of
    # 5 separated by stuff bits: 6 stuff bits; 34 + 6 + 13 = 53.
    assert frame_bitstream(0, False, 0) == [0] * 34
    assert frame_bits(0, False, 0, b"", stuffing="actual") == 53


def test_actual_stuffing_matches_reference_and_never_exceeds_worst() -> None:
    rng = random.Random(7)
    for _ in range(3000):
        ext = rng.random() < 0.5
        ident = rng.randrange(1 << (29 if ext else 11))
        dlc = rng.randrange(9)
        remote = rng.random() < 0.1
        data = bytes(rng.choice([0x00, 0xFF, 0x0F, rng.randrange(256)]) for _ in range(dlc))
        ref = frame_bitstream(ident, ext, dlc, data, is_remote=remote)
        expect = len(ref) + stuff_bit_count(ref) + 10 + IFS_BITS
        got = frame_bits(ident, ext, dlc, data, "actual", is_remote=remote)
        assert got == expect
        assert frame_bits(ident, ext, dlc, stuffing="none", is_remote=remote) <= got
        assert got <= frame_bits(ident, ext, dlc, stuffing="worst", is_remote=remote)


@pytest.mark.parametrize("args, match", [
    ((0x800, False, 8), "out of range"),
    ((-1, False, 8), "out of range"),
    ((1 << 29, True, 8), "out of range"),
    ((0x10, False, 9), "dlc"),
])
def test_frame_bits_rejects_bad_frames(args: tuple, match: str) -> None:
    with pytest.raises(ValueError, match=match):
        frame_bits(*args)


def test_frame_bits_rejects_bad_stuffing_and_payload() -> None:
    with pytest.raises(ValueError, match="stuffing"):
        frame_bits(0x10, False, 8, stuffing="best")  # type: ignore[arg-type]
    with pytest.raises(ValueError, match="needs the payload"):
        frame_bits(0x10, False, 8, None, "actual")
    with pytest.raises(ValueError, match="3 bytes but dlc is 8"):
        frame_bits(0x10, False, 8, b"abc", "actual")


@pytest.mark.parametrize("rate", [0, -500_000, 2_000_000, math.nan, math.inf])
def test_bitrate_validation(rate: float) -> None:
    with pytest.raises(ValueError, match="bitrate_bps"):
        BusTimingModel(rate)


@pytest.mark.parametrize("rate", [125_000, 250_000, 500_000, 1_000_000])
def test_standard_bitrates(rate: int) -> None:
    m = BusTimingModel(rate)
    m.submit("a", 0x10, False, 8, None, 0.0)
    (d,) = m.advance(1.0)
    assert d.t_end_s - d.t_start_s == pytest.approx(135 / rate)


# --------------------------------------------------------------------------------------------
# arbitration


def test_same_instant_frames_go_out_in_identifier_order() -> None:
    m = BusTimingModel(500_000)
    for node, ident in [("c", 0x300), ("a", 0x100), ("d", 0x050), ("b", 0x200)]:
        m.submit(node, ident, False, 8, None, 0.0)
    out = m.advance(0.01)
    assert [d.arbitration_id for d in out] == [0x050, 0x100, 0x200, 0x300]
    assert [d.t_start_s for d in out] == pytest.approx([0, 270 * US, 540 * US, 810 * US])
    assert out[-1].latency_s == pytest.approx(4 * 270 * US)


def test_frame_on_the_wire_is_not_preempted() -> None:
    m = BusTimingModel(500_000)
    m.submit("low", 0x7FF, False, 8, None, 0.0)
    m.submit("high", 0x001, False, 8, None, 10 * US)  # arrives while 0x7FF is sending
    first, second = m.advance(0.01)
    assert (first.arbitration_id, first.t_start_s) == (0x7FF, 0.0)
    assert second.arbitration_id == 0x001
    assert second.t_start_s == pytest.approx(270 * US)
    assert second.queueing_delay_s == pytest.approx(260 * US)


def test_standard_beats_extended_with_same_base_id_and_data_beats_remote() -> None:
    m = BusTimingModel(1_000_000)
    m.submit("x", 0x123 << 18, True, 0, None, 0.0)
    m.submit("y", 0x123, False, 0, None, 0.0, is_remote=True)
    m.submit("z", 0x123, False, 0, None, 0.0)
    order = [(d.node, d.is_remote) for d in m.advance(1.0)]
    assert order == [("z", False), ("y", True), ("x", False)]


def test_queue_policy_within_a_node() -> None:
    for policy, expect in [("priority", [0x050, 0x100, 0x300]), ("fifo", [0x300, 0x100, 0x050])]:
        m = BusTimingModel(500_000, queue_policy=policy)  # type: ignore[arg-type]
        m.submit("blocker", 0x001, False, 8, None, 0.0)  # keeps the bus busy meanwhile
        for ident in (0x300, 0x100, 0x050):
            m.submit("n", ident, False, 8, None, 1 * US)
        assert [d.arbitration_id for d in m.advance(1.0)][1:] == expect


def test_fifo_node_head_of_line_blocking() -> None:
    # with one FIFO mailbox, node n's 0x300 at the head blocks its 0x010 behind it; a
    # priority node m with 0x200 therefore wins against n's head.
    m = BusTimingModel(500_000, queue_policy="fifo")
    m.submit("blocker", 0x001, False, 8, None, 0.0)
    m.submit("n", 0x300, False, 8, None, 1 * US)
    m.submit("n", 0x010, False, 8, None, 2 * US)
    m.submit("m", 0x200, False, 8, None, 3 * US)
    assert [d.arbitration_id for d in m.advance(1.0)] == [0x001, 0x200, 0x300, 0x010]


def test_incremental_advance_equals_one_advance_and_respects_causality() -> None:
    def load(m: BusTimingModel, step: float | None) -> list[tuple]:
        out = []
        for k in range(20):
            t = k * 0.0003
            if step is not None:
                out += m.advance(t)
            m.submit(f"n{k % 3}", 0x100 + (7 * k) % 11, False, k % 9, None, t)
        out += m.advance(1.0)
        return [(d.node, d.arbitration_id, d.t_start_s, d.t_end_s) for d in out]

    assert load(BusTimingModel(250_000), 1) == load(BusTimingModel(250_000), None)
    m = BusTimingModel(250_000)
    m.advance(0.5)
    with pytest.raises(ValueError, match="before the model's current time"):
        m.submit("a", 0x10, False, 1, None, 0.4)
    with pytest.raises(ValueError, match="time only moves on"):
        m.advance(0.1)


def test_frame_in_flight_at_until_is_returned_later() -> None:
    m = BusTimingModel(500_000)
    m.submit("a", 0x10, False, 8, None, 0.0)
    assert m.advance(100 * US) == []
    assert m.latency_stats(0x10).n_pending == 1
    (d,) = m.advance(300 * US)
    assert d.t_end_s == pytest.approx(270 * US)
    assert m.latency_stats(0x10).n_pending == 0


def test_actual_stuffing_in_model_and_tag_passthrough() -> None:
    m = BusTimingModel(1_000_000, stuffing="actual")
    tag = object()
    m.submit("a", 0, False, 0, b"", 0.0, tag=tag)
    (d,) = m.advance(1.0)
    assert d.bits == 53 and d.tag is tag and d.t_end_s == pytest.approx(53 * US)


def test_submit_message_reads_a_can_message() -> None:
    can = pytest.importorskip("can")
    m = BusTimingModel(500_000)
    msg = can.Message(arbitration_id=0x18FF0001, is_extended_id=True, data=bytes(8))
    m.submit_message("a", msg, 0.0)
    (d,) = m.advance(1.0)
    assert d.bits == 160 and d.tag is msg
    with pytest.raises(ValueError, match="CAN FD"):
        m.submit_message("a", can.Message(is_fd=True, data=bytes(12)), 1.0)


# --------------------------------------------------------------------------------------------
# the 6-car example: per period SYNC (4 B) + 6 sensor (8 B) from the plant, and per car one
# state (8 B) + one brake command (5 B), all queued at the start of the period.
#
# Worst-case bits incl. IFS: 8 B = 135, 5 B = 105, 4 B = 95.
#   per period: 12 x 135 + 6 x 105 + 95 = 2345 bits (no stuffing: 12 x 111 + 6 x 87 + 79 = 1933)
#   500 kbit/s: 4690 us per 1 ms period -> offered load 4.69
#   1 Mbit/s:   2345 us per 1 ms period -> offered load 2.345 — it does NOT fit at 1 Mbit/s
#               either (not even without stuffing: 1.933). It needs a period >= 2.345 ms.
# Priorities (low id wins): SYNC 0x080 < commands 0x100+i < sensors 0x180+i < states 0x200+i.

SYNC, CMD, SENSOR, STATE = 0x080, 0x100, 0x180, 0x200
BITS_PER_PERIOD = 12 * 135 + 6 * 105 + 95


def _train_traffic(bitrate: int, period_s: float, n_periods: int,
                   policy: str = "priority") -> BusTimingModel:
    m = BusTimingModel(bitrate, queue_policy=policy)  # type: ignore[arg-type]
    for k in range(n_periods):
        t = k * period_s
        m.submit("plant", SYNC, False, 4, None, t)
        for i in range(6):
            m.submit("plant", SENSOR + i, False, 8, None, t)
        for i in range(6):
            m.submit(f"ecu{i + 1}", STATE + i, False, 8, None, t)
            m.submit(f"ecu{i + 1}", CMD + i, False, 5, None, t)
        m.advance(t + period_s)
    return m


def test_six_cars_1ms_at_500k_does_not_fit_and_queues_grow() -> None:
    n = 40
    m = _train_traffic(500_000, 1e-3, n)
    assert BITS_PER_PERIOD == 2345
    loads = m.load_stats(1e-3)
    assert loads.mean_offered == pytest.approx(4.69)
    assert loads.peak_offered == pytest.approx(4.69)
    assert loads.busy_fraction == pytest.approx(1.0)  # saturated in every period
    assert m.bus_load(0.0, n * 1e-3) == pytest.approx(1.0)
    # only 1000 us / 1 ms of bus time: the backlog grows by ~3.69 ms of frames per period
    backlog = m.pending_count()
    assert backlog > 0.7 * n * 19
    # SYNC (highest priority) is bounded: one blocking 8-byte frame + itself = 270 + 190 us
    assert m.latency_stats(SYNC).max_s <= (135 + 95) * 2 * US + 1e-12
    # low-priority state frames are starved: never delivered, and waiting for the whole run
    for i in range(6):
        st = m.latency_stats(STATE + i)
        assert st.n_delivered == 0 and st.n_pending == n
        assert st.max_pending_age_s == pytest.approx(n * 1e-3)
    # ... and the partially served command 0x103 sees its latency grow from period to period
    lat = m.latency_stats(CMD + 3)
    assert lat.max_s > 5e-3 and lat.p50_s > 1e-3


def test_six_cars_1ms_at_1M_does_not_fit_either() -> None:
    n = 40
    m = _train_traffic(1_000_000, 1e-3, n)
    loads = m.load_stats(1e-3)
    assert loads.mean_offered == pytest.approx(2.345)
    assert loads.mean_busy == pytest.approx(1.0)
    # SYNC + 6 commands take 95 + 6 x 105 = 725 us: they fit; the worst case adds one
    # blocking 8-byte frame (135 us) -> response time <= 860 us, every period
    for i in range(6):
        st = m.latency_stats(CMD + i)
        assert st.n_delivered == n and st.max_s <= 860 * US + 1e-12
    # what is left (275 us/period) carries two sensor frames: sensor 2..5 and all state
    # frames back up without bound
    assert m.latency_stats(SENSOR + 5).n_delivered == 0
    assert m.latency_stats(node="ecu1", msg_id=STATE).n_pending == n
    assert m.pending_count() > 0.5 * n * 10


def test_six_cars_fit_at_1M_with_a_2_5ms_period() -> None:
    n = 20
    m = _train_traffic(1_000_000, 2.5e-3, n)
    loads = m.load_stats(2.5e-3)
    assert loads.mean_offered == pytest.approx(2345 / 2500)
    assert loads.peak_busy == pytest.approx(0.938)
    assert m.pending_count() == 0
    lat = m.latency_by_message()
    assert len(lat) == 19 and all(s.n_delivered == n for s in lat.values())
    # everything queued at the period start; the bus drains in 2345 us, lowest id last
    assert lat[(STATE + 5, False)].max_s == pytest.approx(2345 * US)
    assert lat[(SYNC, False)].max_s == pytest.approx(95 * US)
    assert max(s.max_s for s in lat.values()) == pytest.approx(2345 * US)


def test_load_stats_and_window_validation() -> None:
    m = _train_traffic(1_000_000, 2.5e-3, 4)
    assert m.bus_load(0.0, 2.5e-3) == pytest.approx(0.938)
    assert m.bus_load(0.0, 1e-3) == pytest.approx(1.0)
    assert m.offered_load(1e-3, 2.5e-3) == 0.0
    with pytest.raises(ValueError, match="empty window"):
        m.bus_load(1.0, 1.0)
    with pytest.raises(ValueError, match="advance"):
        m.bus_load(0.0, 1.0)
    with pytest.raises(RuntimeError, match="record_history"):
        BusTimingModel(500_000, record_history=False).bus_load(0.0, 1.0)


def test_actual_frame_bits_is_frame_bits_with_actual_stuffing():
    """The recorder's fast path equals the checked function on random frames (both ID kinds, every DLC)."""
    from canbrake.bus.timing import actual_frame_bits

    rng = random.Random(13)
    for _ in range(3000):
        ext = rng.random() < 0.5
        aid = rng.randrange(0x1FFFFFFF if ext else 0x7FF)
        n = rng.randrange(9)
        data = bytes(rng.randrange(256) for _ in range(n))
        assert actual_frame_bits(aid, ext, n, data) == frame_bits(aid, ext, n, data, stuffing="actual")
    with pytest.raises(ValueError):
        actual_frame_bits(0x100, False, 8, b"\x00")  # DLC and data disagree: the checked path says so
