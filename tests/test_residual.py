"""Residual error of the frame protection (canbrake.bus.residual): the vectorised CRC is the E2E
CRC, the exact undetected-pattern counts match brute force, and the Monte-Carlo counts match the
theory (2^-8 for random frames, A_w / C(n, w) for w-bit errors, none below the Hamming distance)."""
from __future__ import annotations

import math
import os

import numpy as np
import pytest
from crccheck.crc import Crc8SaeJ1850

from canbrake.bus.e2e import crc8_sae_j1850, e2e_crc
from canbrake.bus.residual import (COUNTER_BITS, binomial_interval, count_passing, crc8_batch, error_patterns,
                                   hamming_distance, p_random, p_weight, residual_table, syndrome_columns,
                                   undetected_weights, valid_frames)
from canbrake.bus.secoc import SecOC


def test_batch_crc_is_the_e2e_crc():
    rng = np.random.default_rng(0)
    frames = valid_frames(rng, 500, 0x143, 8)
    assert all(f[0] == e2e_crc(0x143, bytes(f)) for f in frames)
    assert crc8_sae_j1850(b"123456789") == Crc8SaeJ1850.calc(b"123456789") == 0x4B


def test_error_patterns_have_the_asked_weight_and_are_never_zero():
    rng = np.random.default_rng(1)
    for w in (1, 3, 7):
        e = error_patterns(rng, 2000, 5, w)
        assert (np.unpackbits(e, axis=1).sum(axis=1) == w).all()
    assert error_patterns(rng, 5000, 2, "random").any(axis=1).all()


def _brute_force_weights(data_id: int, length: int, exclude=()) -> dict[int, int]:
    """Every data error pattern of a short frame: weight of (data error, its CRC partner)."""
    base = bytes(length)
    ref = e2e_crc(data_id, base)
    k = 8 * (length - 1)
    out: dict[int, int] = {}
    for bits in range(1, 1 << k):
        if any(bits >> (k - 1 - p) & 1 for p in exclude):
            continue
        data = bits.to_bytes(length - 1, "big")
        s = e2e_crc(data_id, b"\0" + data) ^ ref
        w = bin(bits).count("1") + bin(s).count("1")
        out[w] = out.get(w, 0) + 1
    return out


@pytest.mark.parametrize("exclude", [(), COUNTER_BITS])
def test_undetected_weights_match_brute_force(exclude):
    brute = _brute_force_weights(0x083, 3, exclude)
    exact = undetected_weights(syndrome_columns(0x083, 3), 5, exclude=exclude)
    assert exact == {w: brute.get(w, 0) for w in range(1, 6)}


def test_hamming_distance_of_0x1d_is_3_over_canbrake_frames():
    # x^8+x^4+x^3+x^2+1 is primitive (period 255): every 2-bit error in a codeword of at most
    # 255 bits is detected; it has an odd number of terms, so (x+1) does not divide it and
    # some 3-bit errors pass once the data is long enough (here from 16 data bits on).
    g, r = 0x11D, 1
    period = next(n for n in range(1, 256) if (r := (r << 1) ^ (g if (r << 1) & 0x100 else 0)) == 1)
    assert period == 255
    for length in (5, 8):
        assert hamming_distance(undetected_weights(syndrome_columns(0x083, length), 3)) == 3
    assert hamming_distance(undetected_weights(syndrome_columns(0x083, 2), 3)) is None  # 8 data bits: HD 4


@pytest.mark.parametrize("model", ["random", 1, 2, 3, 4])
def test_monte_carlo_matches_theory(model):
    n, length, data_id = 200_000, 8, 0x143
    c = count_passing(np.random.default_rng(7), n, data_id, length, model)
    if model == "random":
        p_crc, p_e2e = p_random(56, 8), (2.0 ** 52 - 1) / (2.0 ** 64 - 1)
    else:
        cols = syndrome_columns(data_id, length)
        p_crc = p_weight(undetected_weights(cols, model)[model], 64, model)
        p_e2e = p_weight(undetected_weights(cols, model, exclude=COUNTER_BITS)[model], 64, model)
    for got, p in ((c.pass_crc, p_crc), (c.pass_e2e, p_e2e)):
        lo, hi = binomial_interval(n, p)
        assert lo <= got <= hi, (model, got, n * p)
    if model in (1, 2):
        assert c.pass_crc == 0


def test_cmac_stops_what_passes_e2e():
    secoc = SecOC(os.urandom(16))
    c = count_passing(np.random.default_rng(3), 100_000, 0x083, 8, 3, secoc=secoc)
    assert c.pass_e2e > 100 and c.pass_mac == 0


def test_table_rows_cover_every_frame_and_model():
    rows = residual_table(n=2000, models=("random", 3))
    assert len(rows) == 6 and {r.hamming_distance for r in rows} == {3}
    assert all(r.frames == 2000 and r.pass_e2e <= r.pass_crc for r in rows)
    assert math.isclose(rows[0].expect_crc, 2000 * p_random(56, 8))
