"""Run orchestration: prepare the run directory, start and supervise the node processes (or run
them in process), then collect traces into signals.csv, summary.json and plots.

Run directory contract (docs/architecture.md): frames.log, signals.csv, summary.json,
scenario.yaml (resolved), canbrake.dbc, plots/*.png, plus per-node traces (ecu_c*.csv,
*_stats.json) and logs/<node>.log for a failed node.
"""
from __future__ import annotations

import json
import multiprocessing as mp
import multiprocessing.connection
import os
import signal
import sys
import threading
import time
import traceback
import uuid
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Callable

import can

from canbrake.atomic import is_temp_of
from canbrake.scenario import Scenario, ScenarioError
from canbrake.startup import (PACKAGE_ENV, check_same_package, server_imports_this_canbrake,
                              children_skip_main, controller_modules, make_module_callable)

BACKENDS = ("memory", "socketcan", "virtual", "inprocess")


class RunFailure(RuntimeError):
    """The run failed after it started (exit status 1); the message names the failed process."""


#: the interface column of frames.log for runs on the in-memory, virtual and in-process buses: a
#: fixed name (the in-memory channel is a random rendezvous name by default), the one the README's
#: ``canplayer -I frames.log vcan0=canbrake0`` maps
LOG_INTERFACE = "canbrake0"


@dataclass
class BusChoice:
    """Which bus a run uses. ``interface`` is a python-can interface name."""

    backend: str
    interface: str | None
    channel: str | None

    #: interface name written into frames.log's candump column: :data:`LOG_INTERFACE` for the
    #: in-memory and one-process buses (whatever their channel, random or named, so logs compare byte
    #: for byte and ``canplayer -I frames.log vcan0=canbrake0`` replays any of them), the interface
    #: itself on SocketCAN or an adapter (what candump writes there)
    log_channel: str = LOG_INTERFACE
    #: keyword arguments for ``can.Bus`` beyond interface/channel (an adapter's bit rate, options)
    bus_kwargs: dict[str, Any] = field(default_factory=dict)

    def describe(self) -> str:
        return f"{self.interface or self.backend}:{self.channel}"


def choose_bus(scn: Scenario, backend: str | None = None, channel: str | None = None,
               interface: str | None = None) -> BusChoice:
    """Resolve backend/interface/channel from the command line and the scenario."""
    backend = backend or scn.bus.backend
    interface = interface or scn.bus.interface
    if backend not in BACKENDS:
        raise ScenarioError(f"--bus: unknown backend {backend!r} (choose from {', '.join(BACKENDS)})")
    channel = channel or scn.bus.channel
    log_channel = LOG_INTERFACE
    if interface not in (None, "canbrake", "socketcan") and backend in ("memory", "socketcan"):
        return _adapter_choice(scn, interface, channel)
    if scn.bus.interface_args:
        raise ScenarioError("bus.interface_args: only used with a python-can interface other than "
                            "canbrake/socketcan (--interface NAME)")
    if backend == "memory":
        interface = interface or "canbrake"
        channel = channel or f"cb{os.getpid()}-{uuid.uuid4().hex[:6]}"
    elif backend == "socketcan":
        interface = interface or "socketcan"
        channel = channel or "vcan0"
        log_channel = channel
    elif backend in ("virtual", "inprocess"):
        interface = None
        channel = channel or "virtual0"
    if backend in ("virtual", "inprocess") and scn.mode != "lockstep":
        raise ScenarioError(f"--bus {backend}: runs in one process and supports --mode lockstep only")
    return BusChoice(backend, interface, channel, log_channel)


#: python-can interfaces that only connect buses inside one process: node processes would never
#: hear each other
_SINGLE_PROCESS_INTERFACES = ("virtual",)


def _adapter_choice(scn: Scenario, interface: str, channel: str | None) -> BusChoice:
    """Any other python-can interface (a CAN adapter: pcan, kvaser, vector, slcan, ...). Channel
    and ``bus.interface_args`` go to ``can.Bus`` as given; ``bus.bitrate_bps`` is passed as
    ``bitrate`` (python-can's adapters configure the controller with it) unless interface_args
    names its own. Every node process opens the channel itself, so the driver must let several
    processes share it and deliver each one's frames to the others, as SocketCAN does."""
    import can.interfaces

    if interface in _SINGLE_PROCESS_INTERFACES:
        raise ScenarioError(f"--interface {interface}: python-can's {interface} bus connects buses inside "
                            f"one process only; use --bus virtual (all nodes in one process) or --bus memory")
    if interface not in can.interfaces.VALID_INTERFACES:
        raise ScenarioError(f"--interface {interface}: not a python-can interface (installed: "
                            f"{', '.join(sorted(can.interfaces.VALID_INTERFACES))})")
    kwargs = {"bitrate": scn.bus.bitrate_bps, **scn.bus.interface_args}
    return BusChoice("adapter", interface, channel, channel or interface, kwargs)


#: files of which a run directory has at least one (from its start, or a sweep's trimmed point):
#: what marks a directory as canbrake's to replace
RUN_DIR_MARKERS = ("scenario.yaml", "summary.json")


def check_out_dir(out_dir: str | Path) -> Path:
    """``out_dir`` may be created or replaced: it does not exist, is empty, or is a canbrake run
    directory (has scenario.yaml or summary.json), and it is not the current directory or one
    of its parents. Raises :class:`ScenarioError` (exit 2) otherwise; writes nothing."""
    out = Path(out_dir)
    if not out.exists() and not out.is_symlink():
        return out
    if not out.is_dir() or out.is_symlink():
        raise ScenarioError(f"--out {out}: exists and is not a directory")
    here = Path.cwd().resolve()
    if out.resolve() == here or out.resolve() in here.parents:
        raise ScenarioError(f"--out {out}: is the current directory or one of its parents; choose a run directory")
    try:
        entries = {p.name for p in out.iterdir()}
    except OSError as e:
        raise ScenarioError(f"--out {out}: cannot read the directory: {e.strerror}") from None
    if entries and not any(m in entries for m in RUN_DIR_MARKERS):
        raise ScenarioError(f"--out {out}: exists and is not a canbrake run directory (no scenario.yaml or summary.json); "
                            f"a run replaces its directory as a whole, so choose another --out or remove it")
    return out


def _clear_run_dir(out: Path) -> None:
    """Replace an existing run directory by an empty one: the old one is renamed aside first (so no
    file of it can mix with the new run's), then deleted."""
    import shutil

    if not out.exists():
        return
    if not any(out.iterdir()):
        return
    aside = out.with_name(f".{out.name}.old-{os.getpid()}-{uuid.uuid4().hex[:6]}")
    os.rename(out, aside)
    shutil.rmtree(aside, ignore_errors=True)


