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
from libc.math cimport NAN, exp, fabs, isfinite
from libc.stdint cimport int64_t

from canbrake.physics._npmath cimport _max, _sign  # numpy's NaN rules, shared
from canbrake.physics._table cimport table_at  # the speed tables' interpolation, shared

import numpy as np

_np_exp = np.exp
_np_empty = np.empty
_ndarray = np.ndarray
_float64 = np.dtype(np.float64)


def step_coupled(const double[::1] w0, const double[::1] J, const double[::1] R, const double[::1] N,
                 const double[::1] T, double v0, double dt, double mass, bint body, double b1, double b2, double b3,
                 double c1, double c2, double c3, double peak, double mu0, double floor, int iters, davis=None,
                 resistance=None, table=None, bint physical=False, double peak_mu0=1.0, double peak_curve=1.0):
        """Newton on J (ω − ω0) = dt (T − F_a(ω, v) R) per axle and, if ``body``, m (v − v0) = dt (Σ F_a −
        F_d(v)) (arrow-shaped Jacobian, Schur complement on v), ``iters`` iterations. Per axle (p,):
        ``w0`` (rad/s), ``J`` (kg·m²), ``R`` (m), ``N`` (N), ``T`` (N·m). The slip curve (eq. 13:
        ``b1..b3``), its speed decay (eq. 15: ``c1..c3``, μ_max(0) = ``mu0``) times ``peak``; ``floor``
        the slip denominator's floor (m/s). F_d: ``davis`` = (a0, a1, a2) for sgn(v) a0 + a1 v + a2 v|v|
        (sgn 0 below 1e-6 m/s), or a ``resistance(v) -> (F_d, dF_d/dv)`` callable, or none;
        ``table`` = (speeds m/s increasing, forces N): the vehicles' resistance tables summed, added
        as sgn(v) T(|v|) (linear between the points, flat beyond the ends; slope T' in dF_d/dv).

        Returns (v_new, ω_new, λ, μ, F_a, finite): ω_new and the adhesion at the new state per axle
        (arrays (p,); :func:`adhesion` with ``physical``, ``peak_mu0``, ``peak_curve``), and whether
        every ω_new is finite."""
        cdef Py_ssize_t p = w0.shape[0], k
        res = _np_empty((8, p))  # ω_new, λ, μ, F_a; then the Newton step's scratch rows
        out, lam_a, mu_a, fa_a = res[:4]
        cdef double[::1] w = out
        w[:] = w0
        cdef double[:, ::1] rows = res
        cdef double* r_w = &rows[0, 0] + 4 * p
        cdef double* a = r_w + p
        cdef double* b = r_w + 2 * p
        cdef double* c = r_w + 3 * p
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
        cdef bint finite = True
        for k in range(p):
            if not isfinite(w[k]):
                finite = False
        _adhesion(w, R, N, v, b1, b2, b3, c1, c2, c3, physical, peak_mu0, peak_curve, floor, lam_a, mu_a, fa_a)
        return v, out, lam_a, mu_a, fa_a, finite


cdef void _adhesion(const double[::1] w, const double[::1] R, const double[::1] N, double v, double b1, double b2,
                    double b3, double c1, double c2, double c3, bint physical, double peak_mu0, double peak_curve,
                    double floor, lam_a, mu_a, fa_a) except *:
    """(λ, μ, F_a) per axle into ``lam_a``, ``mu_a``, ``fa_a`` (arrays (p,)): the operations of
    :meth:`canbrake.physics.wheel_adhesion.WheelSet.adhesion` (slip_ratio, adhesion_coefficient) in
    their order, numpy's NaN rules for sign and maximum and numpy's ``exp`` (one call over every
    axle: its SIMD exp is not libm's in the last bit)."""
    cdef double[::1] lam = lam_a, mu = mu_a, fa = fa_a
    cdef Py_ssize_t p = w.shape[0], k
    cdef double wr, al, scale
    for k in range(p):
        wr = w[k] * R[k]
        lam[k] = (wr - v) / _max(_max(fabs(wr), fabs(v)), floor)  # eq. 11, floored
        mu[k] = -b2 * fabs(lam[k])  # the exponent, then e^it (numpy's)
    _np_exp(mu_a, out=mu_a)
    scale = (c1 + c2 / (c3 + fabs(v))) / (c1 + c2 / (c3 + 0.0))  # eq. 14: μ_max(v) / μ_max(0)
    if physical:
        scale = scale * peak_mu0 / peak_curve
    for k in range(p):
        al = fabs(lam[k])
        mu[k] = scale * (_sign(lam[k]) * (b1 * (1.0 - mu[k]) - al / b3))  # eq. 13, odd in λ
        fa[k] = mu[k] * N[k]  # eq. 10


def adhesion(const double[::1] w, const double[::1] R, const double[::1] N, double v, double b1, double b2,
             double b3, double c1, double c2, double c3, bint physical, double peak_mu0, double peak_curve,
             double floor):
    """(λ, μ, F_a in N) per axle (arrays (p,)) at wheel speeds ``w`` (rad/s) and body speed ``v``
    (m/s): eqs. 10, 11 (denominator floored at ``floor`` m/s) and 13-15, times ``peak_mu0 /
    peak_curve`` if ``physical``; bit for bit :meth:`canbrake.physics.wheel_adhesion.WheelSet.adhesion`."""
    res = _np_empty((3, w.shape[0]))
    lam_a, mu_a, fa_a = res
    _adhesion(w, R, N, v, b1, b2, b3, c1, c2, c3, physical, peak_mu0, peak_curve, floor, lam_a, mu_a, fa_a)
    return lam_a, mu_a, fa_a


