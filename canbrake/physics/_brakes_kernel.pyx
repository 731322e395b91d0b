# cython: language_level=3, cdivision=True, boundscheck=False, wraparound=False
# distutils: extra_compile_args = -ffp-contract=off
"""The coupled train's brake equipment (:mod:`canbrake.physics.brakes`), compiled: ED/friction
blending, the dump valves with their watchdog, and the backward-Euler step of wheelsets and car
bodies with Cai's creep force per axle, or without wheelsets the Coulomb brake/resistance update.

One call per sub-step of :meth:`canbrake.physics.train.TrainPlant.step` with brake equipment
(:meth:`EquipmentKernel.run_sub`, from the compiled period ``_train_kernel.EquippedKernel``; its
Python form :meth:`EquipmentKernel.substep`): arrays in (per car), the new speeds and rail forces
out, the equipment's state arrays updated in place. The coupler, grade and disturbance forces
are the caller's. Written by hand because the numpy form cost about 150 array
operations per sub-step on a handful of cars and axles (one 1-ms sub-step of Chen's 6-car metro
with four wheelsets per car took ~600 us).

Every value is computed with the floating-point operations of the numpy code it replaced, in the
same order (``-ffp-contract=off``; numpy's NaN rules for sign/minimum/maximum from ``_npmath``;
the sums over a car's axles as numpy's ``add.reduce`` adds a row: from 0.0, pairwise by blocks of
eight from eight values on, see :func:`_npsum`); the slip curve's exponentials are numpy's
(``numpy.exp`` over all axles per evaluation: its SIMD exp is not libm's in the last bit), and the
lags' ``1 − exp(−h/τ)`` come from the caller's ``math.exp``.

Arrays are C-contiguous float64. Per-car arrays have N = P·n values (a stack of P plants, or one
plant) or n (one row shared by every point, as numpy broadcasts it); wheelsets only for P = 1,
their per-axle arrays (n, p).
"""
from cpython.mem cimport PyMem_Free, PyMem_Malloc
from libc.math cimport exp, fabs

from canbrake.physics._npmath cimport _max, _min, _sign  # numpy's NaN rules, shared

import numpy as np

_np_exp = np.exp


cdef double _npsum(const double* a, Py_ssize_t n) noexcept nogil:
    """``numpy.add.reduce`` of n contiguous doubles (a row of a C-contiguous array): 0.0 plus
    numpy's pairwise sum (sequential below 8 values, eight accumulators up to 128, halves above)."""
    return 0.0 + _pairwise(a, n)


cdef double _pairwise(const double* a, Py_ssize_t n) noexcept nogil:
    cdef double res, r0, r1, r2, r3, r4, r5, r6, r7
    cdef Py_ssize_t i, n2
    if n < 8:
        res = -0.0
        for i in range(n):
            res = res + a[i]
        return res
    if n <= 128:
        r0, r1, r2, r3, r4, r5, r6, r7 = a[0], a[1], a[2], a[3], a[4], a[5], a[6], a[7]
        i = 8
        while i < n - (n % 8):
            r0 = r0 + a[i]
            r1 = r1 + a[i + 1]
            r2 = r2 + a[i + 2]
            r3 = r3 + a[i + 3]
            r4 = r4 + a[i + 4]
            r5 = r5 + a[i + 5]
            r6 = r6 + a[i + 6]
            r7 = r7 + a[i + 7]
            i += 8
        res = ((r0 + r1) + (r2 + r3)) + ((r4 + r5) + (r6 + r7))
        while i < n:
            res = res + a[i]
            i += 1
        return res
    n2 = n // 2
    n2 -= n2 % 8
    return _pairwise(a, n2) + _pairwise(a + n2, n - n2)


cdef inline Py_ssize_t _wrap(Py_ssize_t i, Py_ssize_t n) noexcept nogil:
    """i mod n for a row index (0 <= i): i itself when i < n, 0 for one shared value, without a
    division in those common cases."""
    if i < n:
        return i
    if n == 1:
        return 0
    return i % n


