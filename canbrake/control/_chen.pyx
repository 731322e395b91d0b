# cython: language_level=3
# distutils: extra_compile_args = -O2 -ffp-contract=off
"""Chen 2023's control law for one ECU and one period, compiled
(:meth:`canbrake.control.chen.ChenConsensusController.step` is :func:`step`).

Written by hand because the paper's law runs once per ECU per period and, in Python, was the
largest single share of the in-process engine's period (six calls of ~3.6 us each of ~130 us,
most of it attribute and call overhead around a few dozen floating-point operations). The
operations are those of the Python law it replaced, in the same order and in C doubles (IEEE
binary64, no contraction into fused multiply-adds: ``-ffp-contract=off``), so the floats are
the same; ``tests/test_control.py`` checks it against :class:`~canbrake.control.chen.ChenBatch`
(the batch engine's numpy form of the same law), and the golden runs' files are byte-identical.

The deflections and the speed disagreement of every configuration are computed here too: peer
positions held as received, extrapolated or dropped when stale (``stale_policy``), the spacing
latched when the first positions come, ``deflection_source="local"``. What stays in Python,
called from here: the observer (``ctrl._obs``: ``update``/``predict``, which a subclass may wrap).
The controller's parameters are read from the object at every call, so a change of a gain (as
:class:`~canbrake.control.chen_compensated.ChenCompensatedController` schedules them) takes effect
at once.
"""
from cpython.bytearray cimport PyByteArray_AS_STRING
from cpython.object cimport PyObject, PyObject_GenericSetAttr
from libc.math cimport isfinite, pow

from canbrake.control._attrs cimport attr as _get

import math

from canbrake.control.base import ControlOutput

cdef object _NEW = object.__new__
cdef object _NAN = math.nan
cdef object _OUTPUT = ControlOutput


cdef inline double _barrier0(double z_lower, double z_upper, bint log_kind):
    """∇U(0) of the barrier (its constant: subtracted so that ∇U(0) = 0)."""
    if log_kind:
        return 1.0 / z_upper - 1.0 / (-z_lower)
    return 2.0 / pow(z_upper, 3.0) - 2.0 / pow(-z_lower, 3.0)  # (as Python's float ** 3: pow)


cdef double _barrier(double z, double z_lower, double z_upper, bint log_kind, double clip, double g0):
    """∇U(z) − ∇U(0) (``g0``: :func:`_barrier0`) with z clipped to ``clip``·bound
    (:func:`barrier_gradient`)."""
    cdef double zl = z_lower * clip, zu = z_upper * clip, a, b, g
    if z > zu:
        z = zu
    elif z < zl:
        z = zl
    if log_kind:
        g = 1.0 / (z_upper - z) - 1.0 / (z - z_lower)
    else:  # cubes as products, as numpy's batch form computes them
        a = z_upper - z
        b = z - z_lower
        g = 2.0 / (a * a * a) - 2.0 / (b * b * b)
    return g - g0


def barrier_gradient(double z, double z_lower, double z_upper, str kind="inverse_square", double clip=0.99):
    """∇U(z) of the barrier on [z_lower, z_upper] (z_lower < 0 < z_upper), with ∇U(0) = 0; ``z``
    clipped to ``clip``·bound so the value stays finite beyond the bounds; ``kind``:
    ``"inverse_square"`` or ``"log"``."""
    if kind != "inverse_square" and kind != "log":
        raise ValueError(kind)
    return _barrier(z, z_lower, z_upper, kind == "log", clip, _barrier0(z_lower, z_upper, kind == "log"))


cdef double _np_sum(double *a, Py_ssize_t n) noexcept:
    """``float(np.sum(a))`` for ``n`` contiguous doubles, bit for bit: numpy's pairwise summation
    (sequential below 8 values, 8 partial sums up to 128, halves above) added to an output that
    starts at 0.0. Written out because the speed disagreement under ``extrapolate``/``drop``
    summed a numpy selection before it was compiled, and its floats must stay those
    (tests/test_control.py checks this against ``np.sum``)."""
    return 0.0 + _pairwise(a, n)


cdef double _pairwise(double *a, Py_ssize_t n) noexcept:
    cdef double res
    cdef double r[8]
    cdef Py_ssize_t i, j, n2
    if n < 8:
        res = 0.0
        for i in range(n):
            res += a[i]
        return res
    if n <= 128:
        for j in range(8):
            r[j] = a[j]
        i = 8
        while i < n - (n % 8):
            for j in range(8):
                r[j] += a[i + j]
            i += 8
        res = ((r[0] + r[1]) + (r[2] + r[3])) + ((r[4] + r[5]) + (r[6] + r[7]))
        while i < n:
            res += a[i]
            i += 1
        return res
    n2 = n // 2
    n2 -= n2 % 8
    return _pairwise(a, n2) + _pairwise(a + n2, n - n2)


