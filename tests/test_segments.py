"""Bus segments and gateways (issue 15 item 5): forwarding delay, paths across segments, the
in-loop timing, per-segment logs and load, the analysis per segment and end to end."""
from __future__ import annotations

import json
import math
import subprocess
import sys
from pathlib import Path

import can
import pytest

from canbrake.bus.segments import GatewayConfig, SegmentedNetwork, SegmentConfig, Topology
from canbrake.bus.timing import frame_bits
from canbrake.build import bus_layout

ROOT = Path(__file__).resolve().parents[1]
SEGMENTED = ROOT / "scenarios" / "chen2023_case1_segmented.yaml"


def _topo(delays: dict[str, float], rates: dict[str, float], edges: dict[str, tuple[str, str]],
          nodes: dict[str, str]) -> Topology:
    adj: dict[str, list[tuple[str, str]]] = {s: [] for s in rates}
    for gw, (a, b) in edges.items():
        adj[a].append((gw, b))
        adj[b].append((gw, a))
    return Topology(list(rates), dict(rates), {"plant": next(iter(rates)), **nodes}, dict(delays), adj)


def _c(ident: int, dlc: int, rate: float) -> float:
    return frame_bits(ident, False, dlc, stuffing="worst") / rate


@pytest.mark.parametrize("delay_s", [1e-4, 7e-4])
def test_a_gateway_adds_its_forwarding_delay(delay_s: float) -> None:
    """A frame from segment a to segment b on idle buses: it ends on a after C_a, is queued on b
    by the gateway delay_s later and ends there C_b after that."""
    topo = _topo({"g": delay_s}, {"a": 500_000.0, "b": 250_000.0}, {"g": ("a", "b")}, {"x": "a"})
    net = SegmentedNetwork(topo)
    net.submit("x", 0x123, False, 8, None, 0.0, src="a", dests={"b"}, tag="f")
    out = net.advance(0.1)
    ends = {seg: d.t_end_s for seg, d in out}
    assert ends["a"] == pytest.approx(_c(0x123, 8, 500_000))
    assert ends["b"] == pytest.approx(ends["a"] + delay_s + _c(0x123, 8, 250_000))
    assert [d.node for _s, d in out] == ["x", "g"]  # queued on b by the gateway (its own queue)
    assert net.pop_completed() == [("f", pytest.approx(ends["b"]))]


def test_a_frame_between_two_cars_crosses_three_segments() -> None:
    """car1 -> gw1 -> backbone -> gw2 -> car2: the latency is at least the three transmission
    times plus two gateway delays, exactly that on idle buses, and more when each segment's own
    higher-priority traffic is in the way (arbitration per segment)."""
    rates = {"backbone": 500_000.0, "car1": 1_000_000.0, "car2": 250_000.0}
    d1, d2 = 2e-4, 3e-4
    topo = _topo({"gw1": d1, "gw2": d2}, rates, {"gw1": ("car1", "backbone"), "gw2": ("car2", "backbone")},
                 {"ecu1": "car1", "ecu2": "car2"})
    assert [h[1] for h in topo.path("car1", "car2")] == ["gw1", "gw2"]
    floor = sum(_c(0x141, 8, r) for r in rates.values()) + d1 + d2
    idle = SegmentedNetwork(topo)
    idle.submit("ecu1", 0x141, False, 8, None, 0.0, src="car1", dests={"car2"}, tag="s")
    idle.advance(0.1)
    assert idle.pop_completed()[0][1] == pytest.approx(floor)
    busy = SegmentedNetwork(topo)
    busy.submit("ecu1", 0x141, False, 8, None, 0.0, src="car1", dests={"car2"}, tag="s")
    # higher-priority frames queued on each segment just before the frame gets there
    busy.submit("other1", 0x010, False, 8, None, 0.0, src="car1", dests={"car1"}, tag="o1")
    t_bb = _c(0x010, 8, 1e6) + _c(0x141, 8, 1e6) + d1
    busy.submit("plant", 0x011, False, 8, None, t_bb - 1e-6, src="backbone", dests={"backbone"}, tag="o2")
    busy.advance(0.1)
    done = dict(busy.pop_completed())
    # it waits for 0x010 on car1 and for 0x011 (queued 1 us before it) on the backbone
    assert done["s"] == pytest.approx(floor + _c(0x010, 8, 1e6) + _c(0x011, 8, 500_000) - 1e-6)


