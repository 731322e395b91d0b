"""Command line: a thin layer of subcommands over the library (cantools-style).

Exit status: 0 success, 1 run failure (names the failed process), 2 bad input (one clear
message, no traceback), 130 interrupted.
"""
from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path
from typing import Any, Sequence

import yaml

EXIT_OK, EXIT_FAIL, EXIT_INPUT, EXIT_INTERRUPTED = 0, 1, 2, 130


from canbrake.errors import InputError  # noqa: E402  (re-exported for callers)



def process_cpu_text(pr: dict) -> str:
    """One line of ``summary.json``'s ``compute.processes``: CPU time per period by node process
    (ECU processes together), the sum and the rate it bounds on this machine's CPUs."""
    us = (lambda x: f"{x * 1e6:.0f} us")
    nodes = pr["nodes"]
    ecu = [v["cpu_per_period_s"] for v in nodes.values() if v.get("role") == "ecu"]
    parts = [f"{n} {us(v['cpu_per_period_s'])}" for n, v in nodes.items() if v.get("role") != "ecu"]
    if ecu:
        parts.append(f"{len(ecu)} ECU process{'es' if len(ecu) > 1 else ''} {us(sum(ecu) / len(ecu))} each"
                     + (f" (max {us(max(ecu))})" if len(ecu) > 1 else ""))
    text = f"{', '.join(parts)}: {us(pr['cpu_per_period_s'])} in all"
    if pr.get("cpu_bound_periods_per_s"):
        text += f", at most {pr['cpu_bound_periods_per_s']:,.0f} periods/s on {pr['cpus']} CPUs"
    if pr.get("wakeups_per_period") is not None:
        text += f"; {pr['wakeups_per_period']:.1f} bus wake-ups per period"
    return text


def _parse_set(items: Sequence[str]) -> dict[str, Any]:
    from canbrake.scenario import DuplicateKeyError, load_yaml

    out: dict[str, Any] = {}
    for item in items:
        if "=" not in item:
            raise InputError(f"--set {item!r}: expected KEY=VALUE, e.g. --set controller.params.k=20")
        k, v = item.split("=", 1)
        try:
            out[k.strip()] = load_yaml(v)
        except DuplicateKeyError as e:
            raise InputError(f"--set {item!r}: duplicate key {e.key!r} in the value") from None
        except yaml.YAMLError:
            raise InputError(f"--set {item!r}: the value is not valid YAML") from None
    return out


def _cmd_run(a: argparse.Namespace) -> int:
    from canbrake.builtin import find_scenario
    from canbrake.run import preflight, run_scenario, stop_node_server
    from canbrake.scenario import ScenarioError, load_scenario

    overrides = _parse_set(a.set or [])
    labels: dict[str, str] = {}  # an override given by its own flag is named by it in messages
    for key, flag, value in (("bus.log_format", "--log-format", a.log_format), ("seed", "--seed", a.seed),
                             ("duration_s", "--duration", a.duration), ("mode", "--mode", a.mode),
                             ("time_scale", "--time-scale", a.time_scale)):
        if value is not None:
            overrides[key] = value
            labels[key] = flag
    a.scenario = str(find_scenario(a.scenario))  # a file, else a built-in scenario's name
    scn = load_scenario(a.scenario, profile=a.profile, overrides=overrides, external=a.external, labels=labels)
    try:
        choice = preflight(scn, a.bus, a.channel, a.interface, source=a.scenario)
    except ScenarioError as e:  # a controller parameter given with --set: name --set, not the file
        from canbrake.scenario import blame_overrides

        raise ScenarioError(blame_overrides(str(e), a.scenario, overrides, labels)) from None
    out = Path(a.out) if a.out else Path("runs") / scn.name
    from canbrake.run import check_out_dir

    check_out_dir(out)
    print(f"canbrake: running {scn.name} ({scn.n_cars} cars, {scn.duration_s:g} s, {scn.mode}, "
          f"bus {a.bus or scn.bus.backend}) -> {out}", file=sys.stderr)
    channel = a.channel
    if choice.backend in ("memory", "socketcan"):
        channel = choice.channel  # the same channel for the run and the hint
        iface = "" if choice.backend == "memory" else " --interface socketcan"
        print(f"canbrake: watch it live: canbrake monitor --channel {channel}{iface} --scenario "
              f"{out / 'scenario.yaml'}", file=sys.stderr)
    if choice.backend == "memory":
        _print_attach(choice.channel, out)
    ext = [p.name for p in scn.placement() if p.external]
    if ext:
        print(f"canbrake: external ECU {', '.join(ext)}: start it on {choice.describe()} now (waiting "
              f"{scn.ecu.external_start_timeout_s:g} s for its heartbeat; docs/lockstep-protocol.md)", file=sys.stderr)
    try:
        summary = run_scenario(scn, out, backend=a.bus, channel=channel, interface=a.interface, dbc_path=a.dbc,
                               plots=not a.no_plots)
    finally:
        stop_node_server()
    _print_summary(summary, out)
    if summary["status"] == "interrupted":
        print(f"canbrake: {summary['message']} (results so far kept in {out})", file=sys.stderr)
        return EXIT_INTERRUPTED
    if summary["status"] != "ok":
        print(f"canbrake: run failed: {summary['message']} (logs kept in {out})", file=sys.stderr)
        return EXIT_FAIL
    if summary.get("verdict") == "diverged":
        print(f"canbrake: the closed loop diverged (results kept in {out})", file=sys.stderr)
        return EXIT_FAIL
    return EXIT_OK


