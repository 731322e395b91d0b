# cython: language_level=3
# distutils: extra_compile_args = -ffp-contract=off
"""The heavy-haul train's integration step (:mod:`canbrake.physics.heavy_haul`), compiled.

Pieces, each one call with arrays in and arrays out: the draft gears' hysteresis
(:class:`GearKernel`, eqs. 7-9, behind ``CouplerBank.step``), the air brake's cylinder fill and
block force (:class:`AirKernel`, eqs. 10-12, brake-pipe signal and pipe pressure, or ECP, behind
``AirBrake.step``), the non-control forces (:meth:`HeavyHaulKernel.passive`, eqs. 3-5) and the
semi-implicit Euler sub-step of the whole train that chains them (:meth:`HeavyHaulKernel.substep`). Written by hand
because numpy's per-call cost dominated the 1 + 105 train's step (about 60 array operations per
sub-step on 106 values). Policy (commands, traction envelopes, divergence messages) stays in Python.

Every value is computed with the floating-point operations of the numpy code it replaced, in the
same order (``-ffp-contract=off``); transcendental functions (exp, sin, cos, cbrt) are evaluated by
numpy in the caller and passed in, so the results are bit for bit those of the former numpy step.
All arrays are C-contiguous float64: per vehicle (n,), per coupler (n-1,).
"""
from libc.math cimport INFINITY, fabs, isfinite

from canbrake.physics._npmath cimport _max, _min, _sign  # numpy's NaN rules, shared

import numpy as np


cdef double KMH = 1.0 / 3.6  # m/s per km/h, as canbrake.physics.heavy_haul.KMH


cdef double route_n(const double[::1] brk, const double[::1] val, double weight, double x) noexcept nogil:
    """Eqs. (4)-(5): grade + curve force (N) on a vehicle of ``weight`` (kN) at position x (m), from the
    route table (breakpoints ``brk``, m; grade + curve ``val``, N/kN: Route._brk, Route._val)."""
    cdef Py_ssize_t lo = 0, hi = brk.shape[0], mid
    while lo < hi:  # numpy.searchsorted(brk, x, side="right")
        mid = (lo + hi) >> 1
        if not (x < brk[mid]):
            lo = mid + 1
        else:
            hi = mid
    if lo == 0:
        return 0.0 * weight
    return val[lo - 1] * weight


def route_force_n(const double[::1] brk, const double[::1] val, const double[::1] weight_kn, const double[::1] x):
    """The route's grade + curve force (N) per vehicle of weight ``weight_kn`` (kN) at positions
    ``x`` (m), each (n,): :meth:`canbrake.physics.route.Route.force_n` from its table, compiled."""
    cdef Py_ssize_t i, n = x.shape[0]
    out = np.empty(n)
    cdef double[::1] o = out
    for i in range(n):
        o[i] = route_n(brk, val, weight_kn[i], x[i])
    return out


