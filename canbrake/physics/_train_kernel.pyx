# cython: language_level=3
# distutils: extra_compile_args = -ffp-contract=off
"""The coupled train's integration loop (:meth:`canbrake.physics.train.TrainPlant.step`), compiled.

One call advances a plant, or a stack of P plants (``stack_plants``: arrays with a leading points
axis), by one control period of ``n_sub`` sub-steps: arrays in, arrays out; the policy (sub-step
count, divergence reports) stays in Python. :class:`CoupledKernel` is the plain train's period,
:class:`EquippedKernel` the period of a train with brake equipment (blending, wheelsets, Li's
draft gears and air brake, route, limits), which calls the equipment's compiled kernels
(``_brakes_kernel``, ``_heavy_haul_kernel``) at C level, once per sub-step each. Written by hand because numpy's cost
per call dominated on arrays of a few cars (about 20 array operations per sub-step on 6 values).

Every value is computed with the floating-point operations of the numpy code it replaces, in the
same order (no contraction into FMA: ``-ffp-contract=off``), so the results are bit for bit those
of the former vectorised step; numpy's ``sign``, ``minimum``, ``maximum`` and ``clip`` semantics,
NaN included, are reproduced by the helpers below. A stack's rows are independent: row p of a
stack gives exactly what plant p would give alone.

Every array is ``(P, n)``, or ``(n,)`` (one row shared by every point), C-contiguous float64.
"""
from cpython.buffer cimport PyBUF_C_CONTIGUOUS, PyBUF_FORMAT, PyBUF_WRITABLE, PyBuffer_Release, PyObject_GetBuffer
from libc.math cimport fabs, isfinite, sin

from canbrake.physics._brakes_kernel cimport EquipmentKernel  # the brake equipment's sub-step
from canbrake.physics._heavy_haul_kernel cimport AirKernel, GearKernel, route_n  # Li's gears, air brake, route
from canbrake.physics._npmath cimport _max, _min, _sign  # numpy's NaN rules, shared
from canbrake.physics._table cimport table_at  # the speed tables' interpolation, shared

import numpy as np

_np_sin, _np_cos, _np_cbrt = np.sin, np.cos, np.cbrt


cdef struct Rows:
    # a float64 array seen as rows of n values: data, and the step between rows (0: one shared row)
    double* p
    Py_ssize_t step


cdef Rows _rows(Py_buffer* view, object a, Py_ssize_t n, Py_ssize_t P, bint writable) except *:
    """``a``'s buffer (C-contiguous float64) as P rows of n, or one row shared by all."""
    PyObject_GetBuffer(a, view, PyBUF_C_CONTIGUOUS | PyBUF_FORMAT | (PyBUF_WRITABLE if writable else 0))
    cdef Rows r
    r.p = <double*>view.buf
    if view.itemsize != 8 or view.format == NULL or view.format[0] != b"d" or view.format[1] != 0:
        PyBuffer_Release(view)
        raise TypeError("the plant kernel needs float64 arrays")
    if view.len == 8 * n * P and P > 1:
        r.step = n
    elif view.len == 8 * n:
        r.step = 0
    else:
        PyBuffer_Release(view)
        raise ValueError(f"the plant kernel needs arrays of {n} or {P} x {n} values, got {view.len // 8}")
    return r


cdef inline double _envelope_n(const double* e, double v_mps) noexcept nogil:
    """Li 2024 eq. 1's traction force limit (N) at speed ``v_mps`` for the envelope row ``e`` (kN,
    km/h; the formula of :meth:`canbrake.physics.heavy_haul.TractionEnvelope.saturate_n`)."""
    cdef double v = fabs(v_mps) / (1.0 / 3.6)
    if v <= e[1]:
        return 1000.0 * e[0]
    if v <= e[4]:
        return 1000.0 * (e[2] - e[3] * v)
    return 1000.0 * (e[5] / v)


cdef inline double _disturbance(const double[::1] start, const double[::1] end, const double[::1] w,
                                const double[::1] ph, const double[:, ::1] off, const double[:, ::1] amp,
                                Py_ssize_t i, double t) noexcept nogil:
    """The disturbance events' force on car ``i`` at ``t`` (N): the sum over the events active at
    ``t`` (``start`` <= t < ``end``) of off + amp·sin(w (t − start) + ph) (libm ``sin``, as
    ``math.sin``); shared by both kernels' loops."""
    cdef double ext = 0.0
    cdef Py_ssize_t k
    for k in range(start.shape[0]):
        if start[k] <= t < end[k]:
            ext = ext + off[k, i] + amp[k, i] * sin(w[k] * (t - start[k]) + ph[k])
    return ext