def _print_attach(channel: str | None, out: Path) -> None:
    """The run's in-memory channel and the commands that attach to it (python-can, cantools)."""
    print(f"canbrake: channel {channel}; to watch it while the run lasts:\n"
          f"  python -m can.logger -i canbrake -c {channel}\n"
          f"  python -m can.viewer -i canbrake -c {channel}\n"
          f"  cantools monitor -i canbrake -c {channel} {out}/canbrake.dbc", file=sys.stderr)


def _print_summary(s: dict[str, Any], out: Path) -> None:
    from canbrake.analysis.verdict import fmt_quantity as q

    m = s.get("metrics", {})
    verdict = s.get("verdict")
    if s["status"] != "ok" and verdict not in (None, "unknown"):
        verdict = f"{verdict} (of the ticks that ran: the run did not finish)"
    lines = [f"status: {s['status']}  verdict: {verdict}  ticks: {s.get('ticks')}  "
             f"wall: {s.get('wall_time_s') or 0:.1f} s"]
    for f in s.get("findings") or []:
        lines.append(f"  {f['kind']}: {f['message']}")
    if m:
        tc = m.get("convergence_time_s")
        lead = m.get("lead_vehicle") or {}
        rmse = f"speed RMSE: {q(max(m['speed_rmse_kmh']), 'km/h')} (worst car)"
        if len(m["speed_rmse_kmh"]) > 1 and lead.get("speed_rmse_kmh") is not None:
            rmse += f", {q(lead['speed_rmse_kmh'], 'km/h')} (lead vehicle)"
        lines.append(f"convergence (±{m['band_kmh']} km/h): {'never' if tc is None else f'{tc:.3f} s'}  "
                     f"max |deflection|: {q(m['max_abs_deflection_m'] * 100, 'cm')}  {rmse}")
        if lead.get("position_error_mean_abs_m") is not None:  # a reference position x*: Cai 2014 Fig. 7
            w = lead["position_error_window_s"]
            lines.append(f"position error x - x* (lead vehicle, {w[0]:g}-{w[1]:g} s): mean |e| "
                         f"{q(lead['position_error_mean_abs_m'] * 1000, 'mm')}  max |e| "
                         f"{q(lead['position_error_max_abs_m'] * 1000, 'mm')}")
    bl = s.get("bus_load", {}) or {}
    if bl.get("bus_load_mean") is not None:
        lines.append(f"bus load: mean {bl['bus_load_mean'] * 100:.1f} %  peak {bl['bus_load_peak'] * 100:.1f} % "
                     f"at {bl['bitrate_bps'] / 1000:g} kbit/s  frames: {s['frames']['on_bus']}")
        if bl.get("segments"):  # bus segments: the line above is the most loaded one
            lines[-1] = "bus load per segment: " + ", ".join(
                f"{seg} {v['bus_load_mean'] * 100:.1f} % (peak {v['bus_load_peak'] * 100:.1f} %) at "
                f"{v['bitrate_bps'] / 1000:g} kbit/s" for seg, v in bl["segments"].items()) + \
                f"  frames: {s['frames']['on_bus']}"

    comp = s.get("compute") or {}  # canbrake.analysis.summary.compute_figures
    if comp:
        us = (lambda x: "?" if x is None else f"{x * 1e6:.0f} us")
        ms, cs = comp["model_step_s"], comp["control_step_s"]
        lines.append(f"compute per period: plant model {us(ms.get('mean_s'))}, controllers {cs['ecus']} x "
                     f"{us(cs['mean_s'])} (worst p99 {us(cs['p99_s'])}, {cs['worst_p99_ecu']}); "
                     f"run loop {us(comp.get('loop_per_period_s'))} per period")
        pr = comp.get("processes")
        if pr:
            lines.append("CPU per period: " + process_cpu_text(pr))
    dm = s.get("deadline_misses") or {}
    if s.get("mode") == "realtime" and dm:
        ticks = s.get("ticks") or 0
        periods = (s.get("realtime") or {}).get("periods") or ticks  # periods that ended (a diverged run: one more)
        rate = f" ({dm.get('plant', 0) / periods * 100:.1f} % of periods)" if periods else ""
        rt = s.get("realtime") or {}
        skipped = rt.get("ecu_skipped_periods") or 0
        lines.append(f"deadline misses: plant {dm.get('plant', 0)}{rate}, ECUs {dm.get('ecus', 0)}"
                     + (f"; ECU periods skipped (the next began first): {skipped}" if skipped else ""))
        if rt:  # canbrake.analysis.summary.realtime_figures
            ms = (lambda x: "late" if x is None else f"{x * 1e3:.3f} ms")
            lines.append(f"command latency (SYNC sent -> last command): p50 {ms(rt.get('cmd_latency_p50_s'))}, "
                         f"p99 {ms(rt.get('cmd_latency_p99_s'))}; the plant's timer -> SYNC sent: p50 "
                         f"{ms(rt.get('sync_delay_p50_s'))}, p99 {ms(rt.get('sync_delay_p99_s'))}; "
                         f"late periods {rt.get('late_periods', 0)} "
                         f"(grid moved on {rt.get('slipped_s', 0.0) * 1e3:.1f} ms); "
                         f"plant scheduling: {(rt.get('scheduling') or {}).get('plant') or '?'}")
    if s.get("finalize_error"):
        lines.append(f"summary incomplete: {s['finalize_error']}")
    sf = s.get("safety") or {}
    if sf.get("verdict", "clean") != "clean":
        rej = ", ".join(f"{k} {v}" for k, v in sf["rejected"].items() if v) or "none"
        lines.append(f"safety: {sf['verdict']}  rejected: {rej}  "
                     f"fail-safe: {sf['fallbacks']['failsafe_entries']} car(s), {sf['fallbacks']['failsafe_time_s']:g} s")
    log = next((p.name for p in sorted(out.glob("frames.*"))), "frames.log")
    lines.append(f"written: {out}/summary.json, signals.csv, {log}" + (", plots/" if s.get("plots") else ""))
    print("\n".join(lines))


