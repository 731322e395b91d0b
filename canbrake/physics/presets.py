"""Published parameter sets, in SI (the scenario files carry the same numbers at the edge units).

``CHEN2023_TABLE2``: Chen, Zhang, Zhou, Du (2023), *Actuators* 12, 111, Table 2 and section 4.
"""
from __future__ import annotations

from typing import Any

import numpy as np

KMH = 1.0 / 3.6  # m/s per km/h

CHEN2023_TABLE2: dict[str, Any] = {
    "n_cars": 6,
    "coupler_stiffness_n_per_m": 80_000.0,
    "coupler_nonlinearity_per_m2": -0.5,
    "mass_kg": np.array([18000.0, 21000.0, 19500.0, 20000.0, 19700.0, 22000.0]),
    "speed_mps": np.array([88.0, 93.0, 87.0, 89.0, 92.0, 95.5]) * KMH,
    "position_m": np.array([10.0, 20.0, 30.0, 40.0, 50.0, 60.0]),
    "alpha1": 120.0,
    "alpha2": 100.0,
    "k": 36.0,
    "k_d": 50.0,
    "delta": 2.0,
    "theta_lower_m": -0.01,
    "theta_upper_m": 0.01,
    "ref_speed_mps": 90.0 * KMH,
    "ref_decel_mps2": 3.5 * KMH,  # 3.5 km/h/s
    "dt_s": 1e-3,
}
