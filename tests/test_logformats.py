"""Frame logs in the formats CAN tools open (python-can's writers), read back by can.LogReader and
`canbrake decode`; what a lockstep timestamp means; simulation-control frames never in the log."""
from __future__ import annotations

import io
import math
import re

import can
import pytest

from canbrake.analysis.decode import decode_log
from canbrake.bus import dbc
from canbrake.bus.timing import frame_bits
from canbrake.cli import main
from canbrake.nodes.recorder import is_sim_control
from canbrake.run import run_scenario
from canbrake.scenario import load_scenario

from conftest import CASE1

FORMATS = ["log", "asc", "blf", "trc", "mf4"]


def _asammdf() -> bool:
    try:
        import asammdf  # noqa: F401
    except ImportError:
        return False
    return True


@pytest.fixture(scope="module")
def reference_run(tmp_path_factory):
    """20 ms of case 1 in process with the default candump log."""
    out = tmp_path_factory.mktemp("log")
    run_scenario(load_scenario(CASE1, overrides={"duration_s": 0.02}), out, backend="inprocess", plots=False)
    return out


def _body(decoded: str) -> list[str]:
    """Decoded lines without the timestamp and channel columns."""
    return [re.sub(r"^\(\S+\) \S+ ", "", ln) for ln in decoded.splitlines()]


@pytest.mark.parametrize("fmt", FORMATS)
def test_every_format_reads_back(tmp_path, reference_run, fmt):
    if fmt == "mf4" and not _asammdf():
        pytest.skip("asammdf not installed (pip install 'canbrake[mf4]')")
    out = tmp_path / fmt
    scn = load_scenario(CASE1, overrides={"duration_s": 0.02, "bus.log_format": fmt})
    run_scenario(scn, out, backend="inprocess", plots=False)
    path = out / f"frames.{fmt}"
    assert path.exists() and not (fmt != "log" and (out / "frames.log").exists())
    ref = list(can.LogReader(str(reference_run / "frames.log")))
    got = list(can.LogReader(str(path)))
    assert [(m.arbitration_id, bytes(m.data)) for m in got] == [(m.arbitration_id, bytes(m.data)) for m in ref]
    # timestamps survive to each format's resolution (TRC: 0.1 ms)
    tol = 1.1e-4 if fmt == "trc" else 1.1e-6
    assert max(abs(a.timestamp - b.timestamp) for a, b in zip(got, ref)) <= tol
    a, b = io.StringIO(), io.StringIO()
    decode_log(str(path), str(out / "canbrake.dbc"), a)
    decode_log(str(reference_run / "frames.log"), None, b)
    assert _body(a.getvalue()) == _body(b.getvalue()) and len(_body(b.getvalue())) == len(ref)


def test_mf4_without_asammdf_is_one_message(tmp_path, monkeypatch, capsys):
    import builtins

    real = builtins.__import__

    def fake(name, *args, **kwargs):
        if name == "asammdf":
            raise ImportError("no asammdf")
        return real(name, *args, **kwargs)

    monkeypatch.setattr(builtins, "__import__", fake)
    code = main(["run", str(CASE1), "--duration", "0.01", "--bus", "inprocess", "--log-format", "mf4",
                 "--out", str(tmp_path / "r")])
    assert code == 2 and "--log-format: mf4 needs asammdf" in capsys.readouterr().err  # the flag given
    assert not (tmp_path / "r").exists()


def _ticks(frames: list[can.Message]) -> list[tuple[int, can.Message]]:
    """Each frame with the tick of the SYNC before it."""
    k, out = -1, []
    for m in frames:
        if m.arbitration_id == dbc.SYNC_ID:
            k = int.from_bytes(m.data[:4], "little")
        out.append((k, m))
    return out


def test_lockstep_stamps_stay_inside_their_period_on_an_overloaded_bus(tmp_path):
    """Case 1 at 1 ms on 1 Mbit/s needs ~1.4 ms of wire time per period: the stamps are compressed
    into the period instead of running ahead of simulated time."""
    scn = load_scenario(CASE1, overrides={"duration_s": 0.05})
    s = run_scenario(scn, tmp_path, backend="inprocess", plots=False)
    assert s["bus_load"]["bus_load_mean"] > 1.0  # the premise: the traffic does not fit
    dt = scn.control_period_s
    frames = list(can.LogReader(str(tmp_path / "frames.log")))
    stamps = [m.timestamp for m in frames]
    assert stamps == sorted(stamps)
    for k, m in _ticks(frames):
        end = dbc.SYNC_END_TICK
        if k in (-1, end):
            continue
        assert k * dt < m.timestamp <= (k + 1) * dt + 1e-9, (k, m)
    assert stamps[-1] <= scn.duration_s + 1e-3  # a 0.05 s run's log ends at 0.05 s (+ the end SYNC)


