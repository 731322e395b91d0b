"""Shared pieces of the consist schemas: the strict base model, vehicle lists, data files."""
from __future__ import annotations

from pathlib import Path
from typing import Any, Generic, TypeVar

import numpy as np
from pydantic import BaseModel, ConfigDict, Field

T = TypeVar("T")


class StrictModel(BaseModel):
    """Unknown keys are errors; defaults are validated."""

    model_config = ConfigDict(extra="forbid", validate_default=True)


class VehicleEntry(StrictModel):
    """``count`` consecutive vehicles of type ``type`` (a key of ``vehicle_types``)."""

    type: str
    count: int = Field(1, ge=1, le=10_000)


def expand_vehicles(types: dict[str, T], vehicles: list[VehicleEntry], where: str = "train") -> list[tuple[str, T]]:
    """[(type name, type)] per vehicle, front first; ValueError naming an unknown type."""
    out: list[tuple[str, T]] = []
    for i, v in enumerate(vehicles):
        if v.type not in types:
            known = ", ".join(sorted(types)) or "none"
            raise ValueError(f"{where}.vehicles.{i}.type: unknown vehicle type {v.type!r} (vehicle_types: {known})")
        out += [(v.type, types[v.type])] * v.count
    return out


class DataFileError(ValueError):
    """A data file named in a scenario cannot be used; the message names file and column."""


def resolve_data_path(path: str | Path, base_dir: Path | None) -> Path:
    """A scenario's data file path: relative paths are relative to the scenario file's folder."""
    p = Path(path)
    if not p.is_absolute() and base_dir is not None:
        p = base_dir / p
    return p


def load_table(path: str | Path, columns: tuple[str, ...], base_dir: Path | None = None) -> dict[str, np.ndarray]:
    """Read a CSV table with a header (``#`` comments allowed) and return the named columns as
    float arrays; every value must be finite. Raises :class:`DataFileError` with file and column."""
    p = resolve_data_path(path, base_dir)
    try:
        text = p.read_text()
    except FileNotFoundError:
        raise DataFileError(f"{p}: no such data file") from None
    except (OSError, UnicodeDecodeError) as e:
        raise DataFileError(f"{p}: cannot read: {e}") from None
    lines = [ln for ln in text.splitlines() if ln.strip() and not ln.lstrip().startswith("#")]
    if not lines:
        raise DataFileError(f"{p}: empty table")
    header = [h.strip() for h in lines[0].split(",")]
    missing = [c for c in columns if c not in header]
    if missing:
        raise DataFileError(f"{p}: missing column(s) {', '.join(missing)} (header: {', '.join(header)})")
    rows: list[list[float]] = []
    for n, ln in enumerate(lines[1:], start=2):
        cells = [c.strip() for c in ln.split(",")]
        if len(cells) != len(header):
            raise DataFileError(f"{p}: data line {n}: {len(cells)} values, header has {len(header)}")
        try:
            rows.append([float(c) for c in cells])
        except ValueError:
            raise DataFileError(f"{p}: data line {n}: not a number in {ln!r}") from None
    arr = np.asarray(rows, dtype=float).reshape(len(rows), len(header))
    out: dict[str, np.ndarray] = {}
    for c in columns:
        col = arr[:, header.index(c)]
        if not np.all(np.isfinite(col)):
            raise DataFileError(f"{p}: column {c}: non-finite value")
        out[c] = col
    return out


def as_dict(model: BaseModel) -> dict[str, Any]:
    return model.model_dump(mode="python")