def measure(double[:, ::1] vrows, double[:, ::1] crows, double position, double v, double accel, double a_last,
            fa_step, const double[::1] lam, const double[::1] mu, const double[::1] fa, const double[::1] omega,
            const double[::1] torque, w_start, double dt, const double[::1] J, const double[::1] R,
            const int64_t[::1] vehicle, const int64_t[::1] number, const double[:, :] davis, table_part,
            const double[::1] mass_cumsum):
    """A rigid train's measurements of one state into ``vrows`` (7 + 5 M, n) and ``crows``
    (2, n − 1) (:meth:`canbrake.physics.train.TrainPlant._rigid_measure` gives the names):
    per vehicle x, v, v (over ground), ``accel``, −Σ F_a of its axles, F_d,i(v) (``davis`` (n, 3),
    plus sgn(v) ``table_part`` (n,) if not None), Σ J ω̇/R of its axles over the last step
    (``w_start``, the wheel speeds before it, ``dt`` s; None: before the first step, zero); per
    coupler 0 and the rigid coupling's force m_{1..j} a − Σ_{i≤j} (Σ F_a,i − F_d,i) with F_a and
    a of the last sub-step (``fa_step``, ``a_last``; None: the state's ``fa`` and 0); per axle
    quantity (ω, λ, μ, F_a, T) and axle number j its row over the vehicles, NaN where a vehicle
    has fewer than j driven axles. Per axle (P,): ``vehicle`` (0-based), ``number`` (1-based).
    The numpy code's operations in its order (bincount and cumsum add in index order)."""
    cdef Py_ssize_t n = vrows.shape[1], P = vehicle.shape[0], M = (vrows.shape[0] - 7) // 5, i, k, q, r
    cdef double sgn = (1.0 if v > 0 else (-1.0 if v < 0 else 0.0)) if fabs(v) > 1e-6 else 0.0
    cdef double a = 0.0 if fa_step is None else a_last, cum = 0.0
    cdef const double[::1] fs = fa if fa_step is None else fa_step
    cdef const double[::1] tp
    cdef const double[::1] ws
    cdef bint has_table = table_part is not None, moved = w_start is not None
    if has_table:
        tp = table_part
    if moved:
        ws = w_start
    for i in range(n):
        vrows[0, i] = position
        vrows[1, i] = v
        vrows[2, i] = v
        vrows[3, i] = accel
        vrows[4, i] = 0.0
        vrows[5, i] = sgn * davis[i, 0] + davis[i, 1] * v + davis[i, 2] * v * fabs(v)
        if has_table:
            vrows[5, i] = vrows[5, i] + sgn * tp[i]
        vrows[6, i] = 0.0
    for k in range(P):  # Σ over each vehicle's axles (bincount)
        vrows[4, vehicle[k]] = vrows[4, vehicle[k]] + fa[k]
        if moved:
            vrows[6, vehicle[k]] = vrows[6, vehicle[k]] + J[k] * (omega[k] - ws[k]) / dt / R[k]
    # the coupler forces: the cumulative net force per vehicle, F_a of the last sub-step
    cdef double[::1] net = _np_empty(n)
    for i in range(n):
        net[i] = 0.0
    for k in range(P):
        net[vehicle[k]] = net[vehicle[k]] + fs[k]
    for i in range(n):
        net[i] = net[i] - vrows[5, i]
        cum = net[i] if i == 0 else cum + net[i]
        if i < n - 1:
            crows[0, i] = 0.0
            crows[1, i] = mass_cumsum[i] * a - cum
    for i in range(n):
        vrows[4, i] = -vrows[4, i]
    for r in range(7, vrows.shape[0]):
        for i in range(n):
            vrows[r, i] = NAN
    for k in range(P):
        i = vehicle[k]
        r = 7 + number[k] - 1
        vrows[r, i] = omega[k]
        vrows[r + M, i] = lam[k]
        vrows[r + 2 * M, i] = mu[k]
        vrows[r + 3 * M, i] = fa[k]
        vrows[r + 4 * M, i] = torque[k]


def axle_torques(commands, const int64_t[::1] vehicle, const int64_t[::1] number):
    """Per driven axle (P,), the torque its vehicle's command ``axle<j>_torque_nm`` asks (N·m):
    ``commands[j - 1]`` is that command over the vehicles (n,) or None; None or NaN: 0."""
    cdef Py_ssize_t P = vehicle.shape[0], k, j, m = len(commands)
    out = _np_empty(P)
    cdef double[::1] t = out
    cdef const double[:] c
    cdef double x
    for k in range(P):
        t[k] = 0.0
    for j in range(m):
        cmd = commands[j]
        if cmd is None:
            continue
        c = cmd if type(cmd) is _ndarray and cmd.dtype is _float64 else np.asarray(cmd, dtype=float)
        for k in range(P):
            if number[k] == j + 1:
                x = c[vehicle[k]]
                t[k] = 0.0 if x != x else x
    return out
