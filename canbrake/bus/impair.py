"""Network impairments on a CAN node's send path (and, per link, on a receive path).

Pure code — no processes, no bus I/O. A node hands each outgoing frame to its
:class:`SendPath` with ``submit`` and, whenever it is about to write to the bus, asks
``release(t_now_s)`` for the frames that may go out now. Between the two, a chain of small
impairment objects decides what happens to the frame:

* a frame impairment implements ``apply(frame) -> list[TxFrame]``: ``[]`` = lost,
  ``[frame]`` = passed (possibly modified: later ``t_release_s``, flipped bits),
  ``[frame, copy]`` = duplicated. ``apply`` owns the frame it is given and may modify it.
* a traffic source (the babbling idiot) implements ``frames_due(t_from_s, t_to_s)``:
  frames it emits in ``(t_from_s, t_to_s]``; the send path feeds them through the same chain.

Every impairment has a :class:`Selector` — identifiers, senders, a ``[start_s, stop_s)``
window on the frame's submit time, and for per-link impairments receivers — and its own
``numpy.random.Generator`` seeded at construction. :func:`build_impairments` derives each
seed from the run seed, the direction, the node name and the spec's index in the scenario
list with a stable hash (CRC-32; never Python's ``hash()``), so results do not depend on
process start order, and never touches numpy's global RNG.

Per-link impairments (spec with ``receivers``): CAN is a broadcast medium, so the send path
of a sender cannot lose a frame for one listener only. The same classes therefore also run
on the *receive* path: ``build_impairments(specs, seed, node="ecu3", direction="rx")`` gives
the chain of every spec that names ``ecu3`` among its ``receivers``; the receiving side
(the bus medium per reader, or the node) submits each received frame with
``t_submit_s = t_release_s = time received`` and hands the node what ``release`` returns.
``senders``/``ids`` still select per frame. Specs with ``receivers`` are never applied on
send paths, and specs without are never applied on receive paths.

Times are seconds on the run's clock (simulated time in lockstep, wall-clock seconds since
the run started in realtime mode); ``start_s``/``stop_s`` compare with ``t_submit_s``.

Example::

    path = build_impairments([{"type": "loss", "probability": 0.1},
                              {"type": "delay", "delay_s": 0.002}], seed=42, node="ecu1")
    path.submit(TxFrame(0x101, False, b"\\x01\\x02", 2, "ecu1", t, t))
    for f in path.release(t_now):  ...  # put f on the bus / in the BusTimingModel

With the timing model, per step: ``release(t)``, ``BusTimingModel.submit(..., t_queue_s=
f.t_release_s)`` for each frame, then ``BusTimingModel.advance(t)``. Nodes that speak
``can.Message`` (``canbrake.nodes.base.SendPath``) wrap the chain in :class:`MessageSendPath`.
"""
from __future__ import annotations

import heapq
import math
import zlib
from dataclasses import dataclass
from typing import (Annotated, Any, ClassVar, Iterable, Literal, Protocol, Sequence, Union,
                    runtime_checkable)

import numpy as np
from pydantic import (AfterValidator, BaseModel, ConfigDict, Field, TypeAdapter,
                      model_validator)

__all__ = [
    "TxFrame", "Selector", "Impairment", "TrafficSource", "FrameImpairment",
    "Delay", "UniformJitter", "NormalJitter", "ExponentialJitter", "BernoulliLoss",
    "GilbertElliottLoss", "Duplicate", "Reorder", "Corrupt", "Silence", "Babbler",
    "SendPath", "MessageSendPath", "build_impairments", "babbling_nodes", "derive_seed",
    "DelaySpec", "JitterSpec", "LossSpec", "GilbertElliottSpec", "DuplicateSpec",
    "ReorderSpec", "CorruptSpec", "SilentSpec", "BabbleSpec", "BitErrorRateSpec",
    "FaultyTransceiverSpec", "BUS_ERROR_SPECS", "ImpairmentSpec",
    "IMPAIRMENT_SPECS",
]

_MAX_EXT_ID = 0x1FFF_FFFF
_MAX_STD_ID = 0x7FF


# --------------------------------------------------------------------------------------------
# the frame on its way to the bus


@dataclass(slots=True)
class TxFrame:
    """A classic CAN frame on its way to the bus (times in seconds on the run's clock).

    ``t_submit_s``: when it was handed to the send path. ``t_release_s``: earliest time it may
    be put on the bus; impairments only ever move it later. ``duplicate`` marks a copy made
    by :class:`Duplicate`, ``corrupted`` a frame whose payload bits were flipped. ``origin``
    is an optional object the frame came from (e.g. the ``can.Message``), kept on copies.
    """

    arbitration_id: int
    is_extended: bool
    data: bytes
    dlc: int
    sender: str
    t_submit_s: float
    t_release_s: float
    is_remote: bool = False
    duplicate: bool = False
    corrupted: bool = False
    origin: Any = None

    def copy(self) -> "TxFrame":
        """A shallow copy (``data`` is immutable bytes)."""
        return TxFrame(self.arbitration_id, self.is_extended, self.data, self.dlc, self.sender,
                       self.t_submit_s, self.t_release_s, self.is_remote, self.duplicate,
                       self.corrupted, self.origin)

    @classmethod
    def from_message(cls, msg: Any, sender: str, t_s: float) -> "TxFrame":
        """From a ``can.Message`` (duck-typed), submitted and releasable at ``t_s``."""
        return cls(int(msg.arbitration_id), bool(msg.is_extended_id), bytes(msg.data),
                   int(msg.dlc), sender, t_s, t_s, bool(getattr(msg, "is_remote_frame", False)),
                   origin=msg)

    def to_message(self, timestamp: float | None = None) -> Any:
        """As a ``can.Message`` (timestamp defaults to ``t_release_s``).

        The ``origin`` message itself is returned when this frame still carries its exact
        payload (not corrupted) and no timestamp is asked for — no copy on the hot path.
        """
        if (timestamp is None and self.origin is not None and not self.corrupted
                and getattr(self.origin, "arbitration_id", None) == self.arbitration_id):
            return self.origin
        import can  # local: keep this module importable without touching python-can

        return can.Message(timestamp=self.t_release_s if timestamp is None else timestamp,
                           arbitration_id=self.arbitration_id, is_extended_id=self.is_extended,
                           is_remote_frame=self.is_remote, dlc=self.dlc,
                           data=None if self.is_remote else self.data)