cdef class GearKernel:
    """Draft gears of every coupler (n-1 of them): loading curves ``cx`` (m), ``cf`` (N), shape
    (n-1, npts); unloading ratio ``ru``, ``slack`` (m), eq. (8) stiffness ``ke`` and solid
    stiffness ``ks`` (N/m), viscous ``damping`` (N·s/m), each (n-1,). (Attributes: the .pxd.)"""

    def __init__(self, cx, cf, ru, slack, ke, ks, damping):
        f = lambda a: np.ascontiguousarray(a, dtype=float)  # noqa: E731
        self.cx, self.cf = f(np.atleast_2d(cx)), f(np.atleast_2d(cf))
        self.nc, self.npts = self.cx.shape[0], self.cx.shape[1]
        self.ru, self.slack, self.ke, self.ks, self.damp = f(ru), f(slack), f(ke), f(ks), f(damping)
        self.stroke, self.fmax = f(np.asarray(self.cx)[:, -1]), f(np.asarray(self.cf)[:, -1])

    cdef void run(self, const double* stretch, const double* rate, const double* fs0, const double* dp0,
                  double* fc, double* fs, double* dp) noexcept nogil:
        """Eqs. (7)-(9): new forces (N, + tension), force state and gear deflections of every coupler."""
        cdef Py_ssize_t j, k, q
        cdef double s, d, ad, trial, fl, fu, lo, hi, f
        for j in range(self.nc):
            s = stretch[j]
            d = _sign(s) * _max(fabs(s) - self.slack[j], 0.0)
            trial = fs0[j] + self.ke[j] * (d - dp0[j])
            ad = fabs(d)
            k = 0
            for q in range(1, self.npts - 1):
                if ad > self.cx[j, q]:
                    k += 1
            if ad > self.stroke[j]:
                fl = self.fmax[j] + self.ks[j] * (ad - self.stroke[j])
            else:
                fl = self.cf[j, k] + (self.cf[j, k + 1] - self.cf[j, k]) * (ad - self.cx[j, k]) / (
                    self.cx[j, k + 1] - self.cx[j, k])
            fu = self.ru[j] * _min(fl, self.fmax[j]) + (fl - self.fmax[j] if ad > self.stroke[j] else 0.0)
            if d >= 0:
                lo, hi = fu, fl
            else:
                lo, hi = -fl, -fu
            f = _min(_max(trial, lo), hi)
            if d == 0.0:
                f = 0.0
            fs[j] = f
            dp[j] = d
            fc[j] = f + (self.damp[j] * rate[j] if d != 0.0 else 0.0)

    def step(self, const double[::1] stretch, const double[::1] rate, const double[::1] force_state,
             const double[::1] defl_prev):
        """(coupler forces N, new force state N, new gear deflections m), each (n-1,), from the
        stretches (m) and their rates (m/s)."""
        fc, fs, dp = np.empty(self.nc), np.empty(self.nc), np.empty(self.nc)
        cdef double[::1] a = fc, b = fs, c = dp
        if self.nc:
            self.run(&stretch[0], &rate[0], &force_state[0], &defl_prev[0], &a[0], &b[0], &c[0])
        return fc, fs, dp


cdef class AirKernel:
    """Air brake of every vehicle (n,): ``dist_m`` behind the locomotive, ``k_full_kn`` (K per block
    at full pressure), ``n_blocks``, ``friction_coef``, ``cylinder_pressure_pa``; scalars ``beta_c``,
    the apply / release wave speeds (m/s) and the brake pipe's ``p0`` (Pa), ``reduction`` (Pa) and
    ``ratio``. (Attributes: the .pxd.)"""

    def __init__(self, dist_m, k_full_kn, n_blocks, friction_coef, cylinder_pressure_pa, *, double beta_c,
                 double apply_wave, double release_wave, double p0=0.0, double reduction=0.0, double ratio=0.0):
        f = lambda a: np.ascontiguousarray(a, dtype=float)  # noqa: E731
        self.dist, self.k_full, self.n_blocks = f(dist_m), f(k_full_kn), f(n_blocks)
        self.coef, self.cyl_p = f(friction_coef), f(cylinder_pressure_pa)
        self.n = self.dist.shape[0]
        self.beta_c, self.apply_wave, self.release_wave = beta_c, apply_wave, release_wave
        self.p0, self.reduction, self.ratio = p0, reduction, ratio

    cdef void run(self, int mode, double t, const double* v, double* fill, const double* target,
                  const double* fill_gain, double* pipe, const double* pipe_gain, double t_apply,
                  double t_release, double* force) noexcept nogil:
        """Cylinder fills over one step ending at ``t`` and the block forces (N) at speeds v.
        ``mode``: 0 ECP (each vehicle follows ``target``), 1 pneumatic signal, 2 pneumatic with the
        brake-pipe pressure, 3 no fill change (forces only); the lags' gains (1 − e^(−dt/τ)) come
        from the caller."""
        cdef Py_ssize_t i
        cdef bint got_a, got_r, sig
        cdef double tg, cyl
        for i in range(self.n):
            if mode == 3:
                pass
            elif mode == 0:
                fill[i] = fill[i] + (target[i] - fill[i]) * fill_gain[i]
            else:
                got_a = t >= t_apply + self.dist[i] / self.apply_wave
                got_r = t >= t_release + self.dist[i] / self.release_wave
                sig = got_a if t_apply >= t_release else (got_a and not got_r)
                if mode == 2:
                    pipe[i] = pipe[i] + (self.p0 - self.reduction * (1.0 if sig else 0.0) - pipe[i]) * pipe_gain[i]
                    cyl = _min(_max(self.ratio * (self.p0 - pipe[i]), 0.0), self.cyl_p[i])
                    tg = cyl / self.cyl_p[i]
                else:
                    tg = 1.0 if sig else 0.0
                fill[i] = fill[i] + (tg - fill[i]) * fill_gain[i]
            force[i] = self.force(i, fill[i], v[i])

    cdef double force(self, Py_ssize_t i, double fill, double v) noexcept nogil:
        """Eq. (10) with eqs. (11)-(12)'s φ at K = the block force at this fill (N)."""
        cdef double k = self.k_full[i] * fill
        cdef double vk = fabs(v / KMH)
        cdef double phi = self.coef[i] * (k + 200.0) / (4.0 * k + 200.0) * (2.0 * vk + 150.0) / (3.0 * vk + 150.0)
        return 1000.0 * self.beta_c * self.n_blocks[i] * phi * k

    def step(self, int mode, double t, const double[::1] v, double[::1] fill, const double[::1] target,
             const double[::1] fill_gain, double[::1] pipe, const double[::1] pipe_gain, double t_apply,
             double t_release):
        """Advance ``fill`` (and, in mode 2, ``pipe``) in place; returns the air-brake force per
        vehicle (N), (n,). See :meth:`run` for ``mode``."""
        out = np.empty(self.n)
        cdef double[::1] o = out
        self.run(mode, t, &v[0], &fill[0], &target[0], &fill_gain[0], &pipe[0], &pipe_gain[0], t_apply, t_release,
                 &o[0])
        return out