def prepare_run_dir(scn: Scenario, out_dir: str | Path, dbc_path: str | Path | None = None,
                    dbc_text: str | None = None) -> Path:
    """Create ``out_dir`` afresh (an earlier run there is replaced as a whole, see
    :func:`check_out_dir`) and write the resolved scenario and the DBC used (checked against the
    scenario; ``dbc_text``: the scenario's own DBC already generated, as the batch engine does once
    for all its points). Raises :class:`ScenarioError` for bad input before anything is removed or
    written."""
    from canbrake.bus import dbc

    out = check_out_dir(out_dir)
    if dbc_path is not None and dbc_text is None:
        check_dbc_matches(scn, dbc_path)
        dbc_text = Path(dbc_path).read_text()  # before the old run (which may hold it) is removed
    elif dbc_text is None:
        from canbrake.build import bus_layout

        dbc_text = bus_layout(scn).database().as_dbc_string()
    user = None
    if scn.bus.dbc is not None:  # the user's own DBC, copied as it is beside canbrake.dbc (the run's
        from canbrake.build import user_dbc_path  # layout: its frames under canbrake's role names)

        src = user_dbc_path(scn)
        try:
            user = (src.name if src.name != "canbrake.dbc" else "user.dbc", src.read_bytes())  # type: ignore[union-attr]
        except OSError as e:
            raise ScenarioError(f"bus.dbc.file: {src}: cannot read: {e.strerror or e}") from None
    try:
        _clear_run_dir(out)
        out.mkdir(parents=True, exist_ok=True)
        (out / "canbrake.dbc").write_text(dbc_text)
        if user is not None:
            (out / user[0]).write_bytes(user[1])
        (out / "scenario.yaml").write_text(scn.to_yaml())
    except OSError as e:
        raise RunDirError(f"--out {out}: cannot write the run directory: {e.strerror or e}") from None
    return out


class RunDirError(ScenarioError):
    """The run directory cannot be written (permissions, full disk): one message, exit 2."""


def check_dbc_matches(scn: Scenario, dbc_path: str | Path) -> None:
    """A user-supplied DBC must describe the scenario's train with canbrake's layout."""
    from canbrake.bus import dbc

    p = Path(dbc_path)
    try:
        db = dbc.load_dbc(p)
    except FileNotFoundError:
        raise ScenarioError(f"{p}: no such DBC file") from None
    except Exception as e:  # cantools raises several parse error types
        raise ScenarioError(f"{p}: not a readable DBC file: {str(e).splitlines()[0] if str(e) else type(e).__name__}") from None
    from canbrake.build import bus_layout

    ref = bus_layout(scn).database()
    n_db = dbc.n_cars_of(db)
    if n_db != scn.n_ecus:
        raise ScenarioError(f"{p}: the DBC describes {n_db} cars (ECUs) but the scenario has {scn.n_ecus} ECUs on "
                            f"{scn.n_cars} vehicles (generate its DBC with `canbrake dbc SCENARIO`)")
    if len(db.messages) != len(ref.messages):
        raise ScenarioError(f"{p}: the DBC has {len(db.messages)} messages, the scenario's placement needs "
                            f"{len(ref.messages)} (generate it with `canbrake dbc SCENARIO`)")
    for m in ref.messages:
        try:
            got = db.get_message_by_frame_id(m.frame_id)
        except KeyError:
            raise ScenarioError(f"{p}: message {m.name} ({m.frame_id:#x}) is missing") from None
        a = [(s.name, s.start, s.length, s.is_signed, s.scale, s.offset, s.byte_order) for s in m.signals]
        b = [(s.name, s.start, s.length, s.is_signed, s.scale, s.offset, s.byte_order) for s in got.signals]
        if got.name != m.name or got.length != m.length or sorted(a) != sorted(b):
            raise ScenarioError(f"{p}: message {m.frame_id:#x} does not match canbrake's layout for {m.name} "
                                f"(generate it with `canbrake dbc SCENARIO`)")


# ----------------------------------------------------------------------------- child processes
def _runnable_others(samples: int = 5, gap_s: float = 0.01) -> int | None:
    """Tasks runnable right now besides this process: the running count of ``/proc/loadavg`` (which
    includes the reader) minus one, the smallest of ``samples`` reads ``gap_s`` apart; None where
    the file cannot be read."""
    least: int | None = None
    for k in range(samples):
        try:
            with open("/proc/loadavg") as f:
                running = int(f.read().split()[3].split("/")[0])
        except (OSError, ValueError, IndexError):
            return None
        least = running - 1 if least is None else min(least, running - 1)
        if k + 1 < samples:
            time.sleep(gap_s)
    return least


def memory_yield() -> bool:
    """Does a node yield the CPU before it blocks on canbrake's memory bus? ``CANBRAKE_MEMORY_YIELD``
    1 = yes, 0 = no; unset (auto): yes unless the machine is busy with other work, where a yield
    gives the CPU away for a whole time slice (Chen case 1 for 2 s beside two CPU-bound processes on
    2 cores: 12.2 s with the yield, 6.3 s without; idle: 3.3 s with, 3.7 s without). Busy: as many
    other tasks runnable right now as CPUs, or the 1-minute load average at or above the number of
    CPUs while anything else is runnable now (the load average lags by a minute both ways: after a
    run, or between a bench's cases, it is high on an idle machine; when other work has just
    started it is still low). A run's orchestrator decides once and hands the answer to its node
    processes (:func:`run_in_processes`), whose siblings are starting when they would ask."""
    v = os.environ.get("CANBRAKE_MEMORY_YIELD", "auto")
    if v in ("0", "1"):
        return v == "1"
    cpus = os.cpu_count() or 1
    others = _runnable_others()
    try:
        load = os.getloadavg()[0]
    except OSError:
        load = 0.0
    if others is None:  # no /proc/loadavg: the load average alone
        return load < cpus
    return not (others >= cpus or (load >= cpus and others >= 1))


def _open_bus(choice: BusChoice, filters: list[dict] | None, role: str = "", lockstep: bool = False) -> can.BusABC:
    if choice.backend == "socketcan" and choice.interface == "socketcan":
        from canbrake.bus.vcan import open_socketcan_bus

        # The kernel silently drops frames for a socket whose receive queue is full: give the
        # recorder, which must see every frame, a large one.
        rcvbuf = 16 << 20 if role == "recorder" else None
        return open_socketcan_bus(choice.channel or "vcan0", rcvbuf_bytes=rcvbuf, can_filters=filters,
                                  receive_own_messages=False)
    kwargs: dict[str, Any] = {}
    if choice.interface == "canbrake" and role == "recorder":
        # the recorder must see every frame: senders wait for it rather than overrun its ring
        kwargs["backpressure"] = True
        if lockstep:  # it writes a period's frames when the next SYNC comes: woken by that alone
            from canbrake.bus.dbc import SYNC_ID

            kwargs["wake_on"] = SYNC_ID
    elif choice.interface == "canbrake" and lockstep:
        # a lockstep node waits for every frame it filters for: a flood may not overwrite those
        # (it is held back instead), frames it filters out may go by (canbrake.bus.memory)
        kwargs["backpressure"] = "accepted"
    if choice.interface == "canbrake" and not memory_yield():
        # no sched_yield before a blocking recv: on a machine loaded by other work a yield hands
        # the CPU to them for a whole time slice (`canbrake bench`, docs/performance.md)
        kwargs["yield_before_sleep"] = False
    kwargs.update(choice.bus_kwargs)
    return can.Bus(interface=choice.interface, channel=choice.channel, can_filters=filters,
                   receive_own_messages=False, **kwargs)


