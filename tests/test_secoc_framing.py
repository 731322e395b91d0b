"""The compiled SecOC framing (canbrake.bus._secoc) against the layout written out with
``cryptography`` directly: MAC input data ID (LE16) | session (BE32) | tick mod 2^32 (BE32) | body,
first three bytes; sign writes it into the last three bytes and recomputes the E2E CRC after it;
STATE_AUTH is CRC | tick (LE32) | MAC over STATE bytes 1..7."""
from __future__ import annotations

from cryptography.hazmat.primitives.ciphers import algorithms
from cryptography.hazmat.primitives.cmac import CMAC
from hypothesis import given, settings
from hypothesis import strategies as st

from canbrake.bus.e2e import e2e_crc
from canbrake.bus.secoc import SecOC, authenticator_tick, state_authenticator

KEY = bytes(range(16))


def _ref_mac(session: int, data_id: int, tick: int, body: bytes) -> bytes:
    c = CMAC(algorithms.AES(KEY))
    c.update(bytes([data_id & 0xFF, (data_id >> 8) & 0xFF]) + (session % 2**32).to_bytes(4, "big")
             + (tick % 2**32).to_bytes(4, "big") + body)
    return c.finalize()[:3]


ids = st.integers(0, 0x7FF)
ticks = st.integers(-2**33, 2**40)   # receivers try origins below 0; ticks wrap at 2^32
sessions = st.integers(0, 2**34)


@settings(max_examples=200, deadline=None)
@given(sessions, ids, ticks, st.binary(min_size=4, max_size=8), st.booleans(), st.integers(0, 7))
def test_sign_and_verify_match_the_reference(session, data_id, tick, payload, has_crc, flip) -> None:
    s = SecOC(KEY, session)
    signed = s.sign(data_id, payload, tick, has_crc=has_crc)
    body = payload[1 if has_crc else 0: len(payload) - 3]
    ref = bytearray(payload[:-3] + _ref_mac(session, data_id, tick, body))
    if has_crc:
        ref[0] = e2e_crc(data_id, ref)
    assert signed == bytes(ref)
    assert s.mac(data_id, tick, body) == _ref_mac(session, data_id, tick, body)
    assert s.verify(data_id, signed, tick, has_crc=has_crc)
    assert s.verify(data_id, bytearray(signed), tick + 2**32, has_crc=has_crc)  # freshness is tick mod 2^32
    assert not s.verify(data_id, signed, tick + 1, has_crc=has_crc)
    bad = bytearray(signed)
    bad[len(bad) - 1 - flip % 3] ^= 0x01  # a MAC bit
    assert not s.verify(data_id, bad, tick, has_crc=has_crc)


@settings(max_examples=200, deadline=None)
@given(sessions, ids, ids, st.integers(0, 2**36), st.binary(min_size=8, max_size=8))
def test_state_authenticator_matches_the_reference(session, auth_id, state_id, tick, state) -> None:
    s = SecOC(KEY, session)
    auth = state_authenticator(s, auth_id, state_id, state, tick)
    ref = bytearray(1) + (tick % 2**32).to_bytes(4, "little") + _ref_mac(session, state_id, tick, state[1:])
    ref[0] = e2e_crc(auth_id, ref)
    assert auth == bytes(ref)
    assert authenticator_tick(auth) == tick % 2**32
    assert s.verify_state(state_id, state, auth)
    assert not s.verify_state(state_id, state[:7] + bytes([state[7] ^ 0x80]), auth)
    assert not s.verify_state(state_id, state, auth[:7])
