"""Defects found trying canbrake as a user (issue 28, "found this turn" 6, 7 and 9): log formats
on any channel name, a user's controller by name, the papers' headline metrics in summary.json."""
from __future__ import annotations

import collections

import can
import pytest

from canbrake.run import choose_bus, run_scenario
from canbrake.scenario import load_scenario

from conftest import CASE1, SCENARIOS

SEGMENTED = SCENARIOS / "chen2023_case1_segmented.yaml"
NUMBERED = ["asc", "blf", "trc", "mf4"]


def _asammdf() -> bool:
    try:
        import asammdf  # noqa: F401
    except ImportError:
        return False
    return True


def _file_channel(fmt: str, channel: int) -> int:
    """The channel number written in the file, from the one python-can's reader gives back: the
    ASC and BLF readers subtract 1 (python-can counts from 0), the TRC and MF4 readers do not."""
    return channel + 1 if fmt in ("asc", "blf") else channel


def _skip_without_asammdf(fmt: str) -> None:
    if fmt == "mf4" and not _asammdf():
        pytest.skip("asammdf not installed (pip install 'canbrake[mf4]')")


# ------------------------------------------------------------------ 6. log formats, channel numbers
@pytest.mark.parametrize("channel", ["train999", "train", "cb4242-0a1962"])
@pytest.mark.parametrize("fmt", NUMBERED)
def test_numbered_formats_write_channel_1_whatever_the_channel_name(tmp_path, fmt, channel):
    """One bus is CAN 1 in .asc/.blf/.trc/.mf4, whether the channel's name ends in digits or not
    (python-can's writers would read ``train999`` as channel 999: MF4's uint8 overflowed)."""
    _skip_without_asammdf(fmt)
    scn = load_scenario(CASE1, overrides={"duration_s": 0.003, "bus.log_format": fmt})
    s = run_scenario(scn, tmp_path / "r", backend="inprocess", channel=channel, plots=False)
    assert s["status"] == "ok", s.get("message")
    msgs = list(can.LogReader(str(tmp_path / "r" / f"frames.{fmt}")))
    assert len(msgs) > 20
    assert {_file_channel(fmt, m.channel) for m in msgs} == {1}
    if fmt == "asc":  # the channel column of the file itself
        rows = [ln.split() for ln in (tmp_path / "r" / "frames.asc").read_text().splitlines()]
        assert {r[1] for r in rows if len(r) > 3 and r[2] == "10"} == {"1"}


@pytest.mark.parametrize("fmt", NUMBERED)
def test_bus_segments_are_channels_1_to_n_in_scenario_order(tmp_path, fmt):
    """With bus segments each segment is its own channel, numbered 1..n in the scenario's order
    (``backbone`` 1, ``car1`` 2, ...), the same number in the merged log and the segment's own; the
    summary says which segment is which number."""
    _skip_without_asammdf(fmt)
    scn = load_scenario(SEGMENTED, overrides={"duration_s": 0.02, "bus.log_format": fmt})
    out = tmp_path / "r"
    s = run_scenario(scn, out, backend="inprocess", plots=False)
    assert s["status"] == "ok", s.get("message")
    segs = s["bus_load"]["segments"]
    names = [seg.name for seg in scn.bus.segments]
    assert [segs[n]["channel"] for n in names] == list(range(1, len(names) + 1))
    merged = collections.defaultdict(list)
    for m in can.LogReader(str(out / f"frames.{fmt}")):
        merged[_file_channel(fmt, m.channel)].append(m)
    assert set(merged) == set(range(1, len(names) + 1))
    tol = 1.1e-4 if fmt == "trc" else 1.1e-6  # each format's time resolution (TRC: 0.1 ms)
    for n in names:  # channel k of the merged log is segment k's own log, frame for frame
        own = list(can.LogReader(str(out / segs[n]["log"])))
        assert {_file_channel(fmt, m.channel) for m in own} == {segs[n]["channel"]}, n
        mine = merged[segs[n]["channel"]]
        assert [(m.arbitration_id, bytes(m.data)) for m in mine] == [(m.arbitration_id, bytes(m.data)) for m in own]
        assert max(abs(a.timestamp - b.timestamp) for a, b in zip(mine, own)) <= tol, n


def test_candump_log_names_one_fixed_interface_on_the_memory_buses(tmp_path):
    """frames.log's interface column is ``canbrake0`` on the in-memory, virtual and in-process
    buses, whatever the channel (the CLI passes the random in-memory channel it printed), so the
    README's ``canplayer -I frames.log vcan0=canbrake0`` replays it; SocketCAN keeps its interface."""
    from canbrake.cli import main

    scn = load_scenario(CASE1)
    for backend in ("memory", "virtual", "inprocess"):
        for channel in (None, "train999", "cb4242-0a1962"):
            assert choose_bus(scn, backend, channel).log_channel == "canbrake0", (backend, channel)
    assert choose_bus(scn, "socketcan", "vcan3").log_channel == "vcan3"
    out = tmp_path / "r"
    assert main(["run", str(CASE1), "--bus", "inprocess", "--channel", "train7", "--duration", "0.003",
                 "--no-plots", "--out", str(out)]) == 0
    assert {ln.split()[1] for ln in (out / "frames.log").read_text().splitlines()} == {"canbrake0"}
    assert {m.channel for m in can.LogReader(str(out / "frames.log"))} == {"canbrake0"}
