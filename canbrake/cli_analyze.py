"""`canbrake analyze`: worst-case response times of a scenario's CAN schedule (Davis et al. 2007),
beside the latencies the timing model simulates for the same schedule."""
from __future__ import annotations

import argparse
import json
import math
import sys
from pathlib import Path
from typing import Any


def simulate_latencies(scn: Any, n_ticks: int) -> dict[tuple[int, bool], Any]:
    """Per-message latency statistics (queued -> end of frame, s) of the nominal schedule over
    ``n_ticks`` control periods, from the same replicated model a ``bus.timing: model`` run uses."""
    from canbrake.build import bus_layout
    from canbrake.bus.schedule import timing_of

    t = timing_of(scn, bus_layout(scn), record_history=True)
    t.run_ticks(n_ticks)
    return t.model.latency_by_message()


def analyze_scenario(scn: Any, *, method: str = "davis2007", sim_ticks: int = 0) -> dict[str, Any]:
    """The analysis of ``scn`` as a JSON-ready dict (plus simulated latencies if ``sim_ticks``)."""
    from canbrake.build import bus_layout
    from canbrake.bus.rta import analyze
    from canbrake.bus.schedule import dbc_cycle_times_s, fifo_like_nodes, message_set

    layout = bus_layout(scn)
    msgs = message_set(scn, layout)
    from canbrake.bus.segments import topology_of

    if topology_of(scn, layout) is not None:
        return analyze_segmented(scn, msgs, method=method, sim_ticks=sim_ticks)
    res = analyze(msgs, scn.bus.bitrate_bps, method=method,  # type: ignore[arg-type]
                  fifo_nodes=fifo_like_nodes(scn, msgs))
    out = {"scenario": scn.name, "profile": scn.profile, "n_cars": scn.n_cars,
           "control_period_s": scn.control_period_s, **res.as_dict()}
    cycles = dbc_cycle_times_s(layout)
    for m in out["messages"]:
        m["dbc_cycle_s"] = cycles.get(m["id"])
    if sim_ticks > 0:
        lat = simulate_latencies(scn, sim_ticks)
        out["simulated_ticks"] = sim_ticks
        for m in out["messages"]:
            st = lat.get((m["id"], m["extended"]))
            if st is None:
                continue
            f = (lambda x: None if not math.isfinite(x) else x)
            m["simulated"] = {"n_delivered": st.n_delivered, "n_pending": st.n_pending, "p50_s": f(st.p50_s),
                              "p99_s": f(st.p99_s), "max_s": f(st.max_s),
                              "max_pending_age_s": st.max_pending_age_s}
    return out