cdef class CoupledKernel:
    """The constant parameters of a coupled train (or a stack of P of them) in C, and its step.

    Per car (``(P, n)`` or ``(n,)``): ``mass``, ``inv_m``, ``c_static`` (c0 + curve resistance, N),
    ``c1``, ``c2`` (Davis), ``grade_force_n`` (N, or None), ``brake_max``, ``trac_max``,
    ``rate_max`` (the actuator's ratings and jerk limit × m, N and N/s); per coupler (``(P, n-1)`` or
    ``(n-1,)``): ``spacing`` (m), ``kappa`` (N/m), ``epsilon`` (1/m²), ``kappa_eps`` (κ·ε);
    disturbances ``dist_start``, ``dist_end`` (s), ``dist_w`` (rad/s), ``dist_phase`` (rad), shape
    (D,), and ``dist_amp``, ``dist_off`` (N), shape (D, n). ``points``: P (1 for a single plant).

    Per-vehicle features (each None = no vehicle has it; rows shared by every point of a stack):
    ``end_stop_m``, ``end_stop_stiffness``, ``end_stop_absorption``: one value for every coupler or
    one per coupler (``inf`` end stop: none on that coupler); ``instant``: 1 per car whose brake
    applies the command at once (an ideal brake in a train with lagged ones), 0 otherwise;
    ``envelope``: shape (n, 6) per car, Li 2024 eq. 1's traction envelope (kN, km/h: start force,
    start until, intercept, slope, linear until, power), a NaN first value for a car without one;
    ``table_start`` (n + 1 offsets), ``table_v`` (m/s, increasing), ``table_f`` (N): each car's
    running-resistance table, interpolated linearly and held flat beyond its ends, added to the
    Davis terms (an empty table: none).
    """

    cdef readonly Py_ssize_t n, nc, points
    cdef object keep
    cdef Rows mass, inv_m, c_static, c1, c2, grade, brake_max, trac_max, rate_max
    cdef Rows spacing, kappa, eps, kappa_eps
    cdef const double[::1] d_start, d_end, d_w, d_ph
    cdef const double[:, ::1] d_amp, d_off
    cdef double g, es_vt
    cdef const double[::1] es_m, es_k, es_a, inst
    cdef const double[:, ::1] env
    cdef const Py_ssize_t[::1] tab_start
    cdef const double[::1] tab_v, tab_f
    cdef bint end_stop, has_grade, unrated, jerk_limited, adhesion_limited, has_instant, has_env, has_table
    cdef Py_ssize_t n_dist
    cdef double[::1] phi
    #: after a step: 1 for each point whose speeds are not all finite, and its last max |Δl| (m)
    cdef readonly object bad, dl_max
    cdef unsigned char[::1] bad_v  # their views, made once (a view made per call costs more than a small step)
    cdef double[::1] dl_max_v

    def __init__(self, mass, inv_m, c_static, c1, c2, grade_force_n, brake_max, trac_max, rate_max,
                 spacing, kappa, epsilon, kappa_eps, dist_start, dist_end, dist_w, dist_phase, dist_amp,
                 dist_off, *, int points, double gravity, end_stop_m, end_stop_stiffness,
                 end_stop_absorption, double end_stop_transition, bint unrated, bint jerk_limited,
                 bint adhesion_limited, instant=None, envelope=None, table_start=None, table_v=None,
                 table_f=None):
        self.points = points
        shp = np.shape(mass)
        n = int(shp[len(shp) - 1])
        self.n, self.nc = n, max(n - 1, 0)
        self.has_grade = grade_force_n is not None
        keep = {}
        cdef Py_buffer view
        for name, a, m in (("mass", mass, n), ("inv_m", inv_m, n), ("c_static", c_static, n), ("c1", c1, n),
                           ("c2", c2, n), ("grade", grade_force_n if self.has_grade else np.zeros(n), n),
                           ("brake_max", brake_max, n), ("trac_max", trac_max, n), ("rate_max", rate_max, n),
                           ("spacing", spacing, n - 1), ("kappa", kappa, n - 1), ("eps", epsilon, n - 1),
                           ("kappa_eps", kappa_eps, n - 1)):
            arr = np.ascontiguousarray(np.broadcast_to(np.asarray(a, dtype=float), np.shape(a)), dtype=float)
            keep[name] = arr  # held for the kernel's lifetime: the Rows below point into it
            if arr.size == 0:
                arr = keep[name] = np.zeros(1)
                m = 1
            r = _rows(&view, arr, m, points, False)
            PyBuffer_Release(&view)  # the array stays alive in self.keep
            if name == "mass": self.mass = r
            elif name == "inv_m": self.inv_m = r
            elif name == "c_static": self.c_static = r
            elif name == "c1": self.c1 = r
            elif name == "c2": self.c2 = r
            elif name == "grade": self.grade = r
            elif name == "brake_max": self.brake_max = r
            elif name == "trac_max": self.trac_max = r
            elif name == "rate_max": self.rate_max = r
            elif name == "spacing": self.spacing = r
            elif name == "kappa": self.kappa = r
            elif name == "eps": self.eps = r
            else: self.kappa_eps = r
        self.keep = keep
        self.d_start = np.ascontiguousarray(dist_start, dtype=float)
        self.d_end = np.ascontiguousarray(dist_end, dtype=float)
        self.d_w = np.ascontiguousarray(dist_w, dtype=float)
        self.d_ph = np.ascontiguousarray(dist_phase, dtype=float)
        self.n_dist = self.d_start.shape[0]
        self.d_amp = np.ascontiguousarray(np.reshape(dist_amp, (self.n_dist, n)), dtype=float)
        self.d_off = np.ascontiguousarray(np.reshape(dist_off, (self.n_dist, n)), dtype=float)
        self.g = gravity
        self.end_stop = end_stop_m is not None
        ncs = max(self.nc, 1)
        per_coupler = lambda a: np.ascontiguousarray(np.broadcast_to(np.asarray(a, dtype=float), (ncs,)))  # noqa: E731
        self.es_m = per_coupler(end_stop_m if end_stop_m is not None else 0.0)
        self.es_k = per_coupler(end_stop_stiffness)
        self.es_a = per_coupler(end_stop_absorption)
        self.es_vt = end_stop_transition
        self.has_instant = instant is not None
        self.inst = np.ascontiguousarray(np.broadcast_to(np.asarray(0.0 if instant is None else instant, dtype=float),
                                                         (n,)))
        self.has_env = envelope is not None
        self.env = np.ascontiguousarray(np.full((n, 6), np.nan) if envelope is None else
                                        np.reshape(np.asarray(envelope, dtype=float), (n, 6)))
        self.has_table = table_start is not None
        self.tab_start = np.ascontiguousarray(np.zeros(n + 1) if table_start is None else table_start, dtype=np.intp)
        self.tab_v = np.ascontiguousarray(np.zeros(1) if table_v is None or len(table_v) == 0 else table_v, dtype=float)
        self.tab_f = np.ascontiguousarray(np.zeros(1) if table_f is None or len(table_f) == 0 else table_f, dtype=float)
        if self.tab_start.shape[0] != n + 1:
            raise ValueError(f"the plant kernel needs {n + 1} table offsets, got {self.tab_start.shape[0]}")
        self.unrated, self.jerk_limited, self.adhesion_limited = unrated, jerk_limited, adhesion_limited
        self.phi = np.zeros(max(self.nc, 1))
        self.bad = np.zeros(points, dtype=np.uint8)
        self.dl_max = np.zeros(points)
        self.bad_v, self.dl_max_v = self.bad, self.dl_max

    def step(self, x0, v0, cmd, rail0, effort, mu, eff, double t0, double h, int n_sub, bint ideal,
             bint plain_rail, double lag, grade_fn=None, lag_per_car=None):
        """Advance ``n_sub`` sub-steps of ``h`` s from time ``t0``: positions ``x0`` (m), speeds ``v0``
        (m/s), brake command ``cmd`` (N, + brakes), the actuator's ``effort`` (N, updated in place).
        ``ideal``: the rail force ``rail0`` (N) is held (the plant computed it); otherwise the actuator
        (lag factor ``lag`` = 1 − e^(−h/τ), ratings, jerk limit) and the rail limits (adhesion ``mu``,
        brake effectiveness ``eff``; ``plain_rail``: neither acts) give it every sub-step.
        ``grade_fn`` (a single plant only): a callable giving m g sin θ (N) per car from the
        positions, evaluated every sub-step. ``lag_per_car``: 1 − e^(−h/τ_i) per car (``(n,)``),
        used instead of ``lag`` (vehicles with different brake lags).

        Returns (time_s, x, v, accel, rail, n_bad, dl, phi): the new state, the acceleration over
        the last sub-step, the last rail force (``rail0`` itself when ideal), the number of points
        whose speeds are not all finite (flagged in :attr:`bad`, their last max |Δl| in
        :attr:`dl_max`) and the couplers of the new state as :meth:`couplers` gives them."""
        cdef Py_ssize_t P = self.points, n = self.n
        shape = x0.shape if type(x0) is np.ndarray else np.shape(x0)
        if len(shape) not in (1, 2) or shape[len(shape) - 1] != n or (len(shape) == 2 and shape[0] != P):
            raise ValueError(f"the plant kernel needs positions of shape ({n},) or ({P}, {n}), got {shape}")  # (n,) or (P, n), a stack of one point included
        x_out = np.empty(shape)
        v_out = np.empty(shape)
        a_out = np.empty(shape)
        rail_out = rail0 if ideal else np.empty(shape)
        cshape = tuple(shape[:len(shape) - 1]) + (self.nc,)
        dl_out, phi_out = np.empty(cshape), np.empty(cshape)
        # the 13 arrays' buffers, released in one place whatever happens (held: how many were taken)
        cdef Py_buffer bufs[13]
        cdef int held = 0
        cdef Rows rx, rv, rc, rr, re, rm, rf, rxo, rvo, rao, rro, rdo, rpo
        cdef unsigned char[::1] bad = self.bad_v
        cdef Py_ssize_t n_bad, p
        try:
            rx = _rows(&bufs[0], x0, n, P, False); held = 1
            rv = _rows(&bufs[1], v0, n, P, False); held = 2
            rc = _rows(&bufs[2], cmd, n, P, False); held = 3
            rr = _rows(&bufs[3], rail0, n, P, False); held = 4
            re = _rows(&bufs[4], effort, n, P, True); held = 5
            rm = _rows(&bufs[5], mu, n, P, False); held = 6
            rf = _rows(&bufs[6], eff, n, P, False); held = 7
            rxo = _rows(&bufs[7], x_out, n, P, True); held = 8
            rvo = _rows(&bufs[8], v_out, n, P, True); held = 9
            rao = _rows(&bufs[9], a_out, n, P, True); held = 10
            rro = _rows(&bufs[10], rail_out, n, P, not ideal); held = 11
            lagv = None if lag_per_car is None else np.ascontiguousarray(
                np.broadcast_to(np.asarray(lag_per_car, dtype=float), (n,)))
            t = self._run(rx, rv, rc, rr, re, rm, rf, rxo, rvo, rao, rro, P, t0, h, n_sub,
                          ideal, plain_rail, lag, grade_fn, x_out, lagv)
            if self.nc:
                rdo = _rows(&bufs[11], dl_out, self.nc, P, True); held = 12
                rpo = _rows(&bufs[12], phi_out, self.nc, P, True); held = 13
                self._couplers(rxo, rvo, rdo, rpo, P)
        finally:
            while held > 0:
                held -= 1
                PyBuffer_Release(&bufs[held])
        n_bad = 0
        for p in range(P):
            n_bad += bad[p]
        return t, x_out, v_out, a_out, rail_out, n_bad, dl_out, phi_out

    def couplers(self, x, v):
        """The couplers at positions ``x`` (m) and speeds ``v`` (m/s), shape ``(n,)`` or ``(P, n)``:
        (Δl, Φ), new arrays of shape ``(..., n − 1)``. Δl_j = x_j − x_{j+1} − s_j (m) and
        Φ_j = κ_j(1 + ε_jΔl_j²)Δl_j (N) plus, with an end stop, its buffer (module docstring of
        :mod:`canbrake.physics.train`: its loading or unloading curve by the rate v_j − v_{j+1}),
        with the operations and order of the plant's former numpy properties (these are not the
        step's: it groups κ + κε·Δl² instead). Draft gears are not included (the plant adds them)."""
        cdef Py_ssize_t P = self.points, n = self.n, nc = self.nc, p, j
        shape = x.shape if type(x) is np.ndarray else np.shape(x)
        if len(shape) not in (1, 2) or shape[len(shape) - 1] != n or shape[0] != (P if len(shape) == 2 else n) \
                or (v.shape if type(v) is np.ndarray else np.shape(v)) != shape or (len(shape) == 1 and P > 1):
            raise ValueError(f"the plant kernel needs positions and speeds of shape ({n},) or ({P}, {n}), "
                             f"got {shape} and {np.shape(v)}")
        out_shape = tuple(shape[:len(shape) - 1]) + (nc,)
        dl_a, phi_a = np.empty(out_shape), np.empty(out_shape)
        if nc == 0:
            return dl_a, phi_a
        cdef Py_buffer bufs[4]
        cdef int held = 0
        cdef Rows rx, rv, rd, rf
        try:
            rx = _rows(&bufs[0], x, n, P, False); held = 1
            rv = _rows(&bufs[1], v, n, P, False); held = 2
            rd = _rows(&bufs[2], dl_a, nc, P, True); held = 3
            rf = _rows(&bufs[3], phi_a, nc, P, True); held = 4
            self._couplers(rx, rv, rd, rf, P)
        finally:
            while held > 0:
                held -= 1
                PyBuffer_Release(&bufs[held])
        return dl_a, phi_a

    cdef void _couplers(self, Rows rx, Rows rv, Rows rd, Rows rf, Py_ssize_t P) noexcept:
        """:meth:`couplers` of P rows of positions ``rx`` and speeds ``rv`` into ``rd``, ``rf``."""
        cdef Py_ssize_t p, j, nc = self.nc
        cdef const double* xp
        cdef const double* vp
        cdef double d, f, over, sg, rate, loading, share
        for p in range(P):
            xp = rx.p + p * rx.step
            vp = rv.p + p * rv.step
            for j in range(nc):
                d = xp[j] - xp[j + 1] - self.spacing.p[p * self.spacing.step + j]
                f = self.kappa.p[p * self.kappa.step + j] * (1.0 + self.eps.p[p * self.eps.step + j] * d * d) * d
                if self.end_stop:
                    over = fabs(d) - self.es_m[j]
                    sg = _sign(d)
                    rate = vp[j] - vp[j + 1]
                    loading = _min(_max(0.5 + sg * rate / (2.0 * self.es_vt), 0.0), 1.0)
                    share = 1.0 - self.es_a[j] * (1.0 - loading)
                    f = f + (sg * over * self.es_k[j] * share if over > 0.0 else 0.0)
                rd.p[p * rd.step + j] = d
                rf.p[p * rf.step + j] = f

    cdef double _run(self, Rows rx0, Rows rv0, Rows rc, Rows rr0, Rows re, Rows rmu, Rows ref, Rows rx, Rows rv,
                     Rows ra, Rows rr, Py_ssize_t P, double t0, double h, int n_sub, bint ideal, bint plain_rail,
                     double lag, object grade_fn, object x_arr, object lag_per_car) except? -1.0:
        cdef Py_ssize_t n = self.n, nc = self.nc, p, i, j, k, s
        cdef double* phi = &self.phi[0]
        cdef double t = t0, hm, d, st, lim, e, rf, cap, dlj, rate, over, sg, loading, share, f, fc, brake
        cdef double ext, speed, r, vi, vn, sgn, dmax, half_h = 0.5 * h, half_hh = 0.5 * h * h
        cdef double* x
        cdef double* v
        cdef double* a
        cdef double* rail
        cdef double* cmd
        cdef double* eff_n
        cdef double* mu
        cdef double* effv
        cdef bint all_moving, moving, finite
        cdef const double[::1] gforce
        cdef unsigned char[::1] bad = self.bad_v
        cdef double[::1] dl_max = self.dl_max_v
        cdef double* mass = self.mass.p
        cdef bint per_car_lag = lag_per_car is not None
        cdef const double[::1] lagv = self.inst  # (a conditional expression would make a view per call)
        if per_car_lag:
            lagv = lag_per_car
        cdef double lag_i = lag
        for p in range(P):
            x = rx.p + p * rx.step
            v = rv.p + p * rv.step
            a = ra.p + p * ra.step
            rail = rr.p + p * rr.step
            cmd = rc.p + p * rc.step
            eff_n = re.p + p * re.step
            mu = rmu.p + p * rmu.step
            effv = ref.p + p * ref.step
            for i in range(n):
                x[i] = rx0.p[p * rx0.step + i]
                v[i] = rv0.p[p * rv0.step + i]
                if not ideal:
                    rail[i] = rr0.p[p * rr0.step + i]
            dmax = 0.0
            t = t0
            for s in range(n_sub):
                if not ideal:
                    for i in range(n):
                        d = cmd[i]
                        if not self.unrated:
                            d = _min(_max(d, -self.trac_max.p[p * self.trac_max.step + i]),
                                     self.brake_max.p[p * self.brake_max.step + i])
                        if self.has_instant and self.inst[i] != 0.0:
                            e = d  # this vehicle's brake applies the command at once
                        else:
                            if per_car_lag:
                                lag_i = lagv[i]
                            st = (d - eff_n[i]) * lag_i
                            if self.jerk_limited:
                                lim = self.rate_max.p[p * self.rate_max.step + i] * h
                                st = _min(_max(st, -lim), lim)
                            e = eff_n[i] + st
                        eff_n[i] = e
                        if plain_rail:
                            rail[i] = e
                        else:
                            rf = e * effv[i] if e > 0.0 else e
                            if self.adhesion_limited:
                                cap = mu[i] * mass[p * self.mass.step + i] * self.g
                                rf = _min(_max(rf, -cap), cap)
                            rail[i] = rf
                        if self.has_env and rail[i] < 0.0 and self.env[i, 0] == self.env[i, 0]:
                            rail[i] = _max(rail[i], -_envelope_n(&self.env[i, 0], v[i]))
                # couplers: Φ_j of the deflection (and, with an end stop, of its rate)
                dmax = 0.0
                for j in range(nc):
                    dlj = x[j] - x[j + 1] - self.spacing.p[p * self.spacing.step + j]
                    if dmax == dmax and not fabs(dlj) <= dmax:  # numpy.max(abs(dl)): NaN wins
                        dmax = fabs(dlj)
                    if self.end_stop:
                        f = self.kappa.p[p * self.kappa.step + j] * (
                            1.0 + self.eps.p[p * self.eps.step + j] * dlj * dlj) * dlj
                        over = fabs(dlj) - self.es_m[j]
                        sg = _sign(dlj)
                        rate = v[j] - v[j + 1]
                        loading = _min(_max(0.5 + sg * rate / (2.0 * self.es_vt), 0.0), 1.0)
                        share = 1.0 - self.es_a[j] * (1.0 - loading)
                        phi[j] = f + (sg * over * self.es_k[j] * share if over > 0.0 else 0.0)
                    else:
                        phi[j] = dlj * (self.kappa.p[p * self.kappa.step + j]
                                        + self.kappa_eps.p[p * self.kappa_eps.step + j] * (dlj * dlj))
                if grade_fn is not None:
                    gforce = np.ascontiguousarray(grade_fn(x_arr), dtype=float)
                all_moving = True
                for i in range(n):
                    if v[i] == 0.0:
                        all_moving = False
                        break
                for i in range(n):
                    # f_i = Φ_{i-1} − Φ_i (the numpy code's incidence product: exact)
                    fc = 0.0
                    if i > 0:
                        fc = fc + phi[i - 1]
                    if i < nc:
                        fc = fc - phi[i]
                    f = fc
                    brake = rail[i]
                    if brake < 0.0:  # traction pushes towards +x
                        f = f - brake
                        brake = 0.0
                    if grade_fn is not None:
                        f = f - gforce[i]
                    elif self.has_grade:
                        f = f + self.grade.p[p * self.grade.step + i]
                    if self.n_dist:
                        f = f + _disturbance(self.d_start, self.d_end, self.d_w, self.d_ph, self.d_off, self.d_amp,
                                             i, t)
                    # dissipative forces: brake + resistance, Coulomb-like
                    vi = v[i]
                    speed = fabs(vi)
                    r = brake + self.c_static.p[p * self.c_static.step + i] + speed * (
                        self.c1.p[p * self.c1.step + i] + self.c2.p[p * self.c2.step + i] * speed)
                    if self.has_table and self.tab_start[i + 1] > self.tab_start[i]:
                        r = r + table_at(&self.tab_v[self.tab_start[i]], &self.tab_f[self.tab_start[i]],
                                         self.tab_start[i + 1] - self.tab_start[i], speed, NULL)
                    hm = h * self.inv_m.p[p * self.inv_m.step + i]
                    if all_moving:
                        sgn = _sign(vi)
                        vn = vi + hm * (f - sgn * r)
                        if sgn * vn < 0.0:  # friction stops a car, never reverses it
                            vn = 0.0
                    else:
                        moving = vi != 0.0
                        sgn = _sign(vi) if moving else _sign(f)
                        vn = vi + (hm * (f - sgn * r) if moving or fabs(f) > r else 0.0)
                        if moving and vn * vi < 0.0:
                            vn = 0.0
                    # position: held forces by the trapezoid, couplers semi-implicitly (+ h² a_c/2)
                    x[i] = x[i] + half_h * (vi + vn) + (
                        half_hh * self.inv_m.p[p * self.inv_m.step + i] * fc if vi != 0.0 or vn != 0.0 else 0.0)
                    a[i] = vi  # the speed one sub-step before, for the acceleration below
                    v[i] = vn
                t = t + h
            finite = True
            for i in range(n):
                a[i] = (v[i] - a[i]) / h
                if not isfinite(v[i]):
                    finite = False
            bad[p] = not finite
            dl_max[p] = dmax
        return t


