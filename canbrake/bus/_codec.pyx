# cython: language_level=3
# distutils: extra_compile_args = -O2 -ffp-contract=off
"""Compiled encode/decode of one CAN message from a field table, with the E2E CRC.

Written by hand because it runs for every frame of every node (cantools' ``Message.encode``
costs ~2.3 us per frame non-strict); cantools stays the model (canbrake.bus.codec builds the
table from a cantools message) and tests/test_codec.py checks this against cantools bit for bit.

A frame is a classical CAN frame (at most 8 bytes), read as one 64-bit little-endian word for
Intel (little-endian) fields and as one 64-bit big-endian word (byte 0 most significant) for
Motorola (big-endian) fields of a user's DBC; either way a field is a shift and a mask. The arithmetic
is Python's, operation for operation: raw = round((v - offset) / scale) (``v / scale`` when the
offset is 0, ``round(v)`` unscaled; round half to even as Python's ``round``: ``rint`` under the
default rounding mode), saturated to the raw range; decoded as raw * scale (+ offset unless it
is 0 and scale > 0), unscaled signals as ints. Values that are neither ints nor floats take
Python's own operators (same results, slower).
"""
from cpython.buffer cimport PyBUF_C_CONTIGUOUS, PyBUF_FORMAT, PyBUF_WRITABLE, PyBuffer_Release, PyObject_GetBuffer
from cpython.bytes cimport PyBytes_AS_STRING, PyBytes_FromStringAndSize, PyBytes_GET_SIZE
from cpython.bytearray cimport PyByteArray_AS_STRING, PyByteArray_GET_SIZE
from cpython.dict cimport PyDict_GetItem, PyDict_SetItem
from cpython.float cimport PyFloat_AS_DOUBLE, PyFloat_AsDouble, PyFloat_FromDouble
from cpython.long cimport PyLong_AsDouble, PyLong_AsLongLongAndOverflow, PyLong_FromLongLong
from cpython.object cimport PyObject
from libc.math cimport INFINITY, NAN, isfinite, isinf, isnan, rint
from libc.stdint cimport int64_t, uint8_t, uint32_t, uint64_t
from libc.string cimport memcpy, memset
from cpython.mem cimport PyMem_Free, PyMem_Malloc, PyMem_Realloc

import numpy as np

from canbrake.bus._crc import TABLE as _CRC_TABLE_TUPLE
from canbrake._buffers cimport is_f64_vector
from canbrake.bus._ring cimport MSG_DATA, MSG_EXT, MSG_ID, msg_get

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
    ROLE_CONST = 4     # a multiplexer: always its page's value

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
    bint big           # Motorola: ``start`` is the shift in the big-endian word
    int64_t const_raw  # ROLE_CONST: the raw value written


cdef inline int64_t _floordiv15(int64_t t):
    """Python's ``t // 15`` (floor, also for negative t)."""
    cdef int64_t q = t / 15
    if t % 15 != 0 and t < 0:
        q -= 1
    return q


cdef inline bint _own_bits(Field* fd, object counter, object tick, uint64_t* x):
    """A field the codec fills itself: the alive counter (``counter`` mod its width), CounterExt
    (floor(``tick`` / 15)) or a constant, its bits in ``x``; False for a field whose value the
    caller gives (the E2E CRC is the caller's to skip)."""
    if fd.role == ROLE_COUNTER and counter is not None:
        x[0] = (<uint64_t><int64_t>counter & fd.mask) << fd.start
    elif fd.role == ROLE_COUNTER_EXT and tick is not None:
        x[0] = (<uint64_t>_floordiv15(<int64_t>tick) & fd.mask) << fd.start
    elif fd.role == ROLE_CONST:
        x[0] = (<uint64_t>fd.const_raw & fd.mask) << fd.start
    else:
        return False
    return True


cdef inline int64_t _field_raw(Field* fd, uint64_t w, uint64_t wb) noexcept:
    """Field ``fd``'s raw value in a frame (its little-endian word ``w``, big-endian word ``wb``)."""
    cdef int64_t raw = <int64_t>(((wb if fd.big else w) >> fd.start) & fd.mask)
    cdef uint64_t half
    if fd.is_signed:
        half = <uint64_t>1 << (fd.nbits - 1)
        raw = <int64_t>(<uint64_t>raw ^ half) - <int64_t>half
    return raw


cdef object _field_value(Field* fd, uint64_t w, uint64_t wb):
    """Field ``fd``'s physical value in a frame, as ``FieldCodec.decode`` gives it (an int for an
    unscaled signal)."""
    cdef int64_t raw = _field_raw(fd, w, wb)
    if not fd.scaled:
        return PyLong_FromLongLong(raw)
    if fd.offset == 0.0 and fd.scale > 0.0:
        return PyFloat_FromDouble(<double>raw * fd.scale)
    return PyFloat_FromDouble(<double>raw * fd.scale + fd.offset)


