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
from cpython.bytes cimport PyBytes_AS_STRING, PyBytes_FromStringAndSize, PyBytes_GET_SIZE
from cpython.bytearray cimport PyByteArray_AS_STRING, PyByteArray_GET_SIZE
from cpython.dict cimport PyDict_GetItem, PyDict_SetItem
from cpython.float cimport PyFloat_AS_DOUBLE, PyFloat_FromDouble
from cpython.long cimport PyLong_AsDouble, PyLong_AsLongLongAndOverflow, PyLong_FromLongLong
from cpython.object cimport PyObject
from libc.math cimport INFINITY, NAN, isfinite, isinf, isnan, rint
from libc.stdint cimport int64_t, uint8_t, uint64_t
from cpython.mem cimport PyMem_Free, PyMem_Malloc, PyMem_Realloc

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
            if fd.role == ROLE_COUNTER and counter is not None:
                x = (<uint64_t><int64_t>counter & fd.mask) << fd.start
            elif fd.role == ROLE_COUNTER_EXT and tick is not None:
                x = (<uint64_t>_floordiv15(<int64_t>tick) & fd.mask) << fd.start
            elif fd.role == ROLE_CONST:
                x = (<uint64_t>fd.const_raw & fd.mask) << fd.start
            else:
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

    cdef bytes _payload_of(self, uint64_t w, uint64_t wb):
        """The payload bytes of the little-endian fields' word ``w`` and the big-endian fields'
        word ``wb``, with the E2E CRC if protected."""
        cdef uint8_t b[8]
        cdef uint8_t crc
        cdef int i
        for i in range(self.length):
            b[i] = <uint8_t>(w >> (8 * i)) | <uint8_t>(wb >> (56 - 8 * i))
        if self.protected:  # the CRC is byte 0 (checked in __init__), in either byte order
            crc = self.crc0
            for i in range(1, self.length):
                crc = CRC_TABLE[crc ^ b[i]]
            b[0] |= <uint8_t>(crc ^ 0xFF)
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
        cdef uint64_t wb = _swap64(w) if self.any_big else 0
        for i in range(self.n):
            fd = &self.f[i]
            raw = <int64_t>(((wb if fd.big else w) >> fd.start) & fd.mask)
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


# ---------------------------------------------------------------- a receiver's peer table
cdef struct PageField:
    Field* field     # the signal's field in its page's FieldCodec (kept alive by PeerTable._codecs)
    double* target   # element j of the array the signal goes to (kept alive by PeerTable.values)


cdef void _decode_into(PageField* pf, int count, uint64_t w) noexcept:
    """Decode ``count`` signals of a frame (its little-endian word ``w``) into their targets, as
    ``FieldCodec.decode`` gives them (the float the array holds)."""
    cdef Field* fd
    cdef int64_t raw
    cdef uint64_t half
    cdef uint64_t wb = _swap64(w)
    cdef int i
    for i in range(count):
        fd = pf[i].field
        raw = <int64_t>(((wb if fd.big else w) >> fd.start) & fd.mask)
        if fd.is_signed:
            half = <uint64_t>1 << (fd.nbits - 1)
            raw = <int64_t>(<uint64_t>raw ^ half) - <int64_t>half
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


