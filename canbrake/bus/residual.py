"""Residual error of the frame protection: how many corrupted frames pass the receiver's checks.

Monte-Carlo, vectorised with numpy: ``n`` valid protected frames (random payload, alive counter
of the current tick, CRC-8 SAE J1850 over data ID + payload) get an error pattern XORed onto the
transmitted bits; we count those that still pass

* **CRC** — CRC-8 alone;
* **E2E** — CRC and the alive counter (the receiver expects the current tick's counter, as the
  brake unit and the ECUs do when each frame arrives in its own period);
* **E2E+CMAC** — additionally the 24-bit truncated AES-CMAC of :mod:`canbrake.bus.secoc`
  (frames with the secured layout; the CMAC is computed with ``cryptography`` only for the frames
  that pass E2E, which is what a receiver does too).

Error models: ``random`` — the received frame is uniformly random among all words different
from the sent one (a burst that scrambles the frame); ``w bits`` — exactly ``w`` distinct bits
flipped, uniformly among the frame's transmitted bits (the low-weight errors a CRC's Hamming
distance speaks about).

Theory (compared in ``docs/safety.md``). The set of error patterns a CRC does not detect is a
linear code: an error ``e = (e_crc, e_data)`` passes iff ``L(e_data) = e_crc`` with ``L`` the
(linear part of the) CRC map, so for the random model P = (2^(k) - 1)/(2^(k+8) - 1) ≈ 2^-8 with
``k`` data bits; requiring the counter nibble unchanged removes 4 free bits (≈ 2^-12); a 24-bit
MAC that behaves as a random function adds 2^-24. For ``w``-bit errors
P_w = A_w / C(n, w), with ``A_w`` the number of weight-``w`` patterns that pass, counted exactly
by :func:`undetected_weights` (enumeration of the low-weight data errors and their CRC images);
the Hamming distance is the smallest ``w`` with ``A_w > 0``.
"""
from __future__ import annotations

import itertools
import math
from dataclasses import dataclass
from typing import Any

import numpy as np

from canbrake.bus.e2e import COUNTER_MODULO, _TABLE

_TAB = np.asarray(_TABLE, dtype=np.uint8)


def crc8_batch(data_id: int, payload: np.ndarray) -> np.ndarray:
    """E2E CRC (:func:`canbrake.bus.e2e.e2e_crc`) of many frames at once.

    ``payload``: uint8 array (N, L); byte 0 (the CRC itself) is ignored. Returns uint8 (N,).
    """
    n = payload.shape[0]
    crc = np.full(n, _TAB[0xFF ^ (data_id & 0xFF)], dtype=np.uint8)
    crc = _TAB[crc ^ np.uint8((data_id >> 8) & 0xFF)]
    for j in range(1, payload.shape[1]):
        crc = _TAB[crc ^ payload[:, j]]
    return crc ^ np.uint8(0xFF)


def valid_frames(rng: np.random.Generator, n: int, data_id: int, length: int,
                 counter: np.ndarray | None = None) -> np.ndarray:
    """``n`` random protected frames (uint8 (n, length)): random bytes 1.., counter 0..14 in the
    low nibble of byte 1 (``counter`` or random), CRC in byte 0."""
    p = rng.integers(0, 256, size=(n, length), dtype=np.uint8)
    c = rng.integers(0, COUNTER_MODULO, size=n, dtype=np.uint8) if counter is None else counter.astype(np.uint8)
    p[:, 1] = (p[:, 1] & 0xF0) | c
    p[:, 0] = crc8_batch(data_id, p)
    return p


def error_patterns(rng: np.random.Generator, n: int, length: int, model: str | int) -> np.ndarray:
    """Error patterns (uint8 (n, length)): ``"random"`` (uniform, nonzero) or ``w`` distinct bits
    flipped (bit 0 = MSB of byte 0, wire order)."""
    if model == "random":
        e = rng.integers(0, 256, size=(n, length), dtype=np.uint8)
        zero = ~e.any(axis=1)
        while zero.any():  # a zero pattern is no error: draw again
            e[zero] = rng.integers(0, 256, size=(int(zero.sum()), length), dtype=np.uint8)
            zero = ~e.any(axis=1)
        return e
    w, nbits = int(model), 8 * length
    if not 1 <= w <= nbits:
        raise ValueError(f"cannot flip {w} distinct bits of a {nbits}-bit frame")
    pos = rng.integers(0, nbits, size=(n, w))
    while True:  # redraw the rows with a repeated position: uniform over the w-subsets
        srt = np.sort(pos, axis=1)
        bad = (srt[:, 1:] == srt[:, :-1]).any(axis=1) if w > 1 else np.zeros(n, dtype=bool)
        if not bad.any():
            break
        pos[bad] = rng.integers(0, nbits, size=(int(bad.sum()), w))
    e = np.zeros((n, length), dtype=np.uint8)
    rows = np.arange(n)
    for j in range(w):
        e[rows, pos[:, j] >> 3] ^= (0x80 >> (pos[:, j] & 7)).astype(np.uint8)
    return e


