# cython: language_level=3
# distutils: extra_compile_args = -ffp-contract=off
"""Backward-Euler step of driven axles and train body (Cai et al. 2014), compiled: the Newton loop of
:meth:`canbrake.physics.wheel_adhesion.WheelSet.step_coupled`.

One call per sub-step: arrays in (per axle), the new body speed and wheel speeds out. Written by
hand because it runs every millisecond over a handful of axles, where numpy's per-call cost would be
~10x the arithmetic and the former plain-Python loop cost ~100 us per step. The operations are the
former Python float code's, in the same order (Python floats are C doubles; ``math.exp`` is libm's
``exp``; ``-ffp-contract=off``), so results are bit-identical to it.
"""
from libc.math cimport exp, fabs

from canbrake.physics._table cimport table_at  # the speed tables' interpolation, shared

import numpy as np


def step_coupled(const double[::1] w0, const double[::1] J, const double[::1] R, const double[::1] N,
                 const double[::1] T, double v0, double dt, double mass, bint body, double b1, double b2, double b3,
                 double c1, double c2, double c3, double peak, double mu0, double floor, int iters, davis=None,
                 resistance=None, table=None):
        """Newton on J (ω − ω0) = dt (T − F_a(ω, v) R) per axle and, if ``body``, m (v − v0) = dt (Σ F_a −
        F_d(v)) (arrow-shaped Jacobian, Schur complement on v), ``iters`` iterations. Per axle (p,):
        ``w0`` (rad/s), ``J`` (kg·m²), ``R`` (m), ``N`` (N), ``T`` (N·m). The slip curve (eq. 13:
        ``b1..b3``), its speed decay (eq. 15: ``c1..c3``, μ_max(0) = ``mu0``) times ``peak``; ``floor``
        the slip denominator's floor (m/s). F_d: ``davis`` = (a0, a1, a2) for sgn(v) a0 + a1 v + a2 v|v|
        (sgn 0 below 1e-6 m/s), or a ``resistance(v) -> (F_d, dF_d/dv)`` callable, or none;
        ``table`` = (speeds m/s increasing, forces N): the vehicles' resistance tables summed, added
        as sgn(v) T(|v|) (linear between the points, flat beyond the ends; slope T' in dF_d/dv).

        Returns (v_new, ω_new as an array (p,))."""
        cdef Py_ssize_t p = w0.shape[0], k
        out = np.array(w0, dtype=float)
        cdef double[::1] w = out
        r_w_a, a_a, b_a, c_a = np.empty(p), np.empty(p), np.empty(p), np.empty(p)
        cdef double[::1] r_w = r_w_a, a = a_a, b = b_a, c = c_a
        cdef double v = v0, av, scale, wr, awr, den, lam, dlam_dw, dlam_dv, alam, ex, sN, dmu, f, fw, fv, ak
        cdef double sum_fa, sum_fv, fd, dfd, r_v, d, dv, s1, s2, sgn
        cdef double a0 = 0.0, a1 = 0.0, a2 = 0.0
        cdef bint has_davis = davis is not None
        if has_davis:
            a0, a1, a2 = davis
        cdef bint has_table = table is not None
        cdef const double[::1] tv
        cdef const double[::1] tf
        cdef Py_ssize_t m = 0
        cdef double s, tval, tslope
        if has_table:
            tv = np.ascontiguousarray(table[0], dtype=float)
            tf = np.ascontiguousarray(table[1], dtype=float)
            m = tv.shape[0]
        for _ in range(iters):
            av = fabs(v)
            scale = (c1 + c2 / (c3 + av)) / mu0 * peak  # eq. 14 (× the variant's peak)
            sum_fa = 0.0
            sum_fv = 0.0
            for k in range(p):
                wr = w[k] * R[k]
                awr = fabs(wr)
                den = awr  # max(|ωR|, |v|, floor), the first of equals as Python's max
                if av > den:
                    den = av
                if floor > den:
                    den = floor
                lam = (wr - v) / den
                if awr >= av and awr >= floor:       # denominator ωR
                    dlam_dw, dlam_dv = R[k] * av / (wr * wr), -1.0 / den
                elif av >= floor:                      # denominator v
                    dlam_dw, dlam_dv = R[k] / den, -wr / (den * den)
                else:                                  # floored denominator
                    dlam_dw, dlam_dv = R[k] / den, -1.0 / den
                alam = fabs(lam)
                ex = exp(-b2 * alam)
                sN = scale * N[k]
                dmu = sN * (b1 * b2 * ex - 1.0 / b3)   # dμ/dλ (eq. 13) × N
                f = sN * (b1 * (1.0 - ex) - alam / b3)
                f = f if lam > 0 else (-f if lam < 0 else 0.0)
                fw, fv = dmu * dlam_dw, dmu * dlam_dv
                r_w[k] = J[k] * (w[k] - w0[k]) - dt * (T[k] - f * R[k])
                ak = J[k] + dt * R[k] * fw
                a[k] = ak if ak > 0.1 * J[k] else J[k]  # past the adhesion peak the slope is negative: damped step
                b[k] = dt * R[k] * fv
                c[k] = -dt * fw
                sum_fa = sum_fa + f
                sum_fv = sum_fv + fv
            if not body:
                for k in range(p):
                    w[k] = w[k] - r_w[k] / a[k]
                continue
            if has_davis:
                sgn = (1.0 if v > 0 else (-1.0 if v < 0 else 0.0)) if fabs(v) > 1e-6 else 0.0
                fd, dfd = sgn * a0 + a1 * v + a2 * v * fabs(v), a1 + 2.0 * a2 * fabs(v)
            elif resistance is not None:
                fd, dfd = resistance(v)
            else:
                fd, dfd = 0.0, 0.0
            if has_table:
                s = fabs(v)
                sgn = (1.0 if v > 0 else (-1.0 if v < 0 else 0.0)) if s > 1e-6 else 0.0
                tval = table_at(&tv[0], &tf[0], m, s, &tslope)
                fd, dfd = fd + sgn * tval, dfd + tslope
            r_v = mass * (v - v0) - dt * (sum_fa - fd)
            d = mass - dt * (sum_fv - dfd)
            s1 = 0.0
            s2 = 0.0
            for k in range(p):
                s1 = s1 + c[k] * r_w[k] / a[k]
            for k in range(p):
                s2 = s2 + c[k] * b[k] / a[k]
            dv = (-r_v + s1) / (d - s2)
            for k in range(p):
                w[k] = w[k] + (-r_w[k] - b[k] * dv) / a[k]
            v = v + dv
        return v, out
