"""SecOC-style authentication of brake commands, state frames and simulation-control frames
(optional, per scenario: ``security:``).

AUTOSAR SecOC adds to a protected PDU a truncated freshness value and a truncated MAC; here:

* **MAC**: AES-CMAC (NIST SP 800-38B, ``cryptography``) with the scenario's key, truncated to its
  first 24 bits (:data:`MAC_BYTES` = 3), carried in the **last three bytes** of the frame.
* **Freshness value**: 64 bits, ``session`` (32, the scenario's ``security.session``: a trip
  counter that the operator increases per run) then the sender's **tick** (32). It is *not*
  transmitted beyond what the frame already carries: for brake commands the receiver
  reconstructs the tick from the 4-bit alive counter (tick mod 15) against its own tick
  (``origin = k - ((k - counter) mod 15)``); SYNC carries its tick in clear; the barrier frames
  carry the low 16 bits and are verified against the receiver's own tick.
* **MAC input**: data ID (16 bits, little-endian, as the E2E CRC) ‖ freshness (8 bytes,
  big-endian) ‖ the frame's bytes without the CRC byte (if any) and without the MAC.
* The E2E CRC (byte 0 of protected frames) is computed *after* the MAC and covers it, so a
  corrupted MAC is an E2E failure, not an authentication failure.

Replay: a verbatim copy of any frame sent at tick t0 carries a MAC over freshness t0. Received
at tick k it is verified with the reconstructed origin; the counter aliases (the origin equals
t0 + 15·m for some m) but the MAC does not, so it fails unless it is the very frame of this tick
(which the "newer than the last accepted" rule rejects as a repetition). Across runs, the
same key and session repeat freshness values: increase ``session`` per run (or change the key).

Secured layouts (DLC grows, the signals keep their places; see :func:`secure_database`)::

    BRAKE_CMD_Ci  8 bytes: 0 CRC | 1 counter/status | 2-4 BrakeForce | 5-7 MAC
    SYNC          8 bytes: 0-3 Tick | 4 reserved (0) | 5-7 MAC (freshness = Tick; END: last tick)
    STATE_DONE_Ci 5 bytes: 0-1 Tick | 2-4 MAC (freshness = k)
    CMD_DONE_Ci   5 bytes: 0-1 Tick | 2-4 MAC (freshness = k)

STATE frames keep their layout (their 8 bytes are full: CRC 8 + counter 4 + speed 20 + position
32 bits); each STATE page is followed by a second PDU, its authenticator (classical CAN, kind
"state_auth" of the identifier plan, :class:`canbrake.bus.dbc.IdPlan`: 0x180 + i next to
STATE_Ci at 0x140 + i)::

    STATE_AUTH_Ci 8 bytes: 0 CRC (over its own id and bytes 1-7) | 1-4 FreshnessTick (the sender's
                  tick, 32 bits, little-endian) | 5-7 MAC over STATE_Ci (data ID = STATE_Ci's id,
                  freshness = FreshnessTick, body = STATE_Ci bytes 1..7)

The authenticator carries the full tick, so its freshness does not alias (2^32 periods). A
receiver holds a STATE page that passed its E2E check as a candidate and applies it only when an
authenticator of the same tick verifies it (:func:`state_authenticator`, :meth:`SecOC.verify_state`);
a candidate that none verifies is rejected as ``authentication``, an authenticator of a tick not
newer than the last accepted one (a replay) as ``freshness``.
"""
from __future__ import annotations

import os
from pathlib import Path

from cryptography.hazmat.primitives.ciphers import algorithms

from canbrake.bus._secoc import Framer, authenticator_tick  # noqa: F401 (re-exported)

MAC_BYTES = 3
KEY_BYTES = 16
#: how many 15-tick aliases back a failing MAC is tried with to call it a stale (replayed) frame
STALE_ALIASES = 8


class KeyFileError(ValueError):
    """The key file named by ``security.key_file`` cannot be used (message says why)."""


def load_key(path: str | Path) -> bytes:
    """Read an AES-128 key: a file holding 32 hex digits (whitespace ignored) or 16 raw bytes."""
    p = Path(path)
    try:
        raw = p.read_bytes()
    except FileNotFoundError:
        raise KeyFileError(f"{p}: no such key file") from None
    except OSError as e:
        raise KeyFileError(f"{p}: cannot read the key file: {e.strerror}") from None
    text = raw.decode("ascii", errors="replace").strip()
    if len(text) == 2 * KEY_BYTES and all(c in "0123456789abcdefABCDEF" for c in text):
        return bytes.fromhex(text)
    if len(raw) == KEY_BYTES:
        return raw
    raise KeyFileError(f"{p}: expected an AES-128 key, {KEY_BYTES} bytes or {2 * KEY_BYTES} hex digits; "
                       f"found {len(raw)} bytes")