def test_lockstep_stamp_is_the_wire_end_time_when_the_traffic_fits(tmp_path):
    """5 ms period at 1 Mbit/s: each SYNC is stamped t_k + its own wire time (actual stuffing),
    REFERENCE right after it."""
    scn = load_scenario(CASE1, overrides={"duration_s": 0.05, "control_period_s": 0.005})
    s = run_scenario(scn, tmp_path, backend="inprocess", plots=False)
    assert s["bus_load"]["bus_load_peak"] < 1.0
    frames = list(can.LogReader(str(tmp_path / "frames.log")))
    bits = lambda m: frame_bits(m.arbitration_id, False, m.dlc, bytes(m.data), stuffing="actual")  # noqa: E731
    for i, m in enumerate(frames[:-1]):
        if m.arbitration_id == dbc.SYNC_ID:
            k = int.from_bytes(m.data[:4], "little")
            t_sync = k * 0.005 + bits(m) / scn.bus.bitrate_bps
            assert m.timestamp == pytest.approx(t_sync, abs=1e-6)
            nxt = frames[i + 1]
            assert nxt.arbitration_id == dbc.REFERENCE_ID
            assert nxt.timestamp == pytest.approx(t_sync + bits(nxt) / scn.bus.bitrate_bps, abs=1e-6)


def test_sim_control_frames_never_in_the_log(tmp_path):
    """An impairment turns the lockstep barrier on (STATE_DONE/CMD_DONE frames on the bus); the log
    holds the same train traffic as without it."""
    base = load_scenario(CASE1, overrides={"duration_s": 0.02})
    plain = run_scenario(base, tmp_path / "plain", backend="inprocess", plots=False)
    imp = load_scenario(CASE1, overrides={"duration_s": 0.02,
                                          "bus.impairments": [{"type": "duplicate", "probability": 0.0}]})
    barrier = run_scenario(imp, tmp_path / "imp", backend="inprocess", plots=False)
    assert barrier["frames"]["by_kind"].get("state_done", 0) > 0  # the barrier ran
    assert plain["frames"]["by_kind"].get("state_done", 0) == 0
    a = [(m.arbitration_id, bytes(m.data)) for m in can.LogReader(str(tmp_path / "plain" / "frames.log"))]
    b = [(m.arbitration_id, bytes(m.data)) for m in can.LogReader(str(tmp_path / "imp" / "frames.log"))]
    assert a == b and not any(is_sim_control(i) for i, _ in b)


def test_decode_hides_sim_control(tmp_path, capsys):
    log = tmp_path / "capture.log"
    with can.Logger(str(log)) as w:
        w.on_message_received(can.Message(timestamp=0.001, arbitration_id=dbc.SYNC_ID, data=b"\0\0\0\0",
                                          is_extended_id=False, channel="vcan0"))
        w.on_message_received(can.Message(timestamp=0.002, arbitration_id=dbc.STATE_DONE_BASE + 1, data=b"\0\0",
                                          is_extended_id=False, channel="vcan0"))
    assert main(["decode", str(log)]) == 0
    assert "STATE_DONE_C1" in capsys.readouterr().out
    assert main(["decode", str(log), "--hide-sim-control"]) == 0
    out = capsys.readouterr().out
    assert "STATE_DONE_C1" not in out and "SYNC" in out


