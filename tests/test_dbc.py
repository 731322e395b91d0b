"""The CAN database: regeneration, layout rules, codec bit-exactness against cantools, E2E."""
from __future__ import annotations

import random

import cantools
import pytest
from crccheck.crc import Crc8SaeJ1850

from canbrake.bus import dbc
from canbrake.bus.codec import FrameCodec
from canbrake.bus.e2e import check_crc, crc8_sae_j1850, e2e_crc

from conftest import ROOT


def test_checked_in_dbc_is_what_the_generator_writes():
    assert (ROOT / "dbc" / "canbrake.dbc").read_bytes() == dbc.dbc_text(6).encode()


def test_cli_regenerates_identical_file(tmp_path):
    from canbrake.cli import main

    assert main(["dbc", "--cars", "6", "-o", str(tmp_path / "x.dbc")]) == 0
    assert (tmp_path / "x.dbc").read_bytes() == (ROOT / "dbc" / "canbrake.dbc").read_bytes()


@pytest.mark.parametrize("n", [1, 6, 63])
def test_layout_rules(n):
    db = cantools.database.load_string(dbc.dbc_text(n), database_format="dbc")
    assert dbc.n_cars_of(db) == n
    for m in db.messages:
        assert m.length <= 8 and not m.is_extended_frame and m.frame_id <= 0x7FF
        for s in m.signals:
            assert s.unit is not None or s.name in ("CRC", "Counter", "Status", "NodeState"), (m.name, s.name)
            assert s.comment, (m.name, s.name)
    # priority: SYNC < brake commands < state frames < heartbeats/diagnostics
    assert dbc.SYNC_ID < dbc.BRAKE_CMD_BASE + 1
    assert dbc.BRAKE_CMD_BASE + n < dbc.STATE_BASE + 1
    assert dbc.STATE_BASE + n < dbc.HEARTBEAT_BASE


def test_rejects_bad_car_count():
    with pytest.raises(ValueError):
        dbc.build_database(0)
    with pytest.raises(ValueError):
        dbc.build_database(64)


def _random_values(m, rng):
    vals = {}
    for s in m.signals:
        lo = s.minimum if s.minimum is not None else s.offset
        hi = s.maximum if s.maximum is not None else s.offset + s.scale * ((1 << s.length) - 1)
        if s.name in ("CRC",):
            continue
        if s.name == "Counter":
            vals[s.name] = rng.randrange(0, 15)
            continue
        raw = rng.randrange(round((lo - s.offset) / s.scale), round((hi - s.offset) / s.scale) + 1)
        vals[s.name] = raw * s.scale + s.offset
    return vals


def test_codec_is_bit_exact_with_cantools():
    db = dbc.build_database(6)
    fc = FrameCodec(db)
    rng = random.Random(7)
    for m in db.messages:
        c = fc.by_id[m.frame_id]
        for _ in range(200):
            vals = _random_values(m, rng)
            ours = c.encode(vals, counter=vals.get("Counter"))
            if c.protected:
                vals["CRC"] = ours[0]
            theirs = m.encode(vals, strict=True)
            assert ours == theirs, m.name
            dec_theirs = m.decode(theirs, decode_choices=False)
            dec_ours = c.decode(theirs)
            for k, v in dec_theirs.items():
                assert dec_ours[k] == pytest.approx(v, abs=1e-9), (m.name, k)


def test_quantisation_is_far_below_control_tolerances():
    fc = FrameCodec(dbc.build_database(6))
    c = fc["STATE_C1"]
    d = c.decode(c.encode({"Speed": 25.000049, "Position": 1234.56789}, counter=0))
    assert abs(d["Speed"] - 25.000049) <= 0.5e-4          # << 0.5 km/h = 0.139 m/s
    assert abs(d["Position"] - 1234.56789) <= 0.5e-4      # << 1 cm


def test_codec_saturates_out_of_range_values():
    fc = FrameCodec(dbc.build_database(6))
    c = fc["BRAKE_CMD_C1"]
    assert c.decode(c.encode({"BrakeForce": 1e9}, counter=1))["BrakeForce"] == 83886070
    assert c.decode(c.encode({"BrakeForce": -1e9}, counter=1))["BrakeForce"] == -83886080


def test_crc8_matches_crccheck():
    rng = random.Random(3)
    assert crc8_sae_j1850(b"123456789") == 0x4B
    for _ in range(500):
        data = bytes(rng.randrange(256) for _ in range(rng.randrange(0, 9)))
        assert crc8_sae_j1850(data) == Crc8SaeJ1850.calc(data)
    for _ in range(100):
        data = bytearray(rng.randrange(256) for _ in range(8))
        did = rng.randrange(0x800)
        assert e2e_crc(did, data) == Crc8SaeJ1850.calc(bytes([did & 0xFF, did >> 8]) + bytes(data[1:]))


def test_e2e_detects_corruption_and_sequence():
    fc = FrameCodec(dbc.build_database(6))
    c = fc["STATE_C2"]
    f0 = c.encode({"Speed": 20.0, "Position": 5.0}, counter=0)
    assert check_crc(c.frame_id, f0)
    # the counter's continuity as the brake units' receiver sees it (compiled CommandTable):
    # repeated, +1 and a jump of up to 3 are in sequence, a larger jump is not
    import numpy as np

    from canbrake.bus._codec import CMD_OUT_OF_SEQUENCE, CommandTable

    arr = np.zeros(1)
    rx = CommandTable(np.zeros(1, np.int64), np.ones(1, np.int64), np.zeros(1, bool), np.full(1, -1, np.int64), 14)
    rx.add_page(c.frame_id, 0, c._c, [("Speed", arr, 0)], None)
    seq = [(f0, 0, False), (f0, 1, False), (c.encode({"Speed": 20.0}, counter=1), 1, False),
           (c.encode({"Speed": 20.0}, counter=4), 4, False), (c.encode({"Speed": 20.0}, counter=10), 10, True)]
    for data, k, oos in seq:
        assert bool(rx.check(c.frame_id, data, k)[0] & CMD_OUT_OF_SEQUENCE) == oos
    for bit in range(64):  # every single-bit error is caught by the CRC
        bad = bytearray(f0)
        bad[bit // 8] ^= 1 << (bit % 8)
        assert not check_crc(c.frame_id, bad)
    # the same payload under another frame id (masquerade) fails
    assert not check_crc(fc["STATE_C3"].frame_id, f0)