cdef class HeavyHaulKernel:
    """The whole consist: per vehicle (n,) ``mass_kg``, ``weight_kn`` (m g / 1000), ``davis_a``,
    ``davis_b``, ``davis_c`` (N/kN, per km/h, per (km/h)²); per coupler ``spacing_m`` (n-1,); the
    route table ``brk`` (breakpoints, m) and ``val`` (grade + curve, N/kN); its gears and air brake."""

    cdef readonly Py_ssize_t n, nc
    cdef const double[::1] mass, weight, da, db, dc, spacing, brk, val
    cdef GearKernel gears
    cdef AirKernel air
    cdef double[::1] fi, stretch, rate

    def __init__(self, mass_kg, weight_kn, davis_a, davis_b, davis_c, spacing_m, brk, val, GearKernel gears,
                 AirKernel air):
        f = lambda a: np.ascontiguousarray(a, dtype=float)  # noqa: E731
        self.mass, self.weight, self.da, self.db, self.dc = f(mass_kg), f(weight_kn), f(davis_a), f(davis_b), f(davis_c)
        self.n = self.mass.shape[0]
        self.nc = max(self.n - 1, 0)
        self.spacing, self.brk, self.val = f(spacing_m), f(brk), f(val)
        self.gears, self.air = gears, air
        self.fi = np.empty(self.n)
        self.stretch, self.rate = np.empty(max(self.nc, 1)), np.empty(max(self.nc, 1))

    cdef inline double resistance(self, Py_ssize_t i, double v) noexcept nogil:
        """Eq. (3): basic running resistance magnitude (N) of vehicle i at speed v (m/s)."""
        cdef double vk = fabs(v) / KMH
        return (self.da[i] + self.db[i] * vk + self.dc[i] * vk * vk) * self.weight[i]

    cdef inline double route(self, Py_ssize_t i, double x) noexcept nogil:
        """Eqs. (4)-(5): grade + curve force (N) on vehicle i at position x (m), from the route table."""
        return route_n(self.brk, self.val, self.weight[i], x)

    cdef void _passive(self, const double* x, const double* v, const double* fc, const double* fa,
                       double* fi) noexcept nogil:
        cdef Py_ssize_t i
        cdef double sgn, front, rear
        for i in range(self.n):
            sgn = _sign(v[i])
            front = fc[i - 1] if i > 0 else 0.0
            rear = fc[i] if i < self.nc else 0.0
            fi[i] = front - rear - self.resistance(i, v[i]) * sgn - self.route(i, x[i]) - fa[i] * sgn

    def passive(self, const double[::1] x, const double[::1] v, const double[::1] fc, const double[::1] air_n):
        """F_i = F_C,i−1 − F_C,i − F_W,i − F_f,i − F_a,i (N), (n,): the nominal non-control forces
        from the state, the coupler forces ``fc`` and the air-brake force ``air_n``."""
        out = np.empty(self.n)
        cdef double[::1] o = out
        cdef double zero = 0.0
        self._passive(&x[0], &v[0], &fc[0] if self.nc else &zero, &air_n[0], &o[0])
        return out

    def substep(self, const double[::1] x0, const double[::1] v0, const double[::1] fc0, const double[::1] air0,
                const double[::1] u, double unc, double dt, const double[::1] dist_n, bint has_dist,
                const double[::1] force_state, const double[::1] defl_prev, int ab_mode, double t_new,
                double[::1] fill, const double[::1] target, const double[::1] fill_gain, double[::1] pipe,
                const double[::1] pipe_gain, double t_apply, double t_release):
        """One semi-implicit Euler sub-step of ``dt`` s (speeds, then positions, then couplers, then
        the air brake at ``t_new``), from positions ``x0``, speeds ``v0``, coupler forces ``fc0``
        and air-brake force ``air0``, with traction ``u`` (N), model uncertainty δ = ``unc``, the
        disturbance ``dist_n`` (N, used if ``has_dist``). ``ab_mode`` (:meth:`AirKernel.run`; −1:
        the brake is untouched, never applied); ``fill`` and ``pipe`` are updated in place.

        Returns (x, v, acc, fc, force_state, defl_prev, air_n, finite)."""
        cdef Py_ssize_t n = self.n, nc = self.nc, i
        x_out, v_out, a_out, air_out = np.empty(n), np.empty(n), np.empty(n), np.empty(n)
        fc_out, fs_out, dp_out = np.empty(nc), np.empty(nc), np.empty(nc)
        cdef double[::1] x = x_out, v = v_out, a = a_out, air = air_out
        cdef double[::1] fc = fc_out, fs = fs_out, dp = dp_out
        cdef double[::1] fi = self.fi, st = self.stretch, rt = self.rate
        cdef double zero = 0.0, total, hold, acc, vn
        cdef bint finite = True, any_rest = False
        self._passive(&x0[0], &v0[0], &fc0[0] if nc else &zero, &air0[0], &fi[0])
        for i in range(n):
            if v0[i] == 0.0:
                any_rest = True
        for i in range(n):
            total = fi[i] * (1.0 + unc)
            total = total + u[i]
            if has_dist:
                total = total + dist_n[i]
            # standstill: resistance and brake hold a vehicle at rest (Karnopp), never reverse it
            if any_rest and v0[i] == 0.0:
                hold = (self.resistance(i, v0[i]) + air0[i]) * (1.0 + unc)
                total = _sign(total) * _max(fabs(total) - hold, 0.0)
            acc = total / self.mass[i]
            vn = v0[i] + acc * dt
            if v0[i] * vn < 0.0:
                vn = 0.0
                acc = -v0[i] / dt
            a[i] = acc
            v[i] = vn
            x[i] = x0[i] + vn * dt
        if nc:
            for i in range(nc):
                st[i] = x[i] - x[i + 1] - self.spacing[i]
                rt[i] = v[i] - v[i + 1]
            self.gears.run(&st[0], &rt[0], &force_state[0], &defl_prev[0], &fc[0], &fs[0], &dp[0])
        if ab_mode >= 0:
            self.air.run(ab_mode, t_new, &v[0], &fill[0], &target[0], &fill_gain[0], &pipe[0], &pipe_gain[0],
                         t_apply, t_release, &air[0])
        else:
            air[:] = air0
        for i in range(n):
            if not (isfinite(v[i]) and isfinite(x[i])):
                finite = False
        return x_out, v_out, a_out, fc_out, fs_out, dp_out, air_out, finite