def _term(signum: int, frame: Any) -> None:
    raise SystemExit(143)


def _unraisable(u: Any) -> None:
    """_term's SystemExit raised inside a finalizer (a bus's ``__del__``) cannot propagate, and
    Python would print it as a traceback and go on: end the process quietly 10 ms later, outside
    the finalizer (a timer's signal; nodes use no other)."""
    if isinstance(u.exc_value, SystemExit):
        signal.signal(signal.SIGALRM, _term)
        signal.setitimer(signal.ITIMER_REAL, 0.01)
        return
    sys.__unraisablehook__(u)


def node_signals() -> None:
    """A node process's signals: SIGINT ignored (the orchestrator decides how a run ends), SIGTERM
    ends it with status 143 through SystemExit (its ``finally`` blocks run), also when it lands
    in a finalizer."""
    signal.signal(signal.SIGINT, signal.SIG_IGN)
    signal.signal(signal.SIGTERM, _term)
    sys.unraisablehook = _unraisable


def _child_main(role: str, car: int, scenario: dict[str, Any], run_dir: str, choice: BusChoice,
                barrier: Any, progress: Any, parent_pid: int, env: dict[str, str] | None = None,
                failure: Any = None) -> None:
    """Entry point of one node process. ``env``: the parent's CANBRAKE_* variables at run start
    (a forkserver child otherwise sees the environment of the moment the server started).
    ``failure``: a shared byte string (multiprocessing Array) for this process's last error line
    when its log cannot be written either (a full disk)."""
    from canbrake.build import build_node
    from canbrake.nodes.driver import drive, freeze_heap

    if env is not None:
        for key in [k for k in os.environ if k.startswith("CANBRAKE_") and k not in env]:
            del os.environ[key]
        os.environ.update(env)
        check_same_package(env)

    node_signals()
    names = scenario.get("_ecu_names", {})
    name = role if role != "ecu" else _ecu_process_name([names.get(str(i), f"ecu{i}") for i in range(1, len(names) + 1)], car)
    _set_title(f"canbrake {name} {scenario.get('name', '')}")
    import warnings

    # a diverging plant overflows before it notices; the verdict reports it, not numpy's warnings
    warnings.simplefilter("ignore", RuntimeWarning)
    node = None
    bus = None
    status = "failed"
    try:
        scn = Scenario.model_validate({k: v for k, v in scenario.items() if k != "_ecu_names"})
        if isinstance(car, (tuple, list)):
            from canbrake.build import bus_layout
            from canbrake.bus.codec import FrameCodec
            from canbrake.bus.schedule import build_bus_timing
            from canbrake.nodes.group import NodeGroup

            layout = bus_layout(scn)
            codec, timing = FrameCodec(layout.database()), build_bus_timing(scn, layout)
            node = NodeGroup([build_node(scn, "ecu", car=c, run_dir=Path(run_dir), codec=codec, layout=layout,
                                         bus_timing=timing) for c in car])
        else:
            node = build_node(scn, role, car=car, run_dir=Path(run_dir), channel=choice.log_channel,
                              progress=progress)
        bus = _open_bus(choice, node.filters(), role, lockstep=scn.mode == "lockstep")
        spin_s = 0.0
        frozen = freeze_heap()  # what is set up: the run's full collections skip it (canbrake.nodes.driver)
        if scn.mode == "realtime":  # SCHED_FIFO / affinity where permitted (canbrake.nodes.rt)
            from canbrake.nodes.rt import setup_realtime
            from canbrake.nodes.rt import spin_s as rt_spin_s

            sched = setup_realtime(role) + (f", gc: {frozen:,} objects frozen" if frozen else "")
            if role == "plant" and hasattr(node, "stats"):
                node.stats.extra["scheduling"] = sched
            for m in getattr(node, "members", [node]):  # every node's own stats say what it obtained
                m.scheduling = sched
            spin_s = rt_spin_s(scn.control_period_s)
        barrier.wait(timeout=_start_timeout_s())
        cpu0 = time.process_time()  # this process's CPU time from the start of the run
        prof_dir = os.environ.get("CANBRAKE_PROFILE_DIR")
        if prof_dir:  # developer aid: a cProfile of every node process (CPU time: waits left out)
            import cProfile

            prof = cProfile.Profile(time.process_time)
            try:
                prof.runcall(drive, node, bus, parent_pid=parent_pid)
            finally:
                prof.dump_stats(str(Path(prof_dir) / f"{name}.prof"))
        else:
            drive(node, bus, parent_pid=parent_pid, spin_s=spin_s)
        status = "ok"
        _write_process_stats(Path(run_dir), name, role, time.process_time() - cpu0, bus)
    except SystemExit:
        status = "terminated"
        raise
    except BaseException as e:  # noqa: BLE001 - report any failure of this process, then exit 1
        # the orchestrator reports it (one message naming this process and the last line of its
        # traceback, from logs/<name>.log); nothing is printed here
        _leave_failure(Path(run_dir) / "logs" / f"{name}.log", traceback.format_exc(), failure)
        sys.exit(1)
    finally:
        if node is not None:
            try:
                node.close(status)
            except Exception:  # noqa: BLE001 - closing must not hide the original failure
                pass
        if bus is not None:
            bus.shutdown()


def _write_process_stats(run_dir: Path, name: str, role: str, cpu_s: float, bus: Any) -> None:
    """``processes/<name>.json``: this node process's CPU time over the run (s, user + system,
    from the start barrier to its end) and, on the memory bus, how often it slept and was woken
    (:meth:`canbrake.bus.memory.MemoryBus.stats`); the summary's ``compute.processes``."""
    from canbrake.atomic import write_text_atomic

    rec: dict[str, Any] = {"name": name, "role": role, "cpu_s": round(cpu_s, 6)}
    st = getattr(bus, "stats", None)
    if callable(st):
        b = st()
        rec.update(sleeps=getattr(b, "sleeps", None), wakeups=getattr(b, "wakeups", None))
    d = run_dir / "processes"
    try:
        d.mkdir(exist_ok=True)
        write_text_atomic(d / f"{name}.json", json.dumps(rec))
    except OSError:
        pass  # a figure of the run's cost, not of its result: the summary leaves it out


