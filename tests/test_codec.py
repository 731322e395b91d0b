"""The compiled codec (canbrake.bus.codec) against cantools, bit for bit, by property testing.

Every message of several databases (Chen's 6 and 63 cars, the 106-ECU ECP train's 29-bit plan,
the emu8 example's paged frames) is encoded with random values of every signal drawn over the
signal's whole raw range (as raw multiples of the scale, and as arbitrary physical values in
range that cantools rounds the same way), and must give exactly cantools' bytes; decoding must
give exactly cantools' values. The old interpreted encoder is a second oracle for values out of
range (saturation), where cantools' strict mode refuses to encode: it lives here, in the tests,
as :func:`_interpreted_encode` (the product has one codec, the compiled one).
"""
from __future__ import annotations

import functools
from pathlib import Path

import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from canbrake.build import bus_layout
from canbrake.bus import dbc
from canbrake.bus.codec import FrameCodec, MessageCodec
from canbrake.bus.e2e import e2e_crc
from canbrake.scenario import load_scenario

ROOT = Path(__file__).resolve().parents[1]


@functools.lru_cache(maxsize=None)
def _database(which: str):
    if which.startswith("chen"):
        db = dbc.build_database(int(which[4:]))
    else:
        db = bus_layout(load_scenario(ROOT / "scenarios" / which)).database()
    return db, FrameCodec(db)


# database -> examples (each example encodes and decodes every message of the database once;
# the large plans repeat the small ones' message shapes hundreds of times, so fewer examples)
DATABASES = {"chen6": 40, "emu8_example.yaml": 25, "chen63": 3, "li2024_ecp_over_can.yaml": 3}


def _interpreted_encode(c: MessageCodec, values, counter=None, tick=None) -> bytes:
    """The interpreted encoder the compiled one replaced: Python's round() (half to even) and
    int arithmetic, saturated to the raw range; the tests' second oracle."""
    word = 0
    for name, start, mask, _length, _signed, scale, offset, lo, hi in c._fields:
        if name == "CRC":
            continue
        if name == "Counter" and counter is not None:
            raw = counter
        elif name == "CounterExt" and tick is not None:
            raw = tick // 15
        else:
            v = values.get(name, offset)
            raw = round((v - offset) / scale) if scale != 1.0 or offset != 0.0 else round(v)
            raw = lo if raw < lo else hi if raw > hi else raw
        word |= (raw & mask) << start
    data = bytearray(word.to_bytes(c.length, "little"))
    if c.protected:
        data[0] = e2e_crc(c.frame_id, data)
    return bytes(data)


def _raw_range(s) -> tuple[int, int]:
    return (-(1 << (s.length - 1)), (1 << (s.length - 1)) - 1) if s.is_signed else (0, (1 << s.length) - 1)


@st.composite
def _values(draw, message, physical: bool):
    """Physical values of every signal but the CRC, inside the raw range (cantools strict accepts them)."""
    vals = {}
    for s in message.signals:
        if s.name == "CRC":
            continue
        lo, hi = _raw_range(s)
        if s.name == "Counter":
            vals[s.name] = draw(st.integers(0, 14))
            continue
        if physical and (s.scale != 1 or s.offset != 0):
            # any float whose raw value rounds inside the range (the half-way ends excluded)
            v = draw(st.floats(lo + 0.5001, hi - 0.5001, allow_nan=False))
            vals[s.name] = v * s.scale + s.offset
        else:
            vals[s.name] = draw(st.integers(lo, hi)) * s.scale + s.offset
    return vals


@pytest.mark.parametrize("which", DATABASES)
def test_codec_is_bit_identical_to_cantools_on_every_message(which):
    settings(max_examples=DATABASES[which], deadline=None,
             suppress_health_check=[HealthCheck.too_slow, HealthCheck.data_too_large])(
        given(data=st.data(), physical=st.booleans())(_check_every_message))(which=which)


def _check_every_message(which, data, physical):
    db, fc = _database(which)
    for m in db.messages:
        c = fc.by_id[m.frame_id]
        vals = data.draw(_values(m, physical), label=m.name)
        ours = c.encode(vals, counter=vals.get("Counter"))
        theirs_vals = dict(vals)
        if c.protected:
            theirs_vals["CRC"] = ours[0]
        elif "CRC" in c.signal_names:
            theirs_vals["CRC"] = 0
        theirs = m.encode(theirs_vals, strict=True)
        assert ours == theirs, (m.name, vals)
        assert ours == _interpreted_encode(c, vals, counter=vals.get("Counter")), m.name
        dec_theirs = m.decode(theirs, decode_choices=False)
        assert c.decode(theirs) == dec_theirs, m.name
        # decoding random bytes (every bit pattern, CRC not checked by a decoder) agrees as well
        raw = data.draw(st.binary(min_size=m.length, max_size=m.length), label=f"{m.name} bytes")
        assert c.decode(raw) == m.decode(raw, decode_choices=False), m.name


