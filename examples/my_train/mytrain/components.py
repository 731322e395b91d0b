"""A user's own train component: running resistance written as railway practice often gives it,
R = A + B·V + C·V² in N with V in km/h, registered as the resistance model ``davis_kmh`` through
the entry point group ``canbrake.components.resistance`` (pyproject.toml). canbrake's component
schema validates it (pydantic) and its ``davis_n()`` hands the coefficients in SI to the physics
(docs/your-own-train.md)."""
from __future__ import annotations

from typing import Literal

from pydantic import BaseModel, ConfigDict, Field


class DavisKmh(BaseModel):
    """Running resistance R = A + B·V + C·V² (N, V in km/h)."""

    model_config = ConfigDict(extra="forbid")

    model: Literal["davis_kmh"] = "davis_kmh"
    a_n: float = Field(..., ge=0, description="A (N)")
    b_n_per_kmh: float = Field(0.0, ge=0, description="B (N per km/h)")
    c_n_per_kmh2: float = Field(0.0, ge=0, description="C (N per (km/h)^2)")

    def davis_n(self) -> tuple[float, float, float]:
        """(c0 N, c1 N·s/m, c2 N·s²/m²) with v in m/s: V = 3.6 v."""
        return float(self.a_n), self.b_n_per_kmh * 3.6, self.c_n_per_kmh2 * 3.6 * 3.6