def _leave_failure(log: Path, text: str, failure: Any) -> None:
    """Write a failed node's traceback to ``log``; when that fails too (the full disk that made
    the node fail), put its last line in the shared ``failure`` string for the orchestrator, so
    that nothing reaches the console but the orchestrator's one line."""
    from canbrake.atomic import write_text_atomic

    try:
        log.parent.mkdir(exist_ok=True)
        write_text_atomic(log, text)
    except OSError:
        lines = [ln.strip() for ln in text.splitlines() if ln.strip()]
        if failure is not None and lines:
            with failure.get_lock():
                if not failure.value:  # the first failure is the cause
                    failure.value = f"{log.stem}\t{lines[-1]}".encode()[:len(failure) - 1]


def _set_title(title: str) -> None:
    """Name this process for ps/top (``canbrake ecu3 chen2023_case1``), if setproctitle is there."""
    try:
        import setproctitle
    except ImportError:
        return
    setproctitle.setproctitle(title)


def stop_node_server() -> None:
    """Stop multiprocessing's forkserver (started for the node processes), so that nothing of a
    run outlives ``canbrake run``. The next run starts a new one."""
    from multiprocessing import forkserver

    try:
        forkserver._forkserver._stop()  # noqa: SLF001 - the stdlib's only way to stop it
    except Exception:  # noqa: BLE001 - best effort at exit
        pass


class Terminated(KeyboardInterrupt):
    """The orchestrator got SIGTERM (ends the run as cleanly as Ctrl-C, and says so)."""


def _signal_name(code: int | None) -> str:
    """``exited with status 3`` / ``killed by SIGKILL`` for a process exit code."""
    if code is not None and code < 0:
        try:
            return f"killed by {signal.Signals(-code).name}"
        except ValueError:
            return f"killed by signal {-code}"
    if code == 143:
        return "terminated (SIGTERM)"
    return f"exited with status {code}"


def _pid_start(pid: int | None) -> int:
    from canbrake.bus.memory_shm import proc_start_time

    return proc_start_time(pid) if pid else 0


def _pid_running(pid: int | None, start: int) -> bool:
    """Is process ``pid`` (started at ``start``, /proc ticks) still running (not a zombie)?"""
    if not pid:
        return False
    try:
        with open(f"/proc/{pid}/stat", "rb") as f:
            fields = f.read().rsplit(b")", 1)[1].split()
    except OSError:
        return False
    return fields[0] != b"Z" and (not start or int(fields[19]) == start)


def _ecu_process_name(placed: Any, car: Any) -> str:
    """Name of an ECU process: the ECU's name, or "first..last" for a process hosting several."""
    name = lambda i: placed[i - 1] if isinstance(placed[i - 1], str) else placed[i - 1].name  # noqa: E731
    if isinstance(car, (tuple, list)):
        return name(car[0]) if len(car) == 1 else f"{name(car[0])}..{name(car[-1])}"
    return name(car)


def _start_timeout_s() -> float:
    """How long node processes may take to start (s): CANBRAKE_START_TIMEOUT_S, default 120
    (an emulated VM needs far more just to import numpy and friends)."""
    try:
        return float(os.environ.get("CANBRAKE_START_TIMEOUT_S", "120"))
    except ValueError:
        return 120.0


#: What every node process imports; a forkserver imports it once and forks the nodes from there.
_NODE_MODULES = ["canbrake.run", "canbrake.build", "canbrake.nodes.driver", "canbrake.nodes.plant",
                 "canbrake.nodes.ecu", "canbrake.nodes.recorder", "canbrake.bus.memory"]


def _mp_context() -> Any:
    """The start method for node processes: ``forkserver`` with the node modules preloaded where
    the platform has it (each node starts in milliseconds instead of importing numpy, scipy,
    pydantic and cantools anew: ~0.6 s of CPU per node here, minutes in an emulated VM), else
    ``spawn``. Never plain ``fork``: the parent may run threads (Dask, pytest plugins).
    CANBRAKE_START_METHOD=spawn|forkserver overrides the choice."""
    method = os.environ.get("CANBRAKE_START_METHOD", "")
    if method not in ("spawn", "forkserver"):
        method = "forkserver" if "forkserver" in mp.get_all_start_methods() else "spawn"
    ctx = mp.get_context(method)
    if method == "forkserver":
        ctx.set_forkserver_preload(_NODE_MODULES)  # takes effect when the server first starts
        from multiprocessing import forkserver

        try:
            with server_imports_this_canbrake():
                forkserver.ensure_running()
        except OSError:
            # The server listens on a unix socket under TMPDIR, which fails when TMPDIR is too
            # long for a socket path or on a file system that cannot hold one (9p, some FUSE).
            ctx = mp.get_context("spawn")
    return ctx


class StallWatch:
    """Decides when a multi-process run has stalled: no new plant tick for ``stall_s`` seconds
    (``start_s`` before the first tick) while the nodes are not computing. Nodes that used more
    than ``busy_share`` of one CPU over a window without a tick (e.g. every ECU process simulating
    the bus timing model ahead) are making progress, for at most ``grace`` windows in all, so a
    node looping forever still ends the run."""

    def __init__(self, start_s: float, stall_s: float, *, busy_share: float = 0.2, grace: int = 10) -> None:
        self.start_s, self.stall_s, self.busy_share, self.grace = start_s, stall_s, busy_share, grace
        self.tick: int | None = None
        self.changed = self.window = 0.0
        self.cpu: float | None = None

    def update(self, tick: int, now: float, cpu_s: Callable[[], float | None]) -> str | None:
        """``tick``: the plant's progress; ``now`` (s); ``cpu_s()``: the nodes' CPU seconds so far.
        Returns the failure message once the run has stalled, else None."""
        if tick != self.tick:
            self.tick, self.changed, self.window, self.cpu = tick, now, now, cpu_s()
            return None
        limit = self.start_s if tick < 0 else self.stall_s
        if now - self.window <= limit:
            return None
        cpu = cpu_s()
        busy = cpu is not None and self.cpu is not None and cpu - self.cpu > self.busy_share * (now - self.window)
        if busy and now - self.changed < self.grace * limit:
            self.window, self.cpu = now, cpu
            return None
        where = "before the first tick" if tick < 0 else f"at tick {tick}"
        why = ("while its nodes kept computing" if busy else
               "(a node is waiting for frames that never came, or is stopped: see frames.log)")
        return f"run stalled {where}: no progress for {now - self.changed:.0f} s {why}"


def _processes_cpu_s(pids: list[int]) -> float | None:
    """User + system CPU seconds used so far by the processes ``pids`` (Linux /proc; None elsewhere).
    Written by hand: psutil is not a dependency, and two fields of /proc/PID/stat are all it takes."""
    tck = os.sysconf("SC_CLK_TCK") if hasattr(os, "sysconf") else 100
    total = 0.0
    for pid in pids:
        try:
            with open(f"/proc/{pid}/stat", "rb") as f:
                fields = f.read().rsplit(b")", 1)[1].split()
        except (OSError, IndexError):
            if not os.path.isdir("/proc"):
                return None
            continue  # it has just exited
        total += (int(fields[11]) + int(fields[12])) / tck  # utime, stime (fields 14, 15 of stat)
    return total