def _cmd_dbc(a: argparse.Namespace) -> int:
    from canbrake.bus.dbc import MAX_CARS, dbc_text

    if a.scenario is not None:
        from canbrake.build import bus_layout
        from canbrake.run import check_buildable
        from canbrake.scenario import load_scenario

        scn = load_scenario(a.scenario, profile=a.profile)
        check_buildable(scn)
        text = bus_layout(scn).database().as_dbc_string()
        what = f"{scn.n_ecus} ECUs on {scn.n_cars} vehicles"
    else:
        cars = 6 if a.cars is None else a.cars
        if not 1 <= cars <= MAX_CARS:
            raise InputError(f"--cars: must be between 1 and {MAX_CARS}, got {cars}")
        text = dbc_text(cars)
        what = f"{cars} cars"
    if a.output in (None, "-"):
        sys.stdout.write(text)
    else:
        try:
            Path(a.output).write_text(text)
        except OSError as e:
            raise InputError(f"-o {a.output}: cannot write: {e.strerror or e}") from None
        print(f"wrote {a.output} ({what})", file=sys.stderr)
    return EXIT_OK


def _cmd_decode(a: argparse.Namespace) -> int:
    from canbrake.analysis.decode import decode_log

    return decode_log(a.log, a.dbc, sys.stdout, only=a.only, hide_sim_control=a.hide_sim_control)


