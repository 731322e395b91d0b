"""The compiled trace row and histogram batch (canbrake.nodes._trace) against the library and
the Python they replace: csv.writer with floats as f"{v:.9g}", LogHistogram.add one by one."""
from __future__ import annotations

import csv
import io
import math
import os

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from canbrake.nodes._trace import csv_row
from canbrake.nodes.base import CsvTrace, LogHistogram

values = st.one_of(
    st.floats(allow_nan=True, allow_infinity=True), st.floats(-1e-300, 1e-300), st.integers(-2**70, 2**70),
    st.booleans(), st.floats(allow_nan=True).map(np.float64), st.integers(-2**63, 2**63 - 1).map(np.int64),
    st.integers(-2**31, 2**31 - 1).map(np.int32), st.booleans().map(np.bool_))


def csv_module(row):
    buf = io.StringIO()
    csv.writer(buf).writerow([f"{v:.9g}" if isinstance(v, float) else v for v in row])
    return buf.getvalue()


@settings(max_examples=500, deadline=None)
@given(st.lists(values, max_size=40))
def test_row_equals_the_csv_module(row):
    assert csv_row(row) == csv_module(row)


def test_other_values_are_left_to_the_csv_writer(tmp_path):
    assert csv_row([1.0, "x"]) is None and csv_row([None]) is None
    t = CsvTrace(tmp_path / "t.csv", ["a", "b", "c"])
    t.append([1.5, "x,y", None])
    t.append([0.1, 2, True])
    t.close()
    assert (tmp_path / "t.csv").read_bytes() == b'a,b,c\r\n1.5,"x,y",\r\n0.100000000,2,True\r\n'.replace(
        b"0.100000000", b"0.1")


class _PyHist:
    """LogHistogram.add as it was in Python (canbrake.nodes.base, before it was compiled): the oracle."""

    LO_S, HI_S = 1e-7, 1e4

    def __init__(self, ratio: float) -> None:
        self.RATIO = ratio
        self._log_ratio = float(np.log(ratio))
        self.bins = int(np.ceil(np.log(self.HI_S / self.LO_S) / self._log_ratio)) + 2
        self.counts = [0] * self.bins
        self.n, self.max, self.total = 0, 0.0, 0.0

    def add(self, x: float) -> None:
        self.n += 1
        self.total += x
        if x > self.max:
            self.max = x
        if x <= self.LO_S:
            self.counts[0] += 1
        else:
            i = 1 + int(math.log(x / self.LO_S) / self._log_ratio)
            self.counts[i if i < self.bins else self.bins - 1] += 1


def _state(h) -> tuple:
    return h.counts, h.n, h.total, h.max, h.bins, h.RATIO


@settings(max_examples=200, deadline=None)
@given(st.lists(st.one_of(st.floats(0, 1e5), st.floats(0, 1e-6), st.sampled_from([0.0, 1e-7, 1e4, 2e4])),
                max_size=60), st.sampled_from([1.001, 1.01]))
def test_add_many_equals_add_one_by_one(xs, ratio):
    a, b, ref = LogHistogram(ratio), LogHistogram(ratio), _PyHist(ratio)
    for x in xs:
        a.add(x)
        ref.add(x)
    b.add_many(xs)
    assert _state(a) == _state(b) == _state(ref)
    assert math.isclose(a.quantile(0.99), b.quantile(0.99)) or a.n == 0
    assert a.figures()["n"] == len(xs) and a.figures()["max_s"] == max(xs, default=0.0)


def test_a_duration_that_is_not_a_number_is_refused_and_not_counted():
    h = LogHistogram()
    h.add(0.5)
    for bad in (math.nan, math.inf):
        with pytest.raises((ValueError, OverflowError)):
            h.add(bad)
    assert h.n == 1 and h.total == 0.5 and sum(h.counts) == 1


finite_or_not = st.one_of(st.floats(allow_nan=True, allow_infinity=True), st.floats(-1e-300, 1e-300),
                          st.just(-0.0), st.integers(-2**52, 2**52).map(float))


@settings(max_examples=300, deadline=None)
@given(st.integers(0, 6), st.integers(2, 8), st.booleans(), st.data())
def test_block_equals_percent_formatting(n, m, last_int, data):
    """csv_bytes (the batch engine's traces, canbrake._batch) against the "%d" / "%.9g" formatting
    it replaced."""
    from canbrake._batch import csv_bytes

    rows = np.array([[float(data.draw(st.integers(0, 10**9)))]
                     + [data.draw(finite_or_not) for _ in range(m - 2)]
                     + [float(data.draw(st.integers(0, 99))) if last_int else data.draw(finite_or_not)]
                     for _ in range(n)], dtype=float).reshape(n, m)
    cells = ["%d"] + ["%.9g"] * (m - 1)
    if last_int:
        cells[-1] = "%d"
    fmt = ",".join(cells) + "\r\n"
    assert csv_bytes(rows, last_int).decode("ascii") == "".join(fmt % tuple(r) for r in rows.tolist())


def test_csv_dict_row_is_csv_row_of_the_values_by_name():
    """csv_dict_row (an ECU's trace row: diagnostics by name) gives csv_row of the row built with
    dict.get, missing names as the default; None where csv_row takes the csv writer."""
    import math

    from canbrake.nodes._trace import csv_dict_row

    diag = {"a": 1.5, "b": 2, "c": np.float64(-0.25), "skip": 9.0}
    names = ("c", "missing", "a", "b")
    want = csv_row([7, 1.25, *[diag.get(n, math.nan) for n in names], math.inf, 3])
    assert csv_dict_row([7, 1.25], diag, names, math.nan, [math.inf, 3]) == want
    assert csv_dict_row([7], {"a": "text"}, ("a",), math.nan, []) is None


