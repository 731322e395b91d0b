"""Running resistance of a carriage (Davis equation) and the published values we use.

Chen 2023 (eq. 4) writes the running resistance as ``f_r = c0 + c1 v + c2 v^2`` but gives no numbers
for its train. We take the original Davis (1926) formula, the standard published Davis form for
multiple-unit passenger stock (as reproduced in the AREA Manual for Railway Engineering and in
Rochard & Schmid 2000, *A review of methods to measure and calculate train resistances*, Proc.
IMechE F 214):

    R [lb / short ton] = 1.3 + 29 / w + b V + C A V^2 / (w n)

with ``w`` the load per axle (short tons), ``n`` the number of axles, ``V`` in mph, ``A`` the frontal
area in ft^2, ``b = 0.03`` (passenger and multiple-unit cars), ``C = 0.00034`` (passenger / MU trailing
cars) or ``C = 0.0024`` (MU leading car). :func:`davis_1926` converts it to SI per carriage. For a
20 t, four-axle metro car with 11 m^2 frontal area it gives c0 ≈ 643 N, c1 ≈ 6.6 N·s/m,
c2 ≈ 0.90 N·s²/m², i.e. ≈ 1.4 kN (0.07 m/s²) at 90 km/h — the usual order for metro stock.

Resistance *opposes motion* and is dissipative: the plant applies it as ``-sign(v) * R(|v|)``, and at
standstill ``c0`` acts as static friction (it never pushes a car at rest).
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

LB_PER_SHORT_TON_TO_N_PER_KG = 4.4482216 / 907.18474  # 1 lbf per short ton, in N/kg
MPH_PER_MPS = 2.2369363
FT2_PER_M2 = 10.763910
LBF_TO_N = 4.4482216


@dataclass(frozen=True)
class DavisResistance:
    """Per-carriage Davis coefficients, arrays of shape ``(n_cars,)``.

    ``c0_n`` (N), ``c1_n_per_mps`` (N·s/m), ``c2_n_per_mps2`` (N·s²/m²): R(v) = c0 + c1|v| + c2 v².
    """

    c0_n: np.ndarray
    c1_n_per_mps: np.ndarray
    c2_n_per_mps2: np.ndarray

    @classmethod
    def zero(cls, n_cars: int) -> "DavisResistance":
        """No running resistance (for analytic tests)."""
        z = np.zeros(n_cars)
        return cls(z, z.copy(), z.copy())

    @classmethod
    def uniform(cls, n_cars: int, c0_n: float, c1_n_per_mps: float, c2_n_per_mps2: float) -> "DavisResistance":
        """The same coefficients for every car."""
        return cls(np.full(n_cars, float(c0_n)), np.full(n_cars, float(c1_n_per_mps)), np.full(n_cars, float(c2_n_per_mps2)))

    def magnitude_n(self, speed_mps: np.ndarray) -> np.ndarray:
        """|R(v)| in N for speeds ``speed_mps`` (shape ``(n_cars,)``)."""
        s = np.abs(speed_mps)
        return self.c0_n + self.c1_n_per_mps * s + self.c2_n_per_mps2 * s * s


def davis_1926(
    mass_kg: np.ndarray | list[float] | float,
    *,
    axles: int = 4,
    frontal_area_m2: float = 11.0,
    leading_car: int | None = None,
) -> DavisResistance:
    """Davis (1926) coefficients for multiple-unit passenger cars, converted to SI per carriage.

    ``mass_kg``: car masses (kg). ``axles``: axles per car. ``frontal_area_m2``: cross-section (m²).
    ``leading_car``: 0-based index of the car that leads (gets the lead-car aerodynamic coefficient
    C = 0.0024 instead of 0.00034); ``None``: all cars trailing.
    """
    m = np.atleast_1d(np.asarray(mass_kg, dtype=float))
    w_tons_per_axle = m / 907.18474 / axles
    c0 = (1.3 + 29.0 / w_tons_per_axle) * LB_PER_SHORT_TON_TO_N_PER_KG * m
    c1 = 0.03 * MPH_PER_MPS * LB_PER_SHORT_TON_TO_N_PER_KG * m
    c_aero = np.full(m.shape, 0.00034)
    if leading_car is not None:
        c_aero[leading_car] = 0.0024
    # C A V^2 / (w n) lb/ton times (w n) tons = C A V^2 lbf, V in mph
    c2 = c_aero * frontal_area_m2 * FT2_PER_M2 * MPH_PER_MPS**2 * LBF_TO_N
    return DavisResistance(c0, c1, c2)