def nan_as_zero(a):
    """``a`` (float64) with every NaN made +0.0, a new array of its shape: numpy's
    ``np.where(np.isnan(a), 0.0, a)`` in one call (the coupled plant's commands, NaN = not
    commanded = no force)."""
    cdef Py_buffer src, dst
    cdef Py_ssize_t i, m
    cdef const double* s
    cdef double* d
    out = np.empty(a.shape if type(a) is np.ndarray else np.shape(a))
    try:
        PyObject_GetBuffer(a, &src, PyBUF_C_CONTIGUOUS | PyBUF_FORMAT)
    except (BufferError, ValueError):  # a strided view (numpy: ValueError): its values in order
        PyObject_GetBuffer(np.ascontiguousarray(a), &src, PyBUF_C_CONTIGUOUS | PyBUF_FORMAT)
    try:
        if src.itemsize != 8 or src.format == NULL or src.format[0] != b"d" or src.format[1] != 0:
            raise TypeError("nan_as_zero needs a float64 array")
        PyObject_GetBuffer(out, &dst, PyBUF_C_CONTIGUOUS | PyBUF_WRITABLE)
        s, d, m = <const double*>src.buf, <double*>dst.buf, src.len // 8
        for i in range(m):
            d[i] = 0.0 if s[i] != s[i] else s[i]
        PyBuffer_Release(&dst)
    finally:
        PyBuffer_Release(&src)
    return out


