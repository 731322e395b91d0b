# The brake equipment's kernel as a C type, so that the coupled plant's compiled period
# (_train_kernel.EquippedKernel) calls its sub-step (run_sub) without Python calls.

cdef class EquipmentKernel:
    cdef bint blending, adhesion_limited, has_env
    cdef double g
    cdef const double[::1] ed_max, ed_power, fade_start, fade_end, friction_lag, valve_lag, max_vent
    cdef const double[:, ::1] env
    cdef Py_ssize_t p, iters, nR, nJ, nsc, nna  # nna: cars (a stack's P·n cars share their rows: i % nna)
    cdef const double[::1] b1, b2, b3, c1, c2, c3, mu0, peak_curve, v_floor  # the slip curve: 1 or n values
    cdef const double[::1] R, J
    cdef const double[:, ::1] N
    cdef Py_ssize_t[::1] na
    cdef bint bare
    cdef object _arg_a, _ex_a, _v_a  # the wheels' work arrays (exponent arguments, exponentials, speeds)
    cdef Py_ssize_t _q

    cdef int run_sub(self, double h, const double[::1] blend_k, const double[::1] valve_k,
                     const double[::1] effort, const double[::1] v, const double[::1] f, const double[::1] r,
                     const double[::1] mass, const double[::1] mu, const double[::1] eff, bint has_wsp,
                     const double[::1] cmd, double[::1] friction, double[::1] ed, double[::1] valve,
                     double[::1] vent, double[::1] omega, double[::1] force, double[::1] slip,
                     double[::1] brake, double[::1] trac, double[::1] rail, double[::1] vnew,
                     double[::1] oth, double[::1] tb, double[::1] td) except -1
    cdef void _prep(self, const double[::1] v, const double[::1] f, const double[::1] r, const double[::1] brake,
                    const double[::1] trac, double[::1] oth, double[::1] tb, double[::1] td) noexcept
    cdef int _creep(self, Py_ssize_t n, const double* w, const double* v, const double[::1] mu, double* lam,
                    double* f, double* fw, double* fv, double[::1] arg, object arg_a, object ex_a) except -1
    cdef void _wheels(self, double h, const double[::1] v0, const double[::1] oth, const double[::1] mass,
                      const double[::1] mu, const double[::1] Tb, const double[::1] Td, double[::1] omega,
                      double[::1] force, double[::1] slip, double[::1] vout) except *
