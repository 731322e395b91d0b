"""Small array helpers shared by the physics and the scenario layers."""
from __future__ import annotations

from typing import Sequence

import numpy as np

ArrayLike = float | Sequence[float] | np.ndarray


def per_car(value: ArrayLike, n: int, name: str) -> np.ndarray:
    """``value`` as a float array of shape ``(n,)``: a scalar is broadcast, a sequence must have
    exactly ``n`` entries (ValueError naming ``name`` otherwise). Always a fresh copy."""
    arr = np.asarray(value, dtype=float)
    if arr.ndim == 0:
        return np.full(n, float(arr))
    if arr.shape != (n,):
        raise ValueError(f"{name}: expected one value or {n} values (one per car/coupler), got {arr.size}")
    return arr.copy()
