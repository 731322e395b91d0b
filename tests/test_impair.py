"""Impairments: statistics with confidence intervals, determinism, release-time guarantees."""
from __future__ import annotations

import math

import numpy as np
import pytest
from pydantic import BaseModel, ValidationError
from scipy import stats

from canbrake.bus.impair import (
    Babbler,
    BernoulliLoss,
    Corrupt,
    Delay,
    Duplicate,
    ExponentialJitter,
    GilbertElliottLoss,
    ImpairmentSpec,
    MessageSendPath,
    NormalJitter,
    Reorder,
    Selector,
    SendPath,
    TxFrame,
    UniformJitter,
    babbling_nodes,
    build_impairments,
    derive_seed,
)
from canbrake.bus.timing import BusTimingModel

ALPHA = 1e-3  # every interval below is a 99.9 % interval; a fixed seed makes each run exact
Z = stats.norm.ppf(1 - ALPHA / 2)


def frame(k: int, t: float, sender: str = "ecu1", ident: int = 0x101) -> TxFrame:
    """A frame whose payload carries its serial number ``k``."""
    return TxFrame(ident, False, k.to_bytes(8, "big"), 8, sender, t, t)


def serial(f: TxFrame) -> int:
    return int.from_bytes(f.data, "big")


def drive(path: SendPath, n: int, dt: float = 1e-3, sender: str = "ecu1",
          ident: int = 0x101) -> list[TxFrame]:
    """Submit n frames every dt and release at each submit time; then drain."""
    out: list[TxFrame] = []
    for k in range(n):
        t = k * dt
        path.submit(frame(k, t, sender, ident))
        out += path.release(t)
    out += path.release(math.inf)
    return out


def assert_in_binomial_ci(k: int, n: int, p: float) -> None:
    ci = stats.binomtest(k, n).proportion_ci(confidence_level=1 - ALPHA, method="wilson")
    assert ci.low <= p <= ci.high, (k, n, p, ci)