def run_processes(scn: Scenario, run_dir: Path, choice: BusChoice, *, stall_timeout_s: float = 60.0,
                  start_timeout_s: float | None = None) -> dict[str, Any]:
    """Run plant, ECUs and recorder as separate OS processes; supervise until done.

    Returns the outcome: ``status`` ok / failed / interrupted, ``message`` (which process, which
    signal or exit status), ``wall_time_s``, ``ticks`` (the plant's last progress) and
    ``live_nodes`` (processes that could not be stopped; their files must not be touched)."""
    clean_killed_runs()
    # decided once, before the nodes start, and before the forkserver: a server just started is
    # still importing the node code (~0.6 s of CPU), and counted as other work runnable it made
    # the choice "busy, no yield" whenever the load average was at the CPUs (as between a
    # bench's cases), though yielding was the faster (`canbrake bench`: 1,658 vs 1,907 periods/s)
    yield_ = memory_yield()
    with children_skip_main():
        ctx = _mp_context()
    env = {k: v for k, v in os.environ.items() if k.startswith("CANBRAKE_")}
    env.update(PACKAGE_ENV, CANBRAKE_IMPORT=",".join(controller_modules(scn)))
    env["CANBRAKE_MEMORY_YIELD"] = "1" if yield_ else "0"
    if start_timeout_s is None:
        start_timeout_s = _start_timeout_s()
    placed = scn.placement()
    per = max(1, scn.ecu.per_process)
    own = [i for i, p in enumerate(placed, start=1) if not p.external]  # external ECUs are not started
    if per == 1:
        ecu_roles: list[tuple[str, Any]] = [("ecu", i) for i in own]
    else:  # several ECUs hosted per process (canbrake.nodes.group)
        ecu_roles = [("ecu", tuple(own[i:i + per])) for i in range(0, len(own), per)]
    roles = [("recorder", 0)] + ecu_roles + [("plant", 0)]
    barrier = ctx.Barrier(len(roles))
    progress = ctx.Value("q", -1, lock=False)
    failure = ctx.Array("c", 512)  # a node's last error line when it cannot write its log (_leave_failure)
    record = _write_run_record(ctx, barrier, choice)
    data = scn.model_dump(mode="json")
    data["_ecu_names"] = {str(i): p.name for i, p in enumerate(placed, start=1)}
    procs: dict[str, mp.process.BaseProcess] = {}
    starts: dict[str, int] = {}
    t_start = time.time()
    outcome: dict[str, Any] = {"status": "ok", "message": ""}
    old_term = old_int = None
    main = threading.current_thread() is threading.main_thread()
    if main:
        def _on_term(signum: int, frame: Any) -> None:
            raise Terminated

        old_term = signal.signal(signal.SIGTERM, _on_term)  # `kill` ends a run as cleanly as Ctrl-C
    try:
        for role, car in roles:
            name = role if role != "ecu" else _ecu_process_name(placed, car)
            p = ctx.Process(target=_child_main, name=f"canbrake-{name}",
                            args=(role, car, data, str(run_dir), choice, barrier, progress, os.getpid(),
                                  env, failure))
            with children_skip_main():
                p.start()
            procs[name] = p
            starts[name] = _pid_start(p.pid)
        watch = StallWatch(start_timeout_s, stall_timeout_s)
        while True:
            alive = [p for p in procs.values() if p.exitcode is None]
            failed = [(n, p) for n, p in procs.items() if p.exitcode not in (None, 0)]
            if failed:
                n, p = failed[0]
                if _pid_running(p.pid, starts[n]):
                    raise RunFailure(f"lost contact with {n} (pid {p.pid}), which is still running: "
                                     f"multiprocessing's forkserver exited or was killed")
                detail = _failure_detail(run_dir, n, failure)
                raise RunFailure(f"{n} (pid {p.pid}) {_signal_name(p.exitcode)}{detail}")
            if not alive:
                break
            plant = procs["plant"]
            if plant.exitcode == 0:
                # The plant sent the end-of-run SYNC; the others stop on it. After an early end
                # (diverged), nodes without authentication do not trust that END (it could be
                # forged, canbrake.bus.guard): the run is over, so they are stopped here.
                plant_status = _load_plant_status(run_dir)
                if plant_status == "external_missing":
                    from canbrake.external import missing_message

                    raise RunFailure(missing_message(scn, run_dir, choice.describe()))
                early = plant_status == "diverged"
                deadline = time.time() + (2.0 if early else 10.0)
                for p in alive:
                    p.join(max(0.0, deadline - time.time()))
                stuck = [n for n, p in procs.items() if p.exitcode is None]
                if stuck and early:
                    for n in stuck:
                        procs[n].terminate()
                        procs[n].join(10.0)
                    break
                if stuck:
                    raise RunFailure(f"{', '.join(stuck)} did not stop after the end of the run")
                continue
            mp.connection.wait([p.sentinel for p in alive], timeout=0.5)
            tick = progress.value
            verdict = watch.update(tick, time.time(), lambda: _processes_cpu_s([p.pid for p in alive]))
            if verdict is not None:
                raise RunFailure(verdict)
    except Terminated:
        outcome = {"status": "interrupted", "message": "terminated by SIGTERM"}
    except KeyboardInterrupt:
        outcome = {"status": "interrupted", "message": "interrupted by the user (Ctrl-C)"}
    except RunFailure as e:
        outcome = {"status": "failed", "message": str(e)}
    finally:
        again: list[int] = []
        if main:  # a second Ctrl-C/SIGTERM must not cut the clean-up short (it is bounded: ~7 s)
            old_int = signal.signal(signal.SIGINT, lambda s, f: again.append(s))
            signal.signal(signal.SIGTERM, lambda s, f: again.append(s))
        try:
            live = _reap(procs, starts)
            barrier.abort()
        finally:
            if main:
                signal.signal(signal.SIGINT, old_int)
                signal.signal(signal.SIGTERM, old_term)
    outcome["live_nodes"] = live
    if live:
        outcome["message"] = (outcome["message"] + "; " if outcome["message"] else "") + \
            f"could not stop {', '.join(live)}: their files were left as they are"
        if outcome["status"] == "ok":
            outcome["status"] = "failed"
    outcome["ticks"] = max(int(progress.value), 0)
    outcome["wall_time_s"] = time.time() - t_start
    if not live:
        drop_temp_files(run_dir, [p.pid for p in procs.values() if p.pid])
    if record is not None and not live:
        record.unlink(missing_ok=True)
    return outcome