@dataclass(frozen=True, slots=True)
class Selector:
    """Which frames an impairment acts on. ``None`` = all.

    A frame matches if ``start_s <= t_submit_s < stop_s`` and its identifier / sender are
    listed. ``receivers`` marks a per-link impairment (receive path only, see module doc).
    """

    ids: frozenset[int] | None = None
    senders: frozenset[str] | None = None
    receivers: frozenset[str] | None = None
    start_s: float = 0.0
    stop_s: float = math.inf

    def matches(self, frame: TxFrame) -> bool:
        t = frame.t_submit_s
        if t < self.start_s or t >= self.stop_s:
            return False
        if self.ids is not None and frame.arbitration_id not in self.ids:
            return False
        if self.senders is not None and frame.sender not in self.senders:
            return False
        return True

    def matches_many(self, t_submit_s: np.ndarray, ids: np.ndarray, sender: str) -> np.ndarray:
        """:meth:`matches` for many frames of one ``sender``: bool array, shape of ``t_submit_s``."""
        if self.senders is not None and sender not in self.senders:
            return np.zeros(t_submit_s.shape, dtype=bool)
        ok = (t_submit_s >= self.start_s) & (t_submit_s < self.stop_s)
        if self.ids is not None:
            ok &= np.isin(ids, np.fromiter(self.ids, dtype=np.int64))
        return ok


_ALL = Selector()


@runtime_checkable
class Impairment(Protocol):
    """Anything on the frame path: ``[]`` lost, ``[f]`` passed/modified, ``[f, g]`` duplicated."""

    def apply(self, frame: TxFrame) -> list[TxFrame]: ...


@runtime_checkable
class TrafficSource(Protocol):
    """Something that creates frames: those it emits at times in ``(t_from_s, t_to_s]``."""

    def frames_due(self, t_from_s: float, t_to_s: float) -> list[TxFrame]: ...


SeedLike = Union[int, np.random.SeedSequence, None]


def _rng(seed: SeedLike) -> np.random.Generator:
    if seed is None:
        seed = 0
    if isinstance(seed, (bool, float)) or (isinstance(seed, int) and seed < 0):
        raise ValueError(f"seed must be a non-negative int or a SeedSequence, got {seed!r}")
    return np.random.default_rng(seed)


def _check_nonneg(name: str, value: float) -> float:
    v = float(value)
    if not math.isfinite(v) or v < 0:
        raise ValueError(f"{name} must be a finite time >= 0 s, got {value!r}")
    return v


def _check_prob(name: str, value: float) -> float:
    v = float(value)
    if not 0.0 <= v <= 1.0:  # also refuses NaN
        raise ValueError(f"{name} must be a probability in [0, 1], got {value!r}")
    return v


