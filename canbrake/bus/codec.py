"""Fast encode/decode of canbrake frames, compiled, from a cantools database.

cantools is the model (:mod:`canbrake.bus.dbc`); this is a codec over that model for the hot
path. Why not ``cantools.Message.encode`` itself: it costs ~2.3 us per frame non-strict (~6 us
strict) and a 6-car tick moves ~30 frames through encode and decode in several processes.
Every signal is a bit field of a classical CAN frame, so a frame is one 64-bit word (Intel
fields) or its byte-swapped twin (Motorola fields of a user's DBC) and a signal is a shift and a
mask: each message becomes a field table (start, bits, signed, scale, offset, raw range, byte
order, role: value, CRC, alive counter or its extension, or a multiplexer's constant page value)
that the compiled :class:`canbrake.bus._codec.FieldCodec` encodes and decodes, E2E CRC included.
A multiplexed message is one page: its signals are those of one multiplexer value (a message of
canbrake's run layout never holds two pages of one multiplexed message; canbrake.bus.userdbc).
``canbrake bench`` compares it with cantools (figure "codec"); tests/test_codec.py checks it
bit for bit against cantools with hypothesis over every message and signal value.

Out-of-range physical values saturate at the signal's raw range (as an ECU's signal
conversion would) instead of raising.
"""
from __future__ import annotations

from typing import Any, Callable, Mapping

from cantools.database.can import Database, Message

from canbrake.bus._codec import FieldCodec
from canbrake.bus._codec import quantise as _quantise

_ROLES = {"CRC": "crc", "Counter": "counter", "CounterExt": "counter_ext"}


class MessageCodec:
    """Encoder/decoder of one message. Values are physical (scaled) floats; CRC/Counter are ints."""

    def __init__(self, message: Message) -> None:
        self.frame_id: int = message.frame_id
        self.name: str = message.name
        self.length: int = message.length
        self.signal_names: tuple[str, ...] = tuple(s.name for s in message.signals)
        self.protected: bool = "CRC" in self.signal_names and "Counter" in self.signal_names
        fields = []
        big: list[bool] = []
        roles: list[str] = []
        consts: list[int | None] = []
        pages = {i for s in message.signals for i in (s.multiplexer_ids or ())}
        if len(pages) > 1:
            raise ValueError(f"{message.name}: signals of several multiplexer values "
                             f"{sorted(pages)}: a codec encodes one page")
        for s in message.signals:
            lo, hi = (-(1 << (s.length - 1)), (1 << (s.length - 1)) - 1) if s.is_signed else (0, (1 << s.length) - 1)
            fields.append((s.name, s.start, (1 << s.length) - 1, s.length, s.is_signed,
                           float(s.scale), float(s.offset), lo, hi))
            big.append(s.byte_order == "big_endian")
            roles.append("const" if s.is_multiplexer and pages else _ROLES.get(s.name, "value"))
            consts.append(next(iter(pages)) if s.is_multiplexer and pages else None)
        #: per signal (name, start bit, mask, bits, signed, scale, offset, raw lo, raw hi); start
        #: as in the DBC (Motorola: the most significant bit)
        self._fields = tuple(fields)
        try:
            self._c = FieldCodec([(f[0], f[1], f[3], f[4], f[5], f[6], r, b, c)
                                  for f, r, b, c in zip(fields, roles, big, consts)],
                                 self.length, self.protected, self.frame_id)
        except ValueError as exc:
            raise ValueError(f"{message.name}: {exc}") from None
        #: ``encode(values, counter=None, tick=None) -> bytes``: ``values`` in physical units; for
        #: protected messages pass ``counter`` (tick mod 15) and the CRC is computed; ``tick`` (the
        #: sender's tick) also fills a ``CounterExt`` field (floor(tick / 15) mod 2^bits). ``decode(data) -> dict``: physical
        #: values (ints for unscaled signals). Both are the compiled methods themselves (no
        #: method-call layer on the hot path).
        self.encode: Callable[..., bytes] = self._c.encode
        self.decode: Callable[[bytes | bytearray], dict[str, float]] = self._c.decode
        #: ``decode(data)`` for callers that only read the result: a payload equal to the last
        #: one returns the same dict, so a broadcast frame is decoded once for all the ECUs of
        #: one process (the in-process engine, hosted ECUs) instead of once per ECU.
        self.decode_shared: Callable[[bytes | bytearray], Mapping[str, float]] = self._c.decode_shared

    def quantiser(self, signal: str) -> "Quantiser":
        """The value a receiver decodes for ``signal`` of this message, as an array function
        (what ``decode(encode({signal: v}))`` gives, for many values at once: the batch engine,
        :mod:`canbrake.batch`). tests/test_batch_sweep.py checks it against encode/decode."""
        for name, _start, _mask, _nbits, _signed, scale, offset, lo, hi in self._fields:
            if name == signal:
                return Quantiser(scale, offset, lo, hi)
        raise KeyError(f"{self.name} has no signal {signal!r}")


class Quantiser:
    """``decode(encode(v))`` of one signal, vectorised (numpy arrays of any shape, SI).

    The same arithmetic as the compiled codec: raw = round((v - offset) / scale) (round half to
    even, as Python's ``round``; ``v / scale`` when the offset is 0), saturated to the raw range,
    decoded as raw * scale + offset. A value that is not finite is left out of the frame by the
    nodes, so it decodes as the signal's default, ``offset``; a finite value whose raw value
    overflows to infinity raises OverflowError, as the codec does."""

    __slots__ = ("scale", "offset", "lo", "hi", "scaled")

    def __init__(self, scale: float, offset: float, lo: int, hi: int) -> None:
        self.scale, self.offset, self.lo, self.hi = scale, offset, lo, hi
        self.scaled = scale != 1.0 or offset != 0.0

    def __call__(self, values: Any) -> Any:
        return _quantise(values, self.scale, self.offset, self.lo, self.hi, self.scaled)


class FrameCodec:
    """All message codecs of a database, by name and by frame id."""

    def __init__(self, db: Database) -> None:
        self.db = db
        self.by_name: dict[str, MessageCodec] = {}
        self.by_id: dict[int, MessageCodec] = {}
        for m in db.messages:
            c = MessageCodec(m)
            self.by_name[m.name] = c
            self.by_id[m.frame_id] = c

    def __getitem__(self, name: str) -> MessageCodec:
        return self.by_name[name]
