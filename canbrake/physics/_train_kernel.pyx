# cython: language_level=3
# distutils: extra_compile_args = -ffp-contract=off
"""The coupled train's integration loop (:meth:`canbrake.physics.train.TrainPlant.step`), compiled.

One call advances a plant, or a stack of P plants (``stack_plants``: arrays with a leading points
axis), by one control period of ``n_sub`` sub-steps: arrays in, arrays out; the policy (sub-step
count, rail conditions, divergence reports) stays in Python. Written by hand because numpy's cost
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

from canbrake.physics._npmath cimport _max, _min, _sign  # numpy's NaN rules, shared
from canbrake.physics._table cimport table_at  # the speed tables' interpolation, shared

import numpy as np


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

        Returns (time_s, x, v, accel, rail, n_bad): the new state, the acceleration over the last
        sub-step, the last rail force (``rail0`` itself when ideal) and the number of points whose
        speeds are not all finite (flagged in :attr:`bad`, their last max |Δl| in :attr:`dl_max`)."""
        cdef Py_ssize_t P = self.points, n = self.n
        shape = np.shape(x0)
        if len(shape) not in (1, 2) or shape[len(shape) - 1] != n or (len(shape) == 2 and shape[0] != P):
            raise ValueError(f"the plant kernel needs positions of shape ({n},) or ({P}, {n}), got {shape}")  # (n,) or (P, n), a stack of one point included
        x_out = np.empty(shape)
        v_out = np.empty(shape)
        a_out = np.empty(shape)
        rail_out = rail0 if ideal else np.empty(shape)
        # the 11 arrays' buffers, released in one place whatever happens (held: how many were taken)
        cdef Py_buffer bufs[11]
        cdef int held = 0
        cdef Rows rx, rv, rc, rr, re, rm, rf, rxo, rvo, rao, rro
        cdef unsigned char[::1] bad = self.bad
        cdef double[::1] dl_max = self.dl_max
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
        finally:
            while held > 0:
                held -= 1
                PyBuffer_Release(&bufs[held])
        n_bad = 0
        for p in range(P):
            n_bad += bad[p]
        return t, x_out, v_out, a_out, rail_out, n_bad

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
        cdef unsigned char[::1] bad = self.bad
        cdef double[::1] dl_max = self.dl_max
        cdef double* mass = self.mass.p
        cdef bint per_car_lag = lag_per_car is not None
        cdef const double[::1] lagv = lag_per_car if per_car_lag else self.inst
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
                        ext = 0.0
                        for k in range(self.n_dist):
                            if self.d_start[k] <= t < self.d_end[k]:
                                ext = ext + self.d_off[k, i] + self.d_amp[k, i] * sin(
                                    self.d_w[k] * (t - self.d_start[k]) + self.d_ph[k])
                        f = f + ext
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


def traction_capped(const double[:, ::1] envelope, const double[::1] v, const double[::1] force):
    """``force`` (N per car, + brakes, − traction) with each car's traction limited by its envelope
    row (``envelope``, shape (n, 6) as :class:`CoupledKernel` takes it; NaN first value: none) at
    its speed ``v`` (m/s): the step with brake equipment (blending, wheelsets), which caps the
    actuator's effort before the equipment, as the kernel caps the rail force. A stack's P rows of
    n cars (``v``, ``force`` of P·n values) share the envelope rows."""
    cdef Py_ssize_t i, k, n = force.shape[0], ne = envelope.shape[0]
    out_a = np.empty(n)
    cdef double[::1] out = out_a
    if ne == 0 or n % ne:
        raise ValueError(f"traction_capped: {n} forces for {ne} envelope rows")
    for i in range(n):
        k = i % ne
        out[i] = force[i]
        if force[i] < 0.0 and envelope[k, 0] == envelope[k, 0]:
            out[i] = _max(force[i], -_envelope_n(&envelope[k, 0], v[i]))
    return out_a


def with_table_resistance(const Py_ssize_t[::1] start, const double[::1] table_v, const double[::1] table_f,
                          const double[::1] speed, const double[::1] r):
    """``r`` (N per car) plus each car's resistance table (offsets ``start``, n + 1; speeds
    ``table_v`` m/s, forces ``table_f`` N, as :class:`CoupledKernel` takes them) at ``speed``
    (|v|, m/s): the step with brake equipment. A stack's P rows of n cars (``speed``, ``r`` of P·n
    values) share the tables."""
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
