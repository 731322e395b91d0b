"""Run a report's runs on worker processes, and stop them all on Ctrl-C or SIGTERM.

A report runs its scenarios on ``jobs`` spawned workers (``concurrent.futures``). The executor's
own ``with`` block waits on an interrupt for every queued task, so a Ctrl-C went on starting the
remaining runs for minutes and ended in a traceback. Here an interrupt (Ctrl-C, or SIGTERM, which
``canbrake.cli`` turns into ``KeyboardInterrupt``) or a failed task cancels what has not started,
asks each busy worker to end its run as ``canbrake run`` ends one on SIGTERM (node processes
reaped, the run directory marked interrupted), waits for them, and re-raises.
"""
from __future__ import annotations

import os
import signal
from typing import Any, Callable, Iterable, TypeVar

T = TypeVar("T")
R = TypeVar("R")


_busy = False      # in a worker: is a task running?
_stopping = False  # in a worker: SIGTERM came; tasks already queued to it are not started


def _worker_init() -> None:
    """In a worker: the terminal's Ctrl-C is the parent's to act on (it reaches the whole process
    group); SIGTERM from the parent ends the current run cleanly (``run.Terminated``), or an idle
    worker quietly."""
    from canbrake.run import Terminated

    def _term(signum: int, frame: Any) -> None:
        global _stopping
        _stopping = True
        if _busy:
            raise Terminated
        raise SystemExit(0)

    signal.signal(signal.SIGINT, signal.SIG_IGN)
    signal.signal(signal.SIGTERM, _term)


def _call(fn: Callable[[T], R], task: T) -> R:
    global _busy
    if _stopping:
        from canbrake.run import Terminated

        raise Terminated
    _busy = True
    try:
        return fn(task)
    finally:
        _busy = False


def map_tasks(fn: Callable[[T], R], tasks: Iterable[T], jobs: int,
              each: Callable[[R], Any] | None = None) -> list[R]:
    """``[fn(t) for t in tasks]``, on ``jobs`` spawned worker processes when ``jobs > 1`` and there
    is more than one task (``fn`` must be picklable: a module-level function); results in task
    order, each also handed to ``each`` (e.g. a progress line) as soon as it and those before it are done."""
    tasks = list(tasks)
    out: list[R] = []
    if jobs <= 1 or len(tasks) <= 1:
        for t in tasks:
            out.append(fn(t))
            if each is not None:
                each(out[-1])
        return out
    import multiprocessing as mp
    from concurrent.futures import ProcessPoolExecutor

    ctx = _RecordingContext(mp.get_context("spawn"))
    ex = ProcessPoolExecutor(max_workers=min(jobs, len(tasks)), mp_context=ctx, initializer=_worker_init)
    try:
        futures = [ex.submit(_call, fn, t) for t in tasks]
        for f in futures:
            out.append(f.result())
            if each is not None:
                each(out[-1])
        return out
    except BaseException:
        # every worker the executor started (its own mapping misses one it is starting right now)
        ex.shutdown(wait=False, cancel_futures=True)
        for p in ctx.started:
            if p.exitcode is None:
                try:
                    os.kill(p.pid, signal.SIGTERM)
                except ProcessLookupError:
                    pass
        _reap(ctx.started, 60.0)
        raise
    finally:
        ex.shutdown(wait=True)
        _reap(ctx.started, 5.0)  # whatever the executor did after the interrupt


def _reap(procs: list[Any], wait_s: float) -> None:
    """Join each process still running, for at most ``wait_s``; kill (and join) one that is not done."""
    for p in procs:
        if p.exitcode is None:
            p.join(wait_s)
            if p.exitcode is None:
                p.kill()
                p.join(5.0)


class _RecordingContext:
    """A multiprocessing context that records every process it starts (the executor's workers),
    delegating everything else to ``ctx``."""

    def __init__(self, ctx: Any) -> None:
        self._ctx = ctx
        self.started: list[Any] = []

    def Process(self, *args: Any, **kwargs: Any) -> Any:  # noqa: N802 - multiprocessing's name
        p = self._ctx.Process(*args, **kwargs)
        self.started.append(p)
        return p

    def __getattr__(self, name: str) -> Any:
        return getattr(self._ctx, name)