def analyze_segmented(scn: Any, msgs: list[Any], *, method: str, sim_ticks: int) -> dict[str, Any]:
    """``bus.segments``: the analysis of every segment (messages forwarded into it are sent by
    their gateway, with the upstream response time as release jitter) and each message's
    end-to-end bound (:func:`canbrake.bus.segments.analyze_network`), with the simulated
    latencies of the segmented timing model beside them."""
    from canbrake.build import bus_layout
    from canbrake.bus.schedule import dbc_cycle_times_s, fifo_like_nodes, timing_of
    from canbrake.bus.segments import analyze_network, forwarding_tables, message_routes, topology_of

    layout = bus_layout(scn)
    topo = topology_of(scn, layout)
    per_seg, e2e = analyze_network(msgs, topo, message_routes(layout, topo, scn.bus.plant_io_on_bus),
                                   method=method, fifo_nodes=lambda seg, on: fifo_like_nodes(scn, on))
    cycles = dbc_cycle_times_s(layout)
    sim = None
    if sim_ticks > 0:
        t = timing_of(scn, layout, record_history=True)
        t.run_ticks(sim_ticks)
        sim = t
    f = (lambda x: None if x is None or not math.isfinite(x) else x)
    segments: dict[str, Any] = {}
    flat: list[dict] = []
    for seg, res in per_seg.items():
        d = res.as_dict()
        lat = sim.net.models[seg].latency_by_message() if sim is not None else {}
        for m in d["messages"]:
            m["segment"] = seg
            m["dbc_cycle_s"] = cycles.get(m["id"])
            st = lat.get((m["id"], m["extended"]))
            if st is not None:
                m["simulated"] = {"n_delivered": st.n_delivered, "n_pending": st.n_pending, "p50_s": f(st.p50_s),
                                  "p99_s": f(st.p99_s), "max_s": f(st.max_s),
                                  "max_pending_age_s": st.max_pending_age_s}
        segments[seg] = d
        flat += d["messages"]
    ends = []
    for e in e2e:
        row = e.as_dict()
        if sim is not None:
            v = sim.net.e2e.get((e.arbitration_id, e.arbitration_id > 0x7FF and layout.plan.extended))
            row["simulated_max_s"] = max(v) if v else None
        ends.append(row)
    out = {"scenario": scn.name, "profile": scn.profile, "n_cars": scn.n_cars,
           "control_period_s": scn.control_period_s, "bitrate_bps": scn.bus.bitrate_bps, "method": method,
           "utilisation": max(d["utilisation"] for d in segments.values()),
           "schedulable": all(d["schedulable"] for d in segments.values()) and all(e["schedulable"] for e in ends),
           "notes": ["per segment: a forwarded message is sent by its gateway, with release jitter = upstream R - "
                     "best-case C; end to end = R on the first segment + sum of (gateway delay + R - J) on the next"],
           "segments": segments, "messages": flat, "end_to_end": ends,
           "gateways": {gw: {"delay_s": d} for gw, d in sorted(topo.delay.items())},
           "forwarding_tables": forwarding_tables(layout, topo)}
    if sim is not None:
        out["simulated_ticks"] = sim_ticks
    return out


def _ms(x: float | None) -> str:
    return "inf" if x is None else f"{x * 1e3:.3f}"


def format_table(a: dict[str, Any]) -> str:
    """The analysis as a fixed-width text table (times in ms)."""
    if "segments" in a:
        return _format_segmented(a)
    sim = "simulated_ticks" in a
    head = (f"{'message':18s} {'id':>6s} {'sender':8s} {'dlc':>3s} {'T':>8s} {'D':>8s} {'C':>6s} {'B':>6s} "
            f"{'busy':>8s} {'Q':>3s} {'R':>8s} {'R1994':>8s} {'ok':>3s}")
    if sim:
        head += f" {'sim p50':>8s} {'sim p99':>8s} {'sim max':>8s}"
    lines = [f"{a['scenario']}" + (f" [{a['profile']}]" if a.get("profile") else "")
             + f": {len(a['messages'])} periodic messages at {a['bitrate_bps'] / 1000:g} kbit/s, control period "
             f"{a['control_period_s'] * 1e3:g} ms; response times per Davis et al. 2007 (ms)", head]
    for m in a["messages"]:
        row = (f"{m['name']:18s} {m['id_hex']:>6s} {m['sender']:8s} {m['dlc']:>3d} {_ms(m['period_s']):>8s} "
               f"{_ms(m['deadline_s']):>8s} {m['c_s'] * 1e3:6.3f} {m['blocking_s'] * 1e3:6.3f} "
               f"{_ms(m['busy_period_s']):>8s} {m['instances']:>3d} {_ms(m['response_s']):>8s} "
               f"{_ms(m['tindell1994_s']):>8s} {'yes' if m['schedulable'] else 'NO':>3s}")
        if sim:
            s = m.get("simulated")
            if s is None or not s["n_delivered"]:
                row += f" {'-':>8s} {'-':>8s} {'starved':>8s}"
            else:
                row += f" {_ms(s['p50_s']):>8s} {_ms(s['p99_s']):>8s} {_ms(s['max_s']):>8s}"
        lines.append(row)
    n_bad = sum(1 for m in a["messages"] if not m["schedulable"])
    lines.append(f"utilisation {a['utilisation'] * 100:.1f} %  —  "
                 + ("schedulable" if a["schedulable"] else f"NOT schedulable ({n_bad} messages miss their deadline)"))
    if sim:
        lines.append(f"sim: the same schedule in the timing model over {a['simulated_ticks']} control periods "
                     "(worst-case stuffing, all frames of a period queued at their nominal instant)")
    for note in a.get("notes", []):
        lines.append(f"note: {note}")
    return "\n".join(lines)