def test_segmented_timing_latency_is_the_farthest_receiver() -> None:
    """The in-loop replica of the segmented scenario: a car's STATE frame is released when it
    has ended on the last car segment (3 segments, 2 gateways); its brake command stays on the
    car's own segment (one transmission)."""
    from canbrake.bus.schedule import SegmentedBusTiming, timing_of
    from canbrake.scenario import load_scenario

    scn = load_scenario(SEGMENTED)
    t = timing_of(scn, bus_layout(scn))
    assert isinstance(t, SegmentedBusTiming)
    lat_state = t.latency_s(0, "ecu3", 0x143, 0.0)
    floor = _c(0x143, 8, 1e6) * 2 + _c(0x143, 8, 500_000) + 2 * 2e-4
    assert lat_state >= floor - 1e-12
    lat_cmd = t.latency_s(0, "ecu3", 0x83, scn.ecu.lockstep_deadline * scn.control_period_s)
    assert lat_cmd == pytest.approx(_c(0x83, 5, 1e6))  # alone on car3 at the decision instant


def test_segment_config_validation() -> None:
    with pytest.raises(ValueError, match="to itself"):
        GatewayConfig(name="g", segments=("a", "a"))
    with pytest.raises(ValueError):
        SegmentConfig(name="car 1")  # not an interface name


def _run(tmp_path: Path, *args: str) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-m", "canbrake", "run", str(SEGMENTED), *args],
                          capture_output=True, text=True, cwd=ROOT, timeout=300)


@pytest.mark.parametrize("change, message", [
    ("bus.segments.1.nodes=[]", "ECU(s) ecu1 on no segment"),
    ("bus.gateways.0.segments=[car1, nowhere]", "bus.gateways.0.segments"),
    ("mode=realtime", "bus.segments"),
])
def test_bad_segment_configs_are_refused(tmp_path: Path, change: str, message: str) -> None:
    bus = "memory" if change.startswith("mode") else "inprocess"  # inprocess is lockstep only anyway
    r = _run(tmp_path, "--bus", bus, "--set", change, "--out", str(tmp_path / "r"))
    assert r.returncode == 2 and message in r.stderr and "Traceback" not in r.stderr, r.stderr
    assert not (tmp_path / "r").exists()


@pytest.mark.slow
def test_segmented_scenario_runs_on_the_memory_bus(tmp_path: Path) -> None:
    """`canbrake run scenarios/chen2023_case1_segmented.yaml` on the in-memory bus (its default):
    a verdict, frames.log with one interface column per segment that python-can reads, one log
    per segment, per-segment bus load that is the log's wire time over the run, and the same
    frames and signals as the in-process engine."""
    mem = _run(tmp_path, "--duration", "0.3", "--no-plots", "--out", str(tmp_path / "mem"))
    assert mem.returncode == 0, mem.stderr
    s = json.loads((tmp_path / "mem" / "summary.json").read_text())
    assert s["bus"].startswith("canbrake:") and s["verdict"] in {"ok", "unsafe", "late", "overloaded"}
    msgs = list(can.LogReader(str(tmp_path / "mem" / "frames.log")))
    segs = {"backbone", "car1", "car2", "car3", "car4", "car5", "car6"}
    assert {m.channel for m in msgs} == segs
    # STATE_C3 of one period: once on car3, on the backbone, and on each other car, in that order
    st = [m for m in msgs if m.arbitration_id == 0x143 and m.data == msgs[[x.arbitration_id for x in msgs].index(0x143)].data]
    assert [m.channel for m in st][:2] == ["car3", "backbone"] and {m.channel for m in st} == segs
    assert st[1].timestamp - st[0].timestamp >= 2e-4 + 270e-6 - 1e-9  # gateway delay + 8 bytes at 500 kbit/s
    stats = json.loads((tmp_path / "mem" / "bus_stats.json").read_text())
    ticks = s["ticks"]
    for seg in segs:
        per = [m for m in can.LogReader(str(tmp_path / "mem" / f"frames_{seg}.log"))]
        assert per and {m.channel for m in per} == {seg}
        timed = [m for m in per if m.arbitration_id not in range(0xC0, 0xC7) and m.data != b"\xff\xff\xff\xff"]
        wire = sum(frame_bits(m.arbitration_id, m.is_extended_id, m.dlc, bytes(m.data), stuffing="actual")
                   for m in timed) / stats["segments"][seg]["bitrate_bps"]
        assert stats["segments"][seg]["bus_load_mean"] == pytest.approx(wire / (ticks * 0.01), rel=0.02)
    assert stats["segments"]["backbone"]["bus_load_mean"] > stats["segments"]["car1"]["bus_load_mean"]
    assert stats["bus_load_mean"] == pytest.approx(max(v["bus_load_mean"] for v in stats["segments"].values()))
    assert s["bus_load"]["segments"] == stats["segments"] and "bus load per segment: backbone" in mem.stdout
    inp = _run(tmp_path, "--bus", "inprocess", "--duration", "0.3", "--no-plots", "--out", str(tmp_path / "inp"))
    assert inp.returncode == 0, inp.stderr
    for f in ("frames.log", "frames_backbone.log", "signals.csv"):
        assert (tmp_path / "mem" / f).read_bytes() == (tmp_path / "inp" / f).read_bytes(), f