cdef inline double _clip01(double x) noexcept nogil:
    """numpy.clip(x, 0, 1) (NaN stays NaN)."""
    return _min(_max(x, 0.0), 1.0)


cdef class EquipmentKernel:
    """Constants of a coupled train's brake equipment, and its sub-step.

    Blending (``blending`` True): per car ``ed_max`` (m/s²) and ``ed_power`` (W/kg), ``fade_start``,
    ``fade_end`` (m/s) and ``friction_lag_s`` (s), each one value or one per car (a car without
    blending: ``ed_max`` 0 and ``friction_lag_s`` 0, so its friction brake gives the demand at
    once); ``envelope``: None, or per car (n, 5) the ED brake's force envelope
    (Li 2024 eq. 2) ``(slope N·s/m, v1 m/s, F_max N, v2 m/s, power W)``, NaN rows for the cars that
    use ``ed_max``/``ed_power`` with the fade: F = slope·|v| up to v1, F_max up to v2, power/|v| above.
    Dump valves: ``valve_lag_s``, ``max_vent_s`` (s; one value, or one per car).
    Wheelsets (``axles`` p > 0, the most any car has): radius ``R`` (m) and inertia ``J`` (kg·m²) of
    a car's wheelsets (one value, or one per car), normal loads ``N`` (n, p) (N), ``active`` (None:
    every car has p axles; or per car its number of axles, 0 for a car without wheels, whose brake
    and resistance act on its body as without wheelsets; a car's axles beyond its own are inactive:
    ω, creep force and slip 0), the slip curve ``b1..b3``, ``c1..c3`` with μ_max(0) = ``mu0`` and the curve's own peak
    ``peak_curve``, the slip denominator's floor ``v_floor`` (m/s), each one value for the train or one per
    car, ``iters`` Newton iterations. A stack of P plants (``stack_plants``) passes P·n cars and P·n·p
    axles to the steps; its points share these rows (car i is row i mod n).
    ``adhesion_limited``: without wheelsets, the rail force is capped at μ m g (``gravity``).
    (Attributes: _brakes_kernel.pxd.)
    """

    def __init__(self, *, bint blending, ed_max, ed_power, fade_start, fade_end,
                 friction_lag_s, valve_lag_s, max_vent_s, bint adhesion_limited,
                 double gravity, envelope=None, int axles=0, R=1.0, J=1.0, N=None, active=None, b1=0.0,
                 b2=0.0, b3=1.0, c1=0.0, c2=0.0, c3=1.0, mu0=1.0, peak_curve=1.0, v_floor=0.1, int iters=5):
        self.blending = blending
        self.ed_max = np.ascontiguousarray(np.atleast_1d(np.asarray(ed_max, dtype=float)))
        self.ed_power = np.ascontiguousarray(np.atleast_1d(np.asarray(ed_power, dtype=float)))
        self.has_env = envelope is not None
        self.env = np.ascontiguousarray(np.zeros((1, 5)) if envelope is None else np.asarray(envelope, dtype=float))
        arr = lambda x: np.ascontiguousarray(np.atleast_1d(np.asarray(x, dtype=float)))  # noqa: E731
        self.fade_start, self.fade_end = arr(fade_start), arr(fade_end)
        self.friction_lag, self.valve_lag, self.max_vent = arr(friction_lag_s), arr(valve_lag_s), arr(max_vent_s)
        self.adhesion_limited, self.g = adhesion_limited, gravity
        self.p, self.iters = axles, iters
        self.nna = 1
        self.R, self.J = arr(R), arr(J)
        self.nR, self.nJ = self.R.shape[0], self.J.shape[0]
        sc = [arr(x) for x in (b1, b2, b3, c1, c2, c3, mu0, peak_curve, v_floor)]
        if len({x.shape[0] for x in sc}) != 1:
            raise ValueError("the slip curve's coefficients need one value each, or one per car each")
        self.b1, self.b2, self.b3, self.c1, self.c2, self.c3, self.mu0, self.peak_curve, self.v_floor = sc
        self.nsc = sc[0].shape[0]
        if axles > 0:
            self.N = np.ascontiguousarray(N, dtype=float)
            na = np.full(self.N.shape[0], axles, dtype=np.intp) if active is None else np.asarray(active, dtype=np.intp)
            self.na = np.ascontiguousarray(na)
            self.nna = self.na.shape[0]
            self.bare = bool(np.any(na == 0))

    def substep(self, double h, const double[::1] blend_k, const double[::1] valve_k, const double[::1] effort,
                const double[::1] v, const double[::1] f, const double[::1] r, const double[::1] mass,
                const double[::1] mu, const double[::1] eff, wsp, double[::1] friction, double[::1] ed,
                double[::1] valve, double[::1] vent, double[::1] omega, double[::1] force, double[::1] slip):
        """One sub-step of ``h`` (s). Per car (N values): ``effort`` the actuator's (N, + brakes),
        ``v`` (m/s), ``f`` the coupler + grade + disturbance forces (N), ``r`` the running
        resistance magnitude (N), ``mass`` (kg), ``mu`` peak adhesion, ``eff`` brake effectiveness;
        ``wsp`` the dump valves' command (0..1, NaN none) or None. State, updated in place:
        ``friction``, ``ed`` (blending, N), ``valve`` (opening) and ``vent`` (s venting) shaped as
        ``wsp``; per axle (n·p): ``omega`` (rad/s), ``force`` (creep force, N), ``slip``.
        ``blend_k``, ``valve_k``: 1 − exp(−h/lag) of the friction brake and the valve (one value,
        or one per car as the lags are given).

        Returns (v_new, rail): the new speeds (m/s) and the rail force per car (N, + brakes)."""
        cdef Py_ssize_t nn = max(v.shape[0], effort.shape[0], f.shape[0]), nv = v.shape[0]
        brake_a, trac_a, rail_a, vnew_a = np.empty(nn), np.empty(nn), np.empty(nn), np.empty(nn)
        oth_a, tb_a, td_a = np.empty(nv), np.empty(nv * self.p), np.empty(nv * self.p)
        cdef const double[::1] cmd = np.zeros(0) if wsp is None else wsp
        self.run_sub(h, blend_k, valve_k, effort, v, f, r, mass, mu, eff, wsp is not None, cmd, friction, ed, valve,
                     vent, omega, force, slip, brake_a, trac_a, rail_a, vnew_a, oth_a, tb_a, td_a)
        return vnew_a, rail_a

    cdef int run_sub(self, double h, const double[::1] blend_k, const double[::1] valve_k,
                     const double[::1] effort, const double[::1] v, const double[::1] f, const double[::1] r,
                     const double[::1] mass, const double[::1] mu, const double[::1] eff, bint has_wsp,
                     const double[::1] cmd, double[::1] friction, double[::1] ed, double[::1] valve,
                     double[::1] vent, double[::1] omega, double[::1] force, double[::1] slip,
                     double[::1] brake, double[::1] trac, double[::1] rail, double[::1] vnew,
                     double[::1] oth, double[::1] tb, double[::1] td) except -1:
        """:meth:`substep` into the caller's buffers: ``cmd`` the dump valves' command (if
        ``has_wsp``); out: ``rail``, ``vnew`` (N values, N = max of the per-car lengths); work:
        ``brake``, ``trac`` (N), ``oth`` (cars), ``tb``, ``td`` (cars × axles)."""
        cdef Py_ssize_t nv = v.shape[0], i
        cdef Py_ssize_t ne = effort.shape[0], nm = mass.shape[0], nmu = mu.shape[0], nef = eff.shape[0]
        cdef Py_ssize_t nf = f.shape[0], nr = r.shape[0]
        cdef Py_ssize_t nn = max(nv, ne)
        cdef double s, fade, per_kg, demand, e, share, total, tr, cap, rail_i, ff, rr, sg, vn, want, ed_cap
        cdef Py_ssize_t nw = 0, nea = self.ed_max.shape[0], nep = self.ed_power.shape[0], nen = self.env.shape[0]
        cdef Py_ssize_t ie, nfs = self.fade_start.shape[0], nfe = self.fade_end.shape[0]
        cdef Py_ssize_t nfl = self.friction_lag.shape[0], nbk = blend_k.shape[0], nvk = valve_k.shape[0]
        cdef Py_ssize_t nvl = self.valve_lag.shape[0], nmv = self.max_vent.shape[0]
        if nf > nn:
            nn = nf
        for i in range(nn):
            e = effort[_wrap(i, ne)]
            if self.blending:
                s = fabs(v[_wrap(i, nv)])
                ie = _wrap(i, nen)
                if self.has_env and self.env[ie, 0] == self.env[ie, 0]:  # the car's envelope (Li eq. 2)
                    if s <= self.env[ie, 1]:
                        ed_cap = self.env[ie, 0] * s
                    elif s <= self.env[ie, 3]:
                        ed_cap = self.env[ie, 2]
                    else:
                        ed_cap = self.env[ie, 4] / _max(s, 1e-9)
                else:
                    fade = _clip01((s - self.fade_end[_wrap(i, nfe)]) / (self.fade_start[_wrap(i, nfs)] - self.fade_end[_wrap(i, nfe)]))
                    per_kg = _min(self.ed_max[_wrap(i, nea)], self.ed_power[_wrap(i, nep)] / _max(s, 1e-9))
                    ed_cap = mass[_wrap(i, nm)] * per_kg * fade
                demand = _max(e, 0.0)
                ed[i] = _min(demand, ed_cap)
                share = demand - ed[i]
                if self.friction_lag[_wrap(i, nfl)] > 0.0:
                    friction[i] = friction[i] + (share - friction[i]) * blend_k[_wrap(i, nbk)]
                else:
                    friction[i] = share
                total = ed[i] + friction[i] + _min(e, 0.0)
            else:
                total = e
            brake[i] = _max(total, 0.0) * eff[_wrap(i, nef)]
            trac[i] = _min(total, 0.0)
        if has_wsp:
            nw = cmd.shape[0]
            for i in range(nw):
                want = cmd[i]
                want = _clip01(0.0 if want != want else want)
                vent[i] = vent[i] + h if want > 0.5 else 0.0
                if vent[i] > self.max_vent[_wrap(i, nmv)]:
                    want = 0.0
                want = _clip01(want)  # the valve's own clip (valve_step)
                if self.valve_lag[_wrap(i, nvl)] <= 0.0:
                    valve[i] = want
                else:
                    valve[i] = valve[i] + (want - valve[i]) * valve_k[_wrap(i, nvk)]
            for i in range(nn):
                brake[i] = brake[i] * (1.0 - valve[_wrap(i, nw)])
        cdef Py_ssize_t p = self.p, k
        if p > 0:  # resistance is Coulomb on the body; the brake acts on the wheels, the rail on the body
            self._prep(v, f, r, brake, trac, oth, tb, td)
            self._wheels(h, v, oth, mass, mu, tb, td, omega, force, slip, vnew)
            for i in range(nv):
                if self.na[_wrap(i, self.nna)] == 0:
                    continue  # a car without wheels: below
                vn = vnew[i]
                vnew[i] = 0.0 if v[i] != 0.0 and vn * v[i] < 0.0 else vn  # the exact stop
                rail[i] = -_npsum(&force[i * p], self.na[_wrap(i, self.nna)])
            if not self.bare:
                return 0
        for i in range(nn):
            if p > 0 and self.na[_wrap(i, self.nna)] > 0:
                continue
            rail_i = brake[i] + trac[i]
            if self.adhesion_limited:
                cap = mu[_wrap(i, nmu)] * mass[_wrap(i, nm)] * self.g
                rail_i = _min(_max(rail_i, -cap), cap)
            rail[i] = rail_i
            ff = f[_wrap(i, nf)] - _min(rail_i, 0.0)
            rr = _max(rail_i, 0.0) + r[_wrap(i, nr)]
            s = v[_wrap(i, nv)]
            if s != 0.0:
                sg = _sign(s)
                vn = s + (h / mass[_wrap(i, nm)]) * (ff - sg * rr)
                vnew[i] = 0.0 if vn * s < 0.0 else vn
            elif fabs(ff) > rr:
                vnew[i] = s + (h / mass[_wrap(i, nm)]) * (ff - _sign(ff) * rr)
            else:
                vnew[i] = s + 0.0
        return 0

    cdef void _prep(self, const double[::1] v, const double[::1] f, const double[::1] r, const double[::1] brake,
                    const double[::1] trac, double[::1] oth, double[::1] tb,
                    double[::1] td) noexcept:
        """The wheels' inputs: the body's forces besides the creep forces (f − sgn(v) r) per car and
        the brake and drive torques per axle (brake·R/p, −traction·R/p with the car's own R and p,
        the same on each of its axles; 0 on inactive axles)."""
        cdef Py_ssize_t i, k, p = self.p, pi
        cdef double b, d, per_axle
        for i in range(v.shape[0]):
            oth[i] = f[i] - _sign(v[i]) * r[i]
            pi = self.na[_wrap(i, self.nna)]
            per_axle = self.R[_wrap(i, self.nR)] / pi if pi > 0 else 0.0
            b = brake[i] * per_axle
            d = -trac[i] * per_axle
            for k in range(p):
                tb[i * p + k] = b if k < pi else 0.0
                td[i * p + k] = d if k < pi else 0.0

    cdef int _creep(self, Py_ssize_t n, const double* w, const double* v, const double[::1] mu, double* lam,
                    double* f, double* fw, double* fv, double[::1] arg, object arg_a, object ex_a) except -1:
        """Creep of every axle (n cars × p) at wheel speeds ``w`` and car speeds ``v``: slip λ, force F
        (N, + forward), ∂F/∂ω and ∂F/∂v (the former Wheelsets.creep formulas, elementwise). The
        exponentials of the slip curve are numpy's (one ``numpy.exp`` over every axle, as before):
        numpy's SIMD exp differs from libm's in the last bit for some arguments."""
        cdef Py_ssize_t i, k, j, p = self.p, nmu = mu.shape[0], pi, ic
        cdef double R, wr, awr, av, den, lm, dw, dv, scale, a, ex, sn, dmu, vf
        cdef const double[::1] exv
        for i in range(n):
            av = fabs(v[i])
            R = self.R[_wrap(i, self.nR)]
            ic = _wrap(i, self.nsc)  # the car's slip curve
            vf = self.v_floor[ic]
            pi = self.na[_wrap(i, self.nna)]
            for k in range(pi, p):  # inactive axles
                j = i * p + k
                lam[j] = 0.0
                fw[j] = 0.0
                fv[j] = 0.0
                arg[j] = 0.0
            for k in range(pi):
                j = i * p + k
                wr = w[j] * R
                awr = fabs(wr)
                den = _max(_max(awr, av), vf)
                lm = (wr - v[i]) / den
                if awr >= av and awr >= vf:
                    dw = R * av / (wr * wr)
                    dv = -1.0 / den
                elif av >= vf:
                    dw = R / den
                    dv = -wr / (den * den)
                else:
                    dw = R / den
                    dv = -1.0 / den
                lam[j] = lm
                fw[j] = dw  # dλ/dω and dλ/dv until the exponentials are known
                fv[j] = dv
                arg[j] = -self.b2[ic] * fabs(lm)
        _np_exp(arg_a, out=ex_a)
        exv = ex_a
        for i in range(n):
            av = fabs(v[i])
            ic = _wrap(i, self.nsc)
            scale = (self.c1[ic] + self.c2[ic] / (self.c3[ic] + av)) / self.mu0[ic] * (mu[_wrap(i, nmu)] / self.peak_curve[ic])
            pi = self.na[_wrap(i, self.nna)]
            for k in range(pi, p):
                f[i * p + k] = 0.0
            for k in range(pi):
                j = i * p + k
                lm = lam[j]
                a = fabs(lm)
                ex = exv[j]
                sn = scale * self.N[_wrap(i, self.nna), k]
                f[j] = _sign(lm) * sn * (self.b1[ic] * (1.0 - ex) - a / self.b3[ic])
                dmu = sn * (self.b1[ic] * self.b2[ic] * ex - 1.0 / self.b3[ic])
                fw[j] = dmu * fw[j]
                fv[j] = dmu * fv[j]
        return 0

    def wheels_step(self, double h, const double[::1] v0, const double[::1] mass, const double[::1] other,
                    const double[::1] tb, const double[::1] td, const double[::1] mu, double[::1] omega,
                    double[::1] force, double[::1] slip):
        """One backward-Euler step of wheels and car bodies (:meth:`Wheelsets.step`): per car (n)
        ``v0`` (m/s), ``mass`` (kg), ``other`` (N), ``mu``; per axle (n·p) brake and drive torques
        ``tb``, ``td`` (N·m); ``omega``, ``force``, ``slip`` updated in place. Returns the new speeds."""
        vout = np.empty(v0.shape[0])
        self._wheels(h, v0, other, mass, mu, tb, td, omega, force, slip, vout)
        return vout

    cdef void _wheels(self, double h, const double[::1] v0, const double[::1] oth, const double[::1] mass,
                      const double[::1] mu, const double[::1] Tb, const double[::1] Td, double[::1] omega,
                      double[::1] force, double[::1] slip, double[::1] vout) except *:
        """Backward Euler of wheels and bodies (Wheelsets.step, module docstring of brakes.py): J(ω − ω0)
        = h(T_d − T_b sgn ω − F R) per axle, m(v − v0) = h(Σ F + other) per car, Newton on the
        arrow-shaped Jacobian; a wheel whose ω would pass through zero under the brake locks."""
        cdef Py_ssize_t n = v0.shape[0], p = self.p, i, k, it, attempt, nmu = mu.shape[0], pi
        cdef double R, J, hR, mh = -h
        cdef double other, spin, ak, d, dv, vv, vi
        cdef bint any_over
        cdef double* buf = <double*>PyMem_Malloc(12 * n * p * sizeof(double))
        cdef unsigned char* flags = <unsigned char*>PyMem_Malloc(2 * n * p)
        if buf == NULL or flags == NULL:
            PyMem_Free(buf)
            PyMem_Free(flags)
            raise MemoryError()
        cdef Py_ssize_t q = n * p
        cdef double *w0 = buf, *w = buf + q, *sg = buf + 2 * q, *lam = buf + 3 * q, *f = buf + 4 * q
        cdef double *fw = buf + 5 * q, *fv = buf + 6 * q, *rw = buf + 7 * q, *a = buf + 8 * q
        cdef double *b = buf + 9 * q, *cc = buf + 10 * q, *tmp = buf + 11 * q
        cdef unsigned char *locked = flags, *over = flags + q
        if self._q != q or self._v_a is None or self._v_a.shape[0] != n:  # work arrays, kept between calls
            self._arg_a, self._ex_a, self._v_a, self._q = np.empty(q), np.empty(q), np.empty(n), q
        arg_a, ex_a = self._arg_a, self._ex_a
        cdef double[::1] v = self._v_a
        v[:] = v0
        cdef double[::1] arg = arg_a
        try:
            for i in range(q):
                w0[i] = omega[i]
            self._creep(n, w0, &v0[0], mu, lam, f, fw, fv, arg, arg_a, ex_a)
            for i in range(n):
                R = self.R[_wrap(i, self.nR)]
                pi = self.na[_wrap(i, self.nna)]
                for k in range(p):
                    if k >= pi:  # an inactive axle: held at rest
                        locked[i * p + k] = 1
                        sg[i * p + k] = 0.0
                        w[i * p + k] = 0.0
                        continue
                    spin = Td[i * p + k] - f[i * p + k] * R
                    if w0[i * p + k] == 0.0:
                        locked[i * p + k] = fabs(spin) <= Tb[i * p + k]
                        sg[i * p + k] = _sign(spin)
                    else:
                        locked[i * p + k] = 0
                        sg[i * p + k] = _sign(w0[i * p + k])
                    w[i * p + k] = 0.0 if locked[i * p + k] else w0[i * p + k]
            for attempt in range(2):
                for it in range(self.iters):
                    self._creep(n, w, &v[0], mu, lam, f, fw, fv, arg, arg_a, ex_a)
                    for i in range(n):
                        pi = self.na[_wrap(i, self.nna)]
                        if pi == 0:
                            continue  # a car without wheels: the caller's Coulomb step
                        R, J = self.R[_wrap(i, self.nR)], self.J[_wrap(i, self.nJ)]
                        hR = h * R
                        vi = v[i]
                        for k in range(pi):
                            if locked[i * p + k]:
                                a[i * p + k] = 1.0
                                rw[i * p + k] = 0.0
                                b[i * p + k] = 0.0
                                cc[i * p + k] = 0.0
                            else:
                                ak = J + hR * fw[i * p + k]
                                a[i * p + k] = ak if ak > 0.1 * J else J
                                rw[i * p + k] = J * (w[i * p + k] - w0[i * p + k]) - h * (
                                    Td[i * p + k] - Tb[i * p + k] * sg[i * p + k] - f[i * p + k] * R)
                                b[i * p + k] = hR * fv[i * p + k]
                                cc[i * p + k] = mh * fw[i * p + k]
                        other = oth[i]
                        vv = mass[i] * (vi - v0[i]) - h * (_npsum(f + i * p, pi) + other)
                        d = mass[i] - h * _npsum(fv + i * p, pi)
                        for k in range(pi):
                            tmp[i * p + k] = cc[i * p + k] * rw[i * p + k] / a[i * p + k]
                        dv = -vv + _npsum(tmp + i * p, pi)
                        for k in range(pi):
                            tmp[i * p + k] = cc[i * p + k] * b[i * p + k] / a[i * p + k]
                        dv = dv / (d - _npsum(tmp + i * p, pi))
                        for k in range(pi):
                            w[i * p + k] = w[i * p + k] + (-rw[i * p + k] - b[i * p + k] * dv) / a[i * p + k]
                        v[i] = vi + dv
                any_over = False
                for i in range(q):  # the brake stopped the wheel within the step: it locks
                    over[i] = not locked[i] and w[i] * sg[i] < 0.0
                    any_over = any_over or over[i]
                if not any_over:
                    break
                for i in range(q):
                    if over[i]:
                        locked[i] = 1
                    if locked[i]:
                        w[i] = 0.0
            self._creep(n, w, &v[0], mu, lam, f, fw, fv, arg, arg_a, ex_a)
            for i in range(n):
                for k in range(p):
                    omega[i * p + k] = w[i * p + k]
                    force[i * p + k] = f[i * p + k]
                    slip[i * p + k] = lam[i * p + k]
                vout[i] = v[i]
        finally:
            PyMem_Free(buf)
            PyMem_Free(flags)