def drop_temp_files(run_dir: Path, pids: list[int]) -> list[str]:
    """Remove the temporary files a node process killed while it wrote a file atomically left in
    the run directory (``.NAME.tmpPID`` of :func:`canbrake.atomic.write_text_atomic`, in the
    run directory, ``logs/`` and ``processes/``): once every process of the run is reaped none will
    rename them, and a run directory holds only whole files. Returns the names removed."""
    gone: list[str] = []
    if not pids:
        return gone
    for d in (run_dir, run_dir / "logs", run_dir / "processes"):
        try:
            entries = list(d.iterdir())
        except OSError:
            continue
        for f in entries:
            if is_temp_of(f.name, pids):
                try:
                    f.unlink()
                    gone.append(str(f.relative_to(run_dir)))
                except OSError:
                    pass
    return gone


# ----------------------------------------------------------------------------- leftovers of killed runs
def _run_records_dir() -> Path:
    from canbrake.bus.memory_shm import resolve_dir

    return Path(resolve_dir())


def _write_run_record(ctx: Any, barrier: Any, choice: BusChoice) -> Path | None:
    """Note what this run leaves in shared places if all its processes are killed (SIGKILL of the
    whole process group): its named semaphores, multiprocessing's temporary directory and its
    in-memory channel. The next run removes them (:func:`clean_killed_runs`); a run that ends
    normally removes the note."""
    import multiprocessing.util as mp_util

    sems = []
    cond = getattr(barrier, "_cond", None)
    for part in ("_lock", "_sleeping_count", "_woken_count", "_wait_semaphore"):
        name = getattr(getattr(getattr(cond, part, None), "_semlock", None), "name", None)
        if name:
            sems.append(name)
    from multiprocessing import forkserver

    servers = [getattr(forkserver._forkserver, "_forkserver_pid", None)]  # noqa: SLF001
    rec = {"pid": os.getpid(), "start": _pid_start(os.getpid()), "semaphores": sems,
           "tempdir": mp_util.get_temp_dir(), "server_pids": [p for p in servers if p],
           "channel": choice.channel if choice.backend == "memory" else None}
    path = _run_records_dir() / f"canbrake-run-{os.getpid()}.json"
    try:
        path.write_text(json.dumps(rec))
        path.chmod(0o600)
    except OSError:
        return None
    return path


def live_runs() -> list[dict[str, Any]]:
    """The notes of this user's canbrake runs that are still running (pid, channel, ...)."""
    out = []
    for note in _run_records_dir().glob("canbrake-run-*.json"):
        try:
            if note.lstat().st_uid != os.geteuid():
                continue
            rec = json.loads(note.read_text())
        except (OSError, ValueError):
            continue
        if _pid_running(rec.get("pid"), rec.get("start", 0)):
            out.append(rec)
    return out


def clean_killed_runs() -> list[str]:
    """Remove what runs killed with SIGKILL left behind (their note, named semaphores,
    multiprocessing temporary directory, in-memory channel), for runs of this user whose
    orchestrator and forkserver are gone. Returns the removed paths/names."""
    import shutil

    removed: list[str] = []
    for note in _run_records_dir().glob("canbrake-run-*.json"):
        try:
            st = note.lstat()
            if st.st_uid != os.geteuid():
                continue
            rec = json.loads(note.read_text())
        except (OSError, ValueError):
            continue
        if _pid_running(rec.get("pid"), rec.get("start", 0)) or any(_pid_running(p, 0) for p in rec.get("server_pids", [])):
            continue
        try:
            import _multiprocessing

            for name in rec.get("semaphores", []):
                try:
                    _multiprocessing.sem_unlink(name)
                    removed.append(name)
                except OSError:
                    pass
        except ImportError:
            pass
        tmp = rec.get("tempdir")
        if tmp and Path(tmp).name.startswith("pymp-") and Path(tmp).is_dir():
            shutil.rmtree(tmp, ignore_errors=True)
            removed.append(tmp)
        if rec.get("channel"):
            try:
                from canbrake.bus.memory import remove_channel

                if remove_channel(rec["channel"]):
                    removed.append(rec["channel"])
            except (can.CanError, OSError):
                pass
        note.unlink(missing_ok=True)
    return removed


def _load_plant_status(run_dir: Path) -> str | None:
    """Status the plant wrote in plant_stats.json when it closed (None if unreadable)."""
    try:
        return json.loads((run_dir / "plant_stats.json").read_text()).get("status")
    except (OSError, ValueError):
        return None


def _failure_detail(run_dir: Path, name: str, failure: Any = None) -> str:
    """The last line of a failed node's traceback: from logs/<name>.log, else from the shared
    ``failure`` string the node left when its log could not be written (:func:`_leave_failure`)."""
    log = run_dir / "logs" / f"{name}.log"
    try:
        lines = [ln for ln in log.read_text().splitlines() if ln.strip()]
    except OSError:
        lines = []
    if lines:
        return f": {lines[-1].strip()} (traceback in {log})"
    note = failure.value.decode(errors="replace") if failure is not None else ""
    if note.startswith(f"{name}\t"):
        return f": {note.split(chr(9), 1)[1]} (its log could not be written)"
    return ""


def _reap(procs: dict[str, mp.process.BaseProcess], starts: dict[str, int] | None = None) -> list[str]:
    """Terminate and join every child; kill the ones that ignore SIGTERM. Children whose exit
    multiprocessing cannot see (their forkserver died) are found by pid and start time and
    signalled directly. Returns the names of processes still running afterwards."""
    starts = starts or {}
    for p in procs.values():
        if p.exitcode is None:
            p.terminate()
    deadline = time.time() + 5.0
    for p in procs.values():
        p.join(max(0.0, deadline - time.time()))
    for p in procs.values():
        if p.exitcode is None:
            p.kill()
            p.join(2.0)
    orphans = {n: p.pid for n, p in procs.items() if _pid_running(p.pid, starts.get(n, 0))}
    for sig in (signal.SIGTERM, signal.SIGKILL):
        for pid in orphans.values():
            try:
                os.kill(pid, sig)
            except OSError:
                pass
        deadline = time.time() + (3.0 if sig == signal.SIGTERM else 2.0)
        while time.time() < deadline and any(_pid_running(pid, starts.get(n, 0)) for n, pid in orphans.items()):
            time.sleep(0.05)
        orphans = {n: pid for n, pid in orphans.items() if _pid_running(pid, starts.get(n, 0))}
        if not orphans:
            break
    return sorted(orphans)


