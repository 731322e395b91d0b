"""The one controller interface: every controller of every train runs in an ECU node.

A controller is one object per ECU with explicit state and no I/O. Every control period the
ECU node (:mod:`canbrake.nodes.ecu`, in its own process or in the in-process engine) builds an
:class:`Observation` from the frames it received — its vehicle's sensor frames, the reference,
the latest STATE frames of the ECUs it listens to — and calls :meth:`Controller.step`.

Units are SI throughout: m, s, m/s, m/s^2, N, kg.
"""
from __future__ import annotations

from abc import ABC, abstractmethod
from dataclasses import dataclass, field
from typing import Any, Callable, Mapping

import numpy as np


@dataclass(frozen=True)
class Observation:
    """What carriage ``car_index``'s ECU knows when it computes tick ``tick``.

    Peer arrays have shape ``(n_cars,)`` and are indexed by car (0-based); the entry of
    the car itself holds its own measurement with age 0. A value never received is NaN
    with age ``inf``. The peer arrays an ECU hands over are read-only views of its peer table,
    valid for the call: copy what a controller keeps (``np.array(obs.peer_speed_mps)``).
    """

    tick: int
    time_s: float
    speed_mps: float
    position_m: float
    ref_speed_mps: float
    ref_decel_mps2: float  # a* > 0 means the reference decelerates
    peer_speed_mps: np.ndarray
    peer_position_m: np.ndarray
    peer_age_s: np.ndarray
    # Locally measured coupler deflections (m); None where there is no coupler or no sensor.
    # front: coupler to car i-1 (Δl_{i-1} = x_{i-1} - x_i - spacing), rear: to car i+1 (Δl_i).
    deflection_front_m: float | None = None
    deflection_rear_m: float | None = None
    #: reference position x*(t_k) (m); NaN when the scenario's reference has none
    ref_position_m: float = float("nan")
    #: every local sensor signal of the ECU by name (SI, names as in
    #: :mod:`canbrake.physics.contract`, e.g. ``speed_mps``, ``passive_force_n``, ``axle1_speed_radps``)
    sensors: Mapping[str, float] = field(default_factory=dict)
    #: broadcast signals received from peers by name, each shape ``(n_ecus,)`` indexed by ECU
    #: (NaN where never received); ages in ``peer_age_s``
    peer_signals: Mapping[str, np.ndarray] = field(default_factory=dict)

    @classmethod
    def of(cls, **fields: Any) -> "Observation":
        """``Observation(**fields)`` with every field given, for the ECU's once-per-period call:
        the same object without the frozen dataclass's per-field ``object.__setattr__`` (about
        a third of the cost)."""
        obs = object.__new__(cls)
        obs.__dict__.update(fields)
        return obs


@dataclass
class ControlOutput:
    """Result of one control step.

    ``brake_force_n`` > 0 decelerates the car, < 0 is traction. ``diagnostics`` holds named
    scalars for the trace (e.g. ``observer_accel_mps2``), all SI.
    """

    brake_force_n: float
    diagnostics: dict[str, float] = field(default_factory=dict)
    #: further actuator commands by name (see :mod:`canbrake.physics.contract`), e.g.
    #: ``{"axle1_torque_nm": ...}``, ``{"airbrake_apply": 1.0}``
    commands: dict[str, float] = field(default_factory=dict)
    #: values this ECU broadcasts to its peers in its next STATE frame, by name
    broadcast: dict[str, float] = field(default_factory=dict)