@dataclass
class ResidualCount:
    """Frames sent with errors and how many passed each layer of checks."""

    frames: int
    pass_crc: int
    pass_e2e: int
    pass_mac: int | None = None


def count_passing(rng: np.random.Generator, n: int, data_id: int, length: int, model: str | int, *,
                  secoc: Any = None, chunk: int = 250_000) -> ResidualCount:
    """Send ``n`` frames through the error ``model`` and count what passes (see module doc).

    With ``secoc`` (a :class:`canbrake.bus.secoc.SecOC`; secured layout, MAC in the last three
    bytes, freshness = the frame's tick) the frames that pass E2E are also MAC-verified. Whether
    a frame passes the CRC depends only on the error pattern (the CRC is affine), so the MAC is
    computed only for those frames: the sent frame is then signed for real and the same error
    applied to it.
    """
    out = ResidualCount(0, 0, 0, 0 if secoc is not None else None)
    done = 0
    while done < n:
        m = min(chunk, n - done)
        ticks = rng.integers(0, 1 << 20, size=m)
        frames = valid_frames(rng, m, data_id, length, counter=ticks % COUNTER_MODULO)
        err = error_patterns(rng, m, length, model)
        rx = frames ^ err
        crc_ok = rx[:, 0] == crc8_batch(data_id, rx)
        e2e_ok = crc_ok & ((rx[:, 1] & 0x0F) == (frames[:, 1] & 0x0F))
        out.frames += m
        out.pass_crc += int(crc_ok.sum())
        out.pass_e2e += int(e2e_ok.sum())
        if secoc is not None:
            for i in np.flatnonzero(e2e_ok):
                sent = secoc.sign(data_id, frames[i].tobytes(), int(ticks[i]), has_crc=True)
                got = bytes(a ^ b for a, b in zip(sent, err[i].tobytes()))
                out.pass_mac += int(got[0] == crc8_batch(data_id, np.frombuffer(got, np.uint8)[None, :])[0]
                                    and secoc.verify(data_id, got, int(ticks[i]), has_crc=True))
        done += m
    return out


# ----------------------------------------------------------------------------- theory
def syndrome_columns(data_id: int, length: int) -> np.ndarray:
    """CRC image of each single-bit data error: uint8 (8·(length-1),), bit order as on the wire
    (bit 0 = MSB of byte 1). The CRC is affine in the data, so the image of any data error
    pattern is the XOR of its bits' columns."""
    base = bytearray(length)
    ref = crc8_batch(data_id, np.frombuffer(bytes(base), dtype=np.uint8)[None, :])[0]
    cols = []
    for pos in range(8 * (length - 1)):
        p = bytearray(base)
        p[1 + (pos >> 3)] ^= 0x80 >> (pos & 7)
        cols.append(crc8_batch(data_id, np.frombuffer(bytes(p), dtype=np.uint8)[None, :])[0] ^ ref)
    return np.asarray(cols, dtype=np.uint8)


_POP8 = np.asarray([bin(i).count("1") for i in range(256)], dtype=np.int64)


