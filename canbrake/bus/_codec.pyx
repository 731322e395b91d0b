# cython: language_level=3
"""Compiled encode/decode of one CAN message from a field table, with the E2E CRC.

Written by hand because it runs for every frame of every node (cantools' ``Message.encode``
costs ~2.3 us per frame non-strict); cantools stays the model (canbrake.bus.codec builds the
table from a cantools message) and tests/test_codec.py checks this against cantools bit for bit.

Every canbrake signal is a little-endian bit field of a classical CAN frame (at most 8 bytes),
so a frame is one 64-bit little-endian word and a field is a shift and a mask. The arithmetic
is Python's, operation for operation: raw = round((v - offset) / scale) (``v / scale`` when the
offset is 0, ``round(v)`` unscaled; round half to even as Python's ``round``: ``rint`` under the
default rounding mode), saturated to the raw range; decoded as raw * scale (+ offset unless it
is 0 and scale > 0), unscaled signals as ints. Values that are neither ints nor floats take
Python's own operators (same results, slower).
"""
from cpython.bytes cimport PyBytes_AS_STRING, PyBytes_FromStringAndSize, PyBytes_GET_SIZE
from cpython.bytearray cimport PyByteArray_AS_STRING, PyByteArray_GET_SIZE
from cpython.dict cimport PyDict_GetItem, PyDict_SetItem
from cpython.float cimport PyFloat_AS_DOUBLE, PyFloat_FromDouble
from cpython.long cimport PyLong_AsDouble, PyLong_AsLongLongAndOverflow, PyLong_FromLongLong
from cpython.object cimport PyObject
from libc.math cimport isinf, isnan, rint
from libc.stdint cimport int64_t, uint8_t, uint64_t

from canbrake.bus._crc import TABLE as _CRC_TABLE_TUPLE

cdef extern from "Python.h":
    bint PyFloat_Check(object o)
    bint PyLong_Check(object o)
    bint PyDict_CheckExact(object o)
    bint PyBytes_CheckExact(object o)
    bint PyByteArray_Check(object o)

# the CRC-8 SAE J1850 byte table of canbrake.bus._crc (one algorithm; this module only looks it up)
cdef uint8_t CRC_TABLE[256]
cdef int _i
for _i in range(256):
    CRC_TABLE[_i] = <uint8_t>_CRC_TABLE_TUPLE[_i]

DEF MAX_FIELDS = 64

# field roles
cdef enum:
    ROLE_VALUE = 0
    ROLE_CRC = 1
    ROLE_COUNTER = 2
    ROLE_COUNTER_EXT = 3

cdef struct Field:
    int start
    int nbits
    uint64_t mask
    bint is_signed
    double scale
    double offset
    int64_t lo
    int64_t hi
    int role
    bint scaled


cdef inline int64_t _floordiv15(int64_t t):
    """Python's ``t // 15`` (floor, also for negative t)."""
    cdef int64_t q = t / 15
    if t % 15 != 0 and t < 0:
        q -= 1
    return q