def _cmd_monitor(a: argparse.Namespace) -> int:
    import can

    from canbrake.monitor import MonitorState, load_database, monitor, open_monitor_bus, spacing_from_scenario
    from canbrake.scenario import load_scenario

    scn = load_scenario(a.scenario) if a.scenario else None
    try:
        db = load_database(a.dbc, scn)
    except FileNotFoundError:
        raise InputError(f"--dbc {a.dbc}: no such DBC file") from None
    bitrate = a.bitrate or (scn.bus.bitrate_bps if scn is not None else 500_000)
    from canbrake.analysis.verdict import deflection_bound_m

    state = MonitorState(db, bitrate_bps=bitrate, spacing_m=spacing_from_scenario(scn) if scn is not None else None,
                         bound_m=deflection_bound_m(scn) if scn is not None else None)
    try:
        bus = open_monitor_bus(a.channel, a.interface)
    except (can.CanError, OSError, ValueError, ImportError) as e:
        raise InputError(f"--channel {a.channel}: cannot listen: {str(e).splitlines()[0] if str(e) else e}") from None
    from canbrake.bus.memory import MemoryBus

    if isinstance(bus, MemoryBus):
        from canbrake.bus import memory_shm as shm

        users = {it["channel"]: len(it.get("pids") or []) for it in shm.channel_info()}
        running = [ch for ch, n in users.items() if n and ch != a.channel]
        if users.get(a.channel, 0) <= 1:  # only this monitor: a typo shows at once; waiting for a run is fine
            print(f"canbrake monitor: no run on channel {a.channel!r} yet, waiting for one"
                  + (f" (channels in use: {', '.join(running)})" if running else ""), file=sys.stderr, flush=True)
    title = f"canbrake monitor — {a.channel}" + (f" — {scn.name}" if scn is not None else "")
    print(f"canbrake monitor: listening on {a.channel}", file=sys.stderr, flush=True)  # scripts wait for it
    try:
        monitor(bus, state, title=title, duration_s=a.duration)
    finally:
        bus.shutdown()
    return EXIT_OK


def _cmd_scenarios(a: argparse.Namespace) -> int:
    from canbrake.builtin import builtin_scenarios

    items = builtin_scenarios()
    width = max((len(b.name) for b in items), default=0)
    for b in items:
        print(f"{b.name:<{width}}  {b.description}".rstrip())
    return EXIT_OK


def _cmd_components(a: argparse.Namespace) -> int:
    from canbrake.consist.components import ComponentError, describe_components

    try:
        lines = describe_components(a.kind)
    except ComponentError as e:
        raise InputError(f"canbrake components: {e}") from None
    print("\n".join(lines))
    return EXIT_OK


def _cmd_init(a: argparse.Namespace) -> int:
    from canbrake.builtin import init_scenario

    for p in init_scenario(a.name, a.dir):
        print(p)
    return EXIT_OK


def _cmd_vcan(a: argparse.Namespace) -> int:
    from canbrake.bus.vcan import VcanError, _check_name, _iface_exists, vcan_down, vcan_up

    try:
        if a.action == "up":
            print(vcan_up(a.name))
        else:
            _check_name(a.name)
            if not _iface_exists(a.name):
                raise InputError(f"{a.name}: no such network interface; nothing to remove "
                                 f"(`ip -brief link` lists them)")
            vcan_down(a.name)
            print(f"{a.name} removed")
    except VcanError as e:
        raise InputError(str(e)) from None
    return EXIT_OK


def _cmd_channels(a: argparse.Namespace) -> int:
    """List the in-memory channels in the shared-memory directory; remove stale ones."""
    from canbrake.bus import memory_shm as shm

    if a.remove_stale:
        from canbrake.run import clean_killed_runs

        removed = clean_killed_runs() + shm.clean_stale_channels()
        print(f"removed {len(removed)} stale channel(s)" + (f": {', '.join(removed)}" if removed else ""))
        return EXIT_OK
    items = shm.channel_info()
    if not items:
        print(f"no canbrake channels in {shm.resolve_dir()}")
    for it in items:
        if "owner" in it:
            state = f"belongs to uid {it['owner']} (not yours: not touched)"
        elif it.get("error"):
            state = f"unreadable: {it['error']}"
        elif it["stale"]:
            state = "stale (no process has it open; `canbrake channels --remove-stale`)"
        else:
            state = f"in use by pids {', '.join(map(str, it['pids']))}"
        print(f"{it['channel']}  {state}")
    return EXIT_OK