cdef class _Peers:
    """One period's peer arrays as C doubles, and the stale policy's view of them."""
    cdef list px, pv, age
    cdef int policy          # 0 hold, 1 extrapolate, 2 drop
    cdef double timeout, ref_decel

    cdef bint ok(self, Py_ssize_t j):
        """``_peer_ok``: its position received (not NaN) and, under ``drop``, not too old."""
        cdef double x = self.px[j]
        if not (x == x):
            return False
        return not (self.policy == 2 and <double>self.age[j] > self.timeout)

    cdef double position(self, Py_ssize_t j):
        """``_peer_position``: as received, or under ``extrapolate`` moved on by its age."""
        cdef double x = self.px[j], age
        if self.policy == 1:
            age = self.age[j]
            if age > 0 and isfinite(age):
                x += <double>self.pv[j] * age - 0.5 * self.ref_decel * age * age
        return x


cdef _Peers _peers(dict d, object ctrl, dict od, object obs, int policy):
    cdef _Peers p = _Peers.__new__(_Peers)
    p.px = (<object>_get(od, obs, "peer_position_m")).tolist()
    p.pv = (<object>_get(od, obs, "peer_speed_mps")).tolist()
    p.age = (<object>_get(od, obs, "peer_age_s")).tolist() if policy else None
    p.policy = policy
    p.timeout = _get(d, ctrl, "stale_timeout_s")
    p.ref_decel = _get(od, obs, "ref_decel_mps2")
    return p


cdef double _speed_disagreement(object ctrl, dict d, list pv, list age, int policy, double timeout,
                                double ref_decel, double v) except? -1.0:
    """Σ_j a_ij (v_i − v_j) over the usable peers (m/s), the neighbours in the velocity graph in
    index order: under ``hold`` (``policy`` 0) every peer received, summed one by one (as the
    batch form sums); under ``extrapolate`` (1) each peer's speed moved on by its age (``age``, s)
    at the reference deceleration ``ref_decel``; under ``drop`` (2) peers older than ``timeout``
    (s) left out; the sums of these two as numpy made them (:func:`_np_sum`)."""
    cdef Py_ssize_t n = len(pv), j, k, cnt = 0, na = 0
    cdef double pj, a
    cdef double[64] sbuf, abuf
    cdef double *speeds = sbuf
    cdef double *ages = abuf
    cdef double total
    cdef bytearray big
    if n > 64:  # a long train: room for every peer
        big = bytearray(16 * n)
        speeds = <double *>PyByteArray_AS_STRING(big)
        ages = speeds + n
    for jo in <tuple>_get(d, ctrl, "_adj_tuple"):
        j = jo
        if j >= n or j < 0:
            raise IndexError(f"peer_speed_mps has {n} values for car {j}")
        pj = pv[j]
        if not (pj == pj):
            continue
        if policy == 2 and not (<double>age[j] <= timeout):
            continue
        speeds[cnt] = pj
        cnt += 1
        if policy == 1:
            a = age[j]
            if isfinite(a):
                ages[na] = a
                na += 1
    if cnt == 0:
        return 0.0
    if policy == 0:
        total = 0.0
        for k in range(cnt):
            total += speeds[k]
    else:
        total = _np_sum(speeds, cnt)
    if policy == 1:
        total -= ref_decel * _np_sum(ages, na)
    return <double>cnt * v - total


