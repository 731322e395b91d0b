# cython: language_level=3
# distutils: extra_compile_args = -O2 -ffp-contract=off
"""An ECU's decision of a period, compiled (:meth:`canbrake.nodes.ecu.EcuNode._phase2`): its own
sensor values into its peer table, the peers' ages, the controller's
:class:`~canbrake.control.base.Observation`, the controller's step (timed) and the command frames
from its :class:`~canbrake.control.base.ControlOutput`, in one call per period.

Written by hand because it runs once per period in every ECU (Chen case 1: six per period in
process, one per process on the memory bus) and was ~25 Python lines around the controller; the
controller itself, what it receives and what it returns are unchanged. ``tests/test_ecu_period.py``
checks it against the Python it replaced (the Observation field by field, the frames byte for
byte, the peer table's arrays).
"""
from cpython.dict cimport PyDict_Copy, PyDict_GetItem, PyDict_SetItem
from cpython.list cimport PyList_GET_SIZE
from cpython.tuple cimport PyTuple_GET_ITEM
from cpython.buffer cimport PyBUF_C_CONTIGUOUS, PyBUF_FORMAT, PyBUF_WRITABLE, PyBuffer_Release, PyObject_GetBuffer
from cpython.mem cimport PyMem_Free, PyMem_Malloc
from cpython.object cimport PyObject, PyObject_GenericSetAttr
from libc.stdint cimport int64_t

import math
import time

from canbrake.bus import _codec
from canbrake.bus._ring import data_frame
from canbrake.bus.e2e import COUNTER_MODULO
from canbrake.nodes._trace import csv_dict_row
from canbrake.nodes._trace cimport write_str
from canbrake._buffers cimport is_f64_vector

cdef object _NEW = object.__new__
cdef object _perf_counter = time.perf_counter
cdef object _NAN = math.nan
cdef object _INF = math.inf
cdef str _SPEED = "speed_mps"
cdef str _POSITION = "position_m"
cdef str _FRONT = "deflection_front_m"
cdef str _REAR = "deflection_rear_m"
cdef str _STATUS_DIAG = "status"
cdef str _BRAKE = "brake_force_n"
# PeerTable.feed's events (canbrake.bus._codec.FEED_*) and its CRC rejection code
cdef int _EV_END = _codec.FEED_END, _EV_FRAME = _codec.FEED_FRAME, _EV_PHASE1 = _codec.FEED_PHASE1
cdef int _EV_PHASE2 = _codec.FEED_PHASE2, _EV_REJECT = _codec.FEED_REJECT, _EV_HELD = _codec.FEED_HELD
cdef int _EV_SYNC = _codec.FEED_SYNC
cdef int _REJECT_CRC = _codec.REJECT_CRC


