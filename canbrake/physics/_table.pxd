# A speed table (resistance, ...) read by the plant kernels (_train_kernel.pyx, _adhesion_kernel.pyx):
# one implementation of its interpolation for both.

cdef inline double table_at(const double* xs, const double* ys, Py_ssize_t m, double s,
                            double* slope) noexcept nogil:
    """The table (``xs`` increasing, ``m`` >= 1 points) at ``s``: linear between points, flat
    beyond the ends; NaN stays NaN. ``slope`` (if not NULL) gets d table / d s there (0 beyond
    the ends)."""
    cdef Py_ssize_t lo = 0, hi = m - 1, mid
    if s <= xs[0]:
        if slope != NULL:
            slope[0] = 0.0
        return ys[0]
    if s >= xs[m - 1]:
        if slope != NULL:
            slope[0] = 0.0
        return ys[m - 1]
    while hi - lo > 1:
        mid = (lo + hi) // 2
        if xs[mid] <= s:
            lo = mid
        else:
            hi = mid
    if slope != NULL:
        slope[0] = (ys[hi] - ys[lo]) / (xs[hi] - xs[lo])
    return ys[lo] + (ys[hi] - ys[lo]) * ((s - xs[lo]) / (xs[hi] - xs[lo]))
