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
from cpython.object cimport PyObject, PyObject_GenericSetAttr
from libc.stdint cimport int64_t

import math
import time

from canbrake.bus._ring import data_frame
from canbrake.bus.e2e import COUNTER_MODULO

cdef object _NEW = object.__new__
cdef object _perf_counter = time.perf_counter
cdef object _NAN = math.nan
cdef str _SPEED = "speed_mps"
cdef str _POSITION = "position_m"
cdef str _FRONT = "deflection_front_m"
cdef str _REAR = "deflection_rear_m"
cdef str _STATUS_DIAG = "status"
cdef str _BRAKE = "brake_force_n"


cdef class EcuPeriod:
    """One ECU's period (``decide``) over its peer table ``table``
    (:class:`~canbrake.bus._codec.PeerTable`) and its sensor dict ``sensors``: ``own``: the
    names of its own sensor values that it writes into the table's arrays at its index ``i``;
    ``views``: the table's arrays as the controller sees them (read-only views), ``obs_cls``:
    the Observation class; ``cmd_msgs``: [(identifier, FieldCodec, keys)] of its command frames;
    ``status_key``: the key of their Status field; ``pending``/``hist``: the controller step's
    wall times (s) not yet added to ``hist`` (:class:`~canbrake.nodes.base.LogHistogram`), added
    1,024 at a time; ``sign(identifier, payload, tick)``: a command frame's signature (SecOC)
    or None."""

    cdef object table, obs_cls, hist, sign
    cdef dict sensors, views, arrays
    cdef tuple own
    cdef list cmd_msgs, pending
    cdef object status_key
    cdef int i
    cdef object i_obj
    cdef double dt
    cdef bint has_front, has_rear

    def __init__(self, table, dict sensors, tuple own, int i, double dt, dict views, obs_cls, bint has_front,
                 bint has_rear, list cmd_msgs, status_key, list pending, hist, sign=None):
        self.table = table
        self.sensors = sensors
        self.arrays = table.values
        self.own = own
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
        cdef Py_ssize_t n
        for nm in self.own:  # this ECU's own entries
            self.arrays[nm][self.i_obj] = sensors[nm]
        pt = self.table
        if hold >= 0:  # lost peers are NaN for the controller: a copy
            peers, dropped = pt.hold_copy(k, hold, self.i)
            in_fallback = dropped
            speed = peers[_SPEED]
            age, fresh, max_age = pt.ages(k, self.dt, self.i, speed)
        else:
            peers = self.views
            speed = peers[_SPEED]
            age, fresh, max_age = pt.ages(k, self.dt, self.i, None)
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
        return result, frames, max_age, fresh, dropped