def build_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(prog="canbrake", description="CAN-bus-in-the-loop emulator for distributed train braking")
    p.add_argument("--version", action="version", version=f"canbrake {__import__('canbrake').__version__}")
    sub = p.add_subparsers(dest="command", required=True, metavar="COMMAND")

    r = sub.add_parser("run", help="run a scenario", description="Run a scenario: one process per ECU, a plant, a recorder.")
    r.add_argument("scenario", help="scenario YAML file, or the name of a built-in scenario (canbrake scenarios)")
    r.add_argument("--bus", choices=["memory", "socketcan", "virtual", "inprocess"],
                   help="memory (default): in-memory cross-process bus; socketcan: Linux SocketCAN (e.g. vcan0); "
                        "virtual: python-can virtual bus in one process; inprocess: fast single-process engine")
    r.add_argument("--channel", help="bus channel (vcan0, can0, or an in-memory channel name)")
    r.add_argument("--interface", help="any python-can interface name (overrides --bus), e.g. pcan, kvaser")
    r.add_argument("--mode", choices=["lockstep", "realtime"])
    r.add_argument("--time-scale", type=float, metavar="X",
                   help="realtime: simulated s per wall s (0.5 half speed for slow hardware, 2 double)")
    r.add_argument("--external", action="append", metavar="ECU",
                   help="leave this ECU (e.g. ecu3) to a program or device outside canbrake "
                        "(docs/lockstep-protocol.md); repeatable")
    r.add_argument("--profile", help="a profile defined in the scenario's profiles: section (e.g. paper, realistic)")
    r.add_argument("--seed", type=int)
    r.add_argument("--duration", type=float, help="simulated seconds")
    r.add_argument("--out", help="run directory (default runs/<scenario name>)")
    r.add_argument("--dbc", help="DBC to use (checked against the scenario); default: generated")
    r.add_argument("--set", action="append", metavar="KEY=VALUE",
                   help="override a scenario field, dotted path, YAML value (repeatable)")
    r.add_argument("--no-plots", action="store_true")
    r.add_argument("--log-format", choices=["log", "asc", "blf", "trc", "mf4"],
                   help="frame log format, written by python-can as frames.<FORMAT> (default log: candump -L; "
                        "mf4 needs asammdf)")
    r.set_defaults(func=_cmd_run)

    mo = sub.add_parser("monitor", help="live view of a running train on a bus",
                        description="Listen to a bus and show per car speed, brake force, coupler deflection and E2E "
                                    "errors, per node frame rates and the bus load, as the run goes.")
    mo.add_argument("--channel", default="vcan0", help="in-memory channel printed by canbrake run, or vcan0/can0")
    mo.add_argument("--interface", help="python-can interface (default: socketcan for vcan*/can*, else canbrake)")
    mo.add_argument("--scenario", help="the run's scenario.yaml (or a built-in scenario's name): car count, bit rate, "
                                       "coupler spacing")
    mo.add_argument("--dbc", help="DBC to decode with (default: from --scenario, else 6 cars)")
    mo.add_argument("--bitrate", type=int, help="bit rate for the bus load (default: the scenario's, else 500000)")
    mo.add_argument("--duration", type=float, help="stop after this many seconds (default: at the end of the run)")
    mo.set_defaults(func=_cmd_monitor)

    sc = sub.add_parser("scenarios", help="list the built-in scenarios",
                        description="List the scenarios shipped with canbrake, one per line (name, description).")
    sc.set_defaults(func=_cmd_scenarios)

    co = sub.add_parser("components", help="list the train components a vehicle type is made of",
                        description="List every component model a vehicle type can use (train.vehicle_types.NAME."
                                    "KIND: {model: NAME, ...}), built-in and from installed packages (entry point "
                                    "group canbrake.components.KIND), with its parameters and defaults (* required).")
    co.add_argument("kind", nargs="?", help="resistance, coupler, brake, traction or wheels (default: all)")
    co.set_defaults(func=_cmd_components)

    ini = sub.add_parser("init", help="copy a built-in scenario to start from",
                         description="Copy a built-in scenario (and the data files it names) into DIR.")
    ini.add_argument("name", help="a built-in scenario (canbrake scenarios lists them)")
    ini.add_argument("dir", nargs="?", default=".", help="destination folder (default: the current one)")
    ini.set_defaults(func=_cmd_init)

    d = sub.add_parser("dbc", help="generate the CAN database",
                       description="Generate the canbrake DBC with cantools: from a scenario's consist and ECU "
                                   "placement, or Chen's one-ECU-per-car layout with --cars N.")
    d.add_argument("scenario", nargs="?", help="scenario file, or the name of a built-in scenario (its placement "
                                               "defines the messages)")
    d.add_argument("--profile", help="profile of the scenario")
    d.add_argument("--cars", type=int, default=None, help="shortcut without a scenario: N cars (default 6)")
    d.add_argument("-o", "--output", help="output file (default stdout)")
    d.set_defaults(func=_cmd_dbc)

    de = sub.add_parser("decode", help="decode a frame log with the DBC",
                        description="Decode a frame log (candump -L .log, .asc, .blf, ... or - for stdin).")
    de.add_argument("log")
    de.add_argument("--dbc", help="default: canbrake.dbc next to the log, else the 6-car database")
    de.add_argument("--only", help="only messages whose name starts with this")
    de.add_argument("--hide-sim-control", action="store_true",
                    help="leave out the lockstep barrier frames (STATE_DONE/CMD_DONE), e.g. in a candump capture "
                         "of a run; a run's own log never has them")
    de.set_defaults(func=_cmd_decode)

    v = sub.add_parser("vcan", help="create/remove a virtual CAN interface (needs root)")
    v.add_argument("action", choices=["up", "down"])
    v.add_argument("name", nargs="?", default="vcan0")
    v.set_defaults(func=_cmd_vcan)

    ch = sub.add_parser("channels", help="list (or remove stale) in-memory bus channels",
                        description="List the in-memory channels of this machine: in use (which pids) or "
                                    "stale (left by killed runs). --remove-stale removes your stale ones.")
    ch.add_argument("--remove-stale", action="store_true", help="remove the channels no process has open")
    ch.set_defaults(func=_cmd_channels)

    for extra in ("sweep", "report", "bench", "analyze"):
        _register_optional(sub, extra)
    return p