def with_table_resistance(const Py_ssize_t[::1] start, const double[::1] table_v, const double[::1] table_f,
                          const double[::1] speed, const double[::1] r):
    """``r`` (N per car) plus each car's resistance table (offsets ``start``, n + 1; speeds
    ``table_v`` m/s, forces ``table_f`` N, as :class:`CoupledKernel` takes them) at ``speed``
    (|v|, m/s): the plant's passive force and static couplers. A stack's P rows of n cars
    (``speed``, ``r`` of P·n values) share the tables."""
    cdef Py_ssize_t i, k, n = r.shape[0], nt = start.shape[0] - 1
    out_a = np.empty(n)
    cdef double[::1] out = out_a
    if nt <= 0 or n % nt:
        raise ValueError(f"with_table_resistance: {n} speeds for {nt} cars' tables")
    for i in range(n):
        k = i % nt
        out[i] = r[i]
        if start[k + 1] > start[k]:
            out[i] = r[i] + table_at(&table_v[start[k]], &table_f[start[k]], start[k + 1] - start[k], speed[i], NULL)
    return out_a


cdef inline double _pymax(double a, double b) noexcept nogil:
    """Python's max(a, b) of two floats: b only if b > a (NaN rules of the builtin)."""
    return b if b > a else a


cdef inline double _pymin(double a, double b) noexcept nogil:
    """Python's min(a, b) of two floats: b only if b < a."""
    return b if b < a else a


