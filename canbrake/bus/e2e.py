"""End-to-end protection of safety-relevant frames, AUTOSAR E2E profile 1 style.

Layout (as in profile 1 with "both bytes of the data ID" mode): byte 0 holds a CRC-8 SAE J1850
computed over the 16-bit data ID (low byte, then high byte) followed by payload bytes 1..DLC-1;
the low nibble of byte 1 holds an alive counter 0..14 (15 is never sent).

The receiver checks the CRC (detects corruption and masquerading frames with a wrong data ID)
and classifies the counter jump (repetition, OK, lost frames, wrong sequence): for the brake
units' command frames in compiled code, ``canbrake.bus._codec.CommandTable``; the ECUs' peer
pages in ``PeerTable``.
"""
from __future__ import annotations

# The CRC itself is compiled (canbrake/bus/_crc.pyx): it runs for every protected frame.
from canbrake.bus._crc import TABLE as _TABLE  # noqa: E402  (byte table, for batch forms)
from canbrake.bus._crc import crc8_sae_j1850, e2e_crc  # noqa: E402,F401

COUNTER_MODULO = 15


def counter_modulus(ext_bits: int) -> int:
    """Modulus of an alive counter with ``ext_bits`` extension bits (canbrake.bus.dbc CounterExt):
    the low nibble counts 0..14, the extension counts its wraps."""
    return COUNTER_MODULO << ext_bits


def extended_counter(payload: bytes | bytearray, ext: tuple[int, int] | None) -> int:
    """The alive counter of ``payload`` with its extension ``ext`` = (start bit, bits), if any:
    the sender's tick mod :func:`counter_modulus`."""
    c = payload[1] & 0x0F
    if ext is None:
        return c
    start, bits = ext
    word = int.from_bytes(bytes(payload), "little")
    return c + COUNTER_MODULO * ((word >> start) & ((1 << bits) - 1))


def protect(data_id: int, payload: bytearray) -> bytearray:
    """Write the CRC into byte 0 of ``payload`` (counter must already be in byte 1)."""
    payload[0] = e2e_crc(data_id, payload)
    return payload


def check_crc(data_id: int, payload: bytes | bytearray) -> bool:
    """True if byte 0 of ``payload`` is the right CRC."""
    return len(payload) >= 2 and payload[0] == e2e_crc(data_id, payload)


def counter_of(payload: bytes | bytearray) -> int:
    """Alive counter (low nibble of byte 1)."""
    return payload[1] & 0x0F