cdef class PeerTable:
    """What one ECU holds of its peers: per signal an array over the train's ECUs (NaN until
    received), per ECU the newest origin (tick) and the state pages of that tick seen.

    ``take`` checks a state page (E2E CRC, counter, origin: :func:`frame_origin`) and decodes it
    straight into the arrays; ``ages`` gives the peers' ages once per period. ``values`` are
    the arrays themselves (numpy, float64, shape (n,))."""

    cdef readonly int n
    cdef readonly dict values
    cdef readonly object origin      # int64 array (n,)
    cdef object _fresh_arr, _pages_arr
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

    def __cinit__(self):
        self._pg = NULL
        self._pf = NULL

    def __dealloc__(self):
        PyMem_Free(self._pg)
        PyMem_Free(self._pf)

    def __init__(self, int n, signal_names, listened, int64_t max_lag):
        import numpy as np

        self.n = n
        self.values = {nm: np.full(n, np.nan) for nm in signal_names}
        self.origin = np.full(max(n, 1), -(10 ** 12), dtype=np.int64)
        self._fresh_arr = np.zeros(max(n, 1), dtype=np.int64)
        self._pages_arr = np.zeros(max(n, 1), dtype=np.int64)
        self._origin = _i64(self.origin)
        self._fresh = _i64(self._fresh_arr)
        self._pages_of = _i64(self._pages_arr)
        self.max_lag = max_lag
        self._index = {}
        self._codecs = []
        self._npg = self._npf = 0
        self._listened_arr = np.asarray(list(listened) or [0], dtype=np.int64)
        self._listened = _i64(self._listened_arr)
        self._nlistened = len(listened)

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
        self._npg += 1
        self._pages_of[j] += 1

    def new_tick(self):
        """A new period: no page of it seen yet."""
        cdef int j
        for j in range(self.n):
            self._fresh[j] = 0

    def origin_of(self, int j):
        """The newest origin (tick) accepted from ECU index j."""
        return self._origin[j]

    cdef int _apply(self, int p, uint64_t w, int64_t origin, int64_t k):
        cdef Page* pg = &self._pg[p]
        cdef int j = pg.j
        _decode_into(self._pf + pg.first, pg.count, w)
        if origin > self._origin[j]:
            self._origin[j] = origin
            self._fresh[j] = 0
        if origin == k:
            self._fresh[j] += 1
            return 2 if self._fresh[j] == self._pages_of[j] else 1
        return 0

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
        cdef Page* pg = &self._pg[p]
        if not _payload(data, &s, &n):
            data = bytes(data)
            _payload(data, &s, &n)
        cdef int64_t o = 0
        cdef int code = _origin(s, n, frame_id, k, self._origin[pg.j], pg.same_tick_ok, False,
                                pg.ext_start, pg.ext_bits, self.max_lag, &o)
        if code < 0:
            return code
        return self._apply(p, _le_word(s, n), o, k)

    def ages(self, int64_t k, double dt, int own, const double[::1] speed):
        """(age, fresh, max_age) at tick ``k``: per ECU the age in s of its newest value (own
        entry 0; inf for an ECU never heard whose speed is unknown), the ECUs with a value of
        this tick (own included) and the oldest finite age (-inf: none)."""
        import numpy as np

        age = np.empty(self.n)
        cdef double[::1] a = age
        cdef int j, fresh = 1
        cdef int64_t o
        cdef double x, max_age = -INFINITY
        for j in range(self.n):
            o = k if j == own else self._origin[j]
            x = INFINITY if o < 0 and isnan(speed[j]) else <double>(k - o) * dt
            a[j] = x
            if x != INFINITY and x > max_age:
                max_age = x
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
        import numpy as np

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
        cdef Py_ssize_t ns = len(sources)
        cdef double** ptr = <double**>PyMem_Malloc((ns if ns > 0 else 1) * sizeof(double*))
        cdef Py_ssize_t* length = <Py_ssize_t*>PyMem_Malloc((ns if ns > 0 else 1) * sizeof(Py_ssize_t))
        if ptr is NULL or length is NULL:
            PyMem_Free(ptr)
            PyMem_Free(length)
            raise MemoryError()
        cdef double[::1] view
        cdef list out = []
        cdef FieldCodec codec
        cdef int p, i, s_
        cdef int64_t e
        cdef uint64_t w, wb, wb_or_w
        cdef double x
        cdef Field* fd
        try:
            for i in range(ns):
                view = sources[i]
                ptr[i] = &view[0] if view.shape[0] > 0 else NULL
                length[i] = view.shape[0]
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
                out.append(codec._payload_of(w, wb))
        finally:
            PyMem_Free(ptr)
            PyMem_Free(length)
        return out


def quantise(values, double scale, double offset, double lo, double hi, bint scaled):
    """``decode(encode(v))`` of one signal for an array of values (the batch engine's
    :class:`canbrake.bus.codec.Quantiser`): a value that is not finite decodes as ``offset``
    (the nodes leave it out of the frame); raw = rint((v - offset) / scale) (``v / scale`` when
    the offset is 0, ``rint(v)`` unscaled) saturated to [lo, hi], decoded as raw * scale + offset
    (raw unscaled). A raw value that overflows to infinity raises OverflowError, as the codec
    does. Returns a new float array of the shape of ``values``."""
    import numpy as np

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
