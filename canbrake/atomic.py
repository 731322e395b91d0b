"""Whole-file writes: a temporary file beside the target, renamed over it.

One place for the temporary name (``.NAME.tmpPID``), so that the orchestrator, which removes
the temporary files of node processes killed mid-write (:func:`canbrake.run.drop_temp_files`),
recognises exactly what the writers create.
"""
from __future__ import annotations

import contextlib
import os
from pathlib import Path


def temp_suffix(pid: int) -> str:
    """The end of the temporary file names process ``pid`` writes (``.NAME.tmpPID``)."""
    return f".tmp{pid}"


def temp_path(path: Path) -> Path:
    """The temporary file this process writes ``path``'s new content to."""
    return path.with_name(f".{path.name}{temp_suffix(os.getpid())}")


def is_temp_of(name: str, pids: list[int]) -> bool:
    """Whether file ``name`` is a temporary file written by one of ``pids``."""
    return name.startswith(".") and name.endswith(tuple(temp_suffix(p) for p in pids))


def write_text_atomic(path: Path, text: str, fsync: bool = False) -> None:
    """Write ``text`` to a temporary file beside ``path`` (fsync'd if ``fsync``) and rename it
    over ``path``: a reader (and a full disk) leaves the old file or the whole new one, never an
    empty or partial one. Raises OSError (the temporary file removed)."""
    tmp = temp_path(path)
    try:
        with open(tmp, "w") as f:
            f.write(text)
            if fsync:
                f.flush()
                os.fsync(f.fileno())
        os.replace(tmp, path)
    except BaseException:
        with contextlib.suppress(OSError):
            tmp.unlink()
        raise