def _model_completions(scn) -> list[tuple[float, int]]:
    """The nominal traffic of ``scn`` fed to a fresh BusTimingModel here, tick by tick (the test's
    own schedule, from the scenario's bus layout): [(t_end_s, arbitration_id)] in bus order."""
    from canbrake.build import bus_layout
    from canbrake.bus.timing import BusTimingModel

    dt, c = scn.control_period_s, scn.ecu.lockstep_deadline * scn.control_period_s
    hb = int(round(scn.ecu.heartbeat_period_s / dt))
    layout = bus_layout(scn)
    model = BusTimingModel(scn.bus.bitrate_bps, stuffing="worst")
    out = []
    for k in range(scn.n_ticks + 1):
        for m in layout.messages:
            sender = "plant" if m.ecu == 0 else f"n{m.ecu}"
            at = {"sync": 0.0, "reference": 0.0, "reference_pos": 0.0, "state": 0.0, "cmd": c,
                  "heartbeat": 0.0 if k % hb == 0 else None}.get(m.kind)
            if at is not None:
                model.submit(sender, m.frame_id, m.extended, m.length, None, k * dt + at)
        out += [(d.t_end_s, d.arbitration_id) for d in model.advance((k + 1) * dt)]
    return out


@pytest.mark.parametrize("period_s", [0.001, 0.005])
def test_timing_model_stamps_are_the_modelled_wire_end_times(tmp_path, period_s):
    """bus.timing: model — each frame is stamped with the modelled end of its transmission: the
    n-th frame of an identifier in the log carries the n-th completion of that identifier on a
    timing model fed here with the scenario's nominal traffic; the log is monotonic and each
    period holds exactly the frames the lockstep delivered in it. At 1 ms the 6 cars' traffic
    does not fit 1 Mbit/s: frames finish periods late on the modelled bus and are stamped then."""
    import csv

    from canbrake.build import bus_layout

    scn = load_scenario(CASE1, overrides={"duration_s": 0.03, "control_period_s": period_s,
                                          "bus.timing": "model", "bus.bitrate_bps": 1_000_000})
    s = run_scenario(scn, tmp_path, backend="inprocess", plots=False)
    assert s["status"] == "ok"
    dt, n = period_s, scn.n_ticks
    done = [(t, aid) for t, aid in _model_completions(scn) if t <= n * dt - dt * 1e-9]  # the run's periods
    frames = [m for m in can.LogReader(str(tmp_path / "frames.log"))][:-1]  # without the end SYNC
    stamps = [m.timestamp for m in frames]
    assert stamps == sorted(stamps)
    layout = bus_layout(scn)
    kinds = {m.frame_id: m.kind for m in layout.messages}
    from_plant = {m.frame_id for m in layout.messages if m.ecu == 0}
    hb = int(round(scn.ecu.heartbeat_period_s / dt))
    per_period = [0] * n
    for aid in {m.arbitration_id for m in frames}:
        got = [m.timestamp for m in frames if m.arbitration_id == aid]
        if kinds[aid] == "sensor":  # local wiring, not on the modelled bus: the period's start
            assert got == pytest.approx([round(t / dt) * dt for t in got], abs=1e-9)
            continue
        ends = [t for t, a in done if a == aid]
        if aid in from_plant:  # sent in its own period whatever the bus: the model's end if it falls
            want = []          # in that period's window (t_k - e, t_k + T - e], else the period's start
            for k in range(0, n, hb if kinds[aid] == "heartbeat" else 1):
                w = [t for t in ends if k * dt - dt * 1e-9 < t <= (k + 1) * dt - dt * 1e-9]
                want.append(w[0] if w else k * dt)
                per_period[k] += 1
        else:  # an ECU holds each frame until the model has it off the wire: every end is logged
            want = ends
            for t in want:  # in the period whose release window holds the end
                per_period[int(math.ceil(t / dt - (1 - 1e-9)))] += 1
        assert len(got) == len(want), (hex(aid), len(got), len(want))
        assert got == pytest.approx(want, abs=1e-6), hex(aid)
    with open(tmp_path / "bus_load.csv") as f:
        delivered = [int(r["frames"]) for r in csv.DictReader(f)]  # frames the recorder got per period
    assert per_period == delivered
    if period_s == 0.001:  # the premise: the bus falls behind, commands end periods after their own
        states = sum(1 for t, aid in done if kinds[aid] == "state")
        assert states < 6 * n / 2, states  # most STATE frames wait for the bus far beyond their period
    # the same stamps on another backend (the recorder's model replica decides, not the medium)
    run_scenario(scn, tmp_path / "v", backend="virtual", plots=False)
    assert (tmp_path / "v" / "frames.log").read_bytes() == (tmp_path / "frames.log").read_bytes()