cdef class EcuPeriod:
    """One ECU's period (``decide``) over its peer table ``table``
    (:class:`~canbrake.bus._codec.PeerTable`) and its sensor dict ``sensors``: ``own``: the
    names of its own sensor values that it writes into the table's arrays at its index ``i``;
    ``views``: the table's arrays as the controller sees them (read-only views), ``obs_cls``:
    the Observation class; ``cmd_msgs``: [(identifier, FieldCodec, keys)] of its command frames;
    ``status_key``: the key of their Status field; ``state_msgs``: [(identifier, FieldCodec, keys,
    its authenticator's identifier)] of its STATE frames, ``auth(authenticator id, identifier,
    payload, tick)``: a STATE frame's authenticator (SecOC) or None; ``pending``/``hist``: the controller step's
    wall times (s) not yet added to ``hist`` (:class:`~canbrake.nodes.base.LogHistogram`), added
    1,024 at a time; ``sign(identifier, payload, tick)``: a command frame's signature (SecOC)
    or None. With a trace (:meth:`set_trace`) each decision leaves its trace row pending
    (:meth:`write_row`; the next ``decide`` writes it first)."""

    cdef object table, obs_cls, hist, sign
    cdef dict sensors, views, arrays
    cdef tuple own
    # the peer table's array of each own name, as a pointer (the table keeps its arrays for its
    # life: PeerTable.values): this ECU's entry is written without numpy's indexing
    cdef double** own_ptr
    cdef Py_ssize_t n_own
    cdef list cmd_msgs, pending, state_msgs
    cdef object auth
    cdef object status_key
    cdef int i
    cdef object i_obj
    cdef double dt
    cdef bint has_front, has_rear
    # the trace: CsvTrace, its file's write (None: rows through CsvTrace.append_dict), the
    # controller's diagnostic names; the pending row (tick, force, diagnostics, max_age, fresh)
    cdef object trace, row_write
    cdef int row_fd  # the trace's file descriptor (rows written there at once), or -1
    cdef tuple diag_names
    cdef bint has_row
    cdef object row_k, row_force, row_diag, row_age, row_fresh

    def __init__(self, table, dict sensors, tuple own, int i, double dt, dict views, obs_cls, bint has_front,
                 bint has_rear, list cmd_msgs, status_key, list pending, hist, sign=None, list state_msgs=None,
                 auth=None):
        cdef Py_buffer view
        self.table = table
        self.sensors = sensors
        self.arrays = table.values
        self.own = own
        self.n_own = len(own)
        self.own_ptr = <double**>PyMem_Malloc((self.n_own if self.n_own > 0 else 1) * sizeof(double*))
        if self.own_ptr is NULL:
            raise MemoryError()
        for j, nm in enumerate(own):
            PyObject_GetBuffer(self.arrays[nm], &view, PyBUF_C_CONTIGUOUS | PyBUF_FORMAT | PyBUF_WRITABLE)
            try:
                if not is_f64_vector(&view) or not 0 <= i < view.shape[0]:
                    raise ValueError(f"peer table array {nm!r}: float64 with an entry {i} needed")
                self.own_ptr[j] = <double*>view.buf
            finally:
                PyBuffer_Release(&view)  # (the table's dict keeps the array, and so its memory)
        self.i = i
        self.i_obj = i
        self.dt = dt
        self.views = views
        self.obs_cls = obs_cls
        self.has_front = has_front
        self.has_rear = has_rear
        self.cmd_msgs = cmd_msgs
        self.status_key = status_key
        self.pending = pending
        self.hist = hist
        self.sign = sign
        self.state_msgs = state_msgs or []
        self.auth = auth

    def decide(self, controller, int64_t k, int64_t hold, bint in_fallback):
        """Tick ``k``'s decision: returns (the controller's output, its command frames,
        max_age, fresh, dropped). ``hold`` >= 0: peers whose newest value is more than that many
        periods old are NaN for the controller (:meth:`PeerTable.hold_copy`; ``dropped``: one
        was), -1: the controller sees the table's views; ``in_fallback``: the node's fallback
        state when ``hold`` is -1. ``max_age`` (s, -inf: none) and ``fresh`` as
        :meth:`PeerTable.ages`."""
        cdef dict sensors = self.sensors
        cdef dict peers
        cdef PyObject* p
        cdef bint dropped = False
        cdef Py_ssize_t n, j
        if self.has_row:  # the last period's row, before the controller makes this one's diagnostics
            self._write_row()
        for j in range(self.n_own):  # this ECU's own entries
            self.own_ptr[j][self.i] = <double>sensors[<object>PyTuple_GET_ITEM(self.own, j)]
        pt = self.table
        if hold >= 0:  # lost peers are NaN for the controller: a copy
            peers, dropped = pt.hold_copy(k, hold, self.i)
            in_fallback = dropped
            speed = peers[_SPEED]
            age, fresh, max_age = pt.ages(k, self.dt, self.i, speed, True)
        else:
            peers = self.views
            speed = peers[_SPEED]
            age, fresh, max_age = pt.ages(k, self.dt, self.i, None, True)
        obs = _NEW(self.obs_cls)
        f = {}
        f["tick"] = k
        f["time_s"] = <double>k * self.dt
        p = PyDict_GetItem(sensors, _SPEED)
        f["speed_mps"] = _NAN if p is NULL else <object>p
        p = PyDict_GetItem(sensors, _POSITION)
        f["position_m"] = _NAN if p is NULL else <object>p
        f["ref_speed_mps"] = pt.v_ref
        f["ref_decel_mps2"] = pt.a_ref
        f["peer_speed_mps"] = speed
        f["peer_position_m"] = peers[_POSITION]
        f["peer_age_s"] = age
        p = PyDict_GetItem(sensors, _FRONT) if self.has_front else NULL
        f["deflection_front_m"] = None if p is NULL else <object>p
        p = PyDict_GetItem(sensors, _REAR) if self.has_rear else NULL
        f["deflection_rear_m"] = None if p is NULL else <object>p
        f["ref_position_m"] = pt.x_ref
        f["sensors"] = PyDict_Copy(sensors)
        f["peer_signals"] = peers
        PyObject_GenericSetAttr(obs, "__dict__", f)  # a frozen dataclass: as Observation.of
        t0 = _perf_counter()
        result = controller.step(obs)
        pending = self.pending
        pending.append(_perf_counter() - t0)
        if PyList_GET_SIZE(pending) >= 1024:
            self.hist.add_many(pending)
            del pending[:]
        diag = result.diagnostics
        status = int(diag[_STATUS_DIAG]) if _STATUS_DIAG in diag else 0
        if in_fallback and status == 0:
            status = 1  # degraded: running without a lost peer
        # the command frames' values (a value that is not finite is left out of the frame)
        commands = result.commands
        values = {_BRAKE: result.brake_force_n, **commands} if commands else {_BRAKE: result.brake_force_n}
        values[self.status_key] = status
        counter = k % COUNTER_MODULO  # the E2E alive counter
        frames = []
        sign = self.sign
        for fid, codec, keys in self.cmd_msgs:
            cmd = codec.encode_from(values, keys, counter, k, True)
            if sign is not None:
                cmd = sign(fid, cmd, k)
            frames.append(data_frame(fid, cmd))
        if self.trace is not None:  # written later (write_row)
            self.has_row = True
            self.row_k = k
            self.row_force = result.brake_force_n
            self.row_diag = diag
            self.row_age = max_age if max_age > -math.inf else _INF
            self.row_fresh = fresh
        return result, frames, max_age, fresh, dropped

    def __cinit__(self, *args, **kwargs):
        self.own_ptr = NULL

    def __dealloc__(self):
        PyMem_Free(self.own_ptr)

    def set_trace(self, trace, tuple names):
        """Leave each decision's trace row to ``trace`` (:class:`~canbrake.nodes.base.CsvTrace`;
        None: no rows): tick, brake force, the diagnostics ``names`` (NaN where missing), max
        peer age (s; inf: none), peers fresh."""
        self.trace = trace
        self.row_write = None if trace is None else trace.row_write()
        self.row_fd = -1 if trace is None else trace.row_fd()
        self.diag_names = names
        self.has_row = False

    def write_row(self):
        """Write the row of the period last decided, if pending
        (:meth:`~canbrake.nodes.ecu.EcuNode.after_send`)."""
        if self.has_row:
            self._write_row()

    cdef _write_row(self):
        """The pending row: its text in one compiled call straight into the trace's file, or
        through ``CsvTrace.append_dict`` (rows flushed one by one, values it writes by the csv module)."""
        self.has_row = False
        head = [self.row_k, self.row_force]
        tail = [self.row_age, self.row_fresh]
        diag = self.row_diag
        self.row_diag = None
        if (self.row_write is not None or self.row_fd >= 0) and type(diag) is dict:
            text = csv_dict_row(head, diag, self.diag_names, _NAN, tail)
            if text is not None:
                if self.row_fd >= 0:  # a node process: handed to the OS now
                    write_str(self.row_fd, text)
                else:
                    self.row_write(text)
                return
        self.trace.append_dict(head, diag, self.diag_names, _NAN, tail)

    def state_frames(self, int64_t k, broadcast):
        """Tick ``k``'s STATE frames (phase 1), each followed by its authenticator with SecOC:
        the sensor values, over the broadcast values of the same name (``broadcast``: the
        controller's last; a value that is not finite is left out of the frame)."""
        cdef list frames = []
        values = {**broadcast, **self.sensors} if broadcast else self.sensors
        counter = k % COUNTER_MODULO
        auth = self.auth
        for fid, codec, keys, auth_id in self.state_msgs:
            payload = codec.encode_from(values, keys, counter, k)
            frames.append(data_frame(fid, payload))
            if auth is not None:  # its authenticator, right after it (canbrake.bus.secoc)
                frames.append(data_frame(auth_id, auth(auth_id, fid, payload, k)))
        return frames