@settings(max_examples=50, deadline=None)
@given(data=st.data())
def test_codec_saturates_like_the_interpreted_encoder(data):
    db, fc = _database("chen6")
    m = data.draw(st.sampled_from(db.messages))
    c = fc.by_id[m.frame_id]
    vals = {s.name: data.draw(st.floats(-1e12, 1e12, allow_nan=False)) for s in m.signals if s.name != "CRC"}
    counter = data.draw(st.none() | st.integers(0, 14))
    if counter is None and "Counter" in vals:
        vals["Counter"] = float(data.draw(st.integers(-100, 100)))
    assert c.encode(vals, counter=counter) == _interpreted_encode(c, vals, counter=counter)


@settings(max_examples=60, deadline=None)
@given(st.lists(st.binary(min_size=8, max_size=8), min_size=1, max_size=6))
def test_decode_shared_is_decode_and_follows_each_new_payload(payloads):
    """The read-only decode shared by the ECUs of one process gives decode's values for every
    payload, also when payloads alternate (a stale cache would repeat the previous one)."""
    _db, fc = _database("chen6")
    m = fc["STATE_C1"]
    for p in payloads:
        for data in (p, bytearray(p)):
            assert m.decode_shared(data) == m.decode(p)


def _any_value(s):
    """Values of every kind the nodes may pass: raw half-way points (ties to even), ints beyond
    64 bits, floats of any magnitude, bools, numpy scalars."""
    import numpy as np

    lo, hi = _raw_range(s)
    return st.one_of(st.integers(lo - 4, hi + 4).map(lambda r: (r + 0.5) * s.scale + s.offset),
                     st.integers(-(1 << 70), 1 << 70), st.booleans(),
                     st.floats(allow_nan=False, allow_infinity=False, width=64),
                     st.floats(lo - 10.0, hi + 10.0).map(lambda r: np.float64(r * s.scale + s.offset)))


@settings(max_examples=150, deadline=None)
@given(data=st.data())
def test_codec_rounds_and_saturates_like_python_on_every_kind_of_value(data):
    """Python's round() (half to even, exact ints) and saturation, as the interpreted encoder,
    on the protected and extended-counter messages of the ECP plan too."""
    which = data.draw(st.sampled_from(["chen6", "li2024_ecp_over_can.yaml"]))
    db, fc = _database(which)
    m = data.draw(st.sampled_from(db.messages))
    c = fc.by_id[m.frame_id]
    vals = {s.name: data.draw(_any_value(s), label=s.name) for s in m.signals if s.name != "CRC"}
    counter = data.draw(st.none() | st.integers(0, 14))
    tick = data.draw(st.none() | st.integers(0, 1 << 31))
    try:
        want = _interpreted_encode(c, vals, counter=counter, tick=tick)
    except OverflowError as exc:  # a float beyond the int range of Python (e.g. 1e308 / 0.001)
        with pytest.raises(OverflowError, match=str(exc)):
            c.encode(vals, counter=counter, tick=tick)
        return
    assert c.encode(vals, counter=counter, tick=tick) == want


@pytest.mark.parametrize("value, error", [(float("nan"), ValueError), (float("inf"), OverflowError),
                                          (-float("inf"), OverflowError), (10 ** 400, OverflowError)])
def test_codec_refuses_what_python_round_refuses(value, error):
    """A value round() cannot convert fails with round()'s own error (the nodes leave non-finite
    values out of their frames; the plant and tests rely on the error)."""
    _db, fc = _database("chen6")
    c = fc["STATE_C1"]
    name = next(n for n, *_rest, scale, offset, _lo, _hi in c._fields if scale != 1.0)
    with pytest.raises(error) as ours:
        c.encode({name: value})
    with pytest.raises(error) as theirs:
        _interpreted_encode(c, {name: value})
    assert str(ours.value) == str(theirs.value)


@settings(max_examples=60, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(data=st.data())
def test_encode_from_is_encode_of_the_finite_values(data):
    """FieldCodec.encode_from (the ECU's state and command frames) gives the bytes of encode()
    over the dict of the values it names that are finite (as floats with ``as_float``): missing,
    NaN and infinite values leave their field at its default."""
    import math

    db, fc = _database(data.draw(st.sampled_from(["chen6", "emu8_example.yaml"])))
    msg = data.draw(st.sampled_from(db.messages))
    c = fc[msg.name]._c
    key_of = {s.name: f"k_{s.name}" for s in msg.signals if data.draw(st.booleans())}
    values = {}
    for name, key in key_of.items():
        values[key] = data.draw(st.one_of(st.floats(-1e4, 1e4), st.integers(-500, 500),
                                          st.sampled_from([math.nan, math.inf, -math.inf])))
    for key in list(values):
        if data.draw(st.integers(0, 5)) == 0:
            del values[key]  # not in the period's values
    as_float = data.draw(st.booleans())
    counter, tick = data.draw(st.one_of(st.none(), st.integers(0, 14))), data.draw(st.integers(0, 10 ** 6))
    want = {name: (float(values[key]) if as_float else values[key]) for name, key in key_of.items()
            if key in values and math.isfinite(values[key])}
    assert c.encode_from(values, c.keys_for(key_of), counter, tick, as_float) == c.encode(want, counter=counter, tick=tick)
