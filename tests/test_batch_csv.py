"""canbrake._batch.csv_bytes (the batch engine's traces, compiled) against the text it replaces,
canbrake.nodes._trace.csv_block, and against csv.writer with "%.9g" floats."""
from __future__ import annotations

import csv
import io

import numpy as np
import pytest

from canbrake._batch import csv_bytes
from canbrake.nodes._trace import csv_block


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