def batch_means_ci(x: np.ndarray, n_batches: int = 50) -> tuple[float, float]:
    """Confidence interval for the mean of a correlated stationary sequence (batch means)."""
    b = np.asarray(x, dtype=float)[: len(x) // n_batches * n_batches].reshape(n_batches, -1)
    means = b.mean(axis=1)
    half = stats.t.ppf(1 - ALPHA / 2, n_batches - 1) * means.std(ddof=1) / math.sqrt(n_batches)
    return means.mean() - half, means.mean() + half


# --------------------------------------------------------------------------------------------
# statistics


def test_bernoulli_loss_rate() -> None:
    n, p = 20_000, 0.1
    imp = BernoulliLoss(p, seed=1)
    lost = sum(not imp.apply(frame(k, 0.0)) for k in range(n))
    assert lost == imp.n_dropped
    assert_in_binomial_ci(lost, n, p)


def test_gilbert_elliott_burst_length_and_stationary_loss() -> None:
    p_gb, p_bg, n = 0.02, 0.25, 100_000
    imp = GilbertElliottLoss(p_gb, p_bg, loss_good=0.0, loss_bad=1.0, seed=3)
    lost = np.array([not imp.apply(frame(k, 0.0)) for k in range(n)])
    # bursts = maximal runs of losses; with loss_bad = 1 they are the sojourns in state bad,
    # i.i.d. geometric with mean 1/p_bg and variance (1 - p_bg)/p_bg**2
    edges = np.diff(np.concatenate(([0], lost.astype(int), [0])))
    bursts = np.flatnonzero(edges == -1) - np.flatnonzero(edges == 1)
    bursts = bursts[1:-1]  # drop possibly censored first/last
    half = Z * math.sqrt((1 - p_bg) / p_bg**2 / len(bursts))
    assert abs(bursts.mean() - 1 / p_bg) <= half
    # stationary loss rate p_gb/(p_gb + p_bg): for a two-state chain the sample mean has
    # asymptotic variance pi(1-pi)/n * (1 + lam)/(1 - lam), lam = 1 - p_gb - p_bg
    pi = p_gb / (p_gb + p_bg)
    lam = 1 - p_gb - p_bg
    half = Z * math.sqrt(pi * (1 - pi) / n * (1 + lam) / (1 - lam))
    assert abs(lost.mean() - pi) <= half
    assert imp.stationary_loss_rate == pytest.approx(pi)


def test_gilbert_elliott_partial_loss_in_both_states() -> None:
    imp = GilbertElliottLoss(0.05, 0.2, loss_good=0.01, loss_bad=0.6, seed=11)
    lost = np.array([not imp.apply(frame(k, 0.0)) for k in range(100_000)])
    lo, hi = batch_means_ci(lost)
    assert lo <= imp.stationary_loss_rate <= hi
    assert imp.stationary_loss_rate == pytest.approx((0.2 * 0.01 + 0.05 * 0.6) / 0.25)


def _jitter_samples(imp, n: int = 5000) -> np.ndarray:  # type: ignore[no-untyped-def]
    out = []
    for k in range(n):
        f = frame(k, 1.0)
        (g,) = imp.apply(f)
        out.append(g.t_release_s - 1.0)
    return np.array(out)


def test_uniform_jitter_distribution() -> None:
    x = _jitter_samples(UniformJitter(1e-4, 5e-4, seed=5))
    assert x.min() >= 1e-4 and x.max() <= 5e-4
    assert stats.kstest(x, stats.uniform(loc=1e-4, scale=4e-4).cdf).pvalue > ALPHA
    half = Z * (4e-4 / math.sqrt(12)) / math.sqrt(len(x))
    assert abs(x.mean() - 3e-4) <= half


def test_truncated_normal_jitter_distribution() -> None:
    mean, std = 2e-4, 3e-4  # truncation at 0 matters: P(N < 0) = 25 %
    x = _jitter_samples(NormalJitter(mean, std, seed=6))
    assert x.min() >= 0.0
    ref = stats.truncnorm(a=(0 - mean) / std, b=np.inf, loc=mean, scale=std)
    assert stats.kstest(x, ref.cdf).pvalue > ALPHA
    assert abs(x.mean() - ref.mean()) <= Z * ref.std() / math.sqrt(len(x))
    # the variance: chi-square-free check via the CLT on (x - mu)^2
    sq = (x - ref.mean()) ** 2
    assert abs(sq.mean() - ref.var()) <= Z * sq.std(ddof=1) / math.sqrt(len(x))


def test_shifted_exponential_jitter_distribution() -> None:
    x = _jitter_samples(ExponentialJitter(1e-4, 2e-4, seed=7))
    assert x.min() >= 1e-4
    assert stats.kstest(x, stats.expon(loc=1e-4, scale=2e-4).cdf).pvalue > ALPHA
    assert abs(x.mean() - 3e-4) <= Z * 2e-4 / math.sqrt(len(x))


def test_duplication_rate_and_gap() -> None:
    n, p, gap = 20_000, 0.05, 2.5e-4
    path = SendPath([Duplicate(p, gap, seed=8)])
    out = drive(path, n)
    copies = [f for f in out if f.duplicate]
    assert len(out) == n + len(copies)
    assert_in_binomial_ci(len(copies), n, p)
    assert all(c.t_release_s == pytest.approx(c.t_submit_s + gap) for c in copies)
    assert path.counters()["duplicated"] == len(copies)


def test_reorder_lets_later_frames_overtake() -> None:
    n, p = 5000, 0.1
    path = SendPath([Reorder(p, hold_max_s=5e-3, hold_min_s=2e-3, seed=9)])
    out = drive(path, n)
    assert sorted(serial(f) for f in out) == list(range(n))  # nothing lost or added
    order = np.array([serial(f) for f in out])
    # overtaken = released after a frame submitted later than it
    overtaken = int(np.sum(order < np.maximum.accumulate(order)))
    held = path.impairments[0].n_modified  # type: ignore[attr-defined]
    assert_in_binomial_ci(held, n, p)
    # only held frames can be overtaken, and a hold of >= 2 periods almost always is (not
    # only if the next frames are held for longer still)
    assert 0.97 * held <= overtaken <= held


def test_corruption_flips_exactly_k_bits_and_e2e_crc_catches_it() -> None:
    e2e = pytest.importorskip("canbrake.bus.e2e")
    # CRC-8 SAE J1850 (0x1D, primitive, period 255) catches every 1- and 2-bit error in a
    # frame this short; it does not contain (x + 1), so some 3-bit errors escape (~1/256).
    for k_bits in (1, 2):
        imp = Corrupt(k_bits, seed=k_bits)
        for k in range(300):
            payload = bytearray(k.to_bytes(8, "big"))
            payload[1] = k % 15
            e2e.protect(0x0101, payload)
            f = TxFrame(0x101, False, bytes(payload), 8, "ecu1", 0.0, 0.0)
            (g,) = imp.apply(f)
            flipped = sum(bin(a ^ b).count("1") for a, b in zip(payload, g.data))
            assert flipped == k_bits and g.dlc == 8 and len(g.data) == 8 and g.corrupted
            assert not e2e.check_crc(0x0101, g.data)


def test_corruption_bit_positions_are_uniform() -> None:
    imp = Corrupt(1, seed=12)
    counts = np.zeros(64)
    for _ in range(6400):
        (g,) = imp.apply(TxFrame(0x1, False, bytes(8), 8, "a", 0.0, 0.0))
        counts[int.from_bytes(g.data, "big").bit_length() - 1] += 1
    assert stats.chisquare(counts).pvalue > ALPHA


# --------------------------------------------------------------------------------------------
# guarantees of the send path


SPECS = [
    {"type": "loss", "probability": 0.1},
    {"type": "gilbert_elliott", "p_gb": 0.05, "p_bg": 0.3},
    {"type": "jitter", "distribution": "exponential", "shift_s": 1e-4, "scale_s": 5e-4},
    {"type": "delay", "delay_s": 1.5e-3},
    {"type": "duplicate", "probability": 0.1, "gap_s": 3e-4},
    {"type": "reorder", "probability": 0.1, "hold_max_s": 4e-3},
    {"type": "corrupt", "probability": 0.05, "n_bits": 2},
]


def _sequence(seed: int, node: str = "ecu1", n: int = 2000) -> list[tuple]:
    path = build_impairments(SPECS, seed, node)
    return [(serial(f), f.t_release_s, f.data, f.duplicate) for f in drive(path, n, sender=node)]


def test_same_seed_same_sequence_different_seed_different() -> None:
    assert _sequence(42) == _sequence(42)
    assert _sequence(42) != _sequence(43)
    assert _sequence(42, "ecu1") != _sequence(42, "ecu2")


def test_seeds_do_not_depend_on_build_order() -> None:
    a1 = build_impairments(SPECS, 7, "ecu1")
    a2 = build_impairments(SPECS, 7, "ecu2")
    b2 = build_impairments(SPECS, 7, "ecu2")
    b1 = build_impairments(SPECS, 7, "ecu1")
    for x, y, node in ((a1, b1, "ecu1"), (a2, b2, "ecu2")):
        sx = [(serial(f), f.t_release_s) for f in drive(x, 500, sender=node)]
        sy = [(serial(f), f.t_release_s) for f in drive(y, 500, sender=node)]
        assert sx == sy
    s1 = derive_seed(7, "tx", "ecu1", 0).generate_state(4)
    assert np.array_equal(s1, derive_seed(7, "tx", "ecu1", 0).generate_state(4))
    assert not np.array_equal(s1, derive_seed(7, "rx", "ecu1", 0).generate_state(4))


def test_never_released_early_and_lost_never_released() -> None:
    path = build_impairments(SPECS, 5, "ecu1")
    rng = np.random.default_rng(0)
    submitted, dropped, released = 0, set(), []
    t = 0.0
    for k in range(3000):
        t += 1e-3
        out = path.submit(frame(k, t))
        submitted += 1
        if not out:
            dropped.add(k)
        t_now = t + rng.uniform(0, 3e-3)  # release at irregular times
        for f in path.release(t_now):
            assert f.t_release_s <= t_now
            assert f.t_release_s >= f.t_submit_s + 1.5e-3 + 1e-4  # delay + jitter floor
            released.append(f)
    for f in path.release(math.inf):
        released.append(f)
    got = {serial(f) for f in released if not f.corrupted}
    assert not (got & dropped)
    assert {serial(f) for f in released if not f.corrupted} | dropped <= set(range(3000))
    c = path.counters()
    assert c["submitted"] == submitted and c["held"] == 0
    assert c["released"] == len(released) == submitted - c["dropped"] + c["duplicated"]


def test_release_order_is_release_time_order() -> None:
    path = build_impairments(SPECS, 9, "ecu1")
    out = drive(path, 2000)
    times = [f.t_release_s for f in out]
    assert times == sorted(times)


def test_start_stop_window_is_respected() -> None:
    imp = BernoulliLoss(1.0, selector=Selector(start_s=1.0, stop_s=2.0), seed=0)
    path = SendPath([imp])
    out = drive(path, 3000, dt=1e-3)
    t_sent = np.array([f.t_submit_s for f in out])
    assert len(out) == 2000
    assert not np.any((t_sent >= 1.0) & (t_sent < 2.0))
    assert imp.n_matched == imp.n_dropped == 1000


def test_selectors_ids_and_senders() -> None:
    path = build_impairments([{"type": "delay", "delay_s": 1.0, "ids": [0x200]},
                              {"type": "loss", "probability": 1.0, "senders": ["ecu2"]}],
                             0, "ecu1")
    assert len(path.impairments) == 1  # the ecu2 loss is not on ecu1's send path
    (f,) = path.submit(frame(0, 0.0, ident=0x200))
    (g,) = path.submit(frame(1, 0.0, ident=0x101))
    assert f.t_release_s == 1.0 and g.t_release_s == 0.0
    assert [serial(x) for x in path.release(0.5)] == [1]
    assert [serial(x) for x in path.release(1.0)] == [0]


def test_silent_node_window() -> None:
    specs = [{"type": "silent", "senders": ["ecu3"], "start_s": 1.0, "stop_s": 2.0}]
    ecu3 = build_impairments(specs, 0, "ecu3")
    ecu1 = build_impairments(specs, 0, "ecu1")
    assert ecu1.impairments == () and len(ecu3.impairments) == 1
    out = drive(ecu3, 3000, sender="ecu3")
    assert len(out) == 2000
    assert all(not 1.0 <= f.t_submit_s < 2.0 for f in out)


def test_babbler_rate_window_and_send_path() -> None:
    b = Babbler("babbler", 0x000, 1000.0, start_s=1.0, stop_s=3.0)
    frames = []
    for k in range(1, 1001):  # pull at irregular 10 ms steps; (t_from, t_to] partitions time
        frames += b.frames_due((k - 1) * 0.01 - 0.003 * (k % 2), k * 0.01 - 0.003 * ((k + 1) % 2))
    frames += b.frames_due(10.0 - 0.003, 20.0)
    times = np.array([f.t_submit_s for f in frames])
    assert len(frames) == 2000  # exactly rate x window, start inclusive, stop exclusive
    assert times[0] == 1.0 and times[-1] < 3.0 and np.all(np.diff(times) > 0)
    assert np.allclose(np.diff(times), 1e-3)
    path = build_impairments([{"type": "babble", "sender": "babbler", "arbitration_id": 0,
                               "rate_hz": 500, "start_s": 0.1, "stop_s": 0.2,
                               "data_hex": "DEADBEEF", "dlc": 4}], 0, "babbler")
    out = path.release(0.151)
    assert len(out) == 26 and out[0].data == bytes.fromhex("DEADBEEF")  # 0.100 .. 0.150
    assert len(path.release(1.0)) == 24
    assert babbling_nodes([{"type": "babble", "sender": "x", "arbitration_id": 1,
                            "rate_hz": 1}, {"type": "loss", "probability": 0.1}]) == ["x"]


def test_babbling_idiot_starves_the_bus_in_the_timing_model() -> None:
    """Glue of both modules: babble frames at id 0 take the bus from a 0x100 sender."""
    babbler = build_impairments([{"type": "babble", "sender": "bab", "arbitration_id": 0,
                                  "rate_hz": 4000, "start_s": 0.05, "stop_s": 0.1}], 0, "bab")
    ecu = build_impairments([], 0, "ecu1")
    bus = BusTimingModel(500_000)
    for k in range(151):
        t = k * 1e-3  # each step: new frames, release what is due by t, bus up to t
        ecu.submit(frame(k, t, ident=0x100))
        for path, node in ((babbler, "bab"), (ecu, "ecu1")):
            for f in path.release(t):
                bus.submit(node, f.arbitration_id, f.is_extended, f.dlc, f.data, f.t_release_s)
        bus.advance(t)
    bus.advance(1.0)
    # 4000 x 270 us = 1.08 s of frames per second: the babbler alone saturates the bus
    assert bus.load_stats(1e-3, 0.06, 0.1).mean_busy == pytest.approx(1.0)
    assert bus.latency_stats(0x100).max_s > 0.04  # starved while it babbles...
    assert bus.latency_stats(0x100).n_pending == 0  # ...and served after it stops


def test_exempt_ids_skip_the_chain() -> None:
    path = build_impairments([{"type": "loss", "probability": 1.0}], 0, "ecu1",
                             exempt_ids=[0x7F0])
    assert path.submit(frame(0, 0.0, ident=0x101)) == []
    assert len(path.submit(frame(1, 0.0, ident=0x7F0))) == 1


def test_per_link_impairment_runs_on_the_receive_path_only() -> None:
    specs = [{"type": "loss", "probability": 1.0, "receivers": ["ecu2"], "senders": ["ecu1"]}]
    assert build_impairments(specs, 0, "ecu1").impairments == ()  # not on any send path
    assert build_impairments(specs, 0, "ecu3", direction="rx").impairments == ()
    rx2 = build_impairments(specs, 0, "ecu2", direction="rx")
    assert rx2.submit(frame(0, 0.0, sender="ecu1")) == []  # ecu2 never hears ecu1
    assert len(rx2.submit(frame(1, 0.0, sender="ecu4"))) == 1


def test_message_send_path_speaks_can_message() -> None:
    can = pytest.importorskip("can")
    path = MessageSendPath(build_impairments([{"type": "delay", "delay_s": 1e-3, "ids": [0x2]},
                                              {"type": "corrupt", "ids": [0x3]}], 0, "ecu1"))
    m1 = can.Message(arbitration_id=0x1, is_extended_id=False, data=b"\x01\x02")
    m2 = can.Message(arbitration_id=0x2, is_extended_id=False, data=b"\x03")
    m3 = can.Message(arbitration_id=0x3, is_extended_id=False, data=b"\x00\x00")
    assert path.submit(m1, 0.0) == [m1] and path.submit(m1, 0.0)[0] is m1
    assert path.submit(m2, 0.0) == []
    (c,) = path.submit(m3, 0.0)
    assert c is not m3 and c.dlc == 2 and bytes(c.data) != b"\x00\x00"
    assert path.release(1e-3) == [m2]


# --------------------------------------------------------------------------------------------
# configuration


class _Bus(BaseModel):
    impairments: list[ImpairmentSpec] = []


def test_spec_union_parses_every_type() -> None:
    bus = _Bus.model_validate({"impairments": SPECS + [
        {"type": "silent", "senders": ["ecu3"], "start_s": 5, "stop_s": 6},
        {"type": "babble", "sender": "x", "arbitration_id": 0, "rate_hz": 1000},
        {"type": "jitter", "distribution": "uniform", "low_s": 0, "high_s": 1e-3},
        {"type": "jitter", "distribution": "normal", "mean_s": 0, "std_s": 1e-3},
    ]})
    kinds = [type(s).__name__ for s in bus.impairments]
    assert kinds[:3] == ["LossSpec", "GilbertElliottSpec", "JitterSpec"]
    assert len(build_impairments(bus.impairments, 1, "x").sources) == 1
    assert _Bus.model_validate(bus.model_dump()) == bus  # round trip


@pytest.mark.parametrize("spec, message", [
    ({"type": "loss", "probability": 1.5}, "probability in [0, 1]"),
    ({"type": "gilbert_elliott", "p_gb": -0.1, "p_bg": 0.5}, "probability in [0, 1]"),
    ({"type": "delay", "delay_s": -1e-3}, "time >= 0"),
    ({"type": "delay", "delay_s": float("nan")}, "finite"),
    ({"type": "delay", "delay": 1e-3}, "delay_s"),
    ({"type": "delay", "delay_s": 1e-3, "start_s": 2, "stop_s": 1}, "stop_s"),
    ({"type": "teleport"}, "does not match any of the expected tags"),
    ({"type": "jitter", "distribution": "normal", "mean_s": 1e-3}, "missing std_s"),
    ({"type": "jitter", "distribution": "uniform", "low_s": 0, "high_s": 1, "std_s": 1},
     "not used by jitter distribution"),
    ({"type": "silent"}, "silent needs senders"),
    ({"type": "loss", "probability": 0.1, "ids": []}, "empty list"),
    ({"type": "babble", "sender": "x", "arbitration_id": 0x800, "rate_hz": 10}, "is_extended"),
    ({"type": "babble", "sender": "x", "arbitration_id": 1, "rate_hz": 0}, "greater than 0"),
    ({"type": "babble", "sender": "x", "arbitration_id": 1, "rate_hz": 1, "data_hex": "00"},
     "dlc is 8"),
])
def test_spec_validation_messages(spec: dict, message: str) -> None:
    with pytest.raises(ValidationError, match=re_escape(message)):
        _Bus.model_validate({"impairments": [spec]})


def re_escape(s: str) -> str:
    import re

    return re.escape(s)


def test_constructor_validation() -> None:
    with pytest.raises(ValueError, match="probability"):
        BernoulliLoss(2.0)
    with pytest.raises(ValueError, match="delay_s"):
        Delay(-1.0)
    with pytest.raises(ValueError, match="seed"):
        BernoulliLoss(0.1, seed=-1)
    with pytest.raises(ValueError, match="rate_hz"):
        Babbler("b", 1, 0.0)
    with pytest.raises(ValueError, match="direction"):
        build_impairments([], 0, "ecu1", direction="up")  # type: ignore[arg-type]


# ---------------------------------------------------------------- fates: the batch engine's form of submit
_CHAINS = [
    [{"type": "loss", "probability": 0.3}, {"type": "delay", "delay_s": 0.0037}],
    [{"type": "delay", "delay_s": 0.002}, {"type": "loss", "probability": 0.5},
     {"type": "jitter", "distribution": "uniform", "low_s": 0.0, "high_s": 0.004}],
    [{"type": "jitter", "distribution": "normal", "mean_s": 0.001, "std_s": 0.002},
     {"type": "loss", "probability": 0.2, "ids": [0x201], "start_s": 0.5, "stop_s": 1.5}],
    [{"type": "jitter", "distribution": "exponential", "shift_s": 0.0005, "scale_s": 0.003},
     {"type": "delay", "delay_s": 0.01, "senders": ["ecu2"]}],
]


@pytest.mark.parametrize("chain", _CHAINS)
@pytest.mark.parametrize("seed", [1, 99])
def test_fates_are_the_release_times_submit_schedules(chain, seed):
    """SendPath.fates (the batch engine's whole-run form) gives, frame for frame, the release time
    the same chain's submit() schedules one frame at a time (inf where submit loses it), from the
    same generators in the same order. A frame of an exempt identifier skips the chain."""
    a = build_impairments(chain, seed, "ecu1", exempt_ids=[0x7F0])
    b = build_impairments(chain, seed, "ecu1", exempt_ids=[0x7F0])
    n = 1500
    t = np.repeat(np.arange(n) * 0.001, 2)
    t[1::2] += 0.0005
    ids = np.tile([0x101, 0x201], n)
    ids[::97] = 0x7F0
    rel = a.fates(t, ids)
    got: dict[int, float] = {}
    for k, (ts, i) in enumerate(zip(t.tolist(), ids.tolist())):
        for f in b.submit(TxFrame(i, False, b"", 8, "ecu1", ts, ts, origin=k)):
            got[f.origin] = f.t_release_s
    ref = np.array([got.get(k, math.inf) for k in range(2 * n)])
    assert np.array_equal(rel, ref)
    assert np.isfinite(rel[::97]).all() and np.array_equal(rel[::97], t[::97])
    # the generators are left where single draws leave them: later frames agree too
    f_a = a.fates(np.array([2.0, 2.001]), np.array([0x101, 0x201]))
    f_b = [b.submit(TxFrame(0x101, False, b"", 8, "ecu1", x, x, origin=x)) for x in (2.0, 2.001)]
    assert f_a.tolist() == [fs[0].t_release_s if fs else math.inf for fs in f_b]


def test_fates_refuse_what_they_cannot_reproduce():
    path = build_impairments([{"type": "duplicate", "probability": 0.5}], 1, "ecu1")
    with pytest.raises(NotImplementedError):
        path.fates(np.zeros(3), np.full(3, 0x101))