def undetected_weights(columns: np.ndarray, max_weight: int, exclude: tuple[int, ...] = ()) -> dict[int, int]:
    """A_w for w = 1..max_weight: the number of weight-w error patterns (over the data bits and
    the 8 CRC bits) that the CRC does not detect; data bits in ``exclude`` (positions in
    ``columns``) are never in error (E2E: a flipped counter bit is caught by the counter check).

    Exact: every data error of weight j <= max_weight is enumerated; its undetected partner in the
    CRC byte is its syndrome, so it contributes to A_{j + popcount(syndrome)}.
    """
    keep = np.asarray([i for i in range(len(columns)) if i not in set(exclude)], dtype=np.int64)
    cols = columns[keep]
    a = {w: 0 for w in range(1, max_weight + 1)}
    for j in range(1, max_weight + 1):
        combos = np.fromiter(itertools.chain.from_iterable(itertools.combinations(range(len(cols)), j)),
                             dtype=np.int64).reshape(-1, j)
        s = np.bitwise_xor.reduce(cols[combos], axis=1)
        w = j + _POP8[s]
        for ww, cnt in zip(*np.unique(w, return_counts=True)):
            if ww <= max_weight:
                a[int(ww)] += int(cnt)
    return a


def hamming_distance(a: dict[int, int]) -> int | None:
    """Smallest w with A_w > 0 (None if none up to the enumerated weight)."""
    return next((w for w in sorted(a) if a[w] > 0), None)


def p_random(data_bits: int, check_bits: int) -> float:
    """P(undetected) for a uniformly random nonzero error on a linear code with ``data_bits``
    free bits and ``check_bits`` check bits: (2^k - 1)/(2^(k+r) - 1)."""
    k, r = data_bits, check_bits
    return (2.0 ** k - 1) / (2.0 ** (k + r) - 1)


def p_weight(a_w: int, n_bits: int, w: int) -> float:
    """P(undetected | exactly w of n_bits flipped) = A_w / C(n, w)."""
    return a_w / math.comb(n_bits, w)


def binomial_interval(n: int, p: float, z: float = 4.0) -> tuple[float, float]:
    """Count expected for ``n`` trials at probability ``p`` ± z standard deviations (normal approx.)."""
    mu = n * p
    sd = math.sqrt(n * p * (1 - p))
    return max(0.0, mu - z * sd), mu + z * sd


# ----------------------------------------------------------------------------- the table
#: (label, data ID, length in bytes, secured) of the frames measured
FRAMES = (("STATE_C3 (8 B, E2E)", 0x143, 8, False),
          ("BRAKE_CMD_C3 (5 B, E2E)", 0x083, 5, False),
          ("BRAKE_CMD_C3 secured (8 B, E2E + CMAC)", 0x083, 8, True))
MODELS: tuple[str | int, ...] = ("random", 1, 2, 3, 4)
COUNTER_BITS = (4, 5, 6, 7)  # low nibble of byte 1, as positions in syndrome_columns (bit 0 = MSB of byte 1)


@dataclass
class ResidualRow:
    frame: str
    model: str
    frames: int
    pass_crc: int
    expect_crc: float          # expected count from theory
    pass_e2e: int
    expect_e2e: float
    pass_mac: int | None
    expect_mac: float | None
    hamming_distance: int | None


def residual_table(n: int = 1_000_000, seed: int = 14, key: bytes | None = None,
                   models: tuple[str | int, ...] = MODELS) -> list[ResidualRow]:
    """Measured and expected residual errors for :data:`FRAMES` x ``models``, ``n`` frames each."""
    import os

    from canbrake.bus.secoc import SecOC

    secoc = SecOC(key or os.urandom(16))
    rng = np.random.default_rng(seed)
    rows = []
    max_w = max((m for m in models if m != "random"), default=1)
    for label, data_id, length, secured in FRAMES:
        cols = syndrome_columns(data_id, length)
        a_crc = undetected_weights(cols, int(max_w))
        a_e2e = undetected_weights(cols, int(max_w), exclude=COUNTER_BITS)
        hd = hamming_distance(a_crc)
        k, nbits = 8 * (length - 1), 8 * length
        for model in models:
            c = count_passing(rng, n, data_id, length, model, secoc=secoc if secured else None)
            if model == "random":
                p_crc, p_e2e = p_random(k, 8), (2.0 ** (k - 4) - 1) / (2.0 ** (k + 8) - 1)
                name = "random (uniform frame)"
            else:
                w = int(model)
                p_crc, p_e2e = p_weight(a_crc[w], nbits, w), p_weight(a_e2e[w], nbits, w)
                name = f"{w} bit{'s' if w > 1 else ''} flipped"
            rows.append(ResidualRow(label, name, c.frames, c.pass_crc, n * p_crc, c.pass_e2e, n * p_e2e,
                                    c.pass_mac, n * p_e2e * 2.0 ** -24 if secured else None, hd))
    return rows
