# cython: language_level=3
# distutils: extra_compile_args = -ffp-contract=off
"""Li 2024's draft gears and air brake (:mod:`canbrake.physics.heavy_haul`), compiled; the coupled
plant (:class:`canbrake.physics.train.TrainPlant`) steps them once per sub-step.

Pieces, each one call with arrays in and arrays out: the draft gears' hysteresis
(:class:`GearKernel`, eqs. 7-9, behind ``CouplerBank.step``), the air brake's cylinder fill and
block force (:class:`AirKernel`, eqs. 10-12, brake-pipe signal and pipe pressure, or ECP, behind
``AirBrake.step``) and the route's grade and curve force (:func:`route_force_n`, eqs. 4-5, behind
``Route.force_n``). Written by hand because numpy's per-call cost dominated the 1 + 105 train's
step. Policy (commands, envelopes, divergence messages) stays in Python.

Every value is computed with the floating-point operations of the numpy code it replaced, in the
same order (``-ffp-contract=off``). All arrays are C-contiguous float64: per vehicle (n,), per
coupler (n-1,).
"""
from libc.math cimport fabs

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