def write_key(path: str | Path) -> Path:
    """Write a fresh random key as hex (mode 0600) and return its path."""
    p = Path(path)
    fd = os.open(p, os.O_WRONLY | os.O_CREAT | os.O_TRUNC, 0o600)
    with os.fdopen(fd, "w") as f:
        f.write(os.urandom(KEY_BYTES).hex() + "\n")
    return p


class SecOC(Framer):
    """Sign and verify frames with one key and session (see module doc for the layout). The
    framing (MAC input, truncation, signing, verification, the STATE_AUTH frame) is the compiled
    :class:`canbrake.bus._secoc.Framer`; the CMAC is ``cryptography``'s."""

    def __init__(self, key: bytes, session: int = 0) -> None:
        if len(key) != KEY_BYTES:
            raise ValueError(f"key must be {KEY_BYTES} bytes, got {len(key)}")
        super().__init__(algorithms.AES(key), session)

    def __reduce__(self) -> tuple:
        # the CMAC context inside does not pickle: a copy (e.g. for a node process) keys its own
        return (type(self), (bytes(self._alg.key), self.session))


def state_authenticator(secoc: "SecOC", auth_id: int, state_id: int, state_payload: bytes | bytearray,
                        tick: int) -> bytes:
    """The 8-byte STATE_AUTH frame authenticating ``state_payload`` (STATE frame ``state_id``)
    sent at ``tick``: CRC | tick (LE32) | MAC."""
    return secoc.state_authenticator(auth_id, state_id, state_payload, tick)


#: messages secured, by name prefix ("SYNC": exactly): has an E2E CRC, secured length (bytes)
SECURED = {"BRAKE_CMD_": (True, 8), "SYNC": (False, 8), "STATE_DONE_": (False, 5), "CMD_DONE_": (False, 5)}


def secured_layout(name: str) -> tuple[bool, int] | None:
    """(has CRC, secured length) of message ``name``, or None if it is not authenticated."""
    for prefix, spec in SECURED.items():
        if name == prefix or (prefix.endswith("_") and name.startswith(prefix)):
            return spec
    return None


def secure_database(db):  # type: ignore[no-untyped-def]
    """The database of a secured run: every message in :data:`SECURED` gets its secured length
    and a ``MAC`` signal (last three bytes) whose comment documents MAC, truncation and freshness.
    Changes ``db`` in place and returns it."""
    from cantools.database.can import Signal
    from cantools.database.conversion import BaseConversion

    for m in db.messages:
        spec = secured_layout(m.name)
        if spec is None:
            continue
        _crc, length = spec
        if m.length > length - MAC_BYTES:
            raise ValueError(f"security: {m.name} uses {m.length} bytes; a {8 * MAC_BYTES}-bit MAC needs "
                             f"{MAC_BYTES} free bytes of {length} (fewer command signals per page)")
        fresh = ("Tick (END frame: the last tick sent)" if m.name == "SYNC" else
                 "the sender's tick, rebuilt by the receiver from Counter (tick mod 15) and its own tick"
                 if m.name.startswith("BRAKE_CMD_") else "the receiver's tick k")
        m.length = length
        m.signals.append(Signal(
            name="MAC", start=8 * (length - MAC_BYTES), length=8 * MAC_BYTES, byte_order="little_endian",
            is_signed=False, conversion=BaseConversion.factory(scale=1, offset=0), minimum=0, maximum=(1 << 24) - 1,
            comment=(f"SecOC: first 24 bits of AES-128-CMAC over data ID (LE16) | freshness (session BE32, tick BE32) "
                     f"| bytes {'1' if _crc else '0'}..{length - MAC_BYTES - 1}; freshness tick = {fresh}; "
                     f"bytes in MAC order"), receivers=list(m.signals[0].receivers) if m.signals else []))
        m.refresh()
    return db


def secoc_of(scn) -> SecOC | None:  # type: ignore[no-untyped-def]
    """The scenario's authenticator (reads the key file), or None when ``security`` is off."""
    sec = getattr(scn, "security", None)
    if sec is None:
        return None
    return SecOC(load_key(sec.key_file), sec.session)