# ----------------------------------------------------------------------------- in-process
def run_in_process(scn: Scenario, run_dir: Path | None, choice: BusChoice) -> dict[str, Any]:
    """All nodes in this process (python-can virtual buses, or direct delivery)."""
    from canbrake.build import build_nodes
    from canbrake.nodes.base import buffered_traces
    from canbrake.nodes.driver import NodeCrash, NodeFailure, run_inprocess

    import warnings

    import numpy as np

    nodes = build_nodes(scn, run_dir, channel=choice.log_channel)
    t0 = time.time()
    status = "failed"
    try:
        # a diverging plant overflows before it notices: the verdict reports it, not numpy's warnings
        with warnings.catch_warnings(), np.errstate(over="ignore", invalid="ignore"), buffered_traces():
            warnings.simplefilter("ignore", RuntimeWarning)
            run_inprocess(nodes, medium="virtual" if choice.backend == "virtual" else "direct")
        status = "ok"
        return {"status": "ok", "message": "", "wall_time_s": time.time() - t0}
    except NodeFailure as e:
        msg = str(e)
        if isinstance(e, NodeCrash) and run_dir is not None:  # its traceback where a node process leaves it
            logs = run_dir / "logs"
            try:
                logs.mkdir(exist_ok=True)
                from canbrake.atomic import write_text_atomic

                write_text_atomic(logs / f"{e.node}.log", "".join(traceback.format_exception(e.__cause__)))
                msg += f" (traceback in {logs / f'{e.node}.log'})"
            except OSError:
                pass
        return {"status": "failed", "message": msg, "wall_time_s": time.time() - t0}
    finally:
        first: BaseException | None = None
        for n in nodes:  # every node closes (and trims its files), also when one fails to (a full disk)
            try:
                n.close(status)
            except BaseException as e:  # noqa: BLE001 - raised below, after the others closed
                first = first or e
        if first is not None:
            raise first


# ----------------------------------------------------------------------------- entry
def run_scenario(scn: Scenario, out_dir: str | Path, *, backend: str | None = None, channel: str | None = None,
                 interface: str | None = None, dbc_path: str | Path | None = None, plots: bool = True,
                 stall_timeout_s: float = 60.0) -> dict[str, Any]:
    """Run ``scn`` and write the run directory. Returns the summary (also in summary.json).

    Raises :class:`ScenarioError` for bad input (before anything runs); a failure during the run
    is reported in the summary's ``status``/``message`` (and all logs written so far are kept).
    """
    from canbrake.analysis.summary import finalize_run

    choice = preflight(scn, backend, channel, interface)
    run_dir = prepare_run_dir(scn, out_dir, dbc_path)
    t0 = time.time()
    try:
        if choice.backend in ("virtual", "inprocess"):
            outcome = run_in_process(scn, run_dir, choice)
        else:
            outcome = run_processes(scn, run_dir, choice, stall_timeout_s=stall_timeout_s)
    except OSError as e:  # a full disk or a vanished run directory while a node writes
        outcome = {"status": "failed", "wall_time_s": time.time() - t0,
                   "message": f"cannot write the run directory {run_dir}: {e.strerror or e}"}
    except KeyboardInterrupt as e:
        outcome = {"status": "interrupted", "wall_time_s": time.time() - t0,
                   "message": "terminated by SIGTERM" if isinstance(e, Terminated) else "interrupted by the user (Ctrl-C)"}
    finally:
        # from here on a further Ctrl-C is noted, not obeyed: the summary must be written
        old_int = signal.signal(signal.SIGINT, lambda s, f: None) \
            if threading.current_thread() is threading.main_thread() else None
        try:
            if choice.backend == "memory":
                _remove_memory_channel(choice.channel)
        finally:
            pass
    try:
        return finalize_run(scn, run_dir, choice.describe(), outcome, plots=plots)
    finally:
        if old_int is not None:
            signal.signal(signal.SIGINT, old_int)


def preflight(scn: Scenario, backend: str | None = None, channel: str | None = None,
              interface: str | None = None, source: str | None = None) -> BusChoice:
    """Every check that can fail on bad input, before anything is written or started.
    Raises :class:`ScenarioError` (exit 2); ``source`` (the scenario file) prefixes the message."""
    try:
        choice = choose_bus(scn, backend, channel, interface)
        check_buildable(scn)
        from canbrake.build import bus_layout
        from canbrake.bus.schedule import check_faults

        check_faults(scn, bus_layout(scn))
        check_impairment_targets(scn)
        external = [p.name for p in scn.placement() if p.external]
        if external and choice.backend in ("virtual", "inprocess"):
            raise ScenarioError(f"ecus: external ECU {', '.join(external)} needs a bus other programs can reach: "
                                f"--bus memory (python-can interface canbrake) or --bus socketcan, not {choice.backend}")
        if choice.backend == "memory":
            _check_memory_channel(scn, choice, explicit=bool(channel or scn.bus.channel))
        if scn.security is not None:
            from canbrake.bus.secoc import KeyFileError, load_key

            try:
                load_key(scn.security.key_file)
            except KeyFileError as e:
                raise ScenarioError(f"security.key_file: {e}") from None
            from canbrake.build import bus_layout

            try:
                bus_layout(scn).database()  # secured layouts: every MAC must fit
            except ValueError as e:
                raise ScenarioError(str(e)) from None
        if choice.backend == "socketcan" and choice.interface == "socketcan":
            from canbrake.bus.vcan import VcanError, check_socketcan_channel

            try:
                check_socketcan_channel(choice.channel or "vcan0")
            except VcanError as e:
                raise ScenarioError(f"--channel {choice.channel}: {e}") from None
            from canbrake.bus.link import check_socketcan_link

            check_socketcan_link(scn, choice.channel or "vcan0")
        elif choice.backend == "adapter":
            _check_adapter(choice)
        if choice.backend not in ("virtual", "inprocess"):
            controller_modules(scn)
        from canbrake.nodes.recorder import check_log_format

        try:
            check_log_format(scn.bus.log_format)
        except ValueError as e:
            raise ScenarioError(str(e)) from None
    except ScenarioError as e:
        if source and not str(e).startswith(source) and not str(e).startswith("--"):
            raise ScenarioError(f"{source}: {e}") from None
        raise
    return choice


def check_impairment_targets(scn: Scenario) -> None:
    """Every impairment must match something of this train: its ``senders``/``receivers``/
    ``sender`` name a node of the run (plant, ecu1..ecuN, or a babbling device it defines) and its
    ``ids`` are frames of the run's DBC. An impairment that matches nothing is a typo, not a result."""
    from canbrake.build import bus_layout

    placed = scn.placement()
    nodes = {"plant", "recorder"} | {p.name for p in placed}
    babblers = {getattr(s, "sender", None) for s in scn.bus.impairments if getattr(s, "type", "") == "babble"}
    known_nodes = nodes | {b for b in babblers if b}
    ids = {m.frame_id for m in bus_layout(scn).messages}
    for i, spec in enumerate(scn.bus.impairments):
        for field_name in ("senders", "receivers"):
            names = getattr(spec, field_name, None) or []
            bad = [x for x in names if x not in known_nodes]
            if bad:
                raise ScenarioError(f"bus.impairments.{i}.{field_name}: {', '.join(map(str, bad))} is not a node of "
                                    f"this run (nodes: plant, {', '.join(p.name for p in placed[:4])}"
                                    f"{', ...' if len(placed) > 4 else ''})")
        spec_ids = getattr(spec, "ids", None) or []
        if getattr(spec, "type", "") != "babble":
            bad_ids = [x for x in spec_ids if x not in ids]
            if bad_ids:
                raise ScenarioError(f"bus.impairments.{i}.ids: {', '.join(hex(x) for x in bad_ids)} is not a frame of "
                                    f"this run's DBC (its canbrake.dbc lists them)")