class FrameImpairment:
    """Base of the frame impairments: selector check, own RNG, counters.

    Subclasses implement :meth:`_apply` for frames the selector matches and draw their random
    numbers with :meth:`_uniform` / :meth:`_normal`, which serve them from blocks of
    ``_BLOCK`` values drawn from ``self.rng`` (a scalar numpy call costs ~1 µs, too much on the
    send path of every frame); the sequence is fixed by the seed all the same. Counters:
    ``n_matched`` (frames acted on), ``n_dropped``, ``n_added`` (copies), ``n_modified``.
    """

    kind: ClassVar[str] = "impairment"
    _BLOCK: ClassVar[int] = 256

    def __init__(self, *, selector: Selector | None = None, seed: SeedLike = None) -> None:
        self.selector = selector or _ALL
        self.rng = _rng(seed)
        self._u: list[float] = []
        self._ui = 0
        self._n: list[float] = []
        self._ni = 0
        self.n_matched = 0
        self.n_dropped = 0
        self.n_added = 0
        self.n_modified = 0

    def apply(self, frame: TxFrame) -> list[TxFrame]:
        if not self.selector.matches(frame):
            return [frame]
        self.n_matched += 1
        return self._apply(frame)

    def _apply(self, frame: TxFrame) -> list[TxFrame]:  # pragma: no cover - abstract
        raise NotImplementedError

    def apply_many(self, t_submit_s: np.ndarray, ids: np.ndarray, sender: str, release_s: np.ndarray,
                   alive: np.ndarray) -> None:
        """:meth:`apply` on a whole sequence of frames of one ``sender``, submitted in array order
        (for the batch engine, :meth:`SendPath.fates`): ``release_s`` (s) and ``alive`` (False =
        lost) are updated in place; the random draws are those ``apply`` would make, in the same
        order. Only impairments that pass, delay or drop a frame (no copies) implement it."""
        raise NotImplementedError(f"{type(self).__name__} has no vectorised form")

    def _draws(self, n: int, normal: bool = False) -> np.ndarray:
        """The next ``n`` values :meth:`_uniform` (or :meth:`_normal`) would return, in order; the
        block buffer is left where ``n`` single draws would leave it."""
        buf, i = (self._n, self._ni) if normal else (self._u, self._ui)
        rest = buf[i:]
        if n <= len(rest):
            out = np.asarray(rest[:n], dtype=float)
            if normal:
                self._ni = i + n
            else:
                self._ui = i + n
            return out
        need = n - len(rest)
        nb = -(-need // self._BLOCK)
        # a Generator draws the same stream in one call of k·256 as in k calls of 256
        new = self.rng.standard_normal(nb * self._BLOCK) if normal else self.rng.random(nb * self._BLOCK)
        out = np.concatenate([np.asarray(rest, dtype=float), new[:need]])
        last = new[(nb - 1) * self._BLOCK:].tolist()
        used = need - (nb - 1) * self._BLOCK
        if normal:
            self._n, self._ni = last, used
        else:
            self._u, self._ui = last, used
        return out

    def _uniform(self) -> float:
        """Next uniform draw in [0, 1)."""
        i = self._ui
        if i >= len(self._u):
            self._u = self.rng.random(self._BLOCK).tolist()
            i = 0
        self._ui = i + 1
        return self._u[i]

    def _normal(self) -> float:
        """Next standard normal draw."""
        i = self._ni
        if i >= len(self._n):
            self._n = self.rng.standard_normal(self._BLOCK).tolist()
            i = 0
        self._ni = i + 1
        return self._n[i]

    def counters(self) -> dict[str, int]:
        return {"matched": self.n_matched, "dropped": self.n_dropped, "added": self.n_added,
                "modified": self.n_modified}

    def __repr__(self) -> str:
        return f"{type(self).__name__}({self.selector})"


# --------------------------------------------------------------------------------------------
# frame impairments


class Delay(FrameImpairment):
    """Fixed extra delay ``delay_s`` (s) on every matching frame."""

    kind = "delay"

    def __init__(self, delay_s: float, *, selector: Selector | None = None,
                 seed: SeedLike = None) -> None:
        super().__init__(selector=selector, seed=seed)
        self.delay_s = _check_nonneg("delay_s", delay_s)

    def _apply(self, frame: TxFrame) -> list[TxFrame]:
        frame.t_release_s += self.delay_s
        self.n_modified += 1
        return [frame]

    def apply_many(self, t_submit_s: np.ndarray, ids: np.ndarray, sender: str, release_s: np.ndarray,
                   alive: np.ndarray) -> None:
        hit = alive & self.selector.matches_many(t_submit_s, ids, sender)
        release_s[hit] += self.delay_s
        n = int(hit.sum())
        self.n_matched += n
        self.n_modified += n


class _Jitter(FrameImpairment):
    kind = "jitter"

    def _sample(self) -> float:  # pragma: no cover - abstract
        raise NotImplementedError

    def _apply(self, frame: TxFrame) -> list[TxFrame]:
        frame.t_release_s += self._sample()
        self.n_modified += 1
        return [frame]

    def _samples(self, n: int) -> np.ndarray:
        """The next ``n`` values of :meth:`_sample`, in order."""
        return np.asarray([self._sample() for _ in range(n)], dtype=float)

    def apply_many(self, t_submit_s: np.ndarray, ids: np.ndarray, sender: str, release_s: np.ndarray,
                   alive: np.ndarray) -> None:
        hit = alive & self.selector.matches_many(t_submit_s, ids, sender)
        n = int(hit.sum())
        release_s[hit] += self._samples(n)
        self.n_matched += n
        self.n_modified += n


class UniformJitter(_Jitter):
    """Random extra delay, uniform in ``[low_s, high_s]`` (s)."""

    def __init__(self, low_s: float, high_s: float, *, selector: Selector | None = None,
                 seed: SeedLike = None) -> None:
        super().__init__(selector=selector, seed=seed)
        self.low_s = _check_nonneg("low_s", low_s)
        self.high_s = _check_nonneg("high_s", high_s)
        if self.high_s < self.low_s:
            raise ValueError(f"high_s={high_s!r} must be >= low_s={low_s!r}")

    def _sample(self) -> float:
        return self.low_s + (self.high_s - self.low_s) * self._uniform()

    def _samples(self, n: int) -> np.ndarray:
        return self.low_s + (self.high_s - self.low_s) * self._draws(n)


class NormalJitter(_Jitter):
    """Random extra delay, normal(``mean_s``, ``std_s``) truncated to >= 0 (s).

    Truncated, not clipped: negative draws are redrawn, so there is no point mass at 0.
    ``mean_s >= 0`` keeps the acceptance rate >= 1/2.
    """

    def __init__(self, mean_s: float, std_s: float, *, selector: Selector | None = None,
                 seed: SeedLike = None) -> None:
        super().__init__(selector=selector, seed=seed)
        self.mean_s = _check_nonneg("mean_s", mean_s)
        self.std_s = _check_nonneg("std_s", std_s)

    def _sample(self) -> float:
        if self.std_s == 0.0:
            return self.mean_s
        while True:
            x = self.mean_s + self.std_s * self._normal()
            if x >= 0.0:
                return x


class ExponentialJitter(_Jitter):
    """Random extra delay ``shift_s + Exp(mean scale_s)`` (s): a floor plus a long tail."""

    def __init__(self, shift_s: float, scale_s: float, *, selector: Selector | None = None,
                 seed: SeedLike = None) -> None:
        super().__init__(selector=selector, seed=seed)
        self.shift_s = _check_nonneg("shift_s", shift_s)
        self.scale_s = _check_nonneg("scale_s", scale_s)

    def _sample(self) -> float:
        return self.shift_s - self.scale_s * math.log1p(-self._uniform())


class BernoulliLoss(FrameImpairment):
    """Each matching frame is lost independently with ``probability``."""

    kind = "loss"

    def __init__(self, probability: float, *, selector: Selector | None = None,
                 seed: SeedLike = None) -> None:
        super().__init__(selector=selector, seed=seed)
        self.probability = _check_prob("probability", probability)

    def _apply(self, frame: TxFrame) -> list[TxFrame]:
        if self._uniform() < self.probability:
            self.n_dropped += 1
            return []
        return [frame]

    def apply_many(self, t_submit_s: np.ndarray, ids: np.ndarray, sender: str, release_s: np.ndarray,
                   alive: np.ndarray) -> None:
        hit = alive & self.selector.matches_many(t_submit_s, ids, sender)
        n = int(hit.sum())
        lost = self._draws(n) < self.probability
        idx = np.flatnonzero(hit)[lost]
        alive[idx] = False
        self.n_matched += n
        self.n_dropped += int(lost.sum())


class GilbertElliottLoss(FrameImpairment):
    """Burst loss: a two-state Markov chain stepped once per matching frame.

    In state good a frame is lost with ``loss_good``, in state bad with ``loss_bad``; after
    each frame the chain moves good→bad with ``p_gb`` and bad→good with ``p_bg``. The bad
    state lasts 1/p_bg frames on average (the mean burst length when loss_bad = 1,
    loss_good = 0); the stationary loss rate is ``(p_bg·loss_good + p_gb·loss_bad) /
    (p_gb + p_bg)``. The initial state is drawn from the stationary distribution.
    """

    kind = "gilbert_elliott"

    def __init__(self, p_gb: float, p_bg: float, loss_good: float = 0.0, loss_bad: float = 1.0,
                 *, selector: Selector | None = None, seed: SeedLike = None) -> None:
        super().__init__(selector=selector, seed=seed)
        self.p_gb = _check_prob("p_gb", p_gb)
        self.p_bg = _check_prob("p_bg", p_bg)
        self.loss_good = _check_prob("loss_good", loss_good)
        self.loss_bad = _check_prob("loss_bad", loss_bad)
        total = self.p_gb + self.p_bg
        self.bad = bool(total > 0 and self._uniform() < self.p_gb / total)

    @property
    def stationary_loss_rate(self) -> float:
        total = self.p_gb + self.p_bg
        if total == 0:
            return self.loss_bad if self.bad else self.loss_good
        return (self.p_bg * self.loss_good + self.p_gb * self.loss_bad) / total

    def _apply(self, frame: TxFrame) -> list[TxFrame]:
        lost = self._uniform() < (self.loss_bad if self.bad else self.loss_good)
        self.bad = (self._uniform() >= self.p_bg) if self.bad else (self._uniform() < self.p_gb)
        if lost:
            self.n_dropped += 1
            return []
        return [frame]


class Duplicate(FrameImpairment):
    """With ``probability``, also send a copy ``gap_s`` (s) after the original's release."""

    kind = "duplicate"

    def __init__(self, probability: float, gap_s: float = 0.0, *,
                 selector: Selector | None = None, seed: SeedLike = None) -> None:
        super().__init__(selector=selector, seed=seed)
        self.probability = _check_prob("probability", probability)
        self.gap_s = _check_nonneg("gap_s", gap_s)

    def _apply(self, frame: TxFrame) -> list[TxFrame]:
        if self._uniform() < self.probability:
            dup = frame.copy()
            dup.duplicate = True
            dup.t_release_s += self.gap_s
            self.n_added += 1
            return [frame, dup]
        return [frame]


class Reorder(FrameImpairment):
    """With ``probability``, hold a frame back by an extra delay uniform in
    ``[hold_min_s, hold_max_s]`` (s), so frames submitted after it overtake it."""

    kind = "reorder"

    def __init__(self, probability: float, hold_max_s: float, hold_min_s: float = 0.0, *,
                 selector: Selector | None = None, seed: SeedLike = None) -> None:
        super().__init__(selector=selector, seed=seed)
        self.probability = _check_prob("probability", probability)
        self.hold_min_s = _check_nonneg("hold_min_s", hold_min_s)
        self.hold_max_s = _check_nonneg("hold_max_s", hold_max_s)
        if self.hold_max_s < self.hold_min_s:
            raise ValueError(f"hold_max_s={hold_max_s!r} must be >= hold_min_s={hold_min_s!r}")

    def _apply(self, frame: TxFrame) -> list[TxFrame]:
        if self._uniform() < self.probability:
            frame.t_release_s += self.hold_min_s + (self.hold_max_s - self.hold_min_s) * self._uniform()
            self.n_modified += 1
        return [frame]


class Corrupt(FrameImpairment):
    """With ``probability``, flip ``n_bits`` distinct random payload bits (DLC kept).

    Models an error the CAN CRC missed, i.e. what the end-to-end CRC must catch. A frame with
    fewer payload bits than ``n_bits`` gets all of them flipped; an empty payload passes.
    """

    kind = "corrupt"

    def __init__(self, n_bits: int = 1, probability: float = 1.0, *,
                 selector: Selector | None = None, seed: SeedLike = None) -> None:
        super().__init__(selector=selector, seed=seed)
        if isinstance(n_bits, bool) or not isinstance(n_bits, (int, np.integer)) or n_bits < 1:
            raise ValueError(f"n_bits must be an int >= 1, got {n_bits!r}")
        self.n_bits = int(n_bits)
        self.probability = _check_prob("probability", probability)

    def _apply(self, frame: TxFrame) -> list[TxFrame]:
        n_payload_bits = 8 * len(frame.data)
        if n_payload_bits == 0 or frame.is_remote:
            return [frame]
        if self.probability < 1.0 and self._uniform() >= self.probability:
            return [frame]
        k = min(self.n_bits, n_payload_bits)
        positions: set[int] = set()
        while len(positions) < k:  # k distinct positions, uniformly
            positions.add(int(self._uniform() * n_payload_bits))
        buf = bytearray(frame.data)
        for pos in sorted(positions):
            buf[pos >> 3] ^= 0x80 >> (pos & 7)  # bit 0 = MSB of byte 0, wire order
        frame.data = bytes(buf)
        frame.corrupted = True
        self.n_modified += 1
        return [frame]


class Silence(FrameImpairment):
    """A silent node: every matching frame is dropped (select the node with ``senders``)."""

    kind = "silent"

    def _apply(self, frame: TxFrame) -> list[TxFrame]:
        self.n_dropped += 1
        return []


class Babbler:
    """Babbling idiot: ``sender`` floods ``arbitration_id`` at ``rate_hz`` in ``[start_s, stop_s)``.

    Emission k is at ``start_s + k / rate_hz``. A low identifier is a high priority (0 wins
    every arbitration). Deterministic: no randomness.
    """

    kind: ClassVar[str] = "babble"

    def __init__(self, sender: str, arbitration_id: int, rate_hz: float, *, dlc: int = 8,
                 data: bytes | None = None, is_extended: bool = False, start_s: float = 0.0,
                 stop_s: float = math.inf) -> None:
        if not sender:
            raise ValueError("sender must be a non-empty node name")
        limit = _MAX_EXT_ID if is_extended else _MAX_STD_ID
        if not 0 <= int(arbitration_id) <= limit:
            raise ValueError(f"arbitration_id 0x{int(arbitration_id):X} out of range 0..0x{limit:X}")
        rate = float(rate_hz)
        if not math.isfinite(rate) or rate <= 0:
            raise ValueError(f"rate_hz must be a finite rate > 0, got {rate_hz!r}")
        if not 0 <= int(dlc) <= 8:
            raise ValueError(f"dlc must be 0..8, got {dlc!r}")
        payload = bytes(int(dlc)) if data is None else bytes(data)
        if len(payload) != int(dlc):
            raise ValueError(f"data has {len(payload)} bytes but dlc is {dlc}")
        self.sender = sender
        self.arbitration_id = int(arbitration_id)
        self.is_extended = bool(is_extended)
        self.rate_hz = rate
        self.dlc = int(dlc)
        self.data = payload
        self.start_s = _check_nonneg("start_s", start_s)
        self.stop_s = float(stop_s)
        if not self.stop_s > self.start_s:
            raise ValueError(f"stop_s={stop_s!r} must be > start_s={start_s!r}")
        self.n_emitted = 0

    def _t(self, k: int) -> float:
        return self.start_s + k / self.rate_hz

    def _first_after(self, t: float) -> int:
        """Smallest k >= 0 with emission time > t."""
        if t < self.start_s:
            return 0
        k = max(0, math.floor((t - self.start_s) * self.rate_hz))
        while self._t(k) <= t:
            k += 1
        while k > 0 and self._t(k - 1) > t:
            k -= 1
        return k

    def frames_due(self, t_from_s: float, t_to_s: float) -> list[TxFrame]:
        """Frames emitted at times in ``(t_from_s, t_to_s]`` (and in ``[start_s, stop_s)``)."""
        hi = min(t_to_s, self.stop_s)
        if hi < self.start_s or t_to_s <= t_from_s:
            return []
        k0 = self._first_after(t_from_s)
        k1 = self._first_after(hi)  # first k beyond hi
        out = []
        for k in range(k0, k1):
            t = self._t(k)
            if t >= self.stop_s:
                break
            out.append(TxFrame(self.arbitration_id, self.is_extended, self.data, self.dlc,
                               self.sender, t, t))
        self.n_emitted += len(out)
        return out

    def __repr__(self) -> str:
        return (f"Babbler({self.sender!r}, 0x{self.arbitration_id:X}, {self.rate_hz} Hz, "
                f"[{self.start_s}, {self.stop_s}))")


# --------------------------------------------------------------------------------------------
# the chain of one node


class SendPath:
    """The impairment chain of one sender (or, per link, one receiver).

    ``submit`` runs a frame through the impairments in order and holds what comes out;
    ``release(t_now_s)`` hands out, in ``(t_release_s, submission)`` order, every held frame
    with ``t_release_s <= t_now_s``, after first pulling the traffic sources' frames due up to
    ``t_now_s`` through the same chain. A delayed frame is never released early and a lost
    frame never at all. Frames whose identifier is in ``exempt_ids`` skip the chain (e.g. the
    lockstep "tick done" control frame, which must never stall the plant).
    """

    def __init__(self, impairments: Sequence[Impairment] = (),
                 sources: Sequence[TrafficSource] = (), *, node: str = "",
                 exempt_ids: Iterable[int] = ()) -> None:
        self.node = node
        self.impairments: tuple[Impairment, ...] = tuple(impairments)
        self.sources: tuple[TrafficSource, ...] = tuple(sources)
        self.exempt_ids = frozenset(int(i) for i in exempt_ids)
        self._held: list[tuple[float, int, TxFrame]] = []
        self._seq = 0
        self._t_sources = -math.inf
        self.n_submitted = 0
        self.n_scheduled = 0
        self.n_released = 0

    def submit(self, frame: TxFrame) -> list[TxFrame]:
        """Run ``frame`` through the chain and hold the result until its release time.

        Returns the frames scheduled (``[]`` if it was lost), for accounting only: they are
        handed out by :meth:`release`, do not send them yourself.
        """
        self.n_submitted += 1
        frames = [frame]
        if frame.arbitration_id not in self.exempt_ids:
            for imp in self.impairments:
                if len(frames) == 1:
                    frames = imp.apply(frames[0])
                else:
                    frames = [g for f in frames for g in imp.apply(f)]
                if not frames:
                    break
        for f in frames:
            heapq.heappush(self._held, (f.t_release_s, self._seq, f))
            self._seq += 1
        self.n_scheduled += len(frames)
        return frames

    def fates(self, t_submit_s: np.ndarray, ids: np.ndarray) -> np.ndarray:
        """Release times (s; ``inf`` = lost) of a known sequence of frames of this node, submitted in
        array order (shape (n,)), as :meth:`submit` would schedule them one by one: the same
        impairments, draws and float operations. For the batch engine (:mod:`canbrake.batch`), which
        knows every frame a node will send before the run. Raises NotImplementedError for chains
        with traffic sources or impairments that copy frames (duplicate) or act on payloads."""
        if self.sources:
            raise NotImplementedError("a send path with traffic sources")
        rel = np.array(t_submit_s, dtype=float)
        alive = ~np.isin(ids, np.fromiter(self.exempt_ids, dtype=np.int64)) if self.exempt_ids else \
            np.ones(rel.shape, dtype=bool)
        chained = alive.copy()
        for imp in self.impairments:
            if not isinstance(imp, FrameImpairment):
                raise NotImplementedError(f"{type(imp).__name__}")
            imp.apply_many(t_submit_s, ids, self.node, rel, chained)
        n = rel.size
        self.n_submitted += n
        self.n_scheduled += int(chained.sum()) + int((~alive).sum())
        rel[~chained & alive] = math.inf
        return rel

    def release(self, t_now_s: float) -> list[TxFrame]:
        """Frames with ``t_release_s <= t_now_s``, in release-time order; the rest stay held."""
        if self.sources and t_now_s > self._t_sources:
            t_from, self._t_sources = self._t_sources, t_now_s
            due = [f for src in self.sources for f in src.frames_due(t_from, t_now_s)]
            due.sort(key=lambda f: f.t_submit_s)  # stable: source order on ties
            for f in due:
                self.submit(f)
        held = self._held
        out: list[TxFrame] = []
        while held and held[0][0] <= t_now_s:
            out.append(heapq.heappop(held)[2])
        self.n_released += len(out)
        return out

    def next_release_s(self) -> float | None:
        """Release time of the earliest held frame (None if none; sources not included)."""
        return self._held[0][0] if self._held else None

    @property
    def n_held(self) -> int:
        return len(self._held)

    def counters(self) -> dict[str, int]:
        """Totals: submitted, scheduled, released, held, dropped, duplicated, modified,
        corrupted (frames with flipped bits)."""
        dropped = added = modified = corrupted = 0
        for imp in self.impairments:
            if isinstance(imp, FrameImpairment):
                dropped += imp.n_dropped
                added += imp.n_added
                modified += imp.n_modified
                if isinstance(imp, Corrupt):
                    corrupted += imp.n_modified
        return {"submitted": self.n_submitted, "scheduled": self.n_scheduled,
                "released": self.n_released, "held": len(self._held), "dropped": dropped,
                "duplicated": added, "modified": modified, "corrupted": corrupted}

    def __repr__(self) -> str:
        return f"SendPath(node={self.node!r}, impairments={list(self.impairments)!r}, " \
               f"sources={list(self.sources)!r})"


class MessageSendPath:
    """A :class:`SendPath` speaking ``can.Message``: the node-side protocol
    (``canbrake.nodes.base.SendPath``) for sender ``node``.

    ``submit(msg, t_s)`` runs ``msg`` through the chain and returns every frame due at ``t_s``
    (held ones included, in release order); ``release(t_s)`` returns the held frames due.
    Unchanged frames come back as the very ``can.Message`` submitted (a duplicate is the same
    object twice); corrupted ones as new messages.
    """

    def __init__(self, path: SendPath, node: str | None = None) -> None:
        self.path = path
        self.node = node if node is not None else path.node

    def submit(self, msg: Any, t_s: float, delay_s: float = 0.0) -> list[Any]:
        """Submit at ``t_s``; the frame may go to the bus from ``t_s + delay_s`` on (s) plus what
        the impairments add. Returns the frames due at ``t_s``."""
        frame = TxFrame.from_message(msg, self.node, t_s)
        frame.t_release_s += delay_s
        self.path.submit(frame)
        return self.release(t_s)

    def release(self, t_s: float) -> list[Any]:
        return [f.to_message() for f in self.path.release(t_s)]

    def counters(self) -> dict[str, int]:
        return self.path.counters()


# --------------------------------------------------------------------------------------------
# configuration (pydantic v2): the scenario's bus.impairments is list[ImpairmentSpec]


def _prob(v: float) -> float:
    if not 0.0 <= v <= 1.0:
        raise ValueError(f"must be a probability in [0, 1], got {v!r}")
    return v


def _time(v: float) -> float:
    if v < 0.0:
        raise ValueError(f"must be a time >= 0 s, got {v!r}")
    return v


def _can_id(v: int) -> int:
    if not 0 <= v <= _MAX_EXT_ID:
        raise ValueError(f"must be a CAN identifier 0..0x{_MAX_EXT_ID:X}, got {v!r}")
    return v


Probability = Annotated[float, AfterValidator(_prob)]
Seconds = Annotated[float, AfterValidator(_time)]
CanId = Annotated[int, AfterValidator(_can_id)]


class _SpecBase(BaseModel):
    model_config = ConfigDict(extra="forbid", frozen=True, allow_inf_nan=False)

    start_s: Seconds = Field(0.0, description="active from this time on (s, inclusive)")
    stop_s: Seconds | None = Field(None, description="active until this time (s, exclusive); "
                                                     "None = to the end of the run")

    @model_validator(mode="after")
    def _window(self) -> "_SpecBase":
        if self.stop_s is not None and self.stop_s <= self.start_s:
            raise ValueError(f"stop_s ({self.stop_s}) must be greater than start_s "
                             f"({self.start_s})")
        return self

    def _stop(self) -> float:
        return math.inf if self.stop_s is None else self.stop_s


class _FrameSpec(_SpecBase):
    ids: list[CanId] | None = Field(None, description="arbitration ids acted on; None = all")
    senders: list[str] | None = Field(None, description="sending nodes acted on; None = all")
    receivers: list[str] | None = Field(
        None, description="per-link: apply on these nodes' receive paths instead of the send "
                          "path; None = send path (every listener)")

    @model_validator(mode="after")
    def _non_empty(self) -> "_FrameSpec":
        for name in ("ids", "senders", "receivers"):
            if getattr(self, name) == []:
                raise ValueError(f"{name} is an empty list, which would select nothing; "
                                 "omit it to select all")
        return self

    def selector(self) -> Selector:
        return Selector(
            ids=None if self.ids is None else frozenset(self.ids),
            senders=None if self.senders is None else frozenset(self.senders),
            receivers=None if self.receivers is None else frozenset(self.receivers),
            start_s=self.start_s, stop_s=self._stop())

    def build(self, seed: SeedLike = None) -> FrameImpairment:  # pragma: no cover - abstract
        raise NotImplementedError


class DelaySpec(_FrameSpec):
    """Fixed delay."""

    type: Literal["delay"] = "delay"
    delay_s: Seconds = Field(description="extra delay (s)")

    def build(self, seed: SeedLike = None) -> FrameImpairment:
        return Delay(self.delay_s, selector=self.selector(), seed=seed)


_JITTER_FIELDS = {"uniform": ("low_s", "high_s"), "normal": ("mean_s", "std_s"),
                  "exponential": ("shift_s", "scale_s")}


class JitterSpec(_FrameSpec):
    """Random extra delay: ``uniform`` (low_s, high_s), ``normal`` truncated at 0
    (mean_s, std_s) or shifted ``exponential`` (shift_s + Exp with mean scale_s)."""

    type: Literal["jitter"] = "jitter"
    distribution: Literal["uniform", "normal", "exponential"] = "uniform"
    low_s: Seconds | None = None
    high_s: Seconds | None = None
    mean_s: Seconds | None = None
    std_s: Seconds | None = None
    shift_s: Seconds | None = None
    scale_s: Seconds | None = None

    @model_validator(mode="after")
    def _fields_for_distribution(self) -> "JitterSpec":
        needed = _JITTER_FIELDS[self.distribution]
        missing = [f for f in needed if getattr(self, f) is None]
        if missing:
            raise ValueError(f"jitter distribution {self.distribution!r} needs "
                             f"{' and '.join(needed)}; missing {', '.join(missing)}")
        unused = [f for d, fs in _JITTER_FIELDS.items() if d != self.distribution for f in fs
                  if getattr(self, f) is not None]
        if unused:
            raise ValueError(f"{', '.join(unused)} not used by jitter distribution "
                             f"{self.distribution!r} (it takes {' and '.join(needed)})")
        if self.distribution == "uniform" and self.high_s < self.low_s:  # type: ignore[operator]
            raise ValueError(f"high_s ({self.high_s}) must be >= low_s ({self.low_s})")
        return self

    def build(self, seed: SeedLike = None) -> FrameImpairment:
        sel = self.selector()
        if self.distribution == "uniform":
            return UniformJitter(self.low_s, self.high_s, selector=sel, seed=seed)  # type: ignore[arg-type]
        if self.distribution == "normal":
            return NormalJitter(self.mean_s, self.std_s, selector=sel, seed=seed)  # type: ignore[arg-type]
        return ExponentialJitter(self.shift_s, self.scale_s, selector=sel, seed=seed)  # type: ignore[arg-type]


class LossSpec(_FrameSpec):
    """Independent (Bernoulli) loss."""

    type: Literal["loss"] = "loss"
    probability: Probability = Field(description="loss probability per frame")

    def build(self, seed: SeedLike = None) -> FrameImpairment:
        return BernoulliLoss(self.probability, selector=self.selector(), seed=seed)


class GilbertElliottSpec(_FrameSpec):
    """Burst loss; mean burst length 1/p_bg frames, see :class:`GilbertElliottLoss`."""

    type: Literal["gilbert_elliott"] = "gilbert_elliott"
    p_gb: Probability = Field(description="P(good -> bad) per frame")
    p_bg: Probability = Field(description="P(bad -> good) per frame")
    loss_good: Probability = Field(0.0, description="loss probability in the good state")
    loss_bad: Probability = Field(1.0, description="loss probability in the bad state")

    def build(self, seed: SeedLike = None) -> FrameImpairment:
        return GilbertElliottLoss(self.p_gb, self.p_bg, self.loss_good, self.loss_bad,
                                  selector=self.selector(), seed=seed)


class DuplicateSpec(_FrameSpec):
    """Duplication: the copy is released ``gap_s`` after the original."""

    type: Literal["duplicate"] = "duplicate"
    probability: Probability = Field(description="duplication probability per frame")
    gap_s: Seconds = Field(0.0, description="copy released this long after the original (s)")

    def build(self, seed: SeedLike = None) -> FrameImpairment:
        return Duplicate(self.probability, self.gap_s, selector=self.selector(), seed=seed)


class ReorderSpec(_FrameSpec):
    """Reordering: hold a frame back by uniform [hold_min_s, hold_max_s]."""

    type: Literal["reorder"] = "reorder"
    probability: Probability = Field(description="probability a frame is held back")
    hold_min_s: Seconds = Field(0.0, description="shortest hold (s)")
    hold_max_s: Seconds = Field(description="longest hold (s)")

    @model_validator(mode="after")
    def _hold(self) -> "ReorderSpec":
        if self.hold_max_s < self.hold_min_s:
            raise ValueError(f"hold_max_s ({self.hold_max_s}) must be >= hold_min_s "
                             f"({self.hold_min_s})")
        return self

    def build(self, seed: SeedLike = None) -> FrameImpairment:
        return Reorder(self.probability, self.hold_max_s, self.hold_min_s,
                       selector=self.selector(), seed=seed)


class CorruptSpec(_FrameSpec):
    """Bit corruption of the payload (DLC kept)."""

    type: Literal["corrupt"] = "corrupt"
    probability: Probability = Field(1.0, description="probability a frame is corrupted")
    n_bits: int = Field(1, ge=1, le=64, description="payload bits flipped per corrupted frame")

    def build(self, seed: SeedLike = None) -> FrameImpairment:
        return Corrupt(self.n_bits, self.probability, selector=self.selector(), seed=seed)


class SilentSpec(_FrameSpec):
    """Silent node(s): every frame of ``senders`` dropped in ``[start_s, stop_s)``."""

    type: Literal["silent"] = "silent"

    @model_validator(mode="after")
    def _needs_senders(self) -> "SilentSpec":
        if not self.senders:
            raise ValueError("silent needs senders: the node(s) that go silent, e.g. [ecu3]")
        return self

    def build(self, seed: SeedLike = None) -> FrameImpairment:
        return Silence(selector=self.selector(), seed=seed)


class BabbleSpec(_SpecBase):
    """Babbling idiot: ``sender`` floods ``arbitration_id`` (low = high priority) at ``rate_hz``.

    ``sender`` may be an existing node (its send path emits the flood) or a phantom node name
    (the bus medium builds a send path for it, see :func:`babbling_nodes`).
    """

    type: Literal["babble"] = "babble"
    sender: str = Field(min_length=1, description="babbling node name, e.g. ecu3 or babbler")
    arbitration_id: CanId = Field(description="identifier flooded; its priority on the bus")
    is_extended: bool = False
    rate_hz: float = Field(gt=0, description="frames per second")
    dlc: int = Field(8, ge=0, le=8)
    data_hex: str | None = Field(None, description="payload as hex, dlc bytes; default zeros")

    @model_validator(mode="after")
    def _check(self) -> "BabbleSpec":
        if not self.is_extended and self.arbitration_id > _MAX_STD_ID:
            raise ValueError(f"arbitration_id 0x{self.arbitration_id:X} needs is_extended: true "
                             f"(standard ids are 0..0x{_MAX_STD_ID:X})")
        if self.data_hex is not None:
            try:
                data = bytes.fromhex(self.data_hex)
            except ValueError:
                raise ValueError(f"data_hex {self.data_hex!r} is not hex") from None
            if len(data) != self.dlc:
                raise ValueError(f"data_hex has {len(data)} bytes but dlc is {self.dlc}")
        return self

    def build(self, seed: SeedLike = None) -> Babbler:
        data = None if self.data_hex is None else bytes.fromhex(self.data_hex)
        return Babbler(self.sender, self.arbitration_id, self.rate_hz, dlc=self.dlc, data=data,
                       is_extended=self.is_extended, start_s=self.start_s, stop_s=self._stop())


class BitErrorRateSpec(_SpecBase):
    """Bit errors on the wire: each bit of every frame is flipped with probability ``ber``.

    Not a send-path impairment: it acts in the CAN timing model (``bus.timing: model``,
    lockstep), where a hit frame becomes an error frame, is retransmitted and raises the error
    counters of its sender (see :mod:`canbrake.bus.faults`)."""

    type: Literal["bit_error_rate"] = "bit_error_rate"
    ber: float = Field(ge=0.0, lt=1.0, description="probability that one bit is corrupted")
    auto_recovery: bool = Field(True, description="bus-off nodes restart after 128 x 11 recessive bits")
    recovery_delay_s: float = Field(0.0, ge=0.0, description="host restart delay before a bus-off node starts its "
                                                              "recovery (s; e.g. AUTOSAR CanSM bus-off time)")


class FaultyTransceiverSpec(_SpecBase):
    """A node whose transceiver corrupts its own frames with ``probability`` (timing model only,
    like ``bit_error_rate``): its TEC rises by 8 per failed attempt and it drifts into bus-off."""

    type: Literal["faulty_transceiver"] = "faulty_transceiver"
    node: str = Field(min_length=1, description="the faulty node, e.g. ecu3")
    probability: Probability = Field(1.0, description="probability that a frame it sends is corrupted")
    auto_recovery: bool = Field(True, description="bus-off nodes restart after 128 x 11 recessive bits")
    recovery_delay_s: float = Field(0.0, ge=0.0, description="host restart delay before a bus-off node starts its "
                                                              "recovery (s; e.g. AUTOSAR CanSM bus-off time)")


#: spec types that act in the timing model's fault confinement, not on a send path
BUS_ERROR_SPECS = (BitErrorRateSpec, FaultyTransceiverSpec)

#: the spec classes in the union, by their ``type`` tag
IMPAIRMENT_SPECS: dict[str, type[_SpecBase]] = {
    "delay": DelaySpec, "jitter": JitterSpec, "loss": LossSpec,
    "gilbert_elliott": GilbertElliottSpec, "duplicate": DuplicateSpec, "reorder": ReorderSpec,
    "corrupt": CorruptSpec, "silent": SilentSpec, "babble": BabbleSpec,
    "bit_error_rate": BitErrorRateSpec, "faulty_transceiver": FaultyTransceiverSpec,
}

ImpairmentSpec = Annotated[
    Union[DelaySpec, JitterSpec, LossSpec, GilbertElliottSpec, DuplicateSpec, ReorderSpec,
          CorruptSpec, SilentSpec, BabbleSpec, BitErrorRateSpec, FaultyTransceiverSpec],
    Field(discriminator="type"),
]

_SPEC_LIST = TypeAdapter(list[ImpairmentSpec], config=ConfigDict(title="bus.impairments"))


# --------------------------------------------------------------------------------------------
# factory


def _stable_u32(text: str) -> int:
    return zlib.crc32(text.encode("utf-8"))


def derive_seed(run_seed: int, *labels: str | int) -> np.random.SeedSequence:
    """Seed for one impairment instance from the run seed and stable labels.

    Uses CRC-32 of string labels (not Python's salted ``hash()``), so every process derives
    the same seed whatever the start order or ``PYTHONHASHSEED``.
    """
    if isinstance(run_seed, bool) or not isinstance(run_seed, (int, np.integer)) or run_seed < 0:
        raise ValueError(f"seed must be a non-negative int, got {run_seed!r}")
    key = tuple(_stable_u32(x) if isinstance(x, str) else int(x) for x in labels)
    return np.random.SeedSequence(int(run_seed), spawn_key=key)


def _validate_specs(specs: Iterable[Any]) -> list[Any]:
    items = list(specs)
    if all(isinstance(s, _SpecBase) for s in items):
        return items
    return _SPEC_LIST.validate_python(
        [s.model_dump() if isinstance(s, BaseModel) else s for s in items])


def build_impairments(specs: Iterable[Any], seed: int, node: str, *,
                      direction: Literal["tx", "rx"] = "tx",
                      exempt_ids: Iterable[int] = ()) -> SendPath:
    """The impairment chain of ``node``, in the order the specs are listed.

    ``direction="tx"``: the send path of sender ``node`` — specs without ``receivers`` whose
    ``senders`` is unset or includes ``node``, plus the babblers whose ``sender`` is ``node``.
    ``direction="rx"``: the per-link receive path of ``node`` — specs whose ``receivers``
    include it. ``specs`` are :data:`ImpairmentSpec` models or plain dicts (validated here).
    Impairment i is seeded with ``derive_seed(seed, direction, node, i)``.
    """
    if direction not in ("tx", "rx"):
        raise ValueError(f"direction must be 'tx' or 'rx', got {direction!r}")
    if not isinstance(node, str) or not node:
        raise ValueError(f"node must be a non-empty name, got {node!r}")
    impairments: list[Impairment] = []
    sources: list[TrafficSource] = []
    for i, spec in enumerate(_validate_specs(specs)):
        if isinstance(spec, BabbleSpec):
            if direction == "tx" and spec.sender == node:
                sources.append(spec.build())
            continue
        if isinstance(spec, BUS_ERROR_SPECS):  # acts in the timing model (canbrake.bus.faults)
            continue
        if direction == "tx":
            if spec.receivers is not None:
                continue
            if spec.senders is not None and node not in spec.senders:
                continue
        elif spec.receivers is None or node not in spec.receivers:
            continue
        impairments.append(spec.build(derive_seed(seed, direction, node, i)))
    return SendPath(impairments, sources, node=node, exempt_ids=exempt_ids)


def babbling_nodes(specs: Iterable[Any]) -> list[str]:
    """Names of the nodes that babble, sorted (phantom ones need a send path of their own)."""
    return sorted({s.sender for s in _validate_specs(specs) if isinstance(s, BabbleSpec)})
