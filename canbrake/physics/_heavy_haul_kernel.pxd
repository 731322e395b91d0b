# The heavy-haul kernels' draft gears and air brake as C types, so that the coupled plant's
# compiled period (_train_kernel.EquippedKernel) calls their C-level steps (cimport).

cdef double route_n(const double[::1] brk, const double[::1] val, double weight, double x) noexcept nogil


cdef class GearKernel:
    cdef readonly Py_ssize_t nc, npts
    cdef const double[:, ::1] cx, cf
    cdef const double[::1] ru, slack, ke, ks, damp, stroke, fmax

    cdef void run(self, const double* stretch, const double* rate, const double* fs0, const double* dp0,
                  double* fc, double* fs, double* dp) noexcept nogil


cdef class AirKernel:
    cdef readonly Py_ssize_t n
    cdef const double[::1] dist, k_full, n_blocks, coef, cyl_p
    cdef double beta_c, apply_wave, release_wave, p0, reduction, ratio

    cdef void run(self, int mode, double t, const double* v, double* fill, const double* target,
                  const double* fill_gain, double* pipe, const double* pipe_gain, double t_apply,
                  double t_release, double* force) noexcept nogil
    cdef double force(self, Py_ssize_t i, double fill, double v) noexcept nogil