cdef class FieldCodec:
    """encode/decode of one message from its field table.

    ``fields``: per signal (name, start bit, bits, signed, scale, offset, role[, big_endian[,
    const]]) with role one of "value", "crc", "counter", "counter_ext", "const" (a multiplexer
    signal, always written as the raw value ``const``); ``start`` as in cantools/DBC (for
    big-endian fields the most significant bit, in the DBC's sawtooth numbering); ``length``:
    payload bytes (<= 8); ``protected``: the CRC field (8 bits, byte 0) holds the E2E CRC over
    ``data_id`` and bytes 1.. (canbrake.bus.e2e)."""

    cdef Field f[MAX_FIELDS]
    cdef int n
    cdef int length
    cdef bint protected
    cdef uint8_t crc0
    cdef tuple names
    cdef tuple defaults       # per field the default value object (its offset, a float)
    cdef tuple lo_obj, hi_obj  # per field the raw range as Python ints (generic path)
    cdef bint any_big
    cdef uint64_t _shared_word
    cdef bint _shared_valid
    cdef object _shared

    def __init__(self, fields, int length, bint protected, unsigned int data_id):
        if length > 8:
            raise ValueError(f"payload of {length} bytes: only classical CAN frames (<= 8 bytes) are supported")
        if len(fields) > MAX_FIELDS:
            raise ValueError(f"{len(fields)} signals: at most {MAX_FIELDS} per message are supported")
        roles = {"value": ROLE_VALUE, "crc": ROLE_CRC, "counter": ROLE_COUNTER, "counter_ext": ROLE_COUNTER_EXT,
                 "const": ROLE_CONST}
        self.n = len(fields)
        self.length = length
        self.protected = protected
        self.any_big = False
        names, defaults, lo_obj, hi_obj = [], [], [], []
        cdef int i = 0
        cdef int lsb
        cdef Field* fd
        for spec in fields:
            name, start, nbits, is_signed, scale, offset, role = spec[:7]
            big = bool(spec[7]) if len(spec) > 7 else False
            const = int(spec[8]) if len(spec) > 8 and spec[8] is not None else 0
            if big:  # the field's least significant bit, counted from byte 0's MSB (bit 0) onwards
                lsb = 8 * (start // 8) + 7 - start % 8 + nbits - 1 if 0 <= start < 64 else 64
                bad = nbits > 63 or nbits < 1 or lsb > 8 * length - 1
            else:
                bad = nbits > 63 or nbits < 1 or start + nbits > 8 * length
            if bad:
                raise ValueError(f"signal {name}: {nbits} bits at bit {start} do not fit a {length}-byte "
                                 "frame as a field of at most 63 bits")
            fd = &self.f[i]
            fd.big = big
            fd.start = 63 - lsb if big else start
            self.any_big = self.any_big or big
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
            fd.const_raw = const
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
        if protected and not any(f[6] == "crc" and f[2] == 8 and f[1] == (7 if len(f) > 7 and f[7] else 0)
                                 for f in fields):
            raise ValueError("the E2E CRC must be the 8 bits of byte 0")
        # the data-ID part of the E2E CRC (low byte, then high byte), a constant of the message
        self.crc0 = CRC_TABLE[CRC_TABLE[0xFF ^ (data_id & 0xFF)] ^ ((data_id >> 8) & 0xFF)]
        self._shared_valid = False
        self._shared = None

    cdef int64_t _raw(self, int i, object v) except? -1:
        """The saturated raw value of field i for the physical value ``v``."""
        cdef Field* fd = &self.f[i]
        cdef int ovf = 0
        cdef long long r
        if PyFloat_Check(v):
            return self._raw_double(i, PyFloat_AS_DOUBLE(v))
        elif PyLong_Check(v):
            if not fd.scaled:
                r = PyLong_AsLongLongAndOverflow(v, &ovf)
                if ovf > 0:
                    return fd.hi
                if ovf < 0:
                    return fd.lo
                return fd.lo if r < fd.lo else fd.hi if r > fd.hi else r
            # OverflowError for an int beyond floats, as Python's int - float
            return self._raw_double(i, PyLong_AsDouble(v))
        else:  # any other number type: Python's operators
            if not fd.scaled:
                ro = round(v)
            elif fd.offset == 0.0:
                ro = round(v / fd.scale)
            else:
                ro = round((v - fd.offset) / fd.scale)
            lo, hi = self.lo_obj[i], self.hi_obj[i]
            return lo if ro < lo else hi if ro > hi else ro

    cdef int64_t _raw_double(self, int i, double x) except? -1:
        """The saturated raw value of field i for the physical value ``x`` (a float)."""
        cdef Field* fd = &self.f[i]
        cdef long long r
        if fd.scaled:
            x = x / fd.scale if fd.offset == 0.0 else (x - fd.offset) / fd.scale
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
        cdef uint64_t wb = 0      # the big-endian (Motorola) fields' word
        cdef uint64_t x
        cdef int i
        cdef Field* fd
        cdef int64_t r
        cdef PyObject* p
        cdef bint exact = PyDict_CheckExact(values)
        for i in range(self.n):
            fd = &self.f[i]
            if fd.role == ROLE_CRC:
                continue
            if not _own_bits(fd, counter, tick, &x):
                if exact:
                    p = PyDict_GetItem(values, self.names[i])
                    v = self.defaults[i] if p is NULL else <object>p
                else:
                    v = values.get(self.names[i], self.defaults[i])
                r = self._raw(i, v)
                x = (<uint64_t>r & fd.mask) << fd.start
            if fd.big:
                wb |= x
            else:
                w |= x
        return self._payload_of(w, wb)

    def keys_for(self, dict key_of):
        """The ``keys`` of :meth:`encode_from` for the fields named in ``key_of`` (field name ->
        key), None for the others."""
        return tuple(key_of.get(nm) for nm in self.names)

    def encode_from(self, dict values, tuple keys, counter, tick, bint as_float=False):
        """``encode({field name: values[keys[i]] for each field i whose key is not None and whose
        value is in ``values`` and finite}, counter, tick)`` without the dict: ``keys`` holds per
        field of this codec the key of its value in ``values`` (a dict) or None (the field's
        default, or its counter, CRC or constant). ``as_float``: each value taken as
        ``float(value)``."""
        cdef uint64_t w = 0
        cdef uint64_t wb = 0
        cdef uint64_t x
        cdef int i
        cdef Field* fd
        cdef int64_t r
        cdef PyObject* p
        cdef double d
        if len(keys) != self.n:
            raise ValueError(f"{len(keys)} keys for {self.n} fields")
        for i in range(self.n):
            fd = &self.f[i]
            if fd.role == ROLE_CRC:
                continue
            if not _own_bits(fd, counter, tick, &x):
                key = keys[i]
                p = NULL if key is None else PyDict_GetItem(values, key)
                if p is NULL:
                    r = self._raw(i, self.defaults[i])
                else:
                    v = <object>p
                    d = PyFloat_AS_DOUBLE(v) if PyFloat_Check(v) else (0.0 if PyLong_Check(v) and not as_float
                                                                       else PyFloat_AsDouble(v))
                    if not isfinite(d):  # left out of the frame: the field's default
                        r = self._raw(i, self.defaults[i])
                    elif as_float:
                        r = self._raw_double(i, d)
                    else:
                        r = self._raw(i, v)
                x = (<uint64_t>r & fd.mask) << fd.start
            if fd.big:
                wb |= x
            else:
                w |= x
        return self._payload_of(w, wb)

    cdef bytes _payload_of(self, uint64_t w, uint64_t wb):
        """The payload bytes of the little-endian fields' word ``w`` and the big-endian fields'
        word ``wb``, with the E2E CRC if protected."""
        cdef uint8_t b[8]
        self._payload_into(w, wb, b)
        return PyBytes_FromStringAndSize(<char*>b, self.length)

    cdef void _payload_into(self, uint64_t w, uint64_t wb, uint8_t* b) noexcept:
        """:meth:`_payload_of` written to ``b`` (``length`` bytes)."""
        cdef uint8_t crc
        cdef int i
        for i in range(self.length):
            b[i] = <uint8_t>(w >> (8 * i)) | <uint8_t>(wb >> (56 - 8 * i))
        if self.protected:  # the CRC is byte 0 (checked in __init__), in either byte order
            crc = self.crc0
            for i in range(1, self.length):
                crc = CRC_TABLE[crc ^ b[i]]
            b[0] |= <uint8_t>(crc ^ 0xFF)

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
        cdef uint64_t wb = _swap64(w) if self.any_big else 0
        for i in range(self.n):
            PyDict_SetItem(d, self.names[i], _field_value(&self.f[i], w, wb))
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


# ---------------------------------------------------------------- receivers' E2E origin
# frame_origin's results below 0: rejected, by reason (canbrake.bus.guard.REASONS)
REJECT_CRC = -1
REJECT_COUNTER = -2
DEF _CRC = -1
DEF _COUNTER = -2
DEF COUNTER_MODULO = 15


cdef inline bint _payload(object data, const uint8_t** s, Py_ssize_t* n) except -1:
    if PyBytes_CheckExact(data):
        s[0] = <const uint8_t*>PyBytes_AS_STRING(data)
        n[0] = PyBytes_GET_SIZE(data)
    elif PyByteArray_Check(data):
        s[0] = <const uint8_t*>PyByteArray_AS_STRING(data)
        n[0] = PyByteArray_GET_SIZE(data)
    else:
        return False
    return True


cdef inline bint _crc_ok(const uint8_t* s, Py_ssize_t n, unsigned int data_id) noexcept:
    """Byte 0 of the payload (``n`` >= 2 bytes) is the E2E CRC over ``data_id`` and bytes 1.."""
    cdef uint8_t c
    cdef Py_ssize_t i
    if n < 2:
        return False
    c = CRC_TABLE[CRC_TABLE[0xFF ^ (data_id & 0xFF)] ^ ((data_id >> 8) & 0xFF)]
    for i in range(1, n):
        c = CRC_TABLE[c ^ s[i]]
    return s[0] == (c ^ 0xFF)


cdef int _origin(const uint8_t* s, Py_ssize_t n, unsigned int data_id, int64_t k, int64_t last_origin,
                 bint same_tick_ok, bint crc_checked, int ext_start, int ext_bits, int64_t max_lag,
                 int64_t* out):
    """The tick a protected frame was sent in (E2E CRC, alive counter, its extension) into
    ``out``, and 0; or a REJECT_* code (< 0)."""
    cdef Py_ssize_t i
    cdef uint64_t w = 0
    cdef int64_t counter, modulus, lag, origin
    if not crc_checked and not _crc_ok(s, n, data_id):
        return _CRC
    if s[1] & 0x0F >= COUNTER_MODULO:
        return _COUNTER
    counter = s[1] & 0x0F
    modulus = COUNTER_MODULO
    if ext_bits > 0:
        for i in range(n if n < 8 else 8):
            w |= (<uint64_t>s[i]) << (8 * i)
        counter += COUNTER_MODULO * <int64_t>((w >> ext_start) & ((<uint64_t>1 << ext_bits) - 1))
        modulus = COUNTER_MODULO << ext_bits
    lag = (k - counter) % modulus
    if lag < 0:  # Python's modulo: non-negative
        lag += modulus
    origin = k - lag
    if lag > max_lag or origin < last_origin or (origin == last_origin and not same_tick_ok):
        return _COUNTER
    out[0] = origin
    return 0


def frame_origin(unsigned int data_id, object payload, int64_t k, int64_t last_origin, bint same_tick_ok,
                 bint crc_checked, object ext, int64_t max_lag):
    """(origin, 0) of a protected frame received at tick ``k``, or (None, REJECT_*): see
    :meth:`canbrake.bus.guard.FrameGuard.origin`; ``ext``: (start bit, bits) of the counter's
    extension or None."""
    cdef const uint8_t* s
    cdef Py_ssize_t n
    cdef int ext_start = 0, ext_bits = 0
    if not _payload(payload, &s, &n):
        payload = bytes(payload)
        _payload(payload, &s, &n)
    if n < 2 and crc_checked:
        payload[1]  # the IndexError of Python's indexing
    if ext is not None:
        ext_start, ext_bits = ext
        if ext_start + ext_bits > 64:
            raise ValueError(f"counter extension {ext} beyond a classical CAN frame")
    cdef int64_t o = 0
    cdef int code = _origin(s, n, data_id, k, last_origin, same_tick_ok, crc_checked, ext_start, ext_bits, max_lag, &o)
    return (None, code) if code < 0 else (o, 0)


# ---------------------------------------------------------------- SYNC at a receiver
#: sync_check's verdicts
SYNC_REJECT = 0        # out of sequence or at a moment the protocol never sends it (reason "sync")
SYNC_TICK = 1          # the next period (if authentic)
SYNC_END = 2           # the end of the run (if authentic)
SYNC_END_IGNORED = 3   # an unauthenticated END before the last scheduled tick
DEF _S_REJECT = 0
DEF _S_TICK = 1
DEF _S_END = 2
DEF _S_END_IGNORED = 3
DEF END_TICK = 0xFFFFFFFF


cdef int _sync_code(const uint8_t* s, Py_ssize_t n, int64_t own_k, bint tick_complete, bint lockstep,
                    bint has_final, int64_t final_tick, bint secured, int64_t* tick) noexcept:
    """The verdict on a SYNC payload (its Tick: bytes 0-3, little-endian, missing bytes 0) at a
    receiver whose last accepted tick is ``own_k``; the tick into ``tick``."""
    cdef int64_t t = 0
    cdef Py_ssize_t i
    for i in range(n if n < 4 else 4):
        t |= (<int64_t>s[i]) << (8 * i)
    tick[0] = t
    cdef bint end = t == END_TICK
    if (lockstep and not tick_complete) or (end and own_k < 0):  # no END before the first tick
        return _S_REJECT
    if not end and (t != own_k + 1 if lockstep else t <= own_k):
        return _S_REJECT
    if end and not secured and has_final and own_k != final_tick:
        return _S_END_IGNORED
    return _S_END if end else _S_TICK


def sync_check(object payload, int64_t own_k, bint tick_complete, bint lockstep, final_tick, bint secured):
    """(SYNC_*, tick) of a SYNC payload: see :func:`canbrake.bus.guard.sync_verdict`."""
    cdef const uint8_t* s
    cdef Py_ssize_t n
    cdef int64_t t = 0
    if not _payload(payload, &s, &n):
        payload = bytes(payload)
        _payload(payload, &s, &n)
    cdef int code = _sync_code(s, n, own_k, tick_complete, lockstep, final_tick is not None,
                               0 if final_tick is None else final_tick, secured, &t)
    return code, t


# ---------------------------------------------------------------- a receiver's peer table
cdef struct PageField:
    Field* field     # the signal's field in its page's FieldCodec (kept alive by PeerTable._codecs)
    double* target   # element j of the array the signal goes to (kept alive by PeerTable.values)


cdef void _decode_into(PageField* pf, int count, uint64_t w) noexcept:
    """Decode ``count`` signals of a frame (its little-endian word ``w``) into their targets, as
    ``FieldCodec.decode`` gives them (the float the array holds)."""
    cdef Field* fd
    cdef int64_t raw
    cdef uint64_t wb = _swap64(w)
    cdef int i
    for i in range(count):
        fd = pf[i].field
        raw = _field_raw(fd, w, wb)
        if not fd.scaled:
            pf[i].target[0] = <double>raw
        elif fd.offset == 0.0 and fd.scale > 0.0:
            pf[i].target[0] = <double>raw * fd.scale
        else:
            pf[i].target[0] = <double>raw * fd.scale + fd.offset


cdef struct Page:
    int j            # sender's ECU index (0-based)
    bint same_tick_ok
    int ext_start
    int ext_bits
    int first        # its fields: _fields[first:first + count]
    int count


cdef struct SensorField:
    Field* field     # the signal's field in its page's FieldCodec (kept alive by PeerTable._codecs)
    PyObject* name   # the sensor's name, the key in the sensors dict (kept alive by PeerTable._names)


cdef struct SensorPage:
    int first        # its fields: _sf[first:first + count]
    int count
    bint last        # the ECU's last sensor page: its phase 1 follows


# what PeerTable.feed does with a frame, by identifier (PeerTable._route: id -> kind << 24 | index)
DEF R_STATE = 1      # a listened ECU's state page (index: its page number)
DEF R_SENSOR = 2     # one of this ECU's sensor pages (index: its number)
DEF R_REF = 3        # the reference (speed, deceleration)
DEF R_REF_POS = 4    # the reference position
DEF R_PY = 5         # the node's Python (barrier frames, secured or linked state frames)
DEF R_SYNC = 6       # SYNC

#: PeerTable.feed's events (low 3 bits of its result; the frame's index above them)
FEED_END = 0         # every frame taken
FEED_FRAME = 1       # this frame is the node's to handle (R_PY)
FEED_PHASE1 = 2      # this frame was the ECU's last sensor page
FEED_PHASE2 = 3      # this state page completed the last peer of the tick in phase 1
FEED_REJECT = 4      # this state page was rejected (PeerTable.last_code: REJECT_*)
FEED_HELD = 5        # this state page came after its sender's barrier frame: held (lockstep)
FEED_ARM = 6         # this state page completed a peer in phase 1, only external peers may be missing
FEED_SYNC = 7        # this SYNC starts tick PeerTable.sync_tick (the table's new tick begun)
DEF _END = 0
DEF _FRAME = 1
DEF _PHASE1 = 2
DEF _PHASE2 = 3
DEF _REJECT = 4
DEF _HELD = 5
DEF _ARM = 6
DEF _SYNC = 7
# the memory bus's slot image (feed_raw, take_batch_raw)
from canbrake.bus._slot cimport (SLOT_BYTES, DATA_OFFSET, MAX_DATA, SLOT_FLAG_EXTENDED, slot_id, slot_flags, slot_len,
                                slot_put)


cdef class PeerTable:
    """What one ECU holds of its peers: per signal an array over the train's ECUs (NaN until
    received), per ECU the newest origin (tick), the state pages of that tick seen and whether
    the ECU is complete for this tick (``peer_done``).

    ``take`` checks a state page (E2E CRC, counter, origin: :func:`frame_origin`) and decodes it
    straight into the arrays; ``ages`` gives the peers' ages once per period. ``values`` are
    the arrays themselves (numpy, float64, shape (n,)).

    An ECU's receive side (:meth:`route_ecu`, :meth:`feed`): a batch of frames goes through one
    compiled loop that takes the state pages, decodes the sensor pages into the ECU's sensor dict
    and the reference into ``v_ref``/``a_ref``/``x_ref``, marks peers complete, and returns to
    the node only where its Python acts (a phase, SYNC, a rejection; see ``FEED_*``)."""

    cdef readonly int n
    cdef readonly dict values
    cdef readonly object origin      # int64 array (n,)
    cdef object _fresh_arr, _pages_arr, _flags_arr
    cdef object _age_arr             # float64 (n,): ages(..., into=True) writes here
    cdef double* _age
    #: a read-only view of the ages ``ages(..., into=True)`` last wrote
    cdef readonly object age_view
    cdef int64_t* _origin
    cdef int64_t* _fresh             # state pages of this tick seen, per ECU
    cdef int64_t* _pages_of          # state pages per ECU and tick
    cdef int64_t max_lag
    cdef dict _index                 # frame id -> page number
    cdef list _codecs
    cdef Page* _pg
    cdef int _npg
    cdef PageField* _pf
    cdef int _npf
    cdef object _listened_arr
    cdef int64_t* _listened
    cdef int _nlistened
    # the peers' completion of this tick: per ECU flags (listened, done, lost, external)
    cdef uint8_t* _is_listened
    cdef uint8_t* _done              # complete this tick (its last page, or its barrier frame)
    cdef uint8_t* _lost              # an external peer given up on this tick (not done)
    cdef uint8_t* _ext               # an external ECU (not canbrake's)
    cdef readonly int missing        # listened ECUs neither done nor lost
    cdef bint _any_ext
    cdef double* _speed              # values["speed_mps"]'s elements (NULL: no such signal)
    # an ECU's receive side (route_ecu)
    cdef dict _route                 # frame id -> kind << 24 | index
    cdef SensorPage* _sp
    cdef int _nsp
    cdef SensorField* _sf
    cdef int _nsf
    cdef list _names
    cdef dict _sensors
    cdef Field* _ref_speed
    cdef Field* _ref_decel
    cdef Field* _ref_pos
    cdef bint _barrier, _lockstep, _per_frame, _has_final
    cdef int64_t _final_tick
    cdef unsigned int _sync_id
    #: the tick of the last FEED_SYNC
    cdef readonly int64_t sync_tick
    #: the reference as last received: speed (m/s), deceleration (m/s^2), position (m)
    cdef public object v_ref, a_ref, x_ref
    #: state pages accepted (take, apply, feed)
    cdef readonly int64_t accepted
    #: the REJECT_* code of the last FEED_REJECT
    cdef readonly int last_code

    def __cinit__(self):
        self._pg = NULL
        self._pf = NULL
        self._sp = NULL
        self._sf = NULL

    def __dealloc__(self):
        PyMem_Free(self._pg)
        PyMem_Free(self._pf)
        PyMem_Free(self._sp)
        PyMem_Free(self._sf)

    def __init__(self, int n, signal_names, listened, int64_t max_lag, external=()):
        """``listened``: the ECU indices (0-based) this ECU listens to, ``external`` those of
        them that are external ECUs."""
        self.n = n
        self.values = {nm: np.full(n, np.nan) for nm in signal_names}
        cdef double[::1] speed
        self._speed = NULL
        if "speed_mps" in self.values and n > 0:
            speed = self.values["speed_mps"]
            self._speed = &speed[0]
        self.origin = np.full(max(n, 1), -(10 ** 12), dtype=np.int64)
        self._fresh_arr = np.zeros(max(n, 1), dtype=np.int64)
        self._pages_arr = np.zeros(max(n, 1), dtype=np.int64)
        self._origin = _i64(self.origin)
        self._age_arr = np.zeros(max(n, 1))
        cdef double[::1] age_mv = self._age_arr
        self._age = &age_mv[0]
        self.age_view = self._age_arr[:n]
        self.age_view.flags.writeable = False
        self._fresh = _i64(self._fresh_arr)
        self._pages_of = _i64(self._pages_arr)
        self.max_lag = max_lag
        self._index = {}
        self._codecs = []
        self._npg = self._npf = self._nsp = self._nsf = 0
        self._listened_arr = np.asarray(list(listened) or [0], dtype=np.int64)
        self._listened = _i64(self._listened_arr)
        self._nlistened = len(listened)
        self._flags_arr = np.zeros((4, max(n, 1)), dtype=np.uint8)
        cdef uint8_t[:, ::1] fl = self._flags_arr
        self._is_listened, self._done, self._lost, self._ext = &fl[0, 0], &fl[1, 0], &fl[2, 0], &fl[3, 0]
        for j in listened:
            if not 0 <= j < n:
                raise ValueError(f"ECU index {j} outside 0..{n - 1}")
            self._is_listened[j] = 1
        for j in external:
            if 0 <= j < n and self._is_listened[j]:
                self._ext[j] = 1
                self._any_ext = True
        self.missing = self._nlistened
        self._route = {}
        self._names = []
        self._sensors = {}
        self._ref_speed = self._ref_decel = self._ref_pos = NULL
        self.v_ref, self.a_ref, self.x_ref = 0.0, 0.0, NAN
        self._lockstep = True
        self.accepted = 0
        self.last_code = 0

    def add_page(self, unsigned int frame_id, int j, FieldCodec codec, signals, bint same_tick_ok, ext):
        """A state page of ECU index j (0-based): ``signals`` = [(array name, signal name)];
        ``ext``: its counter extension (start bit, bits) or None."""
        ext_start, ext_bits = ext if ext is not None else (0, 0)
        if ext_start + ext_bits > 64:
            raise ValueError(f"counter extension {ext} beyond a classical CAN frame")
        if not 0 <= j < self.n:
            raise ValueError(f"ECU index {j} outside 0..{self.n - 1}")
        self._pg = <Page*>PyMem_Realloc(self._pg, (self._npg + 1) * sizeof(Page))
        self._pf = <PageField*>PyMem_Realloc(self._pf, (self._npf + len(signals)) * sizeof(PageField))
        if self._pg is NULL or self._pf is NULL:
            raise MemoryError()
        cdef Page* pg = &self._pg[self._npg]
        pg.j, pg.same_tick_ok, pg.ext_start, pg.ext_bits = j, same_tick_ok, ext_start, ext_bits
        pg.first, pg.count = self._npf, len(signals)
        cdef double[::1] arr
        for sig, dbc_name in signals:
            arr = self.values[sig]
            self._pf[self._npf].field = &codec.f[codec.names.index(dbc_name)]
            self._pf[self._npf].target = &arr[j]
            self._npf += 1
        self._codecs.append(codec)
        self._index[frame_id] = self._npg
        self._route[frame_id] = R_STATE << 24 | self._npg
        self._npg += 1
        self._pages_of[j] += 1

    def route_ecu(self, dict sensors, sensor_pages, FieldCodec reference, unsigned int reference_id,
                  FieldCodec reference_pos, unsigned int reference_pos_id, unsigned int sync_id, python_ids, *,
                  bint barrier, bint lockstep, bint per_frame, final_tick=None):
        """Make this the receive side of an ECU (:meth:`feed`): ``sensors`` its sensor dict
        (name -> value, written by its sensor pages), ``sensor_pages`` [(frame id, codec,
        [(sensor name, signal name)])] in order (the last one starts phase 1), the reference's
        messages (RefSpeed, RefDecel; RefPosition, None: not routed), the SYNC identifier,
        ``python_ids`` the identifiers the node's Python handles (barrier frames, authenticators);
        ``barrier``: peers complete by their barrier frames, not their last page; ``per_frame``:
        state pages and SYNC go to the node's Python one by one (SecOC, receive links);
        ``final_tick``: the last scheduled tick (an unauthenticated END before it is ignored).
        Call after every :meth:`add_page`."""
        cdef FieldCodec c
        cdef int i = 0
        route = {}  # the node's order of checks: a later entry wins
        if reference_pos is not None:
            route[reference_pos_id] = R_REF_POS << 24
        route[reference_id] = R_REF << 24
        for fid, c, sigs in sensor_pages:
            self._sp = <SensorPage*>PyMem_Realloc(self._sp, (self._nsp + 1) * sizeof(SensorPage))
            self._sf = <SensorField*>PyMem_Realloc(self._sf, (self._nsf + len(sigs)) * sizeof(SensorField))
            if self._sp is NULL or self._sf is NULL:
                raise MemoryError()
            self._sp[self._nsp].first, self._sp[self._nsp].count = self._nsf, len(sigs)
            self._sp[self._nsp].last = i == len(sensor_pages) - 1
            for name, dbc_name in sigs:
                self._names.append(name)
                self._sf[self._nsf].field = &c.f[c.names.index(dbc_name)]
                self._sf[self._nsf].name = <PyObject*>name
                self._nsf += 1
            self._codecs.append(c)
            route[fid] = R_SENSOR << 24 | self._nsp
            self._nsp += 1
            i += 1
        route[sync_id] = (R_PY if per_frame else R_SYNC) << 24
        for fid in python_ids:
            route[fid] = R_PY << 24
        for fid, p in self._index.items():
            route[fid] = (R_PY << 24) if per_frame else (R_STATE << 24 | p)
        self._route = route
        self._sensors = sensors
        self._codecs += [reference, reference_pos]
        self._ref_speed = &reference.f[reference.names.index("RefSpeed")]
        self._ref_decel = &reference.f[reference.names.index("RefDecel")]
        if reference_pos is not None:
            self._ref_pos = &reference_pos.f[reference_pos.names.index("RefPosition")]
        self._barrier, self._lockstep, self._per_frame = barrier, lockstep, per_frame
        self._sync_id = sync_id
        self._has_final = final_tick is not None
        self._final_tick = final_tick if final_tick is not None else 0

    def new_tick(self):
        """A new period: no page of it seen yet, no peer complete."""
        self._new_tick()

    cdef void _new_tick(self) noexcept:
        cdef int j
        for j in range(self.n):
            self._fresh[j] = 0
            self._done[j] = 0
        self.missing = 0
        for j in range(self._nlistened):
            self.missing += not self._lost[self._listened[j]]

    def origin_of(self, int j):
        """The newest origin (tick) accepted from ECU index j."""
        return self._origin[j]

    # ------------------------------------------------------------ peers complete this tick
    cdef inline void _peer_done(self, int j) noexcept:
        if self._done[j] or not self._is_listened[j]:
            return
        self._done[j] = 1
        if self._lost[j]:
            self._lost[j] = 0  # a silent external peer on time again
        else:
            self.missing -= 1

    def peer_done(self, int j):
        """ECU index j (listened) is complete for this tick (its last page or barrier frame)."""
        self._peer_done(j)

    def is_done(self, int j):
        """Whether ECU index j is complete for this tick."""
        return bool(self._done[j])

    def is_external(self, int j):
        """Whether ECU index j is a listened external ECU."""
        return bool(self._ext[j])

    def not_done(self):
        """Listened ECUs not complete for this tick."""
        cdef int j, c = 0
        for j in range(self._nlistened):
            c += not self._done[self._listened[j]]
        return c

    def only_external_missing(self):
        """Some listened ECUs are neither complete nor given up, and all of them are external."""
        cdef int j, e
        if self.missing == 0:
            return False
        for j in range(self._nlistened):
            e = self._listened[j]
            if not self._done[e] and not self._lost[e] and not self._ext[e]:
                return False
        return True

    def lose_external(self):
        """Give up, for this tick, on the external peers not complete (they are late)."""
        cdef int j, e
        for j in range(self._nlistened):
            e = self._listened[j]
            if self._ext[e] and not self._done[e] and not self._lost[e]:
                self._lost[e] = 1
                self.missing -= 1

    # ------------------------------------------------------------ state pages
    cdef int _apply(self, int p, uint64_t w, int64_t origin, int64_t k):
        cdef Page* pg = &self._pg[p]
        cdef int j = pg.j
        _decode_into(self._pf + pg.first, pg.count, w)
        self.accepted += 1
        if origin > self._origin[j]:
            self._origin[j] = origin
            self._fresh[j] = 0
        if origin == k:
            self._fresh[j] += 1
            return 2 if self._fresh[j] == self._pages_of[j] else 1
        return 0

    cdef int _take(self, int p, unsigned int frame_id, const uint8_t* s, Py_ssize_t n, int64_t k):
        cdef Page* pg = &self._pg[p]
        cdef int64_t o = 0
        cdef int code = _origin(s, n, frame_id, k, self._origin[pg.j], pg.same_tick_ok, False,
                                pg.ext_start, pg.ext_bits, self.max_lag, &o)
        if code < 0:
            return code
        return self._apply(p, _le_word(s, n), o, k)

    def apply(self, unsigned int frame_id, object data, int64_t origin, int64_t k):
        """Use an accepted state page sent at tick ``origin`` (receiver at tick ``k``): 0 not of
        this tick, 1 of this tick, 2 of this tick and the sender's last page of it."""
        cdef const uint8_t* s
        cdef Py_ssize_t n
        if not _payload(data, &s, &n):
            data = bytes(data)
            _payload(data, &s, &n)
        return self._apply(self._index[frame_id], _le_word(s, n), origin, k)

    def take(self, unsigned int frame_id, object data, int64_t k):
        """Check (E2E, origin) and apply a state page received at tick ``k``: REJECT_* (< 0),
        or as :meth:`apply`."""
        cdef const uint8_t* s
        cdef Py_ssize_t n
        cdef int p = self._index[frame_id]
        if not _payload(data, &s, &n):
            data = bytes(data)
            _payload(data, &s, &n)
        return self._take(p, frame_id, s, n, k)

    # ------------------------------------------------------------ an ECU's batch
    def feed(self, list msgs, Py_ssize_t start, int64_t k, int phase):
        """Take ``msgs[start:]`` (python-can messages, in bus order) at tick ``k`` in ``phase``
        until the end or a frame the node's Python must act on: returns index << 3 | FEED_*.
        State pages are checked and decoded (peers complete: their last page of tick k, unless
        barrier frames complete them), sensor pages decoded into the sensor dict, the reference
        into ``v_ref``/``a_ref``/``x_ref``, a SYNC checked (:func:`sync_check`; its tick starts
        here, anything else goes to the node); frames of identifiers not routed are ignored."""
        cdef Py_ssize_t i, m = len(msgs)
        cdef PyObject* r
        cdef int ev
        cdef const uint8_t* s
        cdef Py_ssize_t n
        for i in range(start, m):
            msg = msgs[i]
            aid_obj = msg_get(msg, MSG_ID)
            r = PyDict_GetItem(self._route, aid_obj)
            if r is NULL:
                continue
            if (<long><object>r) >> 24 == R_PY:
                return i << 3 | _FRAME
            data = msg_get(msg, MSG_DATA)
            if not _payload(data, &s, &n):
                data = bytes(data)
                _payload(data, &s, &n)
            ev = self._feed_one(<long><object>r, aid_obj, msg_get(msg, MSG_EXT), s, n, k, phase)
            if ev >= 0:
                return i << 3 | ev
        return m << 3 | _END

    def feed_raw(self, frames, Py_ssize_t start, int64_t k, int phase):
        """:meth:`feed` for slot images (``canbrake.bus._ring``: the memory bus's ``recv_raw``;
        identifier at byte 8, flags at 16 (bit 0 extended), data length at 18, data at 24 of
        each 96-byte image): the same work, no ``can.Message``; the index is the image's."""
        cdef const uint8_t[::1] v = frames
        cdef Py_ssize_t i, m = v.shape[0] // SLOT_BYTES
        cdef const uint8_t* p
        cdef PyObject* r
        cdef int ev
        if m == 0:
            return start << 3 | _END
        for i in range(start, m):
            p = &v[i * SLOT_BYTES]
            aid_obj = slot_id(p)
            r = PyDict_GetItem(self._route, aid_obj)
            if r is NULL:
                continue
            if (<long><object>r) >> 24 == R_PY:
                return i << 3 | _FRAME
            ev = self._feed_one(<long><object>r, aid_obj, slot_flags(p) & SLOT_FLAG_EXTENDED, p + DATA_OFFSET,
                                slot_len(p), k, phase)
            if ev >= 0:
                return i << 3 | ev
        return m << 3 | _END

    cdef int _feed_one(self, long code, object aid_obj, bint ext, const uint8_t* s, Py_ssize_t n, int64_t k,
                       int phase) except -2:
        """One routed frame (not R_PY) of :meth:`feed`: the event it ends the loop with, or -1."""
        cdef int kind = code >> 24, idx = code & 0xFFFFFF, res, j, f
        cdef uint64_t w, wb
        cdef SensorPage* sp
        cdef unsigned int aid
        cdef int64_t t = 0
        if kind == R_SYNC and ext != (<unsigned int>aid_obj > 0x7FF):
            return -1  # not the SYNC: nothing of this node's
        if kind == R_SYNC:
            if _sync_code(s, n, k, phase == 2 or k < 0, self._lockstep, self._has_final, self._final_tick,
                          False, &t) != _S_TICK:
                return _FRAME  # rejected, or the end: the node's verdict
            self._new_tick()
            self.sync_tick = t
            return _SYNC
        if kind == R_STATE:
            j = self._pg[idx].j
            if self._barrier and self._lockstep and phase != 2 and self._done[j]:
                return _HELD
            aid = aid_obj
            res = self._take(idx, aid, s, n, k)
            if res < 0:
                self.last_code = res
                return _REJECT
            if res == 2 and (not self._barrier or self._ext[j]):
                self._peer_done(j)
                if phase == 1:
                    if self.missing == 0:
                        return _PHASE2
                    if self._any_ext:
                        return _ARM
        elif kind == R_SENSOR:
            sp = &self._sp[idx]
            w = _le_word(s, n)
            wb = _swap64(w)
            for f in range(sp.first, sp.first + sp.count):
                PyDict_SetItem(self._sensors, <object>self._sf[f].name, _field_value(self._sf[f].field, w, wb))
            if sp.last:
                return _PHASE1
        elif kind == R_REF:
            w = _le_word(s, n)
            wb = _swap64(w)
            self.v_ref = _field_value(self._ref_speed, w, wb)
            self.a_ref = _field_value(self._ref_decel, w, wb)
        else:  # R_REF_POS
            w = _le_word(s, n)
            self.x_ref = _field_value(self._ref_pos, w, _swap64(w))
        return -1

    def hold_copy(self, int64_t k, int64_t hold, int own):
        """The peers' arrays for a controller that must not see lost peers: a copy of each of
        ``values`` (same order) with NaN for every listened ECU whose newest value is more than
        ``hold`` periods older than tick ``k`` (ECU index ``own`` counted as of tick k);
        returns (the copies, whether one was dropped)."""
        cdef dict out = {}
        cdef double[::1] c
        cdef int j, e, nlost = 0
        cdef int64_t o
        for j in range(self._nlistened):
            e = self._listened[j]
            o = k if e == own else self._origin[e]
            if k - o > hold:
                nlost += 1
        for nm, arr in self.values.items():
            cp = arr.copy()
            if nlost:
                c = cp
                for j in range(self._nlistened):
                    e = self._listened[j]
                    o = k if e == own else self._origin[e]
                    if k - o > hold:
                        c[e] = NAN
            out[nm] = cp
        return out, nlost > 0

    def ages(self, int64_t k, double dt, int own, speed=None, bint into=False):
        """(age, fresh, max_age) at tick ``k``: per ECU the age in s of its newest value (own
        entry 0; inf for an ECU never heard whose speed, in ``speed`` (float64, (n,); None: the
        table's ``speed_mps``), is unknown), the ECUs with a value of this tick (own included) and
        the oldest finite age (-inf: none). ``age`` is a new array, or with ``into`` the table's
        own, overwritten at the next such call: ``age_view``, read-only (the ECU's period, once
        per period, hands it to the controller as it hands the peers' values: valid for the call)."""
        cdef const double[::1] sv
        cdef const double* sp = self._speed
        if speed is not None or sp is NULL:
            sv = self.values["speed_mps"] if speed is None else speed
            if sv.shape[0] < self.n:
                raise ValueError(f"speed has {sv.shape[0]} values for {self.n} ECUs")
            sp = &sv[0]
        cdef Py_buffer buf  # (its buffer as is: no typed memoryview object per call)
        cdef double* a
        if into:
            age = self.age_view
            a = self._age
        else:
            age = np.empty(self.n)
            PyObject_GetBuffer(age, &buf, PyBUF_WRITABLE)
            a = <double*>buf.buf
        cdef int j, fresh = 1
        cdef int64_t o
        cdef double x, max_age = -INFINITY
        for j in range(self.n):
            o = k if j == own else self._origin[j]
            x = INFINITY if o < 0 and isnan(sp[j]) else <double>(k - o) * dt
            a[j] = x
            if x != INFINITY and x > max_age:
                max_age = x
        if not into:
            PyBuffer_Release(&buf)
        for j in range(self._nlistened):
            if self._origin[self._listened[j]] == k:
                fresh += 1
        return age, fresh, max_age


cdef int64_t* _i64(object arr):
    cdef int64_t[::1] mv = arr
    return &mv[0]


cdef inline uint64_t _swap64(uint64_t w):
    """The big-endian word of the frame whose little-endian word is ``w`` (byte 0 most significant)."""
    cdef uint64_t r = 0
    cdef int i
    for i in range(8):
        r = (r << 8) | ((w >> (8 * i)) & 0xFF)
    return r


cdef inline uint64_t _le_word(const uint8_t* s, Py_ssize_t n):
    cdef uint64_t w = 0
    cdef Py_ssize_t i
    for i in range(n if n < 8 else 8):
        w |= (<uint64_t>s[i]) << (8 * i)
    return w


# ---------------------------------------------------------------- the brake units' command table
cdef struct CmdPage:
    int slot            # the sending ECU's slot (0-based)
    int first           # its fields in CommandTable._cf
    int count
    int last_counter    # the E2E receiver's last good counter (-1: none yet)
    int64_t origin      # tick of the newest accepted frame of this page (-1: none)
    int ext_start
    int ext_bits

#: CommandTable.take/check results (low two bits) and flags
CMD_OLD = 0            # accepted, sent in an earlier tick
CMD_FRESH = 1          # accepted, of this tick
CMD_BAD_CRC = 2        # rejected: E2E CRC
CMD_BAD_COUNTER = 3    # rejected: alive counter / origin window
CMD_OUT_OF_SEQUENCE = 4  # flag: the E2E receiver saw a counter jump (> 3) or an invalid counter
CMD_SLOT_COMPLETE = 8    # flag: this frame completed its ECU's pages of this tick
DEF _OLD = 0
DEF _FRESH = 1
DEF _BAD_CRC = 2
DEF _BAD_COUNTER = 3
DEF _OOS = 4
DEF _COMPLETE = 8
DEF E2E_MAX_DELTA = 3
#: CommandTable.take_batch's events
TAKE_BATCH_END = 0
TAKE_BATCH_OTHER = 1
TAKE_BATCH_RESULT = 2
TAKE_BATCH_TICK = 3


cdef class CommandTable:
    """The brake units' receive side of the command frames (the plant node): per page the E2E
    receiver's counter check (profile 1 as ``canbrake.bus.e2e.E2EReceiver``), the origin window
    (``FrameGuard.origin`` with the CRC already checked) and the decode straight into the plant's
    per-vehicle command arrays; per ECU slot the pages of this tick seen. One call per frame
    (``take``), or ``check`` then ``apply`` when a SecOC verification sits between them."""

    cdef CmdPage* _pg
    cdef int _npg
    cdef PageField* _cf
    cdef int _ncf
    cdef dict _index
    cdef list _keep                # codecs and arrays whose memory the table points into
    cdef int64_t max_lag
    cdef object _fresh_pages_arr, _pages_arr, _fresh_arr
    cdef int64_t* _fresh_pages     # pages of this tick seen, per slot
    cdef int64_t* _pages           # pages per slot and tick
    cdef uint8_t* _fresh           # the slot's pages of this tick are complete
    cdef object _newest_arr
    cdef int64_t* _newest          # tick of the newest accepted command, per slot
    cdef Py_ssize_t _nslots
    cdef object _completed         # take_batch's slots completed so far (a Python int: > 64 ECUs)

    def __cinit__(self):
        self._pg = NULL
        self._cf = NULL

    def __dealloc__(self):
        PyMem_Free(self._pg)
        PyMem_Free(self._cf)

    def __init__(self, fresh_pages, pages_per_slot, fresh, newest, int64_t max_lag):
        """``fresh_pages`` (int64, per slot), ``pages_per_slot`` (int64), ``fresh`` (bool) and
        ``newest`` (int64) are the plant's arrays, updated in place."""
        cdef int64_t[::1] fp = fresh_pages
        cdef int64_t[::1] pp = pages_per_slot
        cdef uint8_t[::1] fr = fresh.view("uint8")
        cdef int64_t[::1] nw = newest
        self._fresh_pages_arr, self._pages_arr, self._fresh_arr = fresh_pages, pages_per_slot, fresh
        self._newest_arr = newest
        self._newest = &nw[0]
        self._fresh_pages = &fp[0]
        self._pages = &pp[0]
        self._fresh = &fr[0]
        self._nslots = fr.shape[0]
        if fp.shape[0] != self._nslots or pp.shape[0] != self._nslots or nw.shape[0] != self._nslots:
            raise ValueError("fresh_pages, pages_per_slot, fresh and newest must have one element per slot")
        self.max_lag = max_lag
        self._index = {}
        self._keep = []
        self._npg = self._ncf = 0

    def add_page(self, unsigned int frame_id, int slot, FieldCodec codec, targets, ext):
        """A command page of ECU slot ``slot``: ``targets`` = [(signal name, float64 array,
        element index)]; ``ext``: its counter extension (start bit, bits) or None."""
        ext_start, ext_bits = ext if ext is not None else (0, 0)
        if ext_start + ext_bits > 64:
            raise ValueError(f"counter extension {ext} beyond a classical CAN frame")
        self._pg = <CmdPage*>PyMem_Realloc(self._pg, (self._npg + 1) * sizeof(CmdPage))
        self._cf = <PageField*>PyMem_Realloc(self._cf, (self._ncf + len(targets)) * sizeof(PageField))
        if self._pg is NULL or self._cf is NULL:
            raise MemoryError()
        cdef CmdPage* pg = &self._pg[self._npg]
        pg.slot, pg.first, pg.count = slot, self._ncf, len(targets)
        pg.last_counter, pg.origin = -1, -1
        pg.ext_start, pg.ext_bits = ext_start, ext_bits
        cdef double[::1] arr
        for dbc_name, array, idx in targets:
            arr = array
            self._cf[self._ncf].field = &codec.f[codec.names.index(dbc_name)]
            self._cf[self._ncf].target = &arr[idx]
            self._ncf += 1
            self._keep.append(array)
        self._keep.append(codec)
        self._index[frame_id] = self._npg
        self._npg += 1

    cdef int _check(self, CmdPage* pg, unsigned int frame_id, const uint8_t* s, Py_ssize_t n, int64_t k,
                    int64_t* origin) noexcept:
        cdef int flags = 0, counter, delta
        # the E2E receiver: CRC, then the counter's continuity (state advances on a good CRC)
        if not _crc_ok(s, n, frame_id):
            return _BAD_CRC
        counter = s[1] & 0x0F
        if counter >= COUNTER_MODULO:
            flags = _OOS
        else:
            if pg.last_counter >= 0:
                delta = (counter - pg.last_counter) % COUNTER_MODULO
                if delta < 0:
                    delta += COUNTER_MODULO
                if delta > E2E_MAX_DELTA:
                    flags = _OOS
            pg.last_counter = counter
        # the origin window (the CRC is checked)
        if _origin(s, n, frame_id, k, pg.origin, False, True, pg.ext_start, pg.ext_bits, self.max_lag,
                   origin) < 0:
            return flags | _BAD_COUNTER
        return flags

    cdef int _apply(self, CmdPage* pg, const uint8_t* s, Py_ssize_t n, int64_t origin, int64_t k) noexcept:
        _decode_into(self._cf + pg.first, pg.count, _le_word(s, n))
        pg.origin = origin
        if origin > self._newest[pg.slot]:
            self._newest[pg.slot] = origin
        if origin != k:
            return _OLD
        self._fresh_pages[pg.slot] += 1
        if self._fresh_pages[pg.slot] >= self._pages[pg.slot] and not self._fresh[pg.slot]:
            self._fresh[pg.slot] = 1
            return _FRESH | _COMPLETE
        return _FRESH

    def check(self, unsigned int frame_id, object data, int64_t k):
        """(result, origin): the E2E and origin checks of a command frame received at tick ``k``
        (result CMD_BAD_CRC / CMD_BAD_COUNTER, possibly | CMD_OUT_OF_SEQUENCE; else 0 or
        CMD_OUT_OF_SEQUENCE and the tick it was sent in). Nothing applied."""
        cdef const uint8_t* s
        cdef Py_ssize_t n
        if not _payload(data, &s, &n):
            data = bytes(data)
            _payload(data, &s, &n)
        cdef int64_t o = -1
        cdef int r = self._check(&self._pg[<int>self._index[frame_id]], frame_id, s, n, k, &o)
        return r, o

    def apply(self, unsigned int frame_id, object data, int64_t origin, int64_t k):
        """Apply a checked command frame sent at tick ``origin``: CMD_OLD or CMD_FRESH (|
        CMD_SLOT_COMPLETE)."""
        cdef const uint8_t* s
        cdef Py_ssize_t n
        if not _payload(data, &s, &n):
            data = bytes(data)
            _payload(data, &s, &n)
        return self._apply(&self._pg[<int>self._index[frame_id]], s, n, origin, k)

    def take(self, unsigned int frame_id, object data, int64_t k):
        """``check`` and, if accepted, ``apply`` in one call: the result with its flags."""
        cdef const uint8_t* s
        cdef Py_ssize_t n
        if not _payload(data, &s, &n):
            data = bytes(data)
            _payload(data, &s, &n)
        cdef CmdPage* pg = &self._pg[<int>self._index[frame_id]]
        cdef int64_t o = -1
        cdef int r = self._check(pg, frame_id, s, n, k, &o)
        if r & 3:
            return r
        return r | self._apply(pg, s, n, o, k)

    def page_origin(self, unsigned int frame_id):
        """Tick of the newest accepted frame of this page (-1: none)."""
        return self._pg[<int>self._index[frame_id]].origin

    def fresh_total(self):
        """Command pages of this tick taken so far, every slot (the sum of ``fresh_pages``)."""
        cdef int64_t t = 0
        cdef Py_ssize_t i
        for i in range(self._nslots):
            t += self._fresh_pages[i]
        return t

    def all_fresh(self):
        """True once every slot's pages of this tick are complete (``fresh.all()``)."""
        cdef Py_ssize_t i
        for i in range(self._nslots):
            if not self._fresh[i]:
                return False
        return True

    def new_tick(self):
        """A new tick: no slot's pages seen (``fresh_pages[:] = 0``, ``fresh[:] = False``)."""
        cdef Py_ssize_t i
        for i in range(self._nslots):
            self._fresh_pages[i] = 0
            self._fresh[i] = 0

    def take_batch(self, list msgs, Py_ssize_t start, int64_t k):
        """:meth:`take` for each frame of ``msgs[start:]`` received at tick ``k`` (the plant's
        lockstep receive loop when every ECU's commands close its slot), back to the caller
        only where it has something to do. Returns ``(i, event, result, completed, accepted)``:
        ``event`` TAKE_BATCH_END (every frame taken, ``i`` = len), TAKE_BATCH_OTHER (``msgs[i]``
        is not a command page: not taken), TAKE_BATCH_RESULT (``msgs[i]`` taken with ``result``
        rejected or out of sequence: the caller's accounting), TAKE_BATCH_TICK (``msgs[i]``
        completed the last slot of tick ``k``); ``completed``: bit s set for each slot s whose
        pages of tick ``k`` the frames up to ``i`` completed; ``accepted``: frames accepted
        cleanly before ``i`` (and ``msgs[i]`` itself for TAKE_BATCH_TICK)."""
        cdef Py_ssize_t i, m = len(msgs)
        cdef int64_t accepted = 0
        cdef int r = 0, ev
        cdef const uint8_t* s
        cdef Py_ssize_t n
        cdef PyObject* p
        self._completed = 0
        for i in range(start, m):
            msg = msgs[i]
            aid_obj = msg_get(msg, MSG_ID)
            p = PyDict_GetItem(self._index, aid_obj)
            if p is NULL:
                return i, TAKE_BATCH_OTHER, 0, self._completed, accepted
            data = msg_get(msg, MSG_DATA)
            if not _payload(data, &s, &n):
                data = bytes(data)
                _payload(data, &s, &n)
            ev = self._take_one(<int><object>p, aid_obj, s, n, k, &r, &accepted)
            if ev != TAKE_BATCH_END:
                return i, ev, r, self._completed, accepted
        return m, TAKE_BATCH_END, 0, self._completed, accepted

    def take_batch_raw(self, frames, Py_ssize_t start, int64_t k):
        """:meth:`take_batch` for the memory bus's slot images (``MemoryBus.recv_raw``: identifier
        at byte 8, data length at 18, data at 24 of each 96-byte image): the same work and
        result, no ``can.Message``; ``i`` is the image's index."""
        cdef const uint8_t[::1] v = frames
        cdef Py_ssize_t i, m = v.shape[0] // SLOT_BYTES
        cdef int64_t accepted = 0
        cdef int r = 0, ev
        cdef const uint8_t* q
        cdef uint32_t aid
        cdef PyObject* p
        self._completed = 0
        for i in range(start, m):
            q = &v[i * SLOT_BYTES]
            aid = slot_id(q)
            aid_obj = aid
            p = PyDict_GetItem(self._index, aid_obj)
            if p is NULL:
                return i, TAKE_BATCH_OTHER, 0, self._completed, accepted
            ev = self._take_one(<int><object>p, aid, q + DATA_OFFSET, slot_len(q), k, &r, &accepted)
            if ev != TAKE_BATCH_END:
                return i, ev, r, self._completed, accepted
        return m, TAKE_BATCH_END, 0, self._completed, accepted

    cdef int _take_one(self, int page, unsigned int frame_id, const uint8_t* s, Py_ssize_t n, int64_t k, int* r,
                       int64_t* accepted) except -1:
        """One command page of :meth:`take_batch` (both variants): taken; the event that ends
        the loop (TAKE_BATCH_END: none, go on), the result in ``r``, ``accepted`` and the batch's
        completed slots (``_completed``) updated."""
        cdef CmdPage* pg = &self._pg[page]
        cdef int64_t o = -1
        cdef Py_ssize_t s_
        r[0] = self._check(pg, frame_id, s, n, k, &o)
        if not r[0] & 3:
            r[0] |= self._apply(pg, s, n, o, k)
        if (r[0] & 3) >= _BAD_CRC or r[0] & _OOS:
            return TAKE_BATCH_RESULT
        accepted[0] += 1
        if r[0] & _COMPLETE:
            self._completed = self._completed | ((<object>1) << (<object>pg.slot))  # Python ints: no C overflow
            for s_ in range(self._nslots):
                if not self._fresh[s_]:
                    return TAKE_BATCH_END
            return TAKE_BATCH_TICK
        return TAKE_BATCH_END


# ---------------------------------------------------------------- the plant's sensor pages
DEF SRC_NONE = -2   # the field has no source: it encodes its default (as a missing signal)
DEF SRC_ZERO = -1   # the value 0.0 (a coupler that does not exist: the train's ends)


cdef class SensorPages:
    """The plant's sensor pages of a period in one call: each page's signals read from the
    period's measurement arrays (``pack(sources)``: a list of float64 arrays, one per source
    name), a non-finite value encoded as a missing signal, as ``FieldCodec.encode`` of the
    finite values would."""

    cdef list _codecs
    cdef object _src_arr, _elem_arr
    cdef int* _src        # per page and codec field: source index, SRC_ZERO or SRC_NONE
    cdef int64_t* _elem   # ... and element index in the source
    cdef int _npg

    def __init__(self, pages):
        """``pages``: per page (FieldCodec, [(signal name, source index or -1 for 0.0, element)])."""
        self._codecs = []
        src = np.full((max(len(pages), 1), MAX_FIELDS), SRC_NONE, dtype=np.intc)
        elem = np.zeros((max(len(pages), 1), MAX_FIELDS), dtype=np.int64)
        cdef FieldCodec codec
        for p, (codec, fields) in enumerate(pages):
            for name, s_, e in fields:
                i = codec.names.index(name)
                src[p, i] = SRC_ZERO if s_ < 0 else s_
                elem[p, i] = e
            self._codecs.append(codec)
        self._npg = len(pages)
        self._src_arr, self._elem_arr = src, elem
        cdef int[:, ::1] sv = src
        cdef int64_t[:, ::1] ev = elem
        self._src = &sv[0, 0]
        self._elem = &ev[0, 0]

    def pack(self, list sources):
        """The pages' payloads (list of bytes, in the order given) from ``sources``."""
        cdef list out = []
        cdef FieldCodec codec
        cdef int p
        cdef uint64_t* w = <uint64_t*>PyMem_Malloc(2 * (self._npg if self._npg > 0 else 1) * sizeof(uint64_t))
        if w is NULL:
            raise MemoryError()
        try:
            self._words(sources, w)
            for p in range(self._npg):
                codec = self._codecs[p]
                out.append(codec._payload_of(w[2 * p], w[2 * p + 1]))
        finally:
            PyMem_Free(w)
        return out

    cdef int _images(self, list sources, uint8_t* images, list ids) except -1:
        """The pages as slot images (``_slot.slot_put``) at ``images``, one per ``SLOT_BYTES``
        (zeroed), page i on identifier ``ids[i]``: :meth:`pack`'s payloads."""
        cdef FieldCodec codec
        cdef int p
        cdef uint8_t b[8]
        cdef uint64_t* w = <uint64_t*>PyMem_Malloc(2 * (self._npg if self._npg > 0 else 1) * sizeof(uint64_t))
        if w is NULL:
            raise MemoryError()
        try:
            self._words(sources, w)
            for p in range(self._npg):
                codec = self._codecs[p]
                codec._payload_into(w[2 * p], w[2 * p + 1], b)
                slot_put(images + p * SLOT_BYTES, <uint32_t>ids[p], b, <uint8_t>codec.length)
        finally:
            PyMem_Free(w)
        return 0

    cdef int _words(self, list sources, uint64_t* words) except -1:
        """Per page its little-endian and big-endian fields' words (``words[2p]``, ``words[2p+1]``)
        from ``sources``: the one encoding behind :meth:`pack` and :meth:`_images`."""
        cdef Py_ssize_t ns = len(sources), held = 0
        cdef double** ptr = <double**>PyMem_Malloc((ns if ns > 0 else 1) * sizeof(double*))
        cdef Py_ssize_t* length = <Py_ssize_t*>PyMem_Malloc((ns if ns > 0 else 1) * sizeof(Py_ssize_t))
        # each source's buffer as is (a typed memoryview object per source and period cost more)
        cdef Py_buffer* views = <Py_buffer*>PyMem_Malloc((ns if ns > 0 else 1) * sizeof(Py_buffer))
        if ptr is NULL or length is NULL or views is NULL:
            PyMem_Free(ptr)
            PyMem_Free(length)
            PyMem_Free(views)
            raise MemoryError()
        cdef FieldCodec codec
        cdef int p, i, s_
        cdef int64_t e
        cdef uint64_t w, wb, wb_or_w
        cdef double x
        cdef Field* fd
        try:
            for i in range(ns):
                PyObject_GetBuffer(sources[i], &views[i], PyBUF_C_CONTIGUOUS | PyBUF_FORMAT)
                held += 1
                if not is_f64_vector(&views[i]):
                    raise ValueError(f"sensor source {i}: a 1-D float64 array is needed")
                ptr[i] = <double*>views[i].buf if views[i].shape[0] > 0 else NULL
                length[i] = views[i].shape[0]
            for p in range(self._npg):
                codec = self._codecs[p]
                w = 0
                wb = 0
                for i in range(codec.n):
                    fd = &codec.f[i]
                    if fd.role == ROLE_CRC:
                        continue
                    if fd.role == ROLE_CONST:
                        wb_or_w = (<uint64_t>fd.const_raw & fd.mask) << fd.start
                        if fd.big:
                            wb |= wb_or_w
                        else:
                            w |= wb_or_w
                        continue
                    s_ = self._src[p * MAX_FIELDS + i]
                    if s_ == SRC_NONE:
                        x = NAN
                    elif s_ == SRC_ZERO:
                        x = 0.0
                    else:
                        e = self._elem[p * MAX_FIELDS + i]
                        if e < 0 or e >= length[s_]:
                            raise IndexError(f"element {e} of source {s_} (length {length[s_]})")
                        x = ptr[s_][e]
                    if not isfinite(x):  # not sent: the default, as a missing signal
                        x = codec.f[i].offset
                    wb_or_w = (<uint64_t>codec._raw_double(i, x) & fd.mask) << fd.start
                    if fd.big:
                        wb |= wb_or_w
                    else:
                        w |= wb_or_w
                words[2 * p] = w
                words[2 * p + 1] = wb
        finally:
            for i in range(held):
                PyBuffer_Release(&views[i])
            PyMem_Free(views)
            PyMem_Free(ptr)
            PyMem_Free(length)
        return 0


cdef class TickFrames:
    """The plant's frames of a period's start in one call: SYNC (Tick = k), REFERENCE (v*, a*),
    REFERENCE_POS (x*, if the layout has it), the plant's heartbeat (NodeState 5, when asked)
    and every sensor page (:class:`SensorPages` from the period's measurement arrays), in that
    order; the same payloads as the codecs' ``encode`` of those values. :meth:`images` encodes
    them as the memory bus's slot images (``canbrake.bus._slot``), :meth:`frames` makes
    ``can.Message`` objects of those images (``messages(images)``): one encoding for both."""

    cdef FieldCodec _sync, _ref, _ref_pos, _hb
    cdef uint32_t _sync_id, _ref_id, _ref_pos_id, _hb_id
    cdef SensorPages _pages
    cdef list _sensor_ids
    cdef tuple _arrays
    cdef object _messages
    cdef object _ndarray, _f64, _ascontiguous
    cdef dict _tick_values, _ref_values, _pos_values, _hb_values

    def __init__(self, FieldCodec sync, sync_id, FieldCodec ref, ref_id, FieldCodec ref_pos, ref_pos_id,
                 FieldCodec heartbeat, heartbeat_id, SensorPages pages, list sensor_ids, arrays, messages):
        """``ref_pos`` None: no REFERENCE_POS frame; ``pages``' payloads go out on ``sensor_ids``
        (in order); ``arrays``: the measurement names the pages read, in their source order;
        ``messages(images)``: the ``can.Message`` list of slot images
        (``canbrake.bus._ring.messages_of``)."""
        if len(sensor_ids) != pages._npg:
            raise ValueError(f"{len(sensor_ids)} identifiers for {pages._npg} sensor pages")
        self._sync, self._sync_id, self._ref, self._ref_id = sync, sync_id, ref, ref_id
        self._ref_pos, self._hb, self._hb_id = ref_pos, heartbeat, heartbeat_id
        self._ref_pos_id = 0 if ref_pos is None else ref_pos_id
        self._pages, self._sensor_ids, self._arrays = pages, list(sensor_ids), tuple(arrays)
        self._messages = messages
        self._tick_values, self._ref_values, self._pos_values = {}, {}, {}
        self._hb_values = {"NodeState": 5}
        self._ndarray, self._f64, self._ascontiguous = np.ndarray, np.dtype(np.float64), np.ascontiguousarray

    def frames(self, int64_t k, v_ref, a_ref, x_ref, bint heartbeat, measurements, sync_payload=None):
        """The frames of tick ``k`` as ``can.Message`` objects (:meth:`images`' arguments)."""
        return self._messages(self.images(k, v_ref, a_ref, x_ref, heartbeat, measurements, sync_payload))

    def images(self, int64_t k, v_ref, a_ref, x_ref, bint heartbeat, measurements, sync_payload=None):
        """The frames of tick ``k`` as slot images (bytes, ``SLOT_BYTES`` each, time stamp and
        sender token 0): ``sync_payload`` (None: the SYNC codec's encoding of k), the reference
        values ``v_ref``, ``a_ref``, ``x_ref`` (m/s, m/s^2, m), the heartbeat if ``heartbeat``,
        the sensor pages from ``measurements`` (name -> per-vehicle array)."""
        cdef list sources = []
        for name in self._arrays:
            arr = measurements[name]
            if type(arr) is not self._ndarray or arr.dtype is not self._f64 or not arr.flags.c_contiguous:
                arr = self._ascontiguous(arr, dtype=float)
            sources.append(arr)
        if sync_payload is None:
            self._tick_values["Tick"] = k
            sync_payload = self._sync.encode(self._tick_values)
        self._ref_values["RefSpeed"] = v_ref
        self._ref_values["RefDecel"] = a_ref
        cdef bytes ref = self._ref.encode(self._ref_values)
        cdef bytes pos = None
        if self._ref_pos is not None:
            self._pos_values["RefPosition"] = x_ref
            pos = self._ref_pos.encode(self._pos_values)
        cdef bytes hb = self._hb.encode(self._hb_values) if heartbeat else None
        cdef Py_ssize_t head = 2 + (pos is not None) + (hb is not None)
        cdef Py_ssize_t count = head + self._pages._npg
        cdef bytes out = PyBytes_FromStringAndSize(NULL, count * SLOT_BYTES)
        cdef uint8_t* p = <uint8_t*>PyBytes_AS_STRING(out)
        memset(p, 0, count * SLOT_BYTES)
        _put_payload(p, self._sync_id, sync_payload)
        _put_payload(p + SLOT_BYTES, self._ref_id, ref)
        cdef Py_ssize_t at = 2
        if pos is not None:
            _put_payload(p + at * SLOT_BYTES, self._ref_pos_id, pos)
            at += 1
        if hb is not None:
            _put_payload(p + at * SLOT_BYTES, self._hb_id, hb)
        self._pages._images(sources, p + head * SLOT_BYTES, self._sensor_ids)
        return out


cdef int _put_payload(uint8_t* p, uint32_t aid, object payload) except -1:
    """``slot_put`` of a payload (bytes-like, at most 8 bytes: a classic frame)."""
    cdef const uint8_t* s
    cdef Py_ssize_t n
    if not _payload(payload, &s, &n):
        payload = bytes(payload)
        _payload(payload, &s, &n)
    if n > MAX_DATA:  # (more than 8: refused by the ring when sent, as a Message would be)
        raise ValueError(f"frame 0x{aid:X}: {n} data bytes (a slot holds at most {MAX_DATA})")
    slot_put(p, aid, s, <uint8_t>n)
    return 0


def quantise(values, double scale, double offset, double lo, double hi, bint scaled):
    """``decode(encode(v))`` of one signal for an array of values (the batch engine's
    :class:`canbrake.bus.codec.Quantiser`): a value that is not finite decodes as ``offset``
    (the nodes leave it out of the frame); raw = rint((v - offset) / scale) (``v / scale`` when
    the offset is 0, ``rint(v)`` unscaled) saturated to [lo, hi], decoded as raw * scale + offset
    (raw unscaled). A raw value that overflows to infinity raises OverflowError, as the codec
    does. Returns a new float array of the shape of ``values``."""
    src = np.ascontiguousarray(values, dtype=np.float64)
    out = np.empty_like(src)
    cdef double[::1] a = src.reshape(-1)
    cdef double[::1] b = out.reshape(-1)
    cdef Py_ssize_t i, n = a.shape[0]
    cdef double x, r
    cdef bint zero_offset = offset == 0.0
    for i in range(n):
        x = a[i]
        if not isfinite(x):
            x = offset
        if scaled:
            r = rint(x / scale) if zero_offset else rint((x - offset) / scale)
        else:
            r = rint(x)
        if isinf(r):
            raise OverflowError("cannot convert float infinity to integer")
        if r < lo:
            r = lo
        elif r > hi:
            r = hi
        b[i] = r * scale + offset if scaled else r
    return out
