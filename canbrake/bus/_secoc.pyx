# cython: language_level=3
# distutils: extra_compile_args = -O2
"""SecOC framing of :mod:`canbrake.bus.secoc`, compiled: the MAC input (data ID, freshness, body),
its truncation, signing into a frame, verification, the STATE_AUTH authenticator frame.

The AES-CMAC itself is ``cryptography``'s: each MAC is computed on a copy of one pristine
``CMAC`` context made once per key (``CMAC.copy()``; the same result as a new ``CMAC(alg)``, at a
third of its cost). Written by hand because it runs for every authenticated frame on the hot
path (sign at the sender, verify at every receiver) and no library frames AUTOSAR-style
truncated MACs and freshness values; the layout is documented in :mod:`canbrake.bus.secoc`.
"""
from cpython.bytes cimport PyBytes_AS_STRING, PyBytes_FromStringAndSize
from libc.string cimport memcpy

from canbrake.bus._crc import e2e_crc

cdef Py_ssize_t MAC_BYTES = 3


cdef class Framer:
    """MAC framing with one key (``alg``: a ``cryptography`` AES algorithm) and one session
    (32 bits); the base class of :class:`canbrake.bus.secoc.SecOC`."""

    cdef object _cmac  # a CMAC context that never sees data: copied for each MAC
    cdef public object _alg
    cdef unsigned long _session

    def __init__(self, alg, session):
        from cryptography.hazmat.primitives.cmac import CMAC

        self._alg = alg
        self._cmac = CMAC(alg)
        self._session = <unsigned long>(int(session) & 0xFFFFFFFF)

    @property
    def session(self):
        """The freshness value's high 32 bits (the scenario's ``security.session``)."""
        return self._session

    cdef bytes _mac(self, unsigned long long data_id, freshness_tick, const unsigned char[::1] body):
        cdef Py_ssize_t n = body.shape[0]
        cdef unsigned long t = <unsigned long>(freshness_tick & 0xFFFFFFFF)
        cdef unsigned long s = self._session
        cdef bytes msg = PyBytes_FromStringAndSize(NULL, 10 + n)
        cdef unsigned char* m = <unsigned char*>PyBytes_AS_STRING(msg)
        # data ID (LE16) | session (BE32) | tick (BE32) | body
        m[0] = data_id & 0xFF
        m[1] = (data_id >> 8) & 0xFF
        m[2] = (s >> 24) & 0xFF
        m[3] = (s >> 16) & 0xFF
        m[4] = (s >> 8) & 0xFF
        m[5] = s & 0xFF
        m[6] = (t >> 24) & 0xFF
        m[7] = (t >> 16) & 0xFF
        m[8] = (t >> 8) & 0xFF
        m[9] = t & 0xFF
        if n:
            memcpy(m + 10, &body[0], n)
        c = self._cmac.copy()
        c.update(msg)
        return c.finalize()[:MAC_BYTES]

    def mac(self, data_id, freshness_tick, body):
        """Truncated AES-CMAC (3 bytes) of ``body`` with freshness (session, tick)."""
        return self._mac(data_id, freshness_tick, bytes(body))

    def sign(self, data_id, payload, freshness_tick, *, has_crc):
        """``payload`` (already of the secured length) with the MAC written into its last three
        bytes and, for E2E-protected frames, the CRC in byte 0 recomputed over it."""
        buf = bytearray(payload)
        buf[-MAC_BYTES:] = self._mac(data_id, freshness_tick, bytes(buf[1 if has_crc else 0: len(buf) - MAC_BYTES]))
        if has_crc:
            buf[0] = e2e_crc(data_id, buf)
        return bytes(buf)

    def verify_state(self, state_id, state_payload, auth_payload):
        """Does STATE_AUTH frame ``auth_payload`` authenticate STATE frame ``state_payload``?"""
        if len(auth_payload) != 8:
            return False
        return bytes(auth_payload[5:8]) == self._mac(state_id, authenticator_tick(auth_payload),
                                                     bytes(state_payload[1:]))

    def verify(self, data_id, payload, freshness_tick, *, has_crc):
        """Does the MAC in the last three bytes match freshness ``freshness_tick``?"""
        cdef Py_ssize_t n = len(payload)
        if n <= MAC_BYTES:
            return False
        return bytes(payload[-MAC_BYTES:]) == self._mac(data_id, freshness_tick,
                                                        bytes(payload[1 if has_crc else 0: n - MAC_BYTES]))

    def state_authenticator(self, auth_id, state_id, state_payload, tick):
        """The 8-byte STATE_AUTH frame authenticating ``state_payload`` (STATE frame ``state_id``)
        sent at ``tick``: CRC | tick (LE32) | MAC."""
        cdef unsigned long t = <unsigned long>(tick & 0xFFFFFFFF)
        cdef bytes mac = self._mac(state_id, tick, bytes(state_payload[1:]))
        cdef bytearray buf = bytearray(8)
        buf[1] = t & 0xFF
        buf[2] = (t >> 8) & 0xFF
        buf[3] = (t >> 16) & 0xFF
        buf[4] = (t >> 24) & 0xFF
        buf[5:8] = mac
        buf[0] = e2e_crc(auth_id, buf)
        return bytes(buf)


def authenticator_tick(payload):
    """FreshnessTick of a STATE_AUTH frame (bytes 1-4, little-endian)."""
    return int.from_bytes(bytes(payload[1:5]), "little")
