# cython: language_level=3
# distutils: extra_compile_args = -O2 -ffp-contract=off
"""The sliding-mode observer's scalar step, compiled: :meth:`SlidingModeObserver.update` and
:meth:`~canbrake.control.observer.SlidingModeObserver.predict` are :func:`update` and
:func:`predict` (its batch form, ``update_many``/``predict_many``, stays numpy).

Written by hand because every chen2023 ECU runs both once per period, and in Python their
attribute and call overhead was most of their cost. The state stays in the observer's attributes
(read and written here, so a copy, a reset or a wrapper sees it as before); the operations are
those of the Python it replaced, in the same order, in C doubles without contraction
(``-ffp-contract=off``): tests/test_control.py checks them against the batch form bit for bit.
"""
from cpython.dict cimport PyDict_SetItem
from libc.math cimport isnan

from canbrake.control._attrs cimport attr


cdef inline double _sat(double z) noexcept:
    return 1.0 if z > 1.0 else (-1.0 if z < -1.0 else z)


def update(self, double position_m, double speed_mps):
    """Correct with this tick's measurement (position in m, speed in m/s); return the filtered
    estimate φ̂ (m/s²)."""
    cdef dict d = self.__dict__
    cdef double v_hat = <double>attr(d, self, "v_hat"), x_hat, e2, emax, raw, phi, phi_hat, lim
    if isnan(v_hat):
        PyDict_SetItem(d, "x_hat", position_m)
        PyDict_SetItem(d, "v_hat", speed_mps)
        v_hat = speed_mps
    e2 = speed_mps - v_hat
    emax = <double>attr(d, self, "error_limit_mps")
    if e2 > emax or e2 < -emax:  # state anti-windup
        e2 = emax if e2 > 0 else -emax
        PyDict_SetItem(d, "v_hat", speed_mps - e2)
    raw = <double>attr(d, self, "gamma2_mps2") * _sat(e2 / <double>attr(d, self, "boundary_vel_mps"))
    PyDict_SetItem(d, "phi_raw_mps2", raw)
    phi_hat = <double>attr(d, self, "phi_hat_mps2")
    phi = phi_hat + <double>attr(d, self, "_alpha") * (raw - phi_hat)
    lim = <double>attr(d, self, "limit_mps2")
    phi_hat = lim if phi > lim else (-lim if phi < -lim else phi)
    PyDict_SetItem(d, "phi_hat_mps2", phi_hat)
    x_hat = <double>attr(d, self, "x_hat")
    PyDict_SetItem(d, "_e1", position_m - x_hat)
    return phi_hat


def predict(self, double brake_force_n):
    """Propagate to the next tick with the force held over the period (N, + = brake)."""
    cdef dict d = self.__dict__
    cdef double dt = <double>attr(d, self, "dt_s")
    cdef double s1 = _sat(<double>attr(d, self, "_e1") / <double>attr(d, self, "boundary_pos_m"))
    cdef double v_hat = <double>attr(d, self, "v_hat")
    cdef double g1 = attr(d, self, "gamma1_mps"), mass = attr(d, self, "mass_kg"), raw = attr(d, self, "phi_raw_mps2")
    PyDict_SetItem(d, "x_hat", <double>attr(d, self, "x_hat") + dt * (v_hat + g1 * s1))
    PyDict_SetItem(d, "v_hat", v_hat + dt * (-brake_force_n / mass + raw))