cdef class FieldCodec:
    """encode/decode of one message from its field table.

    ``fields``: per signal (name, start bit, bits, signed, scale, offset, role) with role one of
    "value", "crc", "counter", "counter_ext"; ``length``: payload bytes (<= 8); ``protected``:
    the CRC field holds the E2E CRC over ``data_id`` and bytes 1.. (canbrake.bus.e2e)."""

    cdef Field f[MAX_FIELDS]
    cdef int n
    cdef int length
    cdef bint protected
    cdef uint8_t crc0
    cdef tuple names
    cdef tuple defaults       # per field the default value object (its offset, a float)
    cdef tuple lo_obj, hi_obj  # per field the raw range as Python ints (generic path)
    cdef uint64_t _shared_word
    cdef bint _shared_valid
    cdef object _shared

    def __init__(self, fields, int length, bint protected, unsigned int data_id):
        if length > 8:
            raise ValueError(f"payload of {length} bytes: only classical CAN frames (<= 8 bytes) are supported")
        if len(fields) > MAX_FIELDS:
            raise ValueError(f"{len(fields)} signals: at most {MAX_FIELDS} per message are supported")
        roles = {"value": ROLE_VALUE, "crc": ROLE_CRC, "counter": ROLE_COUNTER, "counter_ext": ROLE_COUNTER_EXT}
        self.n = len(fields)
        self.length = length
        self.protected = protected
        names, defaults, lo_obj, hi_obj = [], [], [], []
        cdef int i = 0
        cdef Field* fd
        for name, start, nbits, is_signed, scale, offset, role in fields:
            if nbits > 63 or nbits < 1 or start + nbits > 8 * length:
                raise ValueError(f"signal {name}: {nbits} bits at bit {start} do not fit a {length}-byte "
                                 "frame as a field of at most 63 bits")
            fd = &self.f[i]
            fd.start = start
            fd.nbits = nbits
            fd.mask = (<uint64_t>1 << nbits) - 1
            fd.is_signed = is_signed
            fd.scale = scale
            fd.offset = offset
            if is_signed:
                fd.lo = -(<int64_t>1 << (nbits - 1))
                fd.hi = (<int64_t>1 << (nbits - 1)) - 1
            else:
                fd.lo = 0
                fd.hi = <int64_t>fd.mask
            fd.role = roles[role]
            fd.scaled = scale != 1.0 or offset != 0.0
            names.append(name)
            defaults.append(float(offset))
            lo_obj.append(int(fd.lo))
            hi_obj.append(int(fd.hi))
            i += 1
        self.names = tuple(names)
        self.defaults = tuple(defaults)
        self.lo_obj = tuple(lo_obj)
        self.hi_obj = tuple(hi_obj)
        # the data-ID part of the E2E CRC (low byte, then high byte), a constant of the message
        self.crc0 = CRC_TABLE[CRC_TABLE[0xFF ^ (data_id & 0xFF)] ^ ((data_id >> 8) & 0xFF)]
        self._shared_valid = False
        self._shared = None

    cdef int64_t _raw(self, int i, object v) except? -1:
        """The saturated raw value of field i for the physical value ``v``."""
        cdef Field* fd = &self.f[i]
        cdef double x
        cdef int ovf = 0
        cdef long long r
        if PyFloat_Check(v):
            x = PyFloat_AS_DOUBLE(v)
            if fd.scaled:
                x = x / fd.scale if fd.offset == 0.0 else (x - fd.offset) / fd.scale
        elif PyLong_Check(v):
            if not fd.scaled:
                r = PyLong_AsLongLongAndOverflow(v, &ovf)
                if ovf > 0:
                    return fd.hi
                if ovf < 0:
                    return fd.lo
                return fd.lo if r < fd.lo else fd.hi if r > fd.hi else r
            x = PyLong_AsDouble(v)  # OverflowError for an int beyond floats, as Python's int - float
            x = x / fd.scale if fd.offset == 0.0 else (x - fd.offset) / fd.scale
        else:  # any other number type: Python's operators
            if not fd.scaled:
                ro = round(v)
            elif fd.offset == 0.0:
                ro = round(v / fd.scale)
            else:
                ro = round((v - fd.offset) / fd.scale)
            lo, hi = self.lo_obj[i], self.hi_obj[i]
            return lo if ro < lo else hi if ro > hi else ro
        if isnan(x):
            raise ValueError("cannot convert float NaN to integer")
        if isinf(x):
            raise OverflowError("cannot convert float infinity to integer")
        x = rint(x)  # half to even, as Python's round()
        if x >= 9223372036854775808.0:
            return fd.hi
        if x < -9223372036854775808.0:
            return fd.lo
        r = <long long>x
        return fd.lo if r < fd.lo else fd.hi if r > fd.hi else r

    def encode(self, values, counter=None, tick=None):
        """``values`` (a mapping, physical units) -> payload bytes. Missing signals encode their
        offset; out-of-range values saturate at the raw range. Protected messages: ``counter``
        (tick mod 15) fills Counter and the E2E CRC is computed; ``tick`` fills CounterExt
        (floor(tick / 15)). Without them those fields are taken from ``values``."""
        cdef uint64_t w = 0
        cdef int i
        cdef Field* fd
        cdef int64_t r
        cdef PyObject* p
        cdef bint exact = PyDict_CheckExact(values)
        cdef uint8_t b[8]
        cdef uint8_t crc
        for i in range(self.n):
            fd = &self.f[i]
            if fd.role == ROLE_CRC:
                continue
            if fd.role == ROLE_COUNTER and counter is not None:
                w |= (<uint64_t><int64_t>counter & fd.mask) << fd.start
                continue
            if fd.role == ROLE_COUNTER_EXT and tick is not None:
                w |= (<uint64_t>_floordiv15(<int64_t>tick) & fd.mask) << fd.start
                continue
            if exact:
                p = PyDict_GetItem(values, self.names[i])
                v = self.defaults[i] if p is NULL else <object>p
            else:
                v = values.get(self.names[i], self.defaults[i])
            r = self._raw(i, v)
            w |= (<uint64_t>r & fd.mask) << fd.start
        if self.protected:
            for i in range(self.length):
                b[i] = <uint8_t>(w >> (8 * i))
            crc = self.crc0
            for i in range(1, self.length):
                crc = CRC_TABLE[crc ^ b[i]]
            w |= <uint64_t>(crc ^ 0xFF)
        for i in range(self.length):
            b[i] = <uint8_t>(w >> (8 * i))
        return PyBytes_FromStringAndSize(<char*>b, self.length)

    cdef uint64_t _word(self, object data) except? 0xFFFFFFFFFFFFFFFF:
        """The payload's first 8 bytes as a little-endian word (bytes past them set bits no
        field reads; missing bytes are 0)."""
        cdef const uint8_t* s
        cdef Py_ssize_t n, i
        cdef uint64_t w = 0
        if PyBytes_CheckExact(data):
            s = <const uint8_t*>PyBytes_AS_STRING(data)
            n = PyBytes_GET_SIZE(data)
        elif PyByteArray_Check(data):
            s = <const uint8_t*>PyByteArray_AS_STRING(data)
            n = PyByteArray_GET_SIZE(data)
        else:
            data = bytes(data)
            s = <const uint8_t*>PyBytes_AS_STRING(data)
            n = PyBytes_GET_SIZE(data)
        if n > 8:
            n = 8
        for i in range(n):
            w |= (<uint64_t>s[i]) << (8 * i)
        return w

    cdef dict _decode_word(self, uint64_t w):
        cdef dict d = {}
        cdef int i
        cdef Field* fd
        cdef int64_t raw
        cdef uint64_t half
        for i in range(self.n):
            fd = &self.f[i]
            raw = <int64_t>((w >> fd.start) & fd.mask)
            if fd.is_signed:
                half = <uint64_t>1 << (fd.nbits - 1)
                raw = <int64_t>(<uint64_t>raw ^ half) - <int64_t>half
            if not fd.scaled:
                PyDict_SetItem(d, self.names[i], PyLong_FromLongLong(raw))
            elif fd.offset == 0.0 and fd.scale > 0.0:
                PyDict_SetItem(d, self.names[i], PyFloat_FromDouble(<double>raw * fd.scale))
            else:
                PyDict_SetItem(d, self.names[i], PyFloat_FromDouble(<double>raw * fd.scale + fd.offset))
        return d

    def decode(self, data):
        """Payload (bytes-like) -> {signal: physical value} (ints for unscaled signals)."""
        return self._decode_word(self._word(data))

    def decode_shared(self, data):
        """``decode(data)`` for callers that only read the result: a payload equal to the last
        one returns the same dict, so a broadcast frame is decoded once for all the ECUs of one
        process (the in-process engine, hosted ECUs) instead of once per ECU."""
        cdef uint64_t w = self._word(data)
        if not self._shared_valid or w != self._shared_word:
            self._shared = self._decode_word(w)
            self._shared_word = w
            self._shared_valid = True
        return self._shared