def step(ctrl, obs):
    """One period of :class:`~canbrake.control.chen.ChenConsensusController` ``ctrl`` from the
    :class:`~canbrake.control.base.Observation` ``obs``: its
    :class:`~canbrake.control.base.ControlOutput` (brake force in N, + = brake)."""
    cdef dict d = ctrl.__dict__
    cdef dict od = obs.__dict__  # (an Observation's fields are in its instance dict: Observation.of)
    cdef double v = _get(od, obs, "speed_mps")
    cdef double x = _get(od, obs, "position_m")
    cdef double scale = _get(d, ctrl, "_scale")
    cdef double m = _get(d, ctrl, "mass_kg")
    cdef double kb = _get(d, ctrl, "brake_gain")
    cdef double front = 0.0, rear = 0.0, pos, u1 = 0.0, u2 = 0.0, u3, g, unit, zl, zu, clip
    cdef double ff, phi_hat, force_obs = 0.0, force, fm, lim, sd, g0
    cdef bint log_kind
    cdef bint has_front = False, has_rear = False, fast
    cdef int i, n, policy
    cdef _Peers peers = None
    stale = _get(d, ctrl, "stale_policy")
    hold = stale == "hold"
    policy = 0 if hold else 1 if stale == "extrapolate" else 2
    local = _get(d, ctrl, "deflection_source") == "local"
    fast = hold and not local and _get(d, ctrl, "_latched")
    # (Δl_{i−1}, Δl_i) in m
    i = _get(d, ctrl, "car_index")
    n = _get(d, ctrl, "n_cars")
    if fast:  # the common case: positions held as received, the spacing latched
        px = _get(od, obs, "peer_position_m")
        if i > 0:
            front = <double>px.item(i - 1) - x - <double>_get(d, ctrl, "_spacing_front")
            has_front = front == front
        if i < n - 1:
            rear = x - <double>px.item(i + 1) - <double>_get(d, ctrl, "_spacing_rear")
            has_rear = rear == rear
    elif local:  # the ECU's own coupler measurement
        f_obj = _get(od, obs, "deflection_front_m")
        r_obj = _get(od, obs, "deflection_rear_m")
        if f_obj is not None:
            front, has_front = f_obj, True
        if r_obj is not None:
            rear, has_rear = r_obj, True
    else:
        peers = _peers(d, ctrl, od, obs, policy)
        if not _get(d, ctrl, "_latched"):  # the spacing: latched once both neighbours' positions came
            if (i == 0 or peers.ok(i - 1)) and (i == n - 1 or peers.ok(i + 1)):
                if i > 0:
                    d["_spacing_front"] = peers.position(i - 1) - x
                if i < n - 1:
                    d["_spacing_rear"] = x - peers.position(i + 1)
                d["_latched"] = True
        if _get(d, ctrl, "_latched"):
            if i > 0 and peers.ok(i - 1):
                front, has_front = peers.position(i - 1) - x - <double>_get(d, ctrl, "_spacing_front"), True
            if i < n - 1 and peers.ok(i + 1):
                rear, has_rear = x - peers.position(i + 1) - <double>_get(d, ctrl, "_spacing_rear"), True

    if _get(d, ctrl, "consensus"):
        pos = 0.0
        if has_rear:
            pos += rear
        if has_front:
            pos -= front
        if peers is None and not hold:
            peers = _peers(d, ctrl, od, obs, policy)
        if peers is not None:
            sd = _speed_disagreement(ctrl, d, peers.pv, peers.age, policy, peers.timeout, peers.ref_decel, v)
        else:  # hold, the common case: the speeds alone (6 floats as a list: less than a buffer's export)
            sd = _speed_disagreement(ctrl, d, (<object>_get(od, obs, "peer_speed_mps")).tolist(), None, 0, 0.0,
                                     0.0, v)
        u1 = scale * (<double>_get(d, ctrl, "alpha1") * <double>sd + <double>_get(d, ctrl, "alpha2") * pos)

    if _get(d, ctrl, "potential_field"):
        unit = _get(d, ctrl, "barrier_unit_m")
        zl = _get(d, ctrl, "_z_lower")
        zu = _get(d, ctrl, "_z_upper")
        clip = _get(d, ctrl, "barrier_clip")
        kind = _get(d, ctrl, "barrier")
        if kind != "inverse_square" and kind != "log":
            raise ValueError(kind)
        log_kind = kind == "log"
        g0 = _barrier0(zl, zu, log_kind)
        g = 0.0
        if has_rear:
            g += _barrier(rear / unit, zl, zu, log_kind, clip, g0)
        if has_front:
            g -= _barrier(front / unit, zl, zu, log_kind, clip, g0)
        u2 = scale * <double>_get(d, ctrl, "delta") * g

    ref_v = _get(od, obs, "ref_speed_mps")
    ff = _get(od, obs, "ref_decel_mps2") if _get(d, ctrl, "feedforward") == "decel" else ref_v
    u3 = m * (<double>_get(d, ctrl, "k") * (v - <double>ref_v) + ff)

    observer = _get(d, ctrl, "_obs")
    phi_hat = observer.update(x, v)
    if _get(d, ctrl, "observer"):
        if _get(d, ctrl, "observer_cancellation") == "mass":
            force_obs = m * phi_hat
        else:
            force_obs = kb * <double>_get(d, ctrl, "k_d") * phi_hat

    force = kb * (u1 + u2 + u3) + force_obs
    lim = _get(d, ctrl, "brake_force_max_n")
    if force > lim:
        force = lim
    else:
        lim = _get(d, ctrl, "traction_force_max_n")
        if force < -lim:
            force = -lim
    # the observer is driven by the (saturated) force, through the brake-lag model if any
    fm = _get(d, ctrl, "_force_model_n")
    fm += <double>_get(d, ctrl, "_lag_alpha") * (force - fm)
    d["_force_model_n"] = fm
    observer.predict(fm)

    out = _NEW(_OUTPUT)
    PyObject_GenericSetAttr(out, "__dict__", {
        "brake_force_n": force,
        "diagnostics": {
            "observer_accel_mps2": phi_hat,
            "u_consensus_n": kb * u1,
            "u_potential_n": kb * u2,
            "u_tracking_n": kb * u3,
            "u_observer_n": force_obs,
            "deflection_front_m": front if has_front else _NAN,
            "deflection_rear_m": rear if has_rear else _NAN,
        },
        "commands": {},
        "broadcast": {},
    })
    return out
