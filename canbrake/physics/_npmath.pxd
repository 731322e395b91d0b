# numpy's elementwise sign/maximum/minimum for one double, with numpy's NaN rules, shared by the
# plant kernels (_train_kernel.pyx, _heavy_haul_kernel.pyx) so their results stay bit for bit those
# of the numpy code they replaced.

cdef inline double _sign(double a) noexcept nogil:
    """numpy.sign: -1, 0 (+0 for ±0) or 1; NaN stays NaN."""
    if a > 0.0:
        return 1.0
    if a < 0.0:
        return -1.0
    if a == 0.0:
        return 0.0
    return a


cdef inline double _max(double a, double b) noexcept nogil:
    """numpy.maximum: NaN propagates (a NaN ``a`` is returned by its own check, a NaN ``b`` because
    the comparison fails)."""
    if a >= b or a != a:
        return a
    return b


cdef inline double _min(double a, double b) noexcept nogil:
    """numpy.minimum: NaN propagates, as in :func:`_max`."""
    if a <= b or a != a:
        return a
    return b
