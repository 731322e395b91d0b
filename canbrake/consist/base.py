"""Shared pieces of the consist schemas: the strict base model, vehicle lists, data files."""
from __future__ import annotations

import math
from pathlib import Path
from typing import Any, Generic, TypeVar

import numpy as np
from pydantic import BaseModel, ConfigDict, Field, model_validator

T = TypeVar("T")


#: fields where inf is meaningful ("unlimited"); NaN is refused everywhere
_INF_OK = frozenset({"adhesion_mu"})


def _non_finite(value: Any, path: str) -> str | None:
    """Dotted sub-path of the first NaN/inf float in ``value`` (lists and mappings searched),
    followed by ``=<value>``."""
    if isinstance(value, float) and not np.isfinite(value):
        return f"{path}={value}"
    if isinstance(value, (list, tuple)):
        for i, v in enumerate(value):
            if (hit := _non_finite(v, f"{path}.{i}")) is not None:
                return hit
    if isinstance(value, dict):
        for k, v in value.items():
            if (hit := _non_finite(v, f"{path}.{k}")) is not None:
                return hit
    return None


def _raw_non_finite(x: Any) -> str | None:
    """``x`` as written if it is a NaN or infinite number, or a string that reads as one
    (pydantic turns "nan" into a float), else None."""
    if isinstance(x, str):
        try:
            x = float(x)
        except ValueError:
            return None
    if isinstance(x, float) and not math.isfinite(x):
        return str(x)
    return None


class StrictModel(BaseModel):
    """Unknown keys are errors; defaults are validated; no YAML bool where a number belongs; no
    NaN or infinity in any number (except inf where it means unlimited, ``_INF_OK``)."""

    model_config = ConfigDict(extra="forbid", validate_default=True)

    @model_validator(mode="before")
    @classmethod
    def _no_bool_numbers(cls, data: Any) -> Any:
        """`duration_s: true` is not 1 s: a YAML bool where a number belongs is an error (numbers
        stay lax otherwise: PyYAML reads 2.0e6 as a string, which pydantic converts)."""
        if isinstance(data, dict):
            for name, f in cls.model_fields.items():
                v = data.get(name)
                ann = str(f.annotation)
                if ("float" in ann or "int" in ann) and "bool" not in ann and "Any" not in ann:
                    vals = v if isinstance(v, list) else [v]
                    if any(isinstance(x, bool) for x in vals):
                        raise ValueError(f"@{name}: expected a number, got {str(v).lower()}")
                    # NaN/inf before the field's bounds: `le=1` would call a NaN "greater than 1"
                    for i, x in enumerate(vals):
                        bad = _raw_non_finite(x)
                        if bad is not None and not (name in _INF_OK and bad == "inf"):
                            where = f"{name}.{i}" if isinstance(v, list) else name
                            raise ValueError(f"@{where}: must be a finite number, got {bad}")
        return data

    @model_validator(mode="after")
    def _finite(self) -> "StrictModel":
        """No NaN or inf in any field (a NaN mass or gain would fail inside a node, after the run
        directory was replaced), except inf where it means unlimited (``adhesion_mu``)."""
        for name in type(self).model_fields:
            if name == "profiles":
                continue
            v = getattr(self, name)
            if isinstance(v, BaseModel):
                continue  # validated on its own
            hit = _non_finite(v, name)
            if hit is not None:
                if name in _INF_OK and not any(isinstance(x, float) and np.isnan(x)
                                               for x in (v if isinstance(v, list) else [v])):
                    continue
                where, bad = hit.rsplit("=", 1)
                raise ValueError(f"@{where}: must be a finite number, got {bad}")
        return self


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


def check_air_braked_ecus(placed: list[Any], mode: str, wagon: Any) -> None:
    """ValueError (one line) for an ECU whose commands its vehicle cannot take, on a train with an
    automatic air brake (``mode``: pneumatic or ecp): the driver's brake valve (``airbrake_apply``)
    anywhere but on the leading vehicle; a brake force on a wagon (``wagon(vehicle)``, 1-based:
    an air-braked vehicle without traction or electric brake) from a controller that commands
    more than the force, or, without ECP, from any controller (with ECP a wagon's ECU turns a
    force-only controller's demand into its cylinder demand, :class:`canbrake.control.ecp.EcpUnit`).
    The heavy-haul and the coupled kernel's configurations share it."""
    from canbrake.control.base import controller_class

    for p in placed:
        try:
            cmds = tuple(getattr(controller_class(p.controller.name), "command_names", ("brake_force_n",)))
        except Exception:  # noqa: BLE001 - an unknown controller is reported by its own check
            continue
        if "airbrake_apply" in cmds and p.vehicle != 1:
            raise ValueError(f"ecus: ECU {p.name} on vehicle {p.vehicle} runs {p.controller.name}, which works "
                             "the driver's brake valve (airbrake_apply): the valve is on the leading vehicle "
                             "(vehicle 1), where the brake pipe is fed; place that ECU on vehicle 1")
        if not wagon(p.vehicle) or "brake_force_n" not in cmds or "ecp_demand" in cmds:
            continue
        if mode == "ecp" and len(cmds) == 1:
            continue  # wrapped by its ECP brake unit (build_controller)
        if mode == "ecp":
            raise ValueError(f"ecus: ECU {p.name} on wagon {p.vehicle} runs {p.controller.name}, which commands a "
                             f"brake force with {', '.join(c for c in cmds if c != 'brake_force_n')}: a wagon has "
                             "no traction or electric brake, and its ECP brake unit takes a controller that "
                             "commands the force alone (e.g. chen2023) or its cylinder demand (ecp_wagon)")
        raise ValueError(f"ecus: ECU {p.name} on wagon {p.vehicle} runs {p.controller.name}, which commands a "
                         "brake force (brake_force_n): a wagon has no force equipment (no traction or electric "
                         "brake), and with train.air_brake.mode: pneumatic no cylinder of its own to drive "
                         "(use mode: ecp, where its ECU turns the force into its cylinder demand, or a wagon "
                         "controller such as ecp_wagon)")
