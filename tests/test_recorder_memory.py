"""The recorder's per-period bus statistics stay in constant memory (issue 11)."""
from __future__ import annotations

import csv
import tracemalloc

import numpy as np

from canbrake.nodes.recorder import LoadSeries


def test_load_series_matches_numpy_and_streams_every_period(tmp_path):
    rng = np.random.default_rng(3)
    load = rng.uniform(0.0, 1.3, 5_000)
    s = LoadSeries(tmp_path / "bus_load.csv", dt_s=0.001, window_s=0.1, max_windows=8)
    for i, x in enumerate(load):
        s.add(float(x), 3, i % 2)
    s.close()
    assert s.mean == np.float64(load.mean()) or abs(s.mean - load.mean()) < 1e-12
    assert s.peak == load.max()
    base = load.reshape(-1, 100).mean(axis=1)  # 50 windows of 100 ms
    assert abs(s.peak_window - base.max()) < 1e-12
    # 50 base windows into at most 8 stored ones: merged pairwise until they fit; each stored
    # window is the mean of the m consecutive base windows it covers
    m = int(round(s.window_s / 0.1))
    assert len(s.windows) <= 8 and m in (8, 16)
    np.testing.assert_allclose(s.windows, base[: m * len(s.windows)].reshape(-1, m).mean(axis=1))
    assert m * (len(s.windows) + 1) > 50  # nothing dropped but the incomplete last window
    rows = list(csv.reader(open(tmp_path / "bus_load.csv")))
    assert rows[0] == ["period", "t_s", "bus_load", "frames", "error_frames"] and len(rows) == 1 + load.size
    assert s.errors == load.size // 2


def test_load_series_memory_does_not_grow_with_the_run(tmp_path):
    s = LoadSeries(tmp_path / "bus_load.csv", dt_s=0.001, max_windows=64)
    for _ in range(10_000):
        s.add(0.5, 1, 0)
    tracemalloc.start()
    before = tracemalloc.take_snapshot()
    for _ in range(200_000):
        s.add(0.5, 1, 0)
    grown = sum(st.size_diff for st in tracemalloc.take_snapshot().compare_to(before, "filename"))
    tracemalloc.stop()
    s.close()
    assert grown < 16 * 1024, grown  # bounded; per-period arrays would grow by 3.2 MB here


def test_a_cut_short_log_line_is_trimmed(tmp_path):
    """A write cut short (full disk) must not leave half a frame python-can reads as a shorter one."""
    import can

    from canbrake.nodes.recorder import trim_partial_line

    log = tmp_path / "frames.log"
    log.write_text("(0.000100) canbrake0 010#00000000 R\n(0.000200) canbrake0 141#B1C0AD3B")
    trim_partial_line(log)
    frames = list(can.LogReader(str(log)))
    assert len(frames) == 1 and frames[0].arbitration_id == 0x010
    whole = log.read_bytes()
    trim_partial_line(log)  # a complete file is left alone
    assert log.read_bytes() == whole