cdef class EquippedKernel:
    """A coupled train with brake equipment (or a stack of P of them, ``stack_plants``): the whole
    control period of :meth:`canbrake.physics.train.TrainPlant.step` in one call (:meth:`run`).

    Each sub-step: the rail conditions of the moment, the actuator (ratings, first-order lag, jerk
    limit), the traction envelopes and the locomotives' electric-brake and adhesion limits, the
    couplers (Chen's Φ with the end stop, Li's draft gears through :class:`GearKernel` on the
    couplers that have one), the grade (or the plant's grade callback), the route, δ, the
    disturbances and eq. 40, the running resistance with its tables and the air brake's block
    force, then the brake equipment's sub-step (:class:`EquipmentKernel`, C level) and the
    positions, and the air brake (:class:`AirKernel`) at the new speeds. Every value is computed
    with the floating-point operations of the numpy sub-step loop it replaced, in the same order
    (``-ffp-contract=off``); the transcendental functions are those the loop used: libm's ``sin``
    for the disturbances (``math.sin`` there), numpy's ``sin``/``cos``/``cbrt`` for eq. 40 (called
    on the same values), the caller's lag factors.

    Per car, shape (P, n) or (n,): ``mass``, ``c_static``, ``c1``, ``c2``, ``grade_force_n`` (or
    None), the actuator's ``brake_max``, ``trac_max``, ``rate_max``; per coupler (P, n-1) or
    (n-1,): ``spacing``, ``kappa``, ``epsilon``; ``end_stop_m`` (None: none), stiffness and
    absorption (one value or one per coupler). The others are rows shared by the points: see
    :meth:`canbrake.physics.train.TrainPlant._equipped_kernel`, which builds it.
    """

    cdef readonly Py_ssize_t n, nc, points
    cdef EquipmentKernel equip
    cdef GearKernel gears
    cdef AirKernel air
    cdef const Py_ssize_t[::1] gear_idx
    cdef const double[::1] mass, c_static, c1, c2, grade, brake_max, trac_max, rate_max, spacing, kappa, eps
    cdef const double[::1] es_m, es_k, es_a, inst
    cdef double es_vt, g, unc
    cdef bint end_stop, has_grade, unrated, jerk_limited, ideal, has_instant, has_env, has_table, has_route
    cdef bint has_li_dist
    cdef const double[:, ::1] env
    cdef const Py_ssize_t[::1] tab_start
    cdef const double[::1] tab_v, tab_f
    cdef const double[::1] d_start, d_end, d_w, d_ph
    cdef const double[:, ::1] d_amp, d_off
    cdef Py_ssize_t n_dist
    cdef const double[::1] li_on, brk, val, weight
    cdef double li_c0, li_c1, li_c2
    cdef const Py_ssize_t[::1] lim_idx, lim_adh
    cdef const double[:, ::1] lim_env
    cdef const double[::1] lim_mu0
    cdef const double[::1] base_mu, ones, ev_start, ev_end
    cdef const double[:, ::1] ev_mu, ev_eff
    cdef const unsigned char[::1] ev_has_mu, ev_has_eff
    cdef double[::1] w_vb, w_vn, w_dl, w_eff, w_f, w_r, w_phi, w_brake, w_trac, w_oth, w_tb, w_td, w_held
    cdef double[::1] w_gst, w_grt, w_gfc
    cdef object w_vb_a, w_dl_a

    def __init__(self, EquipmentKernel equip, *, int points, mass, c_static, c1, c2, grade_force_n, brake_max,
                 trac_max, rate_max, spacing, kappa, epsilon, end_stop_m, end_stop_stiffness, end_stop_absorption,
                 double end_stop_transition, double gravity, bint ideal, bint unrated, bint jerk_limited,
                 instant=None, envelope=None, table_start=None, table_v=None, table_f=None, dist_start=(),
                 dist_end=(), dist_w=(), dist_phase=(), dist_amp=None, dist_off=None, GearKernel gears=None,
                 gear_couplers=None, AirKernel air=None, double uncertainty=0.0, li_dist_on=None,
                 li_dist_coef=(0.0, 0.0, 0.0), route_brk=None, route_val=None, weight_kn=None, limit_cars=(),
                 limit_envelope=None, limit_adhesion=(), limit_mu0=(), base_mu=None, event_start=(),
                 event_end=(), event_mu=None, event_eff=None):
        c = lambda a, shape: np.ascontiguousarray(np.broadcast_to(np.asarray(a, dtype=float), shape))  # noqa: E731
        P = points
        n = int(np.shape(mass)[len(np.shape(mass)) - 1])
        nc = max(n - 1, 0)
        self.n, self.nc, self.points = n, nc, P
        self.equip, self.gears, self.air = equip, gears, air
        self.gear_idx = np.ascontiguousarray(np.zeros(0) if gear_couplers is None else gear_couplers, dtype=np.intp)
        self.mass, self.c_static = c(mass, (P, n)).reshape(-1), c(c_static, (P, n)).reshape(-1)
        self.c1, self.c2 = c(c1, (P, n)).reshape(-1), c(c2, (P, n)).reshape(-1)
        self.has_grade = grade_force_n is not None
        self.grade = c(0.0 if grade_force_n is None else grade_force_n, (P, n)).reshape(-1)
        self.brake_max, self.trac_max = c(brake_max, (P, n)).reshape(-1), c(trac_max, (P, n)).reshape(-1)
        self.rate_max = c(rate_max, (P, n)).reshape(-1)
        self.spacing, self.kappa = c(spacing, (P, nc)).reshape(-1), c(kappa, (P, nc)).reshape(-1)
        self.eps = c(epsilon, (P, nc)).reshape(-1)
        self.end_stop = end_stop_m is not None
        self.es_m = c(0.0 if end_stop_m is None else end_stop_m, (nc,))
        self.es_k, self.es_a = c(end_stop_stiffness, (nc,)), c(end_stop_absorption, (nc,))
        self.es_vt, self.g = end_stop_transition, gravity
        self.ideal, self.unrated, self.jerk_limited = ideal, unrated, jerk_limited
        self.has_instant = instant is not None
        self.inst = c(0.0 if instant is None else instant, (n,))
        self.has_env = envelope is not None
        self.env = c(np.full((n, 6), np.nan) if envelope is None else envelope, (n, 6))
        self.has_table = table_start is not None
        self.tab_start = np.ascontiguousarray(np.zeros(n + 1) if table_start is None else table_start, dtype=np.intp)
        flat = lambda a: np.ascontiguousarray(np.zeros(1) if a is None or len(a) == 0 else a, dtype=float)  # noqa: E731
        self.tab_v, self.tab_f = flat(table_v), flat(table_f)
        self.d_start, self.d_end = np.ascontiguousarray(dist_start, dtype=float), np.ascontiguousarray(dist_end, dtype=float)
        self.d_w, self.d_ph = np.ascontiguousarray(dist_w, dtype=float), np.ascontiguousarray(dist_phase, dtype=float)
        self.n_dist = self.d_start.shape[0]
        self.d_amp = c(np.zeros((0, n)) if dist_amp is None else np.reshape(dist_amp, (self.n_dist, n)), (self.n_dist, n))
        self.d_off = c(np.zeros((0, n)) if dist_off is None else np.reshape(dist_off, (self.n_dist, n)), (self.n_dist, n))
        self.unc = uncertainty
        self.has_li_dist = li_dist_on is not None
        self.li_on = c(0.0 if li_dist_on is None else np.asarray(li_dist_on, dtype=float), (n,))
        self.li_c0, self.li_c1, self.li_c2 = (float(x) for x in li_dist_coef)
        self.has_route = route_brk is not None
        self.brk, self.val = flat(route_brk), flat(route_val)
        self.weight = c(0.0 if weight_kn is None else weight_kn, (n,))
        nl = len(limit_cars)
        self.lim_idx = np.ascontiguousarray(limit_cars, dtype=np.intp)
        self.lim_env = c(np.full((nl, 10), np.nan) if limit_envelope is None else limit_envelope, (nl, 10))
        self.lim_adh = np.ascontiguousarray(limit_adhesion, dtype=np.intp)
        self.lim_mu0 = np.ascontiguousarray(limit_mu0, dtype=float)
        self.base_mu = c(0.3 if base_mu is None else base_mu, (n,))
        self.ones = np.ones(n)
        ne = len(event_start)
        self.ev_start, self.ev_end = np.ascontiguousarray(event_start, dtype=float), np.ascontiguousarray(event_end, dtype=float)
        mus = [None] * ne if event_mu is None else list(event_mu)
        effs = [None] * ne if event_eff is None else list(event_eff)
        self.ev_has_mu = np.array([m is not None for m in mus], dtype=np.uint8)
        self.ev_has_eff = np.array([e is not None for e in effs], dtype=np.uint8)
        self.ev_mu = c(np.reshape([np.zeros(n) if m is None else m for m in mus], (ne, n)), (ne, n))
        self.ev_eff = c(np.reshape([np.ones(n) if e is None else e for e in effs], (ne, n)), (ne, n))
        N, ng, w = P * n, self.gear_idx.shape[0], lambda k: np.empty(max(k, 1))  # noqa: E731
        self.w_vb_a, self.w_dl_a = np.empty(N), np.empty(P * nc)
        self.w_vb, self.w_dl = self.w_vb_a, (self.w_dl_a if P * nc else w(0))
        self.w_vn, self.w_eff, self.w_f, self.w_r, self.w_phi = w(N), w(N), w(N), w(N), w(P * nc)
        self.w_brake, self.w_trac, self.w_oth, self.w_tb, self.w_td = w(N), w(N), w(N), w(N * equip.p), w(N * equip.p)
        self.w_held, self.w_gst, self.w_grt, self.w_gfc = w(n), w(ng), w(ng), w(ng)

    cdef inline double _saturate(self, Py_ssize_t k, double u, double vi) noexcept nogil:
        """:meth:`canbrake.physics.heavy_haul.TractionEnvelope.saturate_n` of the limited car k's
        envelope row (traction fields, then the brake's: linear slope, until, max, constant until)."""
        cdef const double* e = &self.lim_env[k, 0]
        cdef double v = fabs(vi) / (1.0 / 3.6), hi, lo
        if v <= e[1]:
            hi = e[0]
        elif v <= e[4]:
            hi = e[2] - e[3] * v
        else:
            hi = e[5] / v
        if v <= e[7]:
            lo = e[6] * v
        elif v <= e[9]:
            lo = e[8]
        else:
            lo = e[5] / v
        return _pymin(_pymax(u, -1000.0 * lo), 1000.0 * hi)

    def run(self, x0, v0, cmd, double[::1] act, double t0, double h, int n_sub, double lag, lag_per_car,
            const double[::1] blend_k, const double[::1] valve_k, wsp, double[::1] friction, double[::1] ed,
            double[::1] valve, double[::1] vent, double[::1] omega, double[::1] force, double[::1] slip,
            double[::1] gear_fs, double[::1] gear_dp, int air_mode, double[::1] fill, const double[::1] target,
            const double[::1] fill_gain, double[::1] pipe, const double[::1] pipe_gain, double t_apply,
            double t_release, double[::1] air_n, grade_cb=None, double[::1] fill_before=None):
        """Advance ``n_sub`` sub-steps of ``h`` s from ``t0``: positions ``x0`` (m), speeds ``v0``
        (m/s) and the brake command ``cmd`` (N, + brakes), P·n values each; ``act`` the actuator's
        effort (N, P·n, updated in place; ``lag`` = 1 − e^(−h/τ), or ``lag_per_car`` (n,)).
        Brake equipment (:meth:`EquipmentKernel.substep`): ``blend_k``, ``valve_k``, ``wsp`` (None
        or P·n), its state ``friction``, ``ed``, ``valve``, ``vent``, ``omega``, ``force``,
        ``slip`` (updated in place). Draft gears: their force state and deflections ``gear_fs``,
        ``gear_dp`` (updated). Air brake (``air_mode`` as :meth:`AirKernel.run`, −1: untouched):
        ``fill``, ``pipe`` and its block force ``air_n`` updated; ``fill_before`` (optional): the
        fill before the last sub-step's update (what a command arriving now redoes). ``grade_cb``: the plant's
        grade force (N per car) from the positions, called every sub-step when given.

        Returns (t, t_last, x, v, acc, rail, dl): the time after and at the last sub-step's
        start, the new positions and speeds, the acceleration over the last sub-step, the last
        rail force and the last sub-step's coupler deflections (P·(n−1); the kernel's own array,
        overwritten by the next call)."""
        cdef Py_ssize_t P = self.points, n = self.n, nc = self.nc, N = P * n, i, j, k, p, s, q, e
        cdef Py_ssize_t ng = self.gear_idx.shape[0], nl = self.lim_idx.shape[0], nev = self.ev_start.shape[0]
        cdef Py_ssize_t pe = self.equip.p
        xa, va, raila = np.array(x0, dtype=float).reshape(-1), np.array(v0, dtype=float).reshape(-1), np.empty(N)
        cdef double[::1] x = xa, v = va, rail = raila
        # work arrays, the kernel's own (dl is returned: the caller reads it at once)
        cdef double[::1] vb = self.w_vb, vn = self.w_vn, dl = self.w_dl, eff_b = self.w_eff, f = self.w_f
        cdef double[::1] r = self.w_r, phi = self.w_phi, brake = self.w_brake, trac = self.w_trac
        cdef double[::1] oth = self.w_oth, tb = self.w_tb, td = self.w_td, held = self.w_held
        cdef double[::1] gst = self.w_gst, grt = self.w_grt, gfc = self.w_gfc
        cdef double[::1] cb = self.w_held  # eq. 40's cube roots of |v| replace it before use
        cdef const double[::1] c = np.ascontiguousarray(cmd, dtype=float).reshape(-1)
        cdef bint has_wsp = wsp is not None
        cdef const double[::1] wcmd = np.ascontiguousarray(wsp, dtype=float).reshape(-1) if has_wsp else np.zeros(0)
        cdef bint per_car_lag = lag_per_car is not None
        cdef const double[::1] lagv = np.ascontiguousarray(lag_per_car, dtype=float) if per_car_lag else self.ones
        cdef const double[::1] gforce
        cdef const double[::1] mu, effv
        cdef double t = t0, t_last = t0, d, st, lim, ev, dlj, rate, over, sg, loading, share, ph, fc, ext, acc
        cdef double speed, vi, u, cap, mu_i, unc1 = 1.0 + self.unc, s1 = 0.0, s2 = 0.0, c3 = 0.0, lag_i = lag
        cdef bint finite_phi
        cdef double bad_phi = 0.0
        for s in range(n_sub):
            t_last = t
            # the rail conditions of the moment (TrainPlant._update_rail: a later event overrides)
            mu, effv = self.base_mu, self.ones
            for e in range(nev):
                if self.ev_start[e] <= t < self.ev_end[e]:
                    if self.ev_has_mu[e]:
                        mu = self.ev_mu[e]
                    if self.ev_has_eff[e]:
                        effv = self.ev_eff[e]
            # the actuator (ActuatorState.advance), then each car's traction within its envelope
            for q in range(N):
                i = q if q < n else q % n
                d = c[q]
                if not self.unrated:
                    d = _min(_max(d, -self.trac_max[q]), self.brake_max[q])
                if self.ideal:
                    ev = d
                else:
                    if per_car_lag:
                        lag_i = lagv[i]
                    st = (d - act[q]) * lag_i
                    if self.jerk_limited:
                        lim = self.rate_max[q] * h
                        st = _min(_max(st, -lim), lim)
                    ev = act[q] + st
                    if self.has_instant and self.inst[i] != 0.0:
                        ev = d
                act[q] = ev
                if self.has_env and ev < 0.0 and self.env[i, 0] == self.env[i, 0]:
                    ev = _max(ev, -_envelope_n(&self.env[i, 0], v[q]))
                eff_b[q] = ev
            # the locomotives' electric brake and adhesion (a single plant): each limited car's force,
            # as traction u = −effort, clipped into [−F_B(v), F_T(v)] of its envelope, then at ±μ(v)·m·g
            # of its adhesion (the heavy-haul model's saturate_n and _adhesion_limit, Python's min/max).
            # As there, the command is clipped at the period's first sub-step and the force so held is
            # clipped again at each later sub-step's speed: within a period a limit that falls lowers
            # the force, one that rises does not raise it again (the traction control takes the
            # command once per period)
            for k in range(nl):
                i = self.lim_idx[k]
                u = -(eff_b[i] if s == 0 else held[i])
                vi = v[i]
                if self.lim_env[k, 0] == self.lim_env[k, 0]:
                    u = self._saturate(k, u, vi)
                if self.lim_adh[k] > 0:
                    mu_i = self.lim_mu0[k]
                    if self.lim_adh[k] == 2:  # Curtius-Kniffler
                        mu_i = self.lim_mu0[k] * (0.161 + 7.5 / (fabs(vi) / (1.0 / 3.6) + 44.0)) / (0.161 + 7.5 / 44.0)
                    cap = mu_i * self.mass[i] * self.g
                    u = _pymin(_pymax(u, -cap), cap)
                eff_b[i] = -u
                held[i] = eff_b[i]
            # couplers: Φ(Δl) (+ the end stop's buffer), Li's draft gears where fitted
            if self.has_li_dist:  # eq. 40's time functions, numpy's as the loop had them
                s1 = _np_sin(t + 1.0)
                s2 = _np_sin(2 * t + 2.0)
                c3 = _np_cos(3 * t + 1.0)
                cb = _np_cbrt(np.abs(va))
            if grade_cb is not None:
                gforce = np.ascontiguousarray(grade_cb(xa.reshape(np.shape(x0)).copy()), dtype=float).reshape(-1)
            for p in range(P):
                finite_phi = True
                for j in range(nc):
                    q = p * nc + j
                    dlj = x[p * n + j] - x[p * n + j + 1] - self.spacing[q]
                    dl[q] = dlj
                    ph = self.kappa[q] * (1.0 + self.eps[q] * dlj * dlj) * dlj
                    if self.end_stop:
                        over = fabs(dlj) - self.es_m[j]
                        sg = _sign(dlj)
                        rate = v[p * n + j] - v[p * n + j + 1]
                        loading = _min(_max(0.5 + sg * rate / (2.0 * self.es_vt), 0.0), 1.0)
                        share = 1.0 - self.es_a[j] * (1.0 - loading)
                        ph = ph + (sg * over * self.es_k[j] * share if over > 0.0 else 0.0)
                    phi[q] = ph
                if ng:  # (a single plant)
                    for k in range(ng):
                        j = self.gear_idx[k]
                        gst[k] = dl[j]
                        grt[k] = v[j] - v[j + 1]
                    self.gears.run(&gst[0], &grt[0], &gear_fs[0], &gear_dp[0], &gfc[0], &gear_fs[0], &gear_dp[0])
                    for k in range(ng):
                        phi[self.gear_idx[k]] = gfc[k]
                for j in range(nc):
                    if finite_phi and not isfinite(phi[p * nc + j]):
                        finite_phi = False
                        bad_phi = phi[p * nc + j]
                for i in range(n):
                    q = p * n + i
                    # f_i = Φ_{i-1} − Φ_i: the loop's incidence product (exact; NaN on every car of a
                    # row with a non-finite Φ, as its 0 · Φ_j terms gave)
                    fc = 0.0
                    if i > 0:
                        fc = fc + phi[p * nc + i - 1]
                    if i < nc:
                        fc = fc - phi[p * nc + i]
                    if not finite_phi:
                        fc = 0.0 * bad_phi
                    if grade_cb is not None:
                        fc = fc - gforce[q]
                    elif self.has_grade:
                        fc = fc + self.grade[q]
                    if self.has_route:
                        fc = fc - route_n(self.brk, self.val, self.weight[i], x[q])
                    if self.unc != 0.0:
                        fc = fc * unc1
                    if self.n_dist:
                        fc = fc + _disturbance(self.d_start, self.d_end, self.d_w, self.d_ph, self.d_off, self.d_amp,
                                               i, t)
                    if self.has_li_dist:
                        if self.li_on[i] != 0.0:
                            acc = self.li_c0 + self.li_c1 * s1 + self.li_c2 * cb[i] * (s2 + c3)
                            fc = fc + self.mass[q] * acc
                        else:
                            fc = fc + 0.0
                    f[q] = fc
                    # the running resistance (Davis, table), the air brake's block force, δ
                    speed = fabs(v[q])
                    ev = self.c_static[q] + speed * (self.c1[q] + self.c2[q] * speed)
                    if self.has_table and self.tab_start[i + 1] > self.tab_start[i]:
                        ev = ev + table_at(&self.tab_v[self.tab_start[i]], &self.tab_f[self.tab_start[i]],
                                           self.tab_start[i + 1] - self.tab_start[i], speed, NULL)
                    if self.air is not None:
                        ev = ev + air_n[i]
                    if self.unc != 0.0:
                        ev = ev * unc1
                    r[q] = ev
            # the brake equipment (blending, dump valves, wheelsets or the Coulomb brake)
            self.equip.run_sub(h, blend_k, valve_k, eff_b, v, f, r, self.mass, mu, effv, has_wsp, wcmd, friction, ed,
                               valve, vent, omega, force, slip, brake, trac, rail, vn, oth, tb, td)
            for q in range(N):
                x[q] = x[q] + h * vn[q]
                vb[q] = v[q]
                v[q] = vn[q]
            t = t + h
            if self.air is not None and air_mode >= 0:  # cylinders and pipe to the new time, forces at the new speeds
                if fill_before is not None:
                    for q in range(fill.shape[0]):
                        fill_before[q] = fill[q]
                self.air.run(air_mode, t, &v[0], &fill[0], &target[0], &fill_gain[0], &pipe[0], &pipe_gain[0], t_apply,
                             t_release, &air_n[0])
        acc_a = np.empty(N)
        cdef double[::1] acc_v = acc_a
        for q in range(N):  # the acceleration over the last sub-step
            acc_v[q] = (v[q] - vb[q]) / h
        return t, t_last, xa, va, acc_a, raila, self.w_dl_a
