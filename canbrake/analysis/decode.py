"""Decode frame logs with a DBC, in the spirit of ``cantools decode`` (a filter in a pipe).

Any log python-can reads (.log candump -L, .asc, .blf, .csv, .trc, ...) or candump -L text on
stdin (``-``). Frames unknown to the DBC are printed undecoded, as cantools does.
"""
from __future__ import annotations

import io
import re
import sys
from pathlib import Path
from typing import Iterable, TextIO

import can
import cantools

from canbrake.bus import dbc as cdbc


class DecodeError(Exception):
    pass


#: a complete candump -L line (python-can's CanutilsLogWriter): (time) channel id#data [flags]
_CANDUMP_LINE = re.compile(r"^\(\d+(\.\d+)?\) \S+ [0-9A-Fa-f]{1,8}#(R\d?|#[0-9A-Fa-f][0-9A-Fa-f]*|([0-9A-Fa-f]{2})*)( [RT])?\s*$")


def _suffixes() -> list[str]:
    import can.io.player as player

    return sorted(player.MESSAGE_READERS)


def _check_log_path(log: str) -> Path:
    """The log exists, is a file and has a suffix python-can reads (``.gz`` around it is fine)."""
    from canbrake.errors import InputError

    p = Path(log)
    if not p.exists():
        raise InputError(f"{log}: no such log file")
    if p.is_dir():
        raise InputError(f"{log}: is a directory, not a frame log")
    suffix = "".join(p.suffixes[-2:-1]) if p.suffix.lower() == ".gz" else p.suffix
    if suffix.lower() not in _suffixes():
        raise InputError(f"{log}: python-can cannot read {suffix or 'files without a suffix'} logs "
                         f"(it reads {', '.join(_suffixes())}, optionally .gz)")
    return p


def _truncated_lines(lines: Iterable[str]) -> list[int]:
    """1-based numbers of candump lines cut short (odd hex digits, no data, missing fields)."""
    bad = []
    for i, ln in enumerate(lines, 1):
        if ln.strip() and not _CANDUMP_LINE.match(ln.rstrip("\n")):
            bad.append(i)
    return bad


def _iter_frames(log: str, warn: TextIO) -> Iterable[can.Message]:
    if log == "-":
        text = sys.stdin.read()
    else:
        p = _check_log_path(log)
        if p.suffix.lower() != ".log":
            return can.LogReader(str(p))
        text = p.read_text()
    lines = text.splitlines()
    bad = _truncated_lines(lines)
    if text and not text.endswith("\n") and len(lines) not in bad:
        bad.append(len(lines))  # a last line without its newline: the writer was cut off
    if bad:
        more = f" (and {len(bad) - 1} more)" if len(bad) > 1 else ""
        warn.write(f"canbrake: warning: {log}: line {bad[0]}{more} is not a complete candump -L frame "
                   f"(cut short?); skipped\n")
    keep = [ln for i, ln in enumerate(text.splitlines(), 1) if ln.strip() and i not in set(bad)]
    return can.io.CanutilsLogReader(io.StringIO("\n".join(keep) + "\n"))


def decode_log(log: str, dbc_path: str | None, out: TextIO, only: str | None = None,
               hide_sim_control: bool = False, warn: TextIO | None = None) -> int:
    """Print one decoded line per frame; returns the exit status. Raises InputError (exit 2) for
    a log python-can cannot read, an unknown ``only`` prefix, or a bad DBC; a closed ``out``
    (``| head``) raises BrokenPipeError, which the command line treats as a normal end.
    ``hide_sim_control``: leave out the lockstep barrier frames (STATE_DONE/CMD_DONE)."""
    from canbrake.errors import InputError
    from canbrake.nodes.recorder import is_sim_control

    warn = warn or sys.stderr
    if dbc_path is None and log != "-" and (Path(log).parent / "canbrake.dbc").exists():
        dbc_path = str(Path(log).parent / "canbrake.dbc")
    try:
        db = cantools.database.load_file(dbc_path) if dbc_path else cdbc.build_database(6)
    except FileNotFoundError:
        raise InputError(f"{dbc_path}: no such DBC file") from None
    except Exception as e:  # noqa: BLE001 - cantools raises several parse error types
        raise InputError(f"{dbc_path}: not a readable DBC file ({type(e).__name__})") from None
    if only and not any(m.name.startswith(only) for m in db.messages):
        raise InputError(f"--only {only}: no message of the DBC starts with it "
                         f"(messages: {', '.join(sorted(m.name for m in db.messages)[:12])}, ...)")
    count = 0
    try:
        frames = _iter_frames(log, warn)
        for msg in frames:
            count += 1
            if hide_sim_control and not msg.is_extended_id and is_sim_control(msg.arbitration_id):
                continue
            line = format_frame(db, msg, only)
            if line:
                out.write(line)
    except InputError:
        raise
    except BrokenPipeError:
        raise
    except FileNotFoundError:
        raise InputError(f"{log}: no such log file") from None
    except ValueError as e:
        raise InputError(f"{log}: not a frame log python-can can read (after {count} frames): {e}") from None
    except (OSError, UnicodeDecodeError) as e:
        if out_closed(e):
            raise BrokenPipeError from None
        raise InputError(f"{log}: cannot read: {e}") from None
    except Exception as e:  # noqa: BLE001 - python-can readers raise various errors on corrupt input
        raise InputError(f"{log}: corrupt log near frame {count + 1}: {type(e).__name__}: {e}") from None
    if count == 0 and log != "-" and Path(log).stat().st_size > 0:
        raise InputError(f"{log}: no frames in it: not a {Path(log).suffix} log python-can can read")
    return 0


def out_closed(e: BaseException) -> bool:
    import errno

    return isinstance(e, OSError) and e.errno == errno.EPIPE


def format_frame(db: cantools.database.can.Database, msg: can.Message, only: str | None = None) -> str:
    ch = "-" if msg.channel is None else msg.channel  # (channel 0: the first of a numbered format)
    if msg.is_error_frame:  # python-can's readers keep no id/data for error frames
        return "" if only else f"({msg.timestamp:.6f}) {ch} ERRORFRAME ::\n"
    head = f"({msg.timestamp:.6f}) {ch} {msg.arbitration_id:03X}#{bytes(msg.data).hex().upper()}"
    try:
        m = db.get_message_by_frame_id(msg.arbitration_id)
    except KeyError:
        return "" if only else head + " ::\n"
    if only and not m.name.startswith(only):
        return ""
    try:
        values = m.decode(bytes(msg.data), decode_choices=True, scaling=True)
    except Exception as e:  # noqa: BLE001 - a frame that does not fit its DBC entry
        return f"{head} :: {m.name}: cannot decode ({e})\n"
    parts = []
    for s in m.signals:
        v = values.get(s.name)
        parts.append(f"{s.name}: {v:g}{' ' + s.unit if s.unit else ''}" if isinstance(v, (int, float))
                     else f"{s.name}: {v}")
    return f"{head} :: {m.name}({', '.join(parts)})\n"
