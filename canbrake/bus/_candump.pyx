# cython: language_level=3
"""A period's frames as candump -L lines (``frames.log``), compiled: the text
``can.CanutilsLogWriter.on_message_received`` writes, for a whole period in one call.

Why not python-can's writer here: it is the contract and stays the writer of every other format
(.asc, .blf, .trc, .mf4) and of every frame outside the recorder's per-period path, but it needs
one ``can.Message`` and one Python call per frame, which was most of the recorder's cost per
period. So for the default format the recorder hands the period's (timestamp, frame) pairs here
and this writes the same bytes into the writer's own file, with the writer's own state (its
first timestamp, its default channel). ``tests/test_candump_compiled.py`` checks, with
hypothesis, that every line equals what ``can.CanutilsLogWriter`` writes for the same message.
"""
from libc.stdlib cimport free

from can.io.canutils import CAN_ERR_BUSERROR, CAN_ERR_FLAG

# the line itself: canbrake/bus/_candump.pxd (candump_line), shared with _wire.ideal_tick
assert CANDUMP_ERR_ID == CAN_ERR_FLAG | CAN_ERR_BUSERROR


def channel_name(channel, default):
    """The channel text ``can.CanutilsLogWriter`` writes for a message of ``channel`` (its
    default ``default`` if None; a number ``n`` as ``can<n>``)."""
    ch = channel if channel is not None else default
    if isinstance(ch, int) or (isinstance(ch, str) and ch.isdigit()):
        ch = f"can{ch}"
    return ch


def write_candump(writer, list stamped, channel) -> None:
    """Write ``stamped`` — (timestamp s, frame) pairs, each line as for
    ``can.Message(timestamp=timestamp, arbitration_id, is_extended_id, is_remote_frame,
    is_error_frame, dlc, data=frame.data, channel=channel, is_rx=True)`` (a frame: a
    ``can.Message``, or its memory-bus slot image, bytes of ``canbrake.bus._slot``) — through
    ``writer`` (a ``can.CanutilsLogWriter``) in one write, its state kept as it keeps it."""
    cdef Py_ssize_t i, n = len(stamped)
    cdef Buf b
    cdef double ts, last
    cdef bytes ch
    cdef object pair
    if n == 0:
        return
    ch = str(channel_name(channel, writer.channel)).encode("utf-8")
    if writer.last_timestamp is None:  # the very first message
        writer.last_timestamp = stamped[0][0] or 0.0
    last = writer.last_timestamp
    b.p, b.n, b.cap = NULL, 0, 0
    try:
        for i in range(n):
            pair = stamped[i]
            ts = pair[0]
            candump_line(&b, last if ts < last else ts, ch, len(ch), pair[1])
        writer.file.write(b.p[:b.n].decode("utf-8"))
    finally:
        free(b.p)