def take_batch(node, feed, batch, message, bint raw, now):
    """An ECU's (:class:`~canbrake.nodes.ecu.EcuNode` ``node``) receive loop over ``batch``:
    the peer table's compiled loop ``feed`` (``PeerTable.feed`` over python-can messages,
    ``feed_raw`` over slot images, ``raw``: then ``message(batch, i)`` makes frame i a
    ``can.Message``) takes the frames, and the node's Python is called where it acts (a new
    period, its phases, a frame it handles, a rejection, a held frame); returns the frames to
    send, in order."""
    return _take(node, feed, batch, message, raw, now)


cdef class BatchTaker:
    """``node.handle_batch`` (an :class:`~canbrake.nodes.ecu.EcuNode`'s, over a list of python-can
    messages) as one compiled call, :func:`take_batch` over its peer table's ``feed``: what
    :meth:`~canbrake.nodes.ecu.EcuNode.batch_handler` gives the in-process Router."""

    cdef object node, feed

    def __init__(self, node):
        self.node = node
        self.feed = node._peers.feed

    def __call__(self, list batch, now):
        return _take(self.node, self.feed, batch, None, False, now)


cdef list _take(node, feed, batch, message, bint raw, now):
    """:func:`take_batch`."""
    cdef list out = []
    cdef Py_ssize_t i = 0
    cdef long r
    cdef int ev
    peers = node._peers
    while True:
        r = feed(batch, i, node.k, node.phase)
        ev = r & 7
        i = r >> 3
        if ev == _EV_END:
            break
        if ev == _EV_SYNC:  # the next period (the peer table has begun it)
            node._start_period(peers.sync_tick)
        elif ev == _EV_FRAME:
            out += node._handle_frame(message(batch, i) if raw else batch[i], now)
            if node.finished:
                break
        elif ev == _EV_PHASE1:  # the last sensor page
            if node.clock is not None and node.phase == 0 and node.k >= 0:
                node._p1_at = now + node.clock.offset_s(node.k)  # realtime: when this ECU's timer fires
            else:
                out += node._phase1(now)
        elif ev == _EV_PHASE2:  # the last peer of this tick is in
            out += node._phase2(now)
        elif ev == _EV_REJECT:
            node.guard.reject("crc" if peers.last_code == _REJECT_CRC else "counter")
            node._count_peer_rejection()
        elif ev == _EV_HELD:
            node._late_rx.append(message(batch, i) if raw else batch[i])
        else:  # FEED_ARM
            node._arm_external(now)
        i += 1
    return out
