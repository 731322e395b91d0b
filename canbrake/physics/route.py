"""The line under a train: grade and curvature by position (Li, Zeng & Yu 2024, eqs. 4-5), and the
line-data rule of a long downgrade ahead (section 1.2). Shared by the heavy-haul model
(:mod:`canbrake.physics.heavy_haul`) and the coupled plant (:mod:`canbrake.physics.train`).

Per unit weight: grade i ‰ gives i N/kN (+ uphill: opposes forward motion), a curve of radius R
gives 600/R N/kN; a vehicle of weight W kN feels (i + 600/R)·W N. Positions are metres along the
route, the direction of travel +x.
"""
from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np


@dataclass(frozen=True)
class Route:
    """Piecewise-constant grade and curvature along the line.

    ``grade_start_m`` (ascending, first 0) and ``grade_permille`` (+ uphill) define grade segments;
    ``curve_start_m``/``curve_end_m``/``curve_radius_m`` the curves. Beyond the last segment the
    grade stays; before 0 the line is level and straight (the paper's assumption 3).
    """

    grade_start_m: np.ndarray
    grade_permille: np.ndarray
    curve_start_m: np.ndarray = field(default_factory=lambda: np.zeros(0))
    curve_end_m: np.ndarray = field(default_factory=lambda: np.zeros(0))
    curve_radius_m: np.ndarray = field(default_factory=lambda: np.zeros(0))
    length_m: float = np.inf

    def __post_init__(self):
        brk = np.unique(np.concatenate([[0.0], self.grade_start_m, self.curve_start_m, self.curve_end_m]))
        mid = np.append(0.5 * (brk[1:] + brk[:-1]), brk[-1] + 1.0)
        object.__setattr__(self, "_brk", brk)
        object.__setattr__(self, "_val", self.grade_at(mid) + self.curve_permille_at(mid))
        #: per (min grade, min length) rule of long_downgrade_ahead: its long downgrades' (start, end) (m)
        object.__setattr__(self, "_steep", {})

    @classmethod
    def from_table(cls, position_m, grade_permille, curve_radius_m) -> "Route":
        """A route from a table of breakpoints (ascending ``position_m``, first 0): row r holds the grade
        (‰, + uphill) and curve radius (m, 0 = straight) from its position to the next row's; the last row
        marks the end of the route (its grade continues beyond it). Consecutive rows with equal grade
        (equal radius) form one grade segment (one curve), so splitting a segment changes nothing."""
        x = np.asarray(position_m, dtype=float)
        g = np.asarray(grade_permille, dtype=float)
        r = np.asarray(curve_radius_m, dtype=float)
        if x.size < 2 or x[0] != 0.0 or np.any(np.diff(x) <= 0):
            raise ValueError("route table: position_m must start at 0 and increase, with at least two rows")
        if np.any(r < 0):
            raise ValueError("route table: curve_radius_m must be >= 0 (0 = straight)")
        keep = np.concatenate([[True], g[1:] != g[:-1]])
        gs, gv = x[:-1][keep[:-1]], g[:-1][keep[:-1]]
        cs, ce, cr = [], [], []
        for i in range(x.size - 1):
            if r[i] > 0:
                if cs and ce[-1] == x[i] and cr[-1] == r[i]:
                    ce[-1] = x[i + 1]
                else:
                    cs.append(x[i]); ce.append(x[i + 1]); cr.append(r[i])  # noqa: E702
        return cls(grade_start_m=gs, grade_permille=gv, curve_start_m=np.asarray(cs, dtype=float),
                   curve_end_m=np.asarray(ce, dtype=float), curve_radius_m=np.asarray(cr, dtype=float),
                   length_m=float(x[-1]))

    def total_permille_at(self, x_m: np.ndarray) -> np.ndarray:
        """Grade + curve resistance per unit weight (N/kN) at positions ``x_m`` (table lookup)."""
        idx = np.searchsorted(self._brk, x_m, side="right") - 1
        return np.where(idx < 0, 0.0, self._val[np.clip(idx, 0, None)])

    def grade_at(self, x_m: np.ndarray) -> np.ndarray:
        """Grade (‰, + uphill) at positions ``x_m``."""
        x = np.asarray(x_m, dtype=float)
        idx = np.searchsorted(self.grade_start_m, x, side="right") - 1
        g = self.grade_permille[np.clip(idx, 0, None)]
        return np.where(idx < 0, 0.0, g)

    def curve_permille_at(self, x_m: np.ndarray) -> np.ndarray:
        """Curve resistance per unit weight 600/R (N/kN) at positions ``x_m``."""
        x = np.asarray(x_m, dtype=float)
        out = np.zeros_like(x)
        for a, b, r in zip(self.curve_start_m, self.curve_end_m, self.curve_radius_m):
            out = np.where((x >= a) & (x < b), 600.0 / r, out)
        return out

    def long_downgrade_ahead(self, x_front_m: float, x_rear_m: float, lookahead_m: float = 2500.0,
                             min_grade_permille: float = 8.0, min_length_m: float = 500.0) -> bool:
        """Is there a downgrade steeper than ``min_grade`` ‰ and longer than ``min_length`` m
        overlapping [x_rear, x_front + lookahead]? (the application rule of section 1.2)."""
        seg = self._steep.get((min_grade_permille, min_length_m))  # type: ignore[attr-defined]
        if seg is None:  # the rule's long downgrades, found once (the line does not change)
            starts = self.grade_start_m
            ends = np.append(starts[1:], self.length_m)
            steep = (self.grade_permille < -min_grade_permille) & ((ends - starts) >= min_length_m)
            seg = tuple(zip(starts[steep].tolist(), ends[steep].tolist()))
            self._steep[(min_grade_permille, min_length_m)] = seg  # type: ignore[attr-defined]
        ahead = x_front_m + lookahead_m
        return any(end > x_rear_m and start < ahead for start, end in seg)

    def force_n(self, weight_kn: np.ndarray, x_m: np.ndarray) -> np.ndarray:
        """Grade + curve resistance (N, + opposes forward motion / pulls downhill when negative) on
        vehicles of weight ``weight_kn`` (m g / 1000, kN) at positions ``x_m``, each (n,) (the
        table lookup of :meth:`total_permille_at`, compiled)."""
        from canbrake.physics._heavy_haul_kernel import route_force_n

        return route_force_n(self._brk, self._val, np.ascontiguousarray(weight_kn, dtype=float),
                             np.ascontiguousarray(x_m, dtype=float))