def _check_memory_channel(scn: Scenario, choice: BusChoice, explicit: bool) -> None:
    """The in-memory channel is usable: a valid name, room for every node, files owned by this
    user and not writable by others, and not in use by another run (unless CANBRAKE_JOIN=1)."""
    from canbrake.bus import memory_shm as shm

    try:
        shm.validate_channel(choice.channel)
    except can.CanError as e:
        raise ScenarioError(f"--channel {choice.channel}: {e}") from None
    per = max(1, getattr(scn.ecu, "per_process", 1))
    need = -(-len(scn.placement()) // per) + 2  # ECU processes, plant, recorder
    if need > shm.MAX_READERS:
        raise ScenarioError(f"ecus: {need - 2} ECU processes need {need} buses on the in-memory channel, "
                            f"which holds {shm.MAX_READERS} (host several ECUs per process with ecu.per_process, "
                            f"or use --bus socketcan or inprocess)")
    try:  # before cleaning: a file someone else could have planted is reported, not silently removed
        shm.check_channel_owner(choice.channel)
    except can.CanError as e:
        raise ScenarioError(f"--channel {choice.channel}: {e}") from None
    shm.clean_stale_channels()
    if explicit and os.environ.get("CANBRAKE_JOIN") != "1":
        runs = [r["pid"] for r in live_runs() if r.get("channel") == choice.channel and r.get("pid") != os.getpid()]
        if runs:
            raise ScenarioError(f"--channel {choice.channel}: in use by another canbrake run (pid "
                                f"{', '.join(map(str, runs))}); choose another channel, or set CANBRAKE_JOIN=1 "
                                f"to join it on purpose (python-can tools may always attach)")


def _check_adapter(choice: BusChoice) -> None:
    """Open and close the adapter once here, so that a missing driver, device or permission is one
    message (exit 2) instead of every node process failing."""
    try:
        bus = can.Bus(interface=choice.interface, channel=choice.channel, **choice.bus_kwargs)
    except (can.CanError, OSError, ImportError, ValueError, TypeError) as e:
        first = str(e).splitlines()[0] if str(e) else type(e).__name__
        where = f"--interface {choice.interface}" + (f" --channel {choice.channel}" if choice.channel else
                                                     " (no --channel)")
        raise ScenarioError(f"{where}: cannot open the python-can bus: {first}") from None
    bus.shutdown()


def _controller_fields(scn: Scenario) -> dict[int, str]:
    """The scenario field of each ECU entry's own controller (``ecus.2.controller``), by the
    controller object's id; a placed ECU not in it runs the top-level ``controller``."""
    return {id(e.controller): f"ecus.{i}.controller" for i, e in enumerate(scn.ecus) if e.controller is not None}


def check_controller_params(scn: Scenario) -> None:
    """Every placed controller's parameters against its schema (canbrake.control.base.check_params);
    raises :class:`ScenarioError` naming the field (``controller.params.k``, ``ecus.2.controller...``)."""
    from canbrake.control.base import ControllerError, check_params

    where = _controller_fields(scn)
    for p in scn.placement():
        field = where.get(id(p.controller), "controller")
        try:
            check_params(p.controller.name, p.controller.params)
        except ControllerError as e:
            raise ScenarioError(f"{field}.params.{e.param}: {e}" if e.param else f"{field}.name: {e}") from None


def check_buildable(scn: Scenario) -> None:
    """Build the plant, the bus layout and every controller once in this process, so that
    parameters the schema passes through (``controller.params``, data files) fail here with
    exit 2 rather than in a child."""
    from canbrake.build import build_controller, build_plant_model, bus_layout, reference_fn

    check_controller_params(scn)
    placed = scn.placement()
    try:
        for i in range(1, len(placed) + 1):
            build_controller(scn, i)
    except (TypeError, ValueError) as e:
        raise ScenarioError(f"controller.params: {e}") from None
    try:
        bus_layout(scn)
    except ValueError as e:
        raise ScenarioError(f"ecus: {e}") from None
    try:
        reference_fn(scn)
    except ValueError as e:
        raise ScenarioError(str(e)) from None
    try:
        model = build_plant_model(scn)
    except ValueError as e:
        raise ScenarioError(f"train: {e}") from None
    check_plant_contract(scn, model)


def check_plant_contract(scn: Scenario, model: Any) -> None:
    """Every sensor a placed controller reads is a measurement of this train's plant, and every
    command it sends is one the plant takes (physics/contract.py); otherwise the controller would
    meet a missing value in the plant process, or its commands would be dropped without a word.
    Raises :class:`ScenarioError` naming the controller field, the ECU, the signal and the plant's."""
    from canbrake.build import bus_layout

    measured = set(model.measurements())
    takes = set(getattr(model, "command_names", ()))
    kernel = scn.train.kernel_name
    where = _controller_fields(scn)
    for p, spec in zip(scn.placement(), bus_layout(scn).ecus):
        field = where.get(id(p.controller), "controller")
        reads = ["deflection_m" if s in ("deflection_front_m", "deflection_rear_m") else s for s in spec.sensors]
        missing = [s for s in reads if s not in measured]
        if missing:
            raise ScenarioError(f"{field}.name: {p.controller.name} on {p.name} reads {missing[0]}, which this train's "
                                f"plant ({kernel} kernel) does not measure (it measures "
                                f"{', '.join(sorted(x for x in measured if not x.startswith('axle')))})")
        dropped = [c for c in spec.commands if c not in takes]
        if dropped:
            raise ScenarioError(f"{field}.name: {p.controller.name} on {p.name} commands {dropped[0]}, which this "
                                f"train's plant ({kernel} kernel) does not take (it takes {', '.join(sorted(takes))})")


def _remove_memory_channel(channel: str | None) -> None:
    """Remove the run's temporary in-memory channel (every node has exited by now)."""
    if not channel:
        return
    from canbrake.bus.memory import remove_channel

    try:
        remove_channel(channel)
    except can.CanError as e:
        print(f"canbrake: warning: in-memory channel {channel} not removed: {e}", file=sys.stderr)


def write_json(path: Path, data: Any) -> None:
    path.write_text(json.dumps(data, indent=1, sort_keys=False))


make_module_callable(__name__)  # canbrake.run(...) is the API's run (canbrake/api.py)