def _format_segmented(a: dict[str, Any]) -> str:
    """One table per segment, then the end-to-end bounds through the gateways (ms)."""
    lines = []
    sim = "simulated_ticks" in a
    for seg, d in a["segments"].items():
        sub = {**a, **d, "scenario": f"{a['scenario']} segment {seg}", "profile": None}
        sub.pop("segments")
        lines.append(format_table(sub))
        lines.append("")
    head = (f"{'end to end':18s} {'id':>6s} {'sender':8s} {'path':34s} {'R per segment':28s} {'gw':>6s} "
            f"{'E2E':>8s} {'D':>8s} {'ok':>3s}" + (f" {'sim max':>8s}" if sim else ""))
    lines += [f"{a['scenario']}: end-to-end response times through the gateways (ms): R on the first segment + "
              "sum of (gateway delay + R - J) on the next", head]
    for e in a["end_to_end"]:
        per = " + ".join(_ms(h["response_s"] if h["gateway"] is None else h["bound_s"]) for h in e["hops"])
        row = (f"{e['name']:18s} {e['id_hex']:>6s} {e['sender']:8s} {'>'.join(e['path']):34s} {per:28s} "
               f"{e['gateway_delay_s'] * 1e3:6.3f} {_ms(e['response_s']):>8s} {_ms(e['deadline_s']):>8s} "
               f"{'yes' if e['schedulable'] else 'NO':>3s}")
        if sim:
            row += f" {_ms(e.get('simulated_max_s')) if e.get('simulated_max_s') is not None else '-':>8s}"
        lines.append(row)
    lines.append("end to end: " + ("schedulable" if a["schedulable"] else "NOT schedulable")
                 + f"; most loaded segment {a['utilisation'] * 100:.1f} %")
    return "\n".join(lines)


def _cmd(a: argparse.Namespace) -> int:
    from canbrake.cli import _parse_set
    from canbrake.scenario import load_scenario

    scn = load_scenario(a.scenario, profile=a.profile, overrides=_parse_set(a.set or []))
    ticks = a.ticks if a.ticks is not None else min(scn.n_ticks, 2000)
    from canbrake.control.base import ControllerError
    from canbrake.errors import InputError

    try:
        out = analyze_scenario(scn, method=a.method, sim_ticks=max(0, ticks))
    except ControllerError as e:  # the bus layout needs each ECU's controller class
        raise InputError(f"{a.scenario}: {e}") from None
    print(format_table(out))
    if a.json:
        Path(a.json).write_text(json.dumps(out, indent=1))
        print(f"written: {a.json}", file=sys.stderr)
    return 0


def register(sub: Any) -> None:
    p = sub.add_parser("analyze", help="worst-case CAN response times of a scenario's schedule",
                       description="Worst-case response time of every periodic message of the scenario's CAN schedule "
                                   "(Davis, Burns, Bril, Lukkien 2007: worst-case stuffing, blocking, busy period), "
                                   "schedulability and utilisation, beside the latencies the timing model simulates.")
    p.add_argument("scenario", help="scenario YAML file, or the name of a built-in scenario (canbrake scenarios)")
    p.add_argument("--profile", help="a profile of the scenario")
    p.add_argument("--set", action="append", metavar="KEY=VALUE", help="override a scenario field (repeatable)")
    p.add_argument("--json", metavar="FILE", help="also write the analysis as JSON")
    p.add_argument("--method", choices=["davis2007", "tindell1994"], default="davis2007",
                   help="davis2007 (default); tindell1994 = the original, optimistic analysis, for comparison")
    p.add_argument("--ticks", type=int, help="control periods to simulate beside the bound "
                                             "(default: the scenario's, at most 2000; 0 = none)")
    p.set_defaults(func=_cmd)