@settings(max_examples=300, deadline=None)
@given(st.lists(values, max_size=5), st.dictionaries(st.sampled_from("abcdefgh"), st.one_of(values, st.none())),
       st.lists(st.sampled_from("abcdefghij"), max_size=40), st.lists(values, max_size=5))
def test_csv_dict_row_equals_the_csv_module(head, diag, names, tail):
    """csv_dict_row (made in one buffer, no list; beyond 31 values in a heap buffer) against
    csv.writer over head + the values by name (NaN where missing) + tail; None where a value
    (here None) is left to the csv writer."""
    from canbrake.nodes._trace import csv_dict_row

    row = [*head, *[diag.get(n, math.nan) for n in names], *tail]
    got = csv_dict_row(head, diag, tuple(names), math.nan, tail)
    assert got == (None if any(v is None for v in row) else csv_module(row))


@settings(max_examples=300, deadline=None)
@given(st.lists(st.lists(finite_or_not, min_size=0, max_size=8), min_size=1, max_size=6), st.data())
def test_pick_row_equals_the_row_list(cols, data):
    """csv_pick_row against the list it replaces: the values picked from one concatenation,
    made Python floats, the flags as ints, written by csv_row."""
    from canbrake.nodes._trace import csv_pick_row

    arrays = [np.asarray(c, dtype=float) for c in cols]
    sizes = [a.size for a in arrays]
    total = sum(sizes)
    picks = data.draw(st.lists(st.integers(0, max(total - 1, 0)), max_size=30)) if total else []
    flags = data.draw(st.one_of(st.none(), st.lists(st.booleans(), max_size=5).map(lambda b: np.asarray(b, bool))))
    at = data.draw(st.integers(0, len(picks)))
    head = data.draw(st.lists(st.one_of(st.integers(-10**6, 10**6), finite_or_not), min_size=1, max_size=4))
    start = np.concatenate([[0], np.cumsum(sizes)])
    which = np.searchsorted(start, picks, side="right") - 1
    plan = np.ascontiguousarray(np.column_stack([which, np.asarray(picks) - start[which]]), dtype=np.intp) \
        if picks else np.zeros((0, 2), dtype=np.intp)
    values = np.concatenate(arrays).take(np.asarray(picks, dtype=np.intp)).tolist()
    expected = head + values[:at] + ([int(x) for x in flags] if flags is not None else []) + values[at:]
    assert csv_pick_row(csv_row(head)[:-2], arrays, plan, flags, at) == csv_row(expected)


def test_pick_row_converts_other_arrays_and_refuses_a_stale_plan():
    from canbrake.nodes._trace import csv_pick_row

    plan = np.array([[0, 1], [1, 0], [2, 2]], dtype=np.intp)
    ints, bools, strided = np.array([3, 4]), np.array([True]), np.arange(6.0)[::2]
    assert csv_pick_row("7", [ints, bools, strided], plan, None, 0) == "7,4,1,4\r\n"
    assert csv_pick_row("7", [ints, bools, strided], plan, np.array([True, False]), 1) == "7,4,1,0,1,4\r\n"
    assert csv_pick_row("7", [ints, bools], plan, None, 0) is None            # no array 2
    assert csv_pick_row("7", [ints, bools, strided[:2]], plan, None, 0) is None  # element 2 of 2


@settings(max_examples=200, deadline=None)
@given(st.lists(st.tuples(st.integers(0, 2**70), st.one_of(st.floats(0, 1e5), st.floats(0, 1e-6), st.just(0.0))),
                max_size=20))
def test_add_bits_equals_add_per_set_bit(calls):
    from canbrake.nodes._trace import hist_add_bits

    n = 71
    a, b = [_PyHist(1.01) for _ in range(n)], [LogHistogram(1.01) for _ in range(n)]
    for bits, x in calls:
        for s in range(n):
            if bits >> s & 1:
                a[s].add(x)
        hist_add_bits(b, bits, x)
    assert [(h.counts, h.n, h.total, h.max) for h in a] == [(h.counts, h.n, h.total, h.max) for h in b]


def test_a_node_process_trace_row_goes_to_the_os_at_once(tmp_path):
    """Outside buffered_traces (a node process) CsvTrace.row_fd is the file's descriptor and a
    row written there with write_text is in the file at once, after the header, in order with
    rows appended the csv writer's way; inside, rows stay in the buffer (row_fd -1)."""
    from canbrake.nodes._trace import write_text
    from canbrake.nodes.base import buffered_traces

    t = CsvTrace(tmp_path / "t.csv", ["a", "b"])
    fd = t.row_fd()
    assert fd >= 0
    write_text(fd, csv_row([1, 0.5]))
    assert (tmp_path / "t.csv").read_bytes() == b"a,b\r\n1,0.5\r\n"  # no flush needed
    t.append([2, "x,y"])  # the csv writer's path, flushed: after it
    write_text(fd, csv_row([3, 1e-9]))
    t.close()
    assert (tmp_path / "t.csv").read_bytes() == b'a,b\r\n1,0.5\r\n2,"x,y"\r\n3,1e-09\r\n'
    r, w = os.pipe()
    os.close(r)
    try:
        with pytest.raises(OSError):  # EPIPE: an error of the write is an OSError, as the file's
            write_text(w, "4,4\r\n")
    finally:
        os.close(w)
    with buffered_traces():
        u = CsvTrace(tmp_path / "u.csv", ["a"])
        assert u.row_fd() == -1
        u.close()