def _register_optional(sub: Any, name: str) -> None:
    """Subcommands that live in their own modules register themselves if present."""
    import importlib

    try:
        mod = importlib.import_module(f"canbrake.cli_{name}")
    except ImportError:
        return
    mod.register(sub)


def main(argv: Sequence[str] | None = None) -> int:
    from canbrake.scenario import ScenarioError

    parser = build_parser()
    args = parser.parse_args(argv)
    old_term = _term_as_interrupt()
    try:
        return int(args.func(args) or 0)
    except (InputError, ScenarioError) as e:
        print(f"canbrake: error: {e}", file=sys.stderr)
        return EXIT_INPUT
    except KeyboardInterrupt:
        print("canbrake: interrupted", file=sys.stderr)
        return EXIT_INTERRUPTED
    except BrokenPipeError:
        _quiet_stdout()
        return EXIT_OK
    except OSError as e:  # a full disk or an unwritable file while running: one line, no traceback
        where = f"{e.filename}: " if getattr(e, "filename", None) else ""
        print(f"canbrake: error: {where}{e.strerror or e}", file=sys.stderr)
        return EXIT_FAIL
    finally:
        if old_term is not None:
            import signal

            signal.signal(signal.SIGTERM, old_term)


def _term_as_interrupt() -> Any:
    """SIGTERM ends a command as cleanly as Ctrl-C (and is named as such in a run's summary).
    Returns the previous handler (None off the main thread)."""
    import signal
    import threading

    if threading.current_thread() is not threading.main_thread():
        return None
    from canbrake.run import Terminated

    def _raise(signum: int, frame: Any) -> None:
        raise Terminated

    return signal.signal(signal.SIGTERM, _raise)


def _quiet_stdout() -> None:
    """After a closed stdout (``| head``), point stdout at /dev/null so the interpreter's final
    flush does not complain (the Python docs' recipe for SIGPIPE)."""
    import os

    try:
        devnull = os.open(os.devnull, os.O_WRONLY)
        os.dup2(devnull, sys.stdout.fileno())
    except (OSError, ValueError):
        pass


if __name__ == "__main__":  # pragma: no cover
    sys.exit(main())