def test_a_slow_backbone_makes_state_frames_late_as_the_timing_model_says(tmp_path: Path) -> None:
    """At 125 kbit/s the backbone needs more than c·T = 5 ms for the period's STATE frames: the
    ECUs miss exactly the peer values whose modelled end-to-end latency is past the deadline."""
    from canbrake.bus.schedule import timing_of
    from canbrake.run import run_scenario
    from canbrake.scenario import load_scenario

    scn = load_scenario(SEGMENTED, overrides={"duration_s": 0.1, "bus.segments.0.bitrate_bps": 125000})
    t = timing_of(scn, bus_layout(scn))
    c = scn.ecu.lockstep_deadline * scn.control_period_s
    late = 0
    for k in range(scn.n_ticks):
        for j in range(1, 7):
            if t.latency_s(k, f"ecu{j}", 0x140 + j, k * scn.control_period_s) > c:
                late += 5  # its five listeners compute without it
    assert late > 0
    run_scenario(scn, tmp_path / "r", backend="inprocess", plots=False)
    s = json.loads((tmp_path / "r" / "summary.json").read_text())
    assert s["frames"]["peer_values_missing"] == late


def test_analyze_prints_per_segment_tables_and_end_to_end_bounds(tmp_path: Path) -> None:
    out = tmp_path / "a.json"
    r = subprocess.run([sys.executable, "-m", "canbrake", "analyze", str(SEGMENTED), "--ticks", "50",
                        "--json", str(out)], capture_output=True, text=True, cwd=ROOT)
    assert r.returncode == 0, r.stderr
    assert "segment backbone" in r.stdout and "segment car6" in r.stdout and "end-to-end" in r.stdout
    a = json.loads(out.read_text())
    assert set(a["segments"]) == {"backbone", *(f"car{i}" for i in range(1, 7))}
    by = {e["name"]: e for e in a["end_to_end"]}
    s3 = by["STATE_C3"]
    assert s3["path"][1] == "backbone" and len(s3["path"]) == 3 and s3["gateway_delay_s"] == pytest.approx(4e-4)
    hops = s3["hops"]
    # E2E = R on the first segment + sum over the next of (gateway delay + R - J)
    assert s3["response_s"] == pytest.approx(hops[0]["response_s"] + sum(h["delay_s"] + h["response_s"] - h["jitter_s"]
                                                                          for h in hops[1:]))
    bb = {m["name"]: m for m in a["segments"]["backbone"]["messages"]}
    assert hops[1]["response_s"] == pytest.approx(bb["STATE_C3"]["response_s"]) and bb["STATE_C3"]["sender"] == "gw3"
    # the forwarded copy's release jitter is the upstream response time minus its best case
    c1 = {m["name"]: m for m in a["segments"]["car3"]["messages"]}
    best = frame_bits(0x143, False, 8, stuffing="none") / 1e6
    assert hops[1]["jitter_s"] == pytest.approx(c1["STATE_C3"]["response_s"] - best)
    for e in a["end_to_end"]:  # the simulated end-to-end latency stays under the bound
        assert e["simulated_max_s"] is not None and e["simulated_max_s"] <= e["response_s"] + 1e-9
    assert by["BRAKE_CMD_C3"]["path"] == ["car3"]
    assert math.isclose(a["utilisation"], a["segments"]["backbone"]["utilisation"])
