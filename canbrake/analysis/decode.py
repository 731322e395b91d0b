"""Decode frame logs with a DBC, in the spirit of ``cantools decode`` (a filter in a pipe).

Any log python-can reads (.log candump -L, .asc, .blf, .csv, .trc, ...) or candump -L text on
stdin (``-``). Frames unknown to the DBC are printed undecoded, as cantools does.
"""
from __future__ import annotations

import io
import sys
from pathlib import Path
from typing import Iterable, TextIO

import can
import cantools

from canbrake.bus import dbc as cdbc


class DecodeError(Exception):
    pass


def _iter_frames(log: str) -> Iterable[can.Message]:
    if log == "-":
        text = sys.stdin.read()
        return can.io.CanutilsLogReader(io.StringIO(text))
    p = Path(log)
    if not p.exists():
        raise FileNotFoundError(log)
    return can.LogReader(str(p))


def decode_log(log: str, dbc_path: str | None, out: TextIO, only: str | None = None,
               hide_sim_control: bool = False) -> int:
    """Print one decoded line per frame; returns the exit status. ``hide_sim_control``: leave out
    the lockstep barrier frames (STATE_DONE/CMD_DONE)."""
    from canbrake.errors import InputError
    from canbrake.nodes.recorder import is_sim_control

    if dbc_path is None and log != "-" and (Path(log).parent / "canbrake.dbc").exists():
        dbc_path = str(Path(log).parent / "canbrake.dbc")
    try:
        db = cantools.database.load_file(dbc_path) if dbc_path else cdbc.build_database(6)
    except FileNotFoundError:
        raise InputError(f"{dbc_path}: no such DBC file") from None
    except Exception as e:  # noqa: BLE001 - cantools raises several parse error types
        raise InputError(f"{dbc_path}: not a readable DBC file ({type(e).__name__})") from None
    try:
        frames = _iter_frames(log)
        count = 0
        for msg in frames:
            count += 1
            if hide_sim_control and not msg.is_extended_id and is_sim_control(msg.arbitration_id):
                continue
            out.write(format_frame(db, msg, only))
    except FileNotFoundError:
        raise InputError(f"{log}: no such log file") from None
    except ValueError as e:
        raise InputError(f"{log}: not a frame log python-can can read (after {count} frames): {e}") from None
    except (OSError, UnicodeDecodeError) as e:
        raise InputError(f"{log}: cannot read: {e}") from None
    except Exception as e:  # noqa: BLE001 - python-can readers raise various errors on corrupt input
        raise InputError(f"{log}: corrupt log near frame {count + 1}: {type(e).__name__}: {e}") from None
    return 0


def format_frame(db: cantools.database.can.Database, msg: can.Message, only: str | None = None) -> str:
    if msg.is_error_frame:  # python-can's readers keep no id/data for error frames
        return "" if only else f"({msg.timestamp:.6f}) {msg.channel or '-'} ERRORFRAME ::\n"
    head = f"({msg.timestamp:.6f}) {msg.channel or '-'} {msg.arbitration_id:03X}#{bytes(msg.data).hex().upper()}"
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