class Controller(ABC):
    """One carriage's controller: explicit state, no I/O."""

    #: names of the diagnostics this controller reports, in a stable order
    diagnostic_names: tuple[str, ...] = ()
    #: local sensor signals this controller reads (its ECU's SENSOR frames carry them)
    sensor_names: tuple[str, ...] = ("speed_mps", "position_m")
    #: actuator commands it sends (its ECU's command frames carry them); ``brake_force_n`` is
    #: ``ControlOutput.brake_force_n``, the others come from ``ControlOutput.commands``
    command_names: tuple[str, ...] = ("brake_force_n",)
    #: signals it broadcasts to peers in its STATE frame: sensor names (sent as measured) or
    #: names of ``ControlOutput.broadcast`` (sent one period later)
    broadcast_names: tuple[str, ...] = ("speed_mps", "position_m")
    #: whether it needs the reference position x* (a REFERENCE_POS frame)
    needs_ref_position: bool = False

    def __init__(self, car_index: int, n_cars: int, mass_kg: float, dt_s: float) -> None:
        self.car_index = car_index
        self.n_cars = n_cars
        self.mass_kg = float(mass_kg)
        self.dt_s = float(dt_s)

    @abstractmethod
    def step(self, obs: Observation) -> ControlOutput:
        """Compute this period's command from ``obs``."""

    def reset(self) -> None:  # pragma: no cover - default: stateless
        """Return to the initial state."""


ControllerFactory = Callable[..., Controller]
_REGISTRY: dict[str, ControllerFactory] = {}


def register(name: str) -> Callable[[ControllerFactory], ControllerFactory]:
    """Class decorator: make a controller available under ``name`` in scenarios."""

    def deco(cls: ControllerFactory) -> ControllerFactory:
        _REGISTRY[name] = cls
        return cls

    return deco


def available() -> list[str]:
    """Names of the controllers a scenario can name: built-in, registered, and those installed
    through the ``canbrake.controllers`` entry points (listed by name, loaded only when used)."""
    from importlib.metadata import entry_points

    _load_builtin()
    return sorted(set(_REGISTRY) | {ep.name for ep in entry_points(group="canbrake.controllers")})


class ControllerError(ValueError):
    """A controller name or parameter is wrong; ``param`` names the parameter ("" for the name)."""

    def __init__(self, message: str, param: str = "") -> None:
        super().__init__(message)
        self.param = param


def controller_class(name: str) -> ControllerFactory:
    """The controller registered as ``name`` (built-in, or an entry point of group
    ``canbrake.controllers`` in any installed package, python-can style)."""
    _load_builtin()
    if name not in _REGISTRY:
        _load_entry_point(name)
    try:
        return _REGISTRY[name]
    except KeyError:
        raise ControllerError(f"unknown controller {name!r}; available: {', '.join(available())}") from None


def _param_schema(cls: Any, name: str) -> tuple[dict[str, Any], bool, Any]:
    """(fields, accepts any keyword, pydantic model) of a controller class's constructor, built
    once per class: creating the pydantic model costs ~7 ms, once per ECU of every run otherwise."""
    cached = _SCHEMAS.get(cls)
    if cached is not None:
        return cached
    import inspect

    import pydantic

    sig = inspect.signature(cls)  # type: ignore[arg-type]
    accepts_any = any(p.kind is p.VAR_KEYWORD for p in sig.parameters.values())
    fields: dict[str, Any] = {}
    for pname, p in sig.parameters.items():
        if pname in _FIXED or p.kind in (p.VAR_KEYWORD, p.VAR_POSITIONAL):
            continue
        ann = p.annotation if p.annotation is not inspect.Parameter.empty else Any
        if isinstance(ann, str):  # postponed annotations: resolve in the controller's module
            import sys
            import typing

            mod = sys.modules.get(getattr(cls, "__module__", ""), None)
            try:
                ann = eval(ann, {**vars(typing), **(vars(mod) if mod else {})})  # noqa: S307 - our own annotations
            except Exception:  # noqa: BLE001 - an annotation we cannot resolve is not checked
                ann = Any
        default = p.default if p.default is not inspect.Parameter.empty else ...
        fields[pname] = (ann, default)
    model = pydantic.create_model(f"{name}_params", __config__=pydantic.ConfigDict(
        arbitrary_types_allowed=True), **fields)  # type: ignore[call-overload]
    _SCHEMAS[cls] = (fields, accepts_any, model)
    return fields, accepts_any, model


