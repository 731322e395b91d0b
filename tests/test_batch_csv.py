"""canbrake._batch.csv_bytes (the batch engine's traces, compiled) against Python's "%d" / "%.9g"
text and csv.writer with "%.9g" floats; its fast "%.9g" (canbrake._g9.g9) against Python's,
also on near-ties and powers of ten."""
from __future__ import annotations

import csv
import io

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from canbrake._batch import csv_bytes
from canbrake._g9 import f6, g9, i64


def csv_block(rows: np.ndarray, last_int: bool = False) -> str:
    """The reference: the first column (and with ``last_int`` the last) as ``"%d" % int(v)``,
    the others as ``"%.9g" % v``, csv lines ending ``\\r\\n``."""
    lines = []
    for r in rows.tolist():
        cells = [("%d" % int(v)) if j == 0 or (last_int and j == len(r) - 1) else "%.9g" % v
                 for j, v in enumerate(r)]
        lines.append(",".join(cells) + "\r\n")
    return "".join(lines)


def _rows(seed: int, n: int, m: int) -> np.ndarray:
    rng = np.random.default_rng(seed)
    a = rng.normal(size=(n, m)) * 10.0 ** rng.integers(-12, 13, size=(n, m))
    a[:, 0] = np.arange(n)
    a[:, -1] = rng.integers(0, 20, size=n)
    special = [np.nan, np.inf, -np.inf, -0.0, 0.0, 1e-320, 5e-324, 1.7976931348623157e308, 0.1, 1 / 3, 123456789.5]
    for r, x in enumerate(special):
        a[r % n, 1 + r % (m - 2)] = x
    return a


@pytest.mark.parametrize("last_int", [False, True])
@pytest.mark.parametrize("shape", [(1, 3), (7, 5), (500, 40)])
def test_csv_bytes_is_csv_block(shape: tuple[int, int], last_int: bool) -> None:
    a = _rows(shape[0] * 31 + shape[1], *shape)
    assert csv_bytes(a, last_int) == csv_block(a, last_int).encode("ascii")


def test_csv_bytes_is_csv_writer() -> None:
    a = _rows(3, 50, 6)
    buf = io.StringIO(newline="")
    w = csv.writer(buf)
    for r in a:
        w.writerow([int(r[0]), *(f"{x:.9g}" for x in r[1:-1]), int(r[-1])])
    assert csv_bytes(a, True) == buf.getvalue().encode("ascii")


def test_csv_bytes_edges() -> None:
    assert csv_bytes(np.zeros((0, 4))) == csv_block(np.zeros((0, 4))).encode() == b""
    big = np.array([[1e19, 2.0], [-3e18, -1.5], [-0.7, 2.5]])  # ticks beyond long long; int() truncates
    assert csv_bytes(big) == csv_block(big).encode()
    for bad, err in (([[np.nan, 1.0]], ValueError), ([[np.inf, 1.0]], OverflowError),
                     ([[1.0, np.nan]], ValueError)):
        arr = np.asarray(bad)
        last = bad[0][0] == 1.0
        with pytest.raises(err):
            csv_block(arr, last)
        with pytest.raises(err):
            csv_bytes(arr, last)


def _g9_cases(seed: int) -> np.ndarray:
    rng = np.random.default_rng(seed)
    n = 20000
    wide = rng.normal(size=n) * 10.0 ** rng.integers(-20, 35, size=n)
    # nine-digit numbers and a half (exact ties where representable), and their neighbours
    ties = (rng.integers(10**8, 10**9, size=n) + 0.5) * 10.0 ** rng.integers(-16, 26, size=n)
    p = 10.0 ** np.arange(-20, 35)
    edges = np.concatenate([p, np.nextafter(p, 0), np.nextafter(p, np.inf), p * (1 - 5e-10), p * (1 + 5e-10),
                            999999999.5 * p / 1e9, 999999999.4999999 * p / 1e9])
    near = np.concatenate([ties, np.nextafter(ties, 0), np.nextafter(ties, np.inf), ties * (1 + 1e-15)])
    trace = rng.normal(size=n) * np.array([1e-3, 1.0, 30.0, 5e4])[rng.integers(0, 4, size=n)]
    x = np.concatenate([wide, near, edges, trace])
    return np.concatenate([x, -x])


@pytest.mark.parametrize("seed", [1, 2, 3])
def test_g9_is_pythons(seed: int) -> None:
    x = _g9_cases(seed)
    got = [g9(v) for v in x.tolist()]
    wrong = [(v, g) for v, g in zip(x.tolist(), got) if g is not None and g != f"{v:.9g}"]
    assert not wrong, wrong[:5]
    # the fast path serves a trace's values (it defers only near-ties and extreme magnitudes)
    trace = x[-(x.size // 2) - 20000:-(x.size // 2)]
    assert sum(g9(v) is None for v in trace.tolist()) < 10
    # and csv_bytes takes Python's text where it defers
    a = np.column_stack([np.arange(x.size, dtype=float), x])
    assert csv_bytes(a) == csv_block(a).encode("ascii")


def test_g9_specials() -> None:
    for v in (0.0, -0.0, np.nan, -np.nan, np.inf, -np.inf):  # written directly, as Python writes them
        assert g9(v) == f"{v:.9g}"
    for v in (5e-324, 1e-300, 1e300):
        assert g9(v) in (None, f"{v:.9g}")
    assert g9(1.5) == "1.5" and g9(-123456789.25) == "-123456789" and g9(1e-5) == "1e-05"
    assert g9(0.0001) == "0.0001" and g9(123456789012.0) == "1.23456789e+11"


@settings(max_examples=3000, deadline=None)
@given(st.one_of(st.floats(min_value=0.0, max_value=1e13, allow_nan=False),
                 st.floats(min_value=0.0, max_value=1e-3),
                 st.integers(min_value=0, max_value=2 ** 40).map(lambda k: k / 128.0),  # exact ties
                 st.floats(allow_nan=True, allow_infinity=True)))
def test_f6_is_pythons(x: float) -> None:
    """A candump line's time stamp: "%.6f" (python-can's "(%f)") in exact integer arithmetic,
    ties to even as Python's correctly rounded text; None (Python's text) outside [0, 9e12)."""
    got = f6(x)
    if 0.0 <= x < 9e12 and not (x == 0.0 and np.signbit(x)):
        assert got == "%.6f" % x
    else:
        assert got is None


def test_f6_edges() -> None:
    for x, text in ((0.0, "0.000000"), (0.0078125, "0.007812"), (3 / 128, "0.023438"), (1e-20, "0.000000"),
                    (1733.0000005, "1733.000000"), (1.7e9 + 0.25, "1700000000.250000")):
        assert f6(x) == text == "%.6f" % x
    assert f6(-0.0) is None and f6(-1.0) is None and f6(float("nan")) is None and f6(1e13) is None


@given(st.integers(min_value=-2 ** 63, max_value=2 ** 63 - 1))
def test_i64_is_pythons(v: int) -> None:
    assert i64(v) == "%d" % v