def inherited_params(old: str, new: str, params: Mapping[str, Any]) -> dict[str, Any]:
    """The parameters ``params`` of controller ``old`` that controller ``new`` takes over when a
    scenario switches to it by name: none when the two are unrelated (parameters belong to their
    controller: another one refuses them or reads them otherwise); when one class derives from the
    other (``chen2023_compensated`` from ``chen2023``, which accepts all of its parent's
    parameters), those ``new``'s constructor accepts. Raises :class:`ControllerError` for an
    unknown name."""
    a, b = controller_class(old), controller_class(new)
    if not (isinstance(a, type) and isinstance(b, type) and (issubclass(a, b) or issubclass(b, a))):
        return {}
    fields, accepts_any, _model = _param_schema(b, new)
    return {k: v for k, v in params.items() if accepts_any or k in fields}


_FIXED = frozenset({"car_index", "n_cars", "mass_kg", "dt_s"})
_SCHEMAS: dict[Any, tuple[dict[str, Any], bool, Any]] = {}


def check_params(name: str, params: Mapping[str, Any]) -> dict[str, Any]:
    """Validate ``params`` against the controller's constructor (its schema): unknown names and
    values of the wrong type are errors naming the parameter. Returns the values converted to
    the annotated types (e.g. the YAML string "2.0e5" to a float)."""
    import math

    import pydantic

    fields, accepts_any, model = _param_schema(controller_class(name), name)
    unknown = [k for k in params if k not in fields and k not in _FIXED]
    if unknown and not accepts_any:
        raise ControllerError(f"unknown parameter of controller {name!r} "
                              f"(parameters: {', '.join(sorted(fields)) or 'none'})", unknown[0])
    given = {k: v for k, v in params.items() if k in fields}
    try:
        checked = model(**given)
    except pydantic.ValidationError as e:
        err = e.errors()[0]
        where = ".".join(str(x) for x in err["loc"])
        raise ControllerError(f"{err['msg']} (controller {name!r})", where) from None
    out = dict(params)
    out.update({k: getattr(checked, k) for k in given})
    for k, v in out.items():  # after conversion: the YAML string "nan" becomes a float NaN
        vals = v if isinstance(v, (list, tuple)) else [v]
        bad = next((x for x in vals if isinstance(x, float) and not math.isfinite(x)), None)
        if bad is not None:
            raise ControllerError(f"must be a finite number, got {bad} (controller {name!r})", k)
    return out


def make_controller(
    name: str,
    params: Mapping[str, Any],
    *,
    car_index: int,
    n_cars: int,
    mass_kg: float,
    dt_s: float,
) -> Controller:
    """Build the controller registered as ``name`` for one ECU (``car_index``: the ECU's index,
    0-based; ``n_cars``: number of ECUs; ``mass_kg``: mass of its vehicle)."""
    cls = controller_class(name)
    return cls(car_index=car_index, n_cars=n_cars, mass_kg=mass_kg, dt_s=dt_s, **check_params(name, params))


def _load_entry_point(name: str) -> None:
    from importlib.metadata import entry_points

    for ep in entry_points(group="canbrake.controllers"):
        if ep.name == name:
            try:
                cls = ep.load()
            except Exception as e:  # noqa: BLE001 - a broken third-party package: say which
                dist = getattr(getattr(ep, "dist", None), "name", "?")
                raise ControllerError(f"controller {name!r} (entry point {ep.value!r} of package {dist}) "
                                      f"cannot be loaded: {type(e).__name__}: {e}") from None
            if not (isinstance(cls, type) and issubclass(cls, Controller)):
                raise ControllerError(f"controller {name!r}: entry point {ep.value!r} is not a "
                                      f"canbrake.control.base.Controller subclass")
            _REGISTRY.setdefault(name, cls)


def _load_builtin() -> None:
    # Importing the modules runs their @register decorators.
    from canbrake.control import cai2014, chen, chen_compensated, ecp, li2024, pi  # noqa: F401
