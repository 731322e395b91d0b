"""A train as components: the scenario's ``train:`` section and the assembler behind it.

A vehicle type is a composition of components, one per kind::

    train:
      vehicle_types:
        c80:
          mass_kg: 100000
          length_m: 12.0
          resistance: {model: per_weight, a_n_per_kn: 0.92, b_n_per_kn_per_kmh: 0.0048, c_n_per_kn_per_kmh2: 0.000125}
          coupler: {model: draft_gear, gear: MT-2}
          brake: {model: air, kind: shoe, cylinder_diameter_mm: 254, ...}
      vehicles: [{type: hxd1}, {type: c80, count: 105}]
      every_vehicle: {}        # components deep-merged over every vehicle type (a profile's override for all)
      track: {route: {file: data/li2024_route.csv}}
      air_brake: {mode: ecp, ...}

Component kinds (:data:`KINDS`) and their built-in models:

==============  =============================================================================
``resistance``  ``davis`` (c0 + c1 v + c2 v², N), ``table`` (N at m/s, linear, flat beyond the ends),
                ``per_weight`` (Li eq. 3, N per kN of weight)
``coupler``     ``chen`` (κ (1 + ε Δl²) Δl with optional end stop), ``linear`` (κ Δl), ``draft_gear`` (Li's hysteretic
                draft gear with slack: ``gear`` names one of ``train.draft_gears``), ``rigid``
``brake``       ``ideal``, ``electro_pneumatic`` (lag, jerk limit; both with ED/friction
                ``blending``, ``easing``, ``wsp``), ``air`` (automatic air brake rigging, Li Table 1)
``traction``    ``envelope`` (Li's traction and dynamic-brake envelope; makes a locomotive)
``wheels``      ``wheelsets`` (axles with Cai's slip curve, for WSP), ``driven_axles`` (Cai's
                driven axles), ``adhesion_limit`` (Li: μ·m·g caps traction and dynamic brake)
==============  =============================================================================

Each kind is a registry of named models with a pydantic parameter schema; a user's package adds
models through the entry point group ``canbrake.components.<kind>`` (the entry point's name is the
model name, its object the pydantic class), or in code with :func:`register_component`.

Vehicles: ``vehicles: [{type: NAME, count: N}]``; an entry may give ``mass_kg`` (one value, or a
list: one vehicle per value), so Chen's six different cars are one type and one entry.

The assembler (:meth:`TrainSpec.assemble`) builds the plant through the one plant contract
(:mod:`canbrake.physics.contract`): every train runs on the coupled kernel, ``TrainPlant``
(:data:`KERNELS`): Chen couplers with ideal/electro-pneumatic brakes, Li's draft gears, air brakes
and per-weight resistance (alone, as Li's heavy-haul trains, or mixed with Chen's parts), and
rigidly coupled trains with driven axles (Cai 2014: one body). A combination it does not
implement yet is refused in one line that names the vehicle type, its components and what the
kernel takes.
"""
from __future__ import annotations

import copy
from typing import Any, Callable, Literal, TypeVar

import numpy as np
from pydantic import BaseModel, Field, PrivateAttr, ValidationError, model_validator

from canbrake.consist import heavy_haul as hhs
from canbrake.consist.adhesion import VehicleAxles
from canbrake.consist.brakes import BlendingConfig, CarBrakes, EasingConfig, EdBrake, WheelsConfig, WspConfig
from canbrake.consist.coupled import MAX_VEHICLES, PerCar, _Model

#: the component kinds of a vehicle type, in the order they are listed
KINDS = ("resistance", "coupler", "brake", "traction", "wheels")
#: entry point group of a user's components of kind K: f"{ENTRY_POINT_GROUP}.{K}"
ENTRY_POINT_GROUP = "canbrake.components"

_REGISTRY: dict[str, dict[str, type[BaseModel]]] = {k: {} for k in KINDS}
M = TypeVar("M", bound=type[BaseModel])


class ComponentError(ValueError):
    """An unknown component kind or model, or a component class that cannot be used."""


def register_component(kind: str, name: str) -> Callable[[M], M]:
    """Class decorator: register the pydantic model class as component model ``name`` of ``kind``."""
    if kind not in _REGISTRY:
        raise ComponentError(f"unknown component kind {kind!r} (kinds: {', '.join(KINDS)})")

    def deco(cls: M) -> M:
        _REGISTRY[kind][name] = cls
        return cls
    return deco


def _entry_points(kind: str) -> list[Any]:
    from importlib.metadata import entry_points

    return list(entry_points(group=f"{ENTRY_POINT_GROUP}.{kind}"))


def available_components(kind: str) -> list[str]:
    """Model names of ``kind``: built-in and from installed entry points."""
    return sorted(set(_REGISTRY[kind]) | {ep.name for ep in _entry_points(kind)})


def component_class(kind: str, name: str) -> type[BaseModel]:
    """The pydantic class of component model ``name`` of ``kind`` (built-in or entry point);
    :class:`ComponentError` (one line, listing the known models) otherwise."""
    if kind not in _REGISTRY:
        raise ComponentError(f"unknown component kind {kind!r} (kinds: {', '.join(KINDS)})")
    if name not in _REGISTRY[kind]:
        for ep in _entry_points(kind):
            if ep.name == name:
                try:
                    cls = ep.load()
                except Exception as e:  # noqa: BLE001 - a broken plugin is the user's to fix, in one line
                    raise ComponentError(f"{kind} model {name!r} (entry point {ep.value}) cannot be loaded: "
                                         f"{type(e).__name__}: {e}") from None
                if not (isinstance(cls, type) and issubclass(cls, BaseModel)):
                    raise ComponentError(f"{kind} model {name!r} (entry point {ep.value}) is not a pydantic model class")
                _REGISTRY[kind].setdefault(name, cls)
                break
    try:
        return _REGISTRY[kind][name]
    except KeyError:
        raise ComponentError(f"unknown {kind} model {name!r} (models: {', '.join(available_components(kind))})") from None


def describe_components(kind: str | None = None) -> list[str]:
    """Lines describing every component model (of ``kind``, or of every kind): its name, the first
    line of its docstring and its parameters with their defaults (``*`` required), built-in and
    from installed entry points; ComponentError for an unknown kind or a broken plugin."""
    kinds = KINDS if kind is None else (kind,)
    lines: list[str] = []
    for k in kinds:
        if k not in _REGISTRY:
            raise ComponentError(f"unknown component kind {k!r} (kinds: {', '.join(KINDS)})")
        lines.append(f"{k}:")
        for name in available_components(k):
            cls = component_class(k, name)
            doc = " ".join((cls.__doc__ or "").strip().split("\n\n")[0].split()).replace("``", "")
            lines.append(f"  {name}: {doc}" if doc else f"  {name}")
            params = []
            for fname, f in cls.model_fields.items():
                if fname == "model":
                    continue
                params.append(f"{fname}*" if f.is_required() else f"{fname}={f.get_default(call_default_factory=True)!r}")
            if params:
                lines.append("      " + ", ".join(params))
            runs = [kn for kn, sup in KERNELS.items() if name in sup[k] or (  # a user's davis_n() resistance too
                k == "resistance" and callable(getattr(cls, "davis_n", None)))]
            lines.append(f"      physics: {', '.join(f'{kn} ({_KERNEL_PLANT[kn]})' for kn in runs) or 'none yet'}")
    if kind is None:
        lines.append("physics kernels (chosen by the components; a vehicle type's components must all fit one):")
        for kn, sup in KERNELS.items():
            lines.append(f"  {kn} ({_KERNEL_PLANT[kn]}): {_support(sup)}")
            lines.append(f"      {KERNEL_LIMITS[kn]}")
    return lines


def parse_component(kind: str, data: Any) -> BaseModel | None:
    """``data`` (a mapping with ``model``) as the component's pydantic object; ValueError whose
    message starts with ``@sub.path: `` for a bad parameter (the scenario loader's convention)."""
    if data is None or isinstance(data, BaseModel):
        return data
    if not isinstance(data, dict):
        raise ValueError(f"expected a mapping with `model` ({', '.join(available_components(kind))}), got {data!r}")
    if "model" not in data:
        raise ValueError(f"@model: missing: which {kind} model ({', '.join(available_components(kind))})")
    cls = component_class(kind, str(data["model"]))
    return _validated(cls, data)


def _params(c: BaseModel | None) -> dict[str, Any]:
    """A component's parameters (its fields without ``model``)."""
    return {} if c is None else {k: v for k, v in c.model_dump().items() if k != "model"}


def _name(c: BaseModel | None) -> str:
    return "none" if c is None else str(getattr(c, "model", type(c).__name__))


# --- built-in component models ----------------------------------------------------------------
@register_component("resistance", "davis")
class DavisResistance(_Model):
    """Running resistance c0 + c1 v + c2 v² (N, v in m/s)."""

    model: Literal["davis"] = "davis"
    c0_n: float = Field(0.0, ge=0)
    c1_n_s_per_m: float = Field(0.0, ge=0)
    c2_n_s2_per_m2: float = Field(0.0, ge=0)

    def davis_n(self) -> tuple[float, float, float]:
        """(c0 N, c1 N s/m, c2 N s²/m²): what the coupled kernel takes."""
        return float(self.c0_n), float(self.c1_n_s_per_m), float(self.c2_n_s2_per_m2)


@register_component("resistance", "table")
class TableResistance(_Model):
    """Running resistance from a table: ``force_n`` (N) at ``speed_mps`` (m/s, increasing from
    >= 0), linear between the points, held flat beyond the ends."""

    model: Literal["table"] = "table"
    speed_mps: list[float] = Field(min_length=2, description="speeds (m/s), increasing, the first >= 0")
    force_n: list[float] = Field(min_length=2, description="resistance at each speed (N, >= 0)")

    @model_validator(mode="after")
    def _table(self) -> "TableResistance":
        v, f = self.speed_mps, self.force_n
        if len(f) != len(v):
            raise ValueError(f"@force_n: {len(f)} values for {len(v)} speeds (speed_mps); give one force per speed")
        if v[0] < 0:
            raise ValueError(f"@speed_mps.0: speeds are |v| and must be >= 0, got {v[0]:g}")
        for i in range(1, len(v)):
            if not v[i] > v[i - 1]:
                raise ValueError(f"@speed_mps.{i}: speeds must increase, got {v[i]:g} after {v[i - 1]:g}")
        for i, x in enumerate(f):
            if x < 0:
                raise ValueError(f"@force_n.{i}: a resistance must be >= 0 N, got {x:g}")
        return self


@register_component("resistance", "per_weight")
class PerWeightResistance(hhs.Resistance):
    """Li 2024 eq. 3: w = a + b v + c v² in N per kN of weight (v in km/h)."""

    model: Literal["per_weight"] = "per_weight"

    def davis_n_for(self, mass_kg: float) -> tuple[float, float, float]:
        """(c0 N, c1 N s/m, c2 N s²/m²) of a vehicle of ``mass_kg``: eq. 3 times its weight
        m·g/1000 kN (g = 9.81 m/s², v in km/h = 3.6 v in m/s), what the coupled kernel takes."""
        w = mass_kg * 9.81 / 1000.0
        return (float(self.a_n_per_kn) * w, float(self.b_n_per_kn_per_kmh) * w * 3.6,
                float(self.c_n_per_kn_per_kmh2) * w * 3.6 * 3.6)


@register_component("coupler", "chen")
class ChenCoupler(_Model):
    """Chen 2023's nonlinear coupler Φ = κ (1 + ε Δl²) Δl at the vehicle's rear, with an optional
    end stop (buffer) beyond ``end_stop_m``."""

    model: Literal["chen"] = "chen"
    stiffness_n_per_m: float = Field(80000.0, gt=0, description="κ")
    epsilon_per_m2: float = Field(-0.5, description="ε (1/m²; negative = softening)")
    end_stop_m: float | None = Field(None, gt=0, description="|Δl| at which the buffer acts (none by default)")
    end_stop_stiffness_n_per_m: float = Field(2.0e7, gt=0)
    end_stop_absorption: float = Field(0.6, ge=0, lt=1)


@register_component("coupler", "linear")
class LinearCoupler(_Model):
    """A linear coupler Φ = κ Δl at the vehicle's rear (Chen's coupler with ε = 0), with an
    optional end stop (buffer) beyond ``end_stop_m``."""

    model: Literal["linear"] = "linear"
    stiffness_n_per_m: float = Field(..., gt=0, description="κ")
    end_stop_m: float | None = Field(None, gt=0, description="|Δl| at which the buffer acts (none by default)")
    end_stop_stiffness_n_per_m: float = Field(2.0e7, gt=0)
    end_stop_absorption: float = Field(0.6, ge=0, lt=1)

    @property
    def epsilon_per_m2(self) -> float:
        """ε = 0: the coupled kernel's nonlinear term vanishes."""
        return 0.0


@register_component("coupler", "draft_gear")
class DraftGearCoupler(_Model):
    """Li 2024's hysteretic draft gear with slack at the vehicle's rear: ``gear`` names one of
    ``train.draft_gears``."""

    model: Literal["draft_gear"] = "draft_gear"
    gear: str = Field(min_length=1)


@register_component("coupler", "rigid")
class RigidCoupler(_Model):
    """Rigid coupling (Cai 2014, eq. 3): the train moves as one body."""

    model: Literal["rigid"] = "rigid"


class _EpFunctions(_Model):
    """The brake control functions both ideal and electro-pneumatic equipment may carry."""

    max_brake_decel_mps2: float | None = Field(None, gt=0, description="brake rating as force/mass (null = none)")
    max_traction_accel_mps2: float | None = Field(None, ge=0, description="traction rating as force/mass (null = none)")
    blending: BlendingConfig | None = Field(None, description="ED/friction blending")
    easing: EasingConfig | None = Field(None, description="jerk-limited easing before standstill (an ECU function)")
    wsp: WspConfig | None = Field(None, description="wheel-slide protection (needs wheels)")
    ed_brake: EdBrake | None = Field(None, description="this vehicle's electro-dynamic brake under the blending: "
                                     "{model: per_mass, ...}, {model: envelope, ...} (Li 2024 eq. 2) or {model: none} "
                                     "(a trailer); default: blending.ed_max_decel_mps2")


@register_component("brake", "ideal")
class IdealBrake(_EpFunctions):
    """Brake/traction equipment that applies the commanded force at once (Chen 2023)."""

    model: Literal["ideal"] = "ideal"


@register_component("brake", "electro_pneumatic")
class ElectroPneumaticBrake(_EpFunctions):
    """Electro-pneumatic brake/traction equipment: first-order lag, jerk limit, ratings."""

    model: Literal["electro_pneumatic"] = "electro_pneumatic"
    lag_s: float = Field(0.3, gt=0, description="first-order brake lag time constant")
    jerk_limit_mps3: float | None = Field(1.0, gt=0, description="max |dF/dt|/m (null = none)")


@register_component("brake", "air")
class AirBrakeRigging(hhs.BrakeEquipment):
    """A vehicle's automatic air brake rigging (Li 2024 Table 1); the train's pipe and its
    application rules are ``train.air_brake``."""

    model: Literal["air"] = "air"


@register_component("traction", "envelope")
class TractionEnvelope(hhs.Envelope):
    """Li 2024's traction and dynamic-brake envelope; a vehicle with traction is a locomotive (on
    Chen's couplers the traction curve limits the vehicle's traction, brake_force_n < 0)."""

    model: Literal["envelope"] = "envelope"


@register_component("wheels", "wheelsets")
class Wheelsets(WheelsConfig):
    """Wheelsets with wheel–rail adhesion per axle (Cai's slip curve scaled to train.wheel_rail.adhesion_mu)."""

    model: Literal["wheelsets"] = "wheelsets"


@register_component("wheels", "driven_axles")
class DrivenAxles(VehicleAxles):
    """Cai 2014's driven axles: their loads, imbalances and wheels (``wheel`` the default); per-axle
    torque commands, on a rigidly coupled train."""

    model: Literal["driven_axles"] = "driven_axles"


@register_component("wheels", "adhesion_limit")
class AdhesionLimit(hhs.Adhesion):
    """Li 2024: μ·m·g caps a locomotive's traction and dynamic brake (constant or Curtius–Kniffler)."""

    model: Literal["adhesion_limit"] = "adhesion_limit"


# --- the train ----------------------------------------------------------------------------------
#: keys of the former train families, and where they went
_MOVED_TRAIN = {
    "model": "there are no train families any more: a train is vehicle_types composed of components (resistance, "
             "coupler, brake, traction, wheels) and vehicles; the physics follows from the components",
    "mass_kg": "moved to train.vehicles (e.g. vehicles: [{type: car, mass_kg: [18000, 21000]}]) or "
               "train.vehicle_types.NAME.mass_kg",
    "coupler": "moved to the coupler component: train.every_vehicle.coupler or train.vehicle_types.NAME.coupler "
               "({model: chen, stiffness_n_per_m, epsilon_per_m2, end_stop_m, ...})",
    "davis": "moved to the resistance component: train.vehicle_types.NAME.resistance or train.every_vehicle.resistance "
             "({model: davis, c0_n, c1_n_s_per_m, c2_n_s2_per_m2})",
    "grade_permille": "moved to train.track.grade_permille",
    "curve_resistance_n": "moved to train.track.curve_resistance_n",
    "route": "moved to train.track.route",
    "brakes": "moved to the components: blending, easing and wsp to the brake component (train.every_vehicle.brake: "
              "{model: ideal|electro_pneumatic, blending, easing, wsp}), wheels to the wheels component "
              "(train.every_vehicle.wheels: {model: wheelsets, axles, radius_m, ...})",
}
_MOVED_TYPE = {
    "davis": "moved to resistance: {model: davis, c0_n, c1_n_s_per_m, c2_n_s2_per_m2}",
    "draft_gear": "moved to coupler: {model: draft_gear, gear: NAME}",
    "wheel": "moved to wheels: {model: driven_axles, wheel, axles}",
    "axles": "moved to wheels: {model: driven_axles, wheel, axles}",
    "adhesion": "moved to wheels: {model: adhesion_limit, mu, curve}",
}
#: top-level scenario keys that moved into train:
MOVED_TOP = {
    "actuator": "moved to train: each vehicle type's brake component (train.every_vehicle.brake or "
                "train.vehicle_types.NAME.brake: {model: ideal|electro_pneumatic, lag_s, jerk_limit_mps3, "
                "max_brake_decel_mps2, max_traction_accel_mps2}) and train.wheel_rail (adhesion_mu, adhesion_limited)",
}


def _deep_merge(base: dict[str, Any], over: dict[str, Any]) -> dict[str, Any]:
    out = copy.deepcopy(base)
    for k, v in over.items():
        out[k] = _deep_merge(out[k], v) if isinstance(v, dict) and isinstance(out.get(k), dict) else copy.deepcopy(v)
    return out


class VehicleTypeSpec(_Model):
    """One kind of vehicle: mass (kg), length over couplers (m) and its components (each a mapping
    with ``model``; see the module docstring). A component left out takes the kernel's default
    (Chen's coupler, an ideal brake, the default running resistance of the coupled kernel)."""

    mass_kg: float | None = Field(None, gt=0, description="default for the vehicles of this type")
    length_m: float | None = Field(None, gt=0, description="over couplers; spaces the vehicles at rest")
    resistance: Any = None
    coupler: Any = None
    brake: Any = None
    traction: Any = None
    wheels: Any = None

    @model_validator(mode="before")
    @classmethod
    def _moved_and_parsed(cls, data: Any) -> Any:
        if not isinstance(data, dict):
            return data
        for k, why in _MOVED_TYPE.items():
            if k in data:
                raise ValueError(f"@{k}: {why}")
        data = dict(data)
        for kind in KINDS:
            if data.get(kind) is not None:
                try:
                    data[kind] = parse_component(kind, data[kind])
                except ValueError as e:
                    msg = str(e)
                    raise ValueError(f"@{kind}.{msg[1:]}" if msg.startswith("@") else f"@{kind}: {msg}") from None
        return data

    def components(self) -> dict[str, str]:
        return {k: _name(getattr(self, k)) for k in KINDS}


class VehicleEntrySpec(_Model):
    """``count`` vehicles of type ``type``; ``mass_kg``: their mass (one value), or one vehicle per
    value of a list (then ``count`` is the list's length)."""

    type: str
    count: int | None = Field(None, ge=1, le=10_000)
    mass_kg: float | list[float] | None = None

    @model_validator(mode="after")
    def _count(self) -> "VehicleEntrySpec":
        if isinstance(self.mass_kg, list):
            if not self.mass_kg:
                raise ValueError("@mass_kg: an empty list")
            if self.count is not None and self.count != len(self.mass_kg):
                raise ValueError(f"@count: {self.count}, but mass_kg lists {len(self.mass_kg)} vehicles")
            for i, m in enumerate(self.mass_kg):
                if not m > 0:
                    raise ValueError(f"@mass_kg.{i}: mass must be > 0 kg, got {m}")
        elif self.mass_kg is not None and not self.mass_kg > 0:
            raise ValueError(f"@mass_kg: mass must be > 0 kg, got {self.mass_kg}")
        return self

    def n(self) -> int:
        return len(self.mass_kg) if isinstance(self.mass_kg, list) else (self.count or 1)


class TrackSpec(_Model):
    """The track: a constant grade and curve resistance, or a route file (grade and curvature by position)."""

    grade_permille: float = Field(0.0, ge=-100, le=100, description="positive uphill (‰)")
    curve_resistance_n: PerCar = Field(0.0, description="extra resistance per vehicle, e.g. 0.004·m·D_c (N)")
    route: hhs.Route | None = Field(None, description="route file: position_m, grade_permille, curve_radius_m")


class WheelRailSpec(_Model):
    """Wheel–rail conditions: the adhesion μ per vehicle and whether it caps the rail force
    (μ·m·g), and Cai's slip-curve rail conditions (``conditions``, ``base``, ``windows``, ``curve``)."""

    adhesion_mu: PerCar = Field(0.3, description="base wheel-rail adhesion μ per vehicle")
    adhesion_limited: bool = Field(False, description="cap the rail force at μ·m·g")
    curve: Literal["paper", "physical"] = "paper"
    v_floor_mps: float = Field(0.1, gt=0)
    conditions: dict[str, Any] | None = Field(None, description="slip-curve coefficients by rail condition")
    base: str | None = None
    windows: list[Any] = Field(default_factory=list)


def _support(kinds: dict[str, set[str | None]]) -> str:
    return ", ".join(f"{k} {'|'.join(sorted(x or 'none' for x in v))}" for k, v in kinds.items())


#: what each physics kernel implements, by component kind (None: the component left out)
KERNELS: dict[str, dict[str, set[str | None]]] = {
    "coupled": {"coupler": {"chen", "linear", "draft_gear", "rigid", None},
                "brake": {"ideal", "electro_pneumatic", "air", None},
                "resistance": {"davis", "table", "per_weight", None}, "traction": {"envelope", None},
                "wheels": {"wheelsets", "driven_axles", "adhesion_limit", None}},
}
_KERNEL_PLANT = {"coupled": "TrainPlant"}
#: what a kernel still takes once for the whole train (everything else may differ per vehicle)
KERNEL_LIMITS: dict[str, str] = {
    "coupled": "per vehicle: mass, resistance (davis, table or per_weight), coupler (chen/linear: stiffness, ε, "
               "end stop; or Li's draft_gear), brake model (ideal, electro_pneumatic or air), lag, jerk limit, "
               "ratings, ED brake, blending (or none: friction only), easing, wsp, traction envelope, wheelsets "
               "(axles, radius, inertia, slip curve b1..b3, c1..c3, v_floor_mps, or none) but none under an air "
               "brake, a locomotive's adhesion_limit; once for the train: the rail conditions (train.wheel_rail), "
               "the air brake (train.air_brake, fed from a locomotive at the head) and a constant grade, or with "
               "draft gears or air brakes a route (train.track.route), uncertainty and disturbance (eq. 40); rigid "
               "couplers (Cai 2014: the train is one body) with driven axles (per-axle torque commands) and the "
               "rail schedule of their slip curve (train.wheel_rail: conditions, base, windows), per vehicle mass, "
               "resistance (davis, table or per_weight) and driven axles, nothing else yet",
}
#: train-level fields only trains with Li's draft gears or air brakes use
_HH_ONLY = ("draft_gears", "air_brake", "uncertainty", "disturbance", "start_position_m", "integration_step_s")
#: what the coupled kernel also takes of them with draft gears or air brakes (Li's line and disturbances)
_LI_COUPLED = ("uncertainty", "disturbance", "start_position_m", "integration_step_s", "track.route")


def _hh_defaults() -> dict[str, Any]:
    return {"draft_gears": {}, "air_brake": None, "uncertainty": 0.0, "disturbance": hhs.Disturbance(),
            "start_position_m": 0.0, "integration_step_s": None}


_HH_DEFAULTS = _hh_defaults()


def _fits(vt: VehicleTypeSpec, kernel: str) -> bool:
    for kind, ok in KERNELS[kernel].items():
        c = getattr(vt, kind)
        name = None if c is None else getattr(c, "model", None)
        if kind == "resistance" and c is not None and name not in ok and callable(getattr(c, "davis_n", None)):
            continue  # a user's resistance model that gives Davis coefficients
        if name not in ok:
            return False
    return True


class TrainSpec(_Model):
    """``train:``: vehicle types composed of components, the vehicles, and the train-level parts."""

    vehicle_types: dict[str, VehicleTypeSpec] = Field(min_length=1)
    vehicles: list[VehicleEntrySpec] = Field(min_length=1)
    every_vehicle: dict[str, Any] = Field(default_factory=dict, description="components (and mass_kg/length_m) "
                                          "deep-merged over every vehicle type: an override for all vehicles")
    track: TrackSpec = Field(default_factory=TrackSpec)
    wheel_rail: WheelRailSpec = Field(default_factory=WheelRailSpec)
    draft_gears: dict[str, hhs.DraftGear] = Field(default_factory=dict, description="draft gears by name "
                                                  "(coupler: {model: draft_gear, gear: NAME})")
    air_brake: hhs.AirBrake | None = Field(None, description="the automatic air brake: brake pipe, mode "
                                           "(pneumatic or ecp), application; fed from the leading locomotive")
    uncertainty: float = Field(0.0, ge=-0.5, le=0.5, description="δ: non-control forces are (1 + δ) x nominal")
    disturbance: hhs.Disturbance = Field(default_factory=hhs.Disturbance)
    start_position_m: float = Field(0.0, description="draft-gear trains: the first vehicle's centre on the route")
    integration_step_s: float | None = Field(None, gt=0, description="draft-gear trains: the integration step "
                                             "(default: the control period over plant.substeps)")

    _kernel: Any = PrivateAttr(None)
    _kernel_name: str = PrivateAttr("")

    @model_validator(mode="before")
    @classmethod
    def _moved_and_merged(cls, data: Any) -> Any:
        if not isinstance(data, dict):
            return data
        for k, why in _MOVED_TRAIN.items():
            if k in data:
                raise ValueError(f"@{k}: {why}")
        every = data.get("every_vehicle")
        types = data.get("vehicle_types")
        if isinstance(every, dict) and every and isinstance(types, dict):
            data = dict(data)
            data["vehicle_types"] = {k: _deep_merge(v, every) if isinstance(v, dict) else v for k, v in types.items()}
            for v in data["vehicle_types"].values():  # a bad value of every_vehicle's: once, where it is written
                if not isinstance(v, dict):
                    continue
                try:
                    _validated(VehicleTypeSpec, v)
                except ValueError as e:
                    msg = str(e)
                    if msg.startswith("@") and ": " in msg:
                        loc, text = msg[1:].split(": ", 1)
                        if _sets(every, loc.split(".")):
                            raise ValueError(f"@every_vehicle.{loc}: {text}") from None
                    continue  # a type's own problem: reported per vehicle type below
        return data

    @model_validator(mode="after")
    def _assemble(self) -> "TrainSpec":
        ex = self.expanded()
        if len(ex) > MAX_VEHICLES:
            raise ValueError(f"@vehicles: {len(ex)} vehicles; at most {MAX_VEHICLES}")
        kernel = self._choose_kernel(ex)
        if kernel == "coupled" and any(isinstance(vt.coupler, RigidCoupler) or isinstance(vt.wheels, DrivenAxles)
                                       for _, vt, _ in ex):
            self._check_rigid_couplers(ex)
        # what the train takes of Li's train-level parts: its draft gears and air brake
        used = {k for k, kind, m in (("draft_gears", "coupler", "draft_gear"), ("air_brake", "brake", "air"))
                if any(_name(getattr(vt, kind)) == m for _, vt, _ in ex)}
        if used:  # Li's line and disturbances go with his draft gears or air brakes
            used |= set(_LI_COUPLED)
        given = [k for k in _HH_ONLY if k not in used and getattr(self, k) != _HH_DEFAULTS[k]] + \
                (["track.route"] if self.track.route is not None and "track.route" not in used else [])
        if given and used:
            what = {"draft_gears": "a draft gear (coupler: {model: draft_gear, gear: NAME})",
                    "air_brake": "an air brake (brake: {model: air})"}[given[0]]
            raise ValueError(f"@{given[0]}: no vehicle type of this train has {what}, the only user of "
                             f"train.{given[0]}; remove it or give a vehicle type one")
        if given:
            raise ValueError(f"@{given[0]}: used by draft-gear trains (coupler: {{model: draft_gear}}) only; "
                             f"this train's couplers are {_name(ex[0][1].coupler) if ex[0][1].coupler else 'chen'}")
        self._kernel_name = kernel
        self._kernel = getattr(self, f"_lower_{kernel}")(ex)
        return self

    # --- the vehicles --------------------------------------------------------------------------
    def expanded(self) -> list[tuple[str, VehicleTypeSpec, float]]:
        """(type name, type, mass kg) per vehicle, front first; ValueError naming an unknown type
        or a vehicle without a mass."""
        out: list[tuple[str, VehicleTypeSpec, float]] = []
        for i, v in enumerate(self.vehicles):
            vt = self.vehicle_types.get(v.type)
            if vt is None:
                raise ValueError(f"@vehicles.{i}.type: unknown vehicle type {v.type!r} "
                                 f"(vehicle_types: {', '.join(sorted(self.vehicle_types))})")
            if v.mass_kg is None and vt.mass_kg is None:
                raise ValueError(f"@vehicles.{i}.mass_kg: no mass: give it here or in vehicle_types.{v.type}.mass_kg")
            masses = v.mass_kg if isinstance(v.mass_kg, list) else [v.mass_kg if v.mass_kg is not None
                                                                     else vt.mass_kg] * v.n()
            out += [(v.type, vt, float(m)) for m in masses]  # type: ignore[arg-type]
        return out

    def _choose_kernel(self, ex: list[tuple[str, VehicleTypeSpec, float]]) -> str:
        first = ex[0][1]
        cname = _name(first.coupler) if first.coupler is not None else None
        guess = "coupled"
        for name, vt, _ in ex:
            if not _fits(vt, guess):
                alt = [k for k in KERNELS if all(_fits(t, k) for _, t, _ in ex)]
                if alt:
                    return alt[0]
                comps = ", ".join(f"{k}={v}" for k, v in vt.components().items())
                sup = "; ".join(f"{k} ({_KERNEL_PLANT[k]}) takes {_support(s)}" for k, s in KERNELS.items())
                raise ValueError(f"@vehicle_types.{name}: no physics kernel implements this train yet: vehicle type "
                                 f"{name} has {comps} (with {_name(ex[0][1].coupler) if cname else 'chen'} couplers "
                                 f"at the head); {sup}")
        return guess

    @property
    def kernel(self) -> Any:
        """The assembled kernel configuration (internal): its ``build_plant(scn, base_dir)`` builds the plant."""
        return self._kernel

    @property
    def kernel_name(self) -> str:
        """``coupled``: the physics kernel the components chose (the one there is)."""
        return self._kernel_name

    def assemble(self, scn: Any, base_dir: Any = None) -> Any:
        """The plant of scenario ``scn`` (an object following :class:`canbrake.physics.contract.PlantModel`)."""
        return self._kernel.build_plant(scn, base_dir)

    # --- lowering onto today's kernels ----------------------------------------------------------
    def _uniform(self, ex: list[tuple[str, VehicleTypeSpec, float]], kind: str, what: str,
                 per_vehicle: frozenset[str] = frozenset(), default: BaseModel | None = None) -> BaseModel | None:
        """The component ``kind`` every vehicle shares (the coupled kernel takes one for the train;
        the fields ``per_vehicle`` may differ; a vehicle without one has ``default``)."""
        first_name, first = ex[0][0], getattr(ex[0][1], kind) or default
        dump = lambda c: None if c is None else c.model_dump(exclude=set(per_vehicle))  # noqa: E731
        want = dump(first)
        for name, vt in {n: t for n, t, _ in ex}.items():  # each type once, in train order
            c = getattr(vt, kind) or default
            if dump(c) != want:
                raise ValueError(f"@vehicle_types.{name}.{kind}: the coupled kernel (TrainPlant) takes one {what} for "
                                 f"the whole train; vehicle types {first_name} and {name} differ (set it in "
                                 f"train.every_vehicle.{kind})")
        return first

    def _wheels(self, ex: list[tuple[str, VehicleTypeSpec, float]]) -> BaseModel | None:
        """The first vehicle's wheelsets that has them (the train's, as the brake functions see them);
        vehicles may differ in every field (axles, radius, inertia, slip curve, ``v_floor_mps``) or have
        none: ``wheels_per_car`` then holds each car's."""
        return next((vt.wheels for _, vt, _ in ex if vt.wheels is not None), None)

    def _lower_coupled(self, ex: list[tuple[str, VehicleTypeSpec, float]]) -> Any:
        from canbrake.consist.brakes import BrakeSystemConfig
        from canbrake.consist.coupled import ActuatorConfig, TrainConfig

        if any(isinstance(vt.coupler, RigidCoupler) or isinstance(vt.wheels, DrivenAxles) for _, vt, _ in ex):
            return self._lower_rigid(ex)
        n = len(ex)
        li = self._li_coupled(ex)  # Li's line and locomotive limits; the adhesion limits taken out of ex
        ex = li.pop("_ex")
        air = [vt.brake if isinstance(vt.brake, AirBrakeRigging) else None for _, vt, _ in ex]
        gears = [vt.coupler.gear if isinstance(vt.coupler, DraftGearCoupler) else None for _, vt, _ in ex[:-1]]
        self._check_mixed(ex, air, gears)
        for name, vt, _ in ex:
            b = vt.brake
            if b is not None and getattr(b, "wsp", None) is not None and b.wsp.enabled and vt.wheels is None:
                raise ValueError(f"@vehicle_types.{name}.brake.wsp: wheel-slide protection needs axles, and vehicle "
                                 f"type {name} has no wheels (give it wheels: {{model: wheelsets, axles, radius_m, "
                                 f"inertia_kgm2}})")
        rated = ("max_brake_decel_mps2", "max_traction_accel_mps2", "jerk_limit_mps3")  # may differ per vehicle
        # a vehicle without a brake has an ideal one where others have one
        ideal = IdealBrake() if any(vt.brake is not None for _, vt, _ in ex) else None
        functions = ("blending", "easing", "wsp")  # per vehicle too: BrakeSystemConfig.cars where they differ
        brake = ex[0][1].brake or ideal  # every field of the brake may differ per vehicle
        wheels = self._wheels(ex)
        data: dict[str, Any] = {"model": "coupled", "mass_kg": [m for _, _, m in ex]}
        if any(vt.resistance is not None for _, vt, _ in ex):
            table = [vt.resistance if isinstance(vt.resistance, TableResistance) else None for _, vt, _ in ex]
            ds = [vt.resistance.davis_n_for(m) if isinstance(vt.resistance, PerWeightResistance) else
                  vt.resistance.davis_n() if vt.resistance is not None and t is None else (0.0, 0.0, 0.0)
                  for (_, vt, m), t in zip(ex, table)]
            data["davis"] = {"c0_n": [d[0] for d in ds], "c1_n_s_per_m": [d[1] for d in ds],
                             "c2_n_s2_per_m2": [d[2] for d in ds]}
            if any(t is not None for t in table):
                data["resistance_table"] = table
        if any(vt.traction is not None for _, vt, _ in ex):
            data["traction_envelope"] = [None if vt.traction is None else hhs.Envelope.model_validate(_params(vt.traction))
                                         for _, vt, _ in ex]
        cps = [vt.coupler if vt.coupler is not None else ChenCoupler() for _, vt, _ in ex]
        act = cps[:-1] or cps
        chen = next((c for c in act if not isinstance(c, DraftGearCoupler)), ChenCoupler())
        # a draft-gear coupler's Chen terms are not used (its draft gear's force replaces Φ): the
        # first Chen coupler's, without an end stop
        act = [c if not isinstance(c, DraftGearCoupler) else chen.model_copy(update={"end_stop_m": None}) for c in act]
        coupler: dict[str, Any] = {}
        for f in ("stiffness_n_per_m", "epsilon_per_m2"):
            vals = [float(getattr(c, f)) for c in act]
            coupler[f] = vals[0] if len(set(vals)) == 1 else vals
        for f in ("end_stop_m", "end_stop_stiffness_n_per_m", "end_stop_absorption"):  # one value, or per coupler
            vals = [getattr(c, f) for c in act]
            coupler[f] = vals[0] if len(set(vals)) == 1 else vals
        if any(g is not None for g in gears):
            data["draft_gears"] = {k: g for k, g in self.draft_gears.items() if k in gears}
            data["coupler_gear"] = gears
        if any(a is not None for a in air):
            data["air_brake"] = self.air_brake
            data["air_rigging"] = [None if a is None else hhs.BrakeEquipment.model_validate(_params(a)) for a in air]
            data["length_m"] = [vt.length_m for _, vt, _ in ex]
        lengths = [vt.length_m for _, vt, _ in ex]
        if n > 1 and all(x is not None for x in lengths):
            coupler["spacing_m"] = [0.5 * (a + b) for a, b in zip(lengths, lengths[1:])]  # type: ignore[operator]
        data["coupler"] = coupler
        data["grade_permille"] = self.track.grade_permille
        data["curve_resistance_n"] = self.track.curve_resistance_n
        parts: dict[str, Any] = {k: getattr(brake, k, None) for k in functions}
        own = [{k: getattr(vt.brake, k, None) for k in functions} for _, vt, _ in ex]
        differ = any(o[k] != own[0][k] for o in own for k in functions)
        if differ:  # each car its own; the train's fields: the first car's that has one
            parts = {k: next((o[k] for o in own if o[k] is not None), None) for k in functions}
            if parts["wsp"] is not None and not parts["wsp"].enabled:
                parts["wsp"] = next((o["wsp"] for o in own if o["wsp"] is not None and o["wsp"].enabled), parts["wsp"])
            parts["cars"] = [CarBrakes(vehicle_type=name, **o) for (name, _, _), o in zip(ex, own)]
        eds = [getattr(vt.brake, "ed_brake", None) for _, vt, _ in ex]
        if any(e is not None for e in eds):
            lacking = [nm for (nm, _, _), e, o in zip(ex, eds, own) if e is not None and o["blending"] is None]
            if parts["blending"] is None or (differ and lacking):
                name = lacking[0] if lacking else next(nm for (nm, _, _), e in zip(ex, eds) if e is not None)
                raise ValueError(f"@vehicle_types.{name}.brake.ed_brake: an ED brake is blended with the friction "
                                 f"brake by brake.blending, which {'this train' if not differ else 'vehicle type ' + name}"
                                 f"'s brake does not have")
            parts["blending"] = BlendingConfig.model_validate(
                {**parts["blending"].model_dump(exclude={"per_car"}),
                 "per_car": [None if e is None else e.model_dump() for e in eds]})
        if wheels is not None:
            parts["wheels"] = WheelsConfig.model_validate(_params(wheels))
            if any(_params(vt.wheels) != _params(wheels) for _, vt, _ in ex):  # some vehicles' wheels differ
                parts["wheels_per_car"] = [None if vt.wheels is None else WheelsConfig.model_validate(_params(vt.wheels))
                                           for _, vt, _ in ex]
        if any(v is not None for v in parts.values()):
            data["brakes"] = BrakeSystemConfig(**parts)
        a: dict[str, Any] = {"adhesion_limited": self.wheel_rail.adhesion_limited,
                             "adhesion_mu": self.wheel_rail.adhesion_mu}
        if brake is not None:  # an air-braked vehicle's brake_force_n (a locomotive's traction/ED brake) is ideal
            brakes = [ideal if vt.brake is None or isinstance(vt.brake, AirBrakeRigging) else vt.brake
                      for _, vt, _ in ex]

            def per_vehicle(f: str, instead: Any = None) -> Any:  # one value, or one per vehicle where they differ
                vals = [getattr(b, f, instead) for b in brakes]
                return vals[0] if all(v == vals[0] for v in vals) else vals
            a["max_brake_decel_mps2"] = per_vehicle("max_brake_decel_mps2")
            a["max_traction_accel_mps2"] = per_vehicle("max_traction_accel_mps2")
            if any(b.model == "electro_pneumatic" for b in brakes):  # an ideal brake among them: lag 0, no jerk limit
                a.update(model="realistic", lag_s=per_vehicle("lag_s", 0.0), jerk_limit_mps3=per_vehicle("jerk_limit_mps3"))
        data["actuator"] = ActuatorConfig(**a)
        data.update(li)
        return TrainConfig.model_validate(data)

    def _li_coupled(self, ex: list[tuple[str, VehicleTypeSpec, float]]) -> dict[str, Any]:
        """The coupled kernel's fields for Li 2024's line and locomotive (TrainConfig: route,
        start_position_m, static_couplers, electric_brake_envelope, loco_adhesion, uncertainty,
        disturbance, max_substep_s), and under ``_ex`` the vehicles with the adhesion limits
        (wheels: adhesion_limit, a locomotive's, not wheelsets) taken out. A train on a route starts
        in static equilibrium (as the heavy-haul kernel's); in a train with draft gears or air brakes
        every traction envelope's electric brake caps its vehicle's brake effort (elsewhere the
        compiled coupled step caps traction only, for now). One-line error: an adhesion limit
        without traction."""
        out: dict[str, Any] = {}
        adh = [vt.wheels if isinstance(vt.wheels, AdhesionLimit) else None for _, vt, _ in ex]
        for (name, vt, _), a in zip(ex, adh):
            if a is not None and vt.traction is None:
                raise ValueError(f"@vehicle_types.{name}.wheels: adhesion on vehicle type {name}, which has no "
                                 "driven axles (no traction: a wagon); give it a traction envelope or leave "
                                 "wheels out")
        if any(a is not None for a in adh):
            out["loco_adhesion"] = [None if a is None else hhs.Adhesion.model_validate(_params(a)) for a in adh]
            ex = [(nm, vt.model_copy(update={"wheels": None}) if a is not None else vt, m)
                  for (nm, vt, m), a in zip(ex, adh)]
        li = any(isinstance(vt.brake, AirBrakeRigging) or isinstance(vt.coupler, DraftGearCoupler) for _, vt, _ in ex)
        if li and any(vt.traction is not None for _, vt, _ in ex):  # (the compiled step caps traction only:
            out["electric_brake_envelope"] = True                 # a train without Li's parts keeps it, and its stacks)
        if self.track.route is not None:
            if self.track.grade_permille != 0 or self.track.curve_resistance_n != 0:
                raise ValueError("@track.grade_permille: a train on a route takes its grade and curves from "
                                 "train.track.route")
            out.update(route=self.track.route, start_position_m=self.start_position_m, static_couplers=True)
        if self.uncertainty != 0.0:
            out["uncertainty"] = self.uncertainty
        if self.disturbance.enabled:
            bad = [v for v in self.disturbance.vehicles if not 1 <= v <= len(ex)]
            if bad:
                raise ValueError(f"@disturbance.vehicles: {bad} outside 1..{len(ex)}")
            out["disturbance"] = self.disturbance
        if self.integration_step_s is not None:  # as given (else the period over plant.substeps)
            out["max_substep_s"] = self.integration_step_s
        out["_ex"] = ex
        return out

    def _check_mixed(self, ex: list[tuple[str, VehicleTypeSpec, float]], air: list[Any],
                     gears: list[str | None]) -> None:
        """One-line errors for Li's draft gears and air brakes on the coupled kernel: an unknown gear,
        an air brake without the train's brake pipe, without a locomotive at the head feeding it,
        without the vehicles' lengths (the pipe's distances), or on a vehicle with wheelsets."""
        for (name, vt, _), g in zip(ex, gears):
            if g is not None and g not in self.draft_gears:
                raise ValueError(f"@vehicle_types.{name}.coupler.gear: unknown draft gear {g!r} "
                                 f"(draft_gears: {', '.join(sorted(self.draft_gears)) or 'none'})")
        if all(a is None for a in air):
            return
        name = next(nm for (nm, _, _), a in zip(ex, air) if a is not None)
        if self.air_brake is None:
            raise ValueError(f"@air_brake: vehicle type {name} has an air brake, which needs the train's brake pipe "
                             "and its rules (train.air_brake: mode, apply_wave_mps, release_wave_mps, "
                             "cylinder_tau_s, service_factor)")
        head, hvt, _ = ex[0]
        if hvt.traction is None:
            raise ValueError(f"@vehicles.0.type: vehicle type {name} has an air brake, but nothing feeds the brake "
                             f"pipe: the leading vehicle ({head}) is not a locomotive (no traction); the pipe is "
                             "charged and its driver's valve (with ECP: the head-end unit) worked from a locomotive "
                             "at the head: put a vehicle type with traction first")
        for nm, vt, _ in ex:
            if vt.length_m is None:
                raise ValueError(f"@vehicle_types.{nm}.length_m: a train with air brakes needs each vehicle's length "
                                 "(the brake pipe's distance from the head)")
            if isinstance(vt.brake, AirBrakeRigging) and vt.wheels is not None:
                raise ValueError(f"@vehicle_types.{nm}.wheels: an air-braked vehicle's block force acts on its body "
                                 "on the coupled kernel; wheelsets (adhesion per axle) take an ideal or "
                                 "electro_pneumatic brake: leave wheels out of an air-braked vehicle type")

    def _kernel_types(self, make: Callable[[VehicleTypeSpec, float], dict[str, Any]]
                      ) -> tuple[dict[str, Any], list[dict[str, Any]]]:
        """The kernel's vehicle types (``make(type, mass)``) and its vehicle list, in the order of
        ``vehicles``; an entry that gives its own mass makes a type of its own per mass
        (``NAME@<mass>kg``)."""
        types: dict[str, Any] = {}
        vehicles: list[dict[str, Any]] = []
        for v in self.vehicles:
            vt = self.vehicle_types[v.type]
            listed = isinstance(v.mass_kg, list)
            for m in (v.mass_kg if listed else [v.mass_kg]):  # type: ignore[union-attr]
                tname = v.type if m is None or m == vt.mass_kg else f"{v.type}@{m:g}kg"
                if tname not in types:
                    types[tname] = make(vt, float(vt.mass_kg if m is None else m))  # type: ignore[arg-type]
                vehicles.append({"type": tname, "count": 1 if listed else v.n()})
        return types, vehicles

    @staticmethod
    def _check_rigid_couplers(ex: list[tuple[str, VehicleTypeSpec, float]]) -> None:
        """One-line errors for a train that mixes rigid and elastic couplers, or has driven axles
        without rigid couplers (neither is implemented yet)."""
        couplers = [(name, vt.coupler) for name, vt, _ in (ex[:-1] or ex)]
        stiff = next(((nm, c) for nm, c in couplers if not isinstance(c, RigidCoupler)), None)
        if stiff is None:
            return
        rigid = next((nm for nm, c in couplers if isinstance(c, RigidCoupler)), None)
        kind = _name(stiff[1]) if stiff[1] is not None else "chen"
        if rigid is None:
            name = next(nm for nm, vt, _ in ex if isinstance(vt.wheels, DrivenAxles))
            raise ValueError(f"@vehicle_types.{name}.wheels: driven axles (Cai 2014, per-axle torque commands) run "
                             f"on a rigidly coupled train only yet, and vehicle type {stiff[0]}'s coupler is {kind} "
                             f"(give every vehicle coupler: {{model: rigid}}, e.g. in train.every_vehicle, or use "
                             f"wheels: {{model: wheelsets}})")
        at = stiff[0] if isinstance(couplers[0][1], RigidCoupler) else rigid  # the one unlike the head's
        raise ValueError(f"@vehicle_types.{at}.coupler: vehicle type {rigid} is rigidly coupled and {stiff[0]} has "
                         f"a {kind} coupler: a train mixing rigid and elastic couplers is not implemented yet "
                         f"(rigid on every vehicle, or none)")

    def _lower_rigid(self, ex: list[tuple[str, VehicleTypeSpec, float]]) -> Any:
        """A train with rigid couplers or driven axles (Cai 2014) as the coupled kernel's rigidly
        coupled train (:meth:`canbrake.physics.train.TrainPlant._rigid_init`): every coupler rigid,
        per vehicle mass, resistance and driven axles, the slip curve's rail schedule."""
        from canbrake.consist.coupled import TrainConfig

        self._check_rigid_couplers(ex)
        for name, vt in {n: t for n, t, _ in ex}.items():
            for kind in ("brake", "traction", "wheels"):
                c = getattr(vt, kind)
                if c is not None and not (kind == "wheels" and isinstance(c, DrivenAxles)):
                    raise ValueError(f"@vehicle_types.{name}.{kind}: a rigidly coupled train (coupler: {{model: "
                                     f"rigid}}) takes mass, resistance and driven axles (wheels: {{model: "
                                     f"driven_axles}}) only yet; vehicle type {name} has {kind} {_name(c)}")
        wr = self.wheel_rail
        if wr.conditions is None or wr.base is None:
            raise ValueError("@wheel_rail.conditions: a rigidly coupled train with driven axles needs the rail "
                             "conditions of its slip curve (wheel_rail: conditions, base, windows)")
        if wr.adhesion_mu != WheelRailSpec().adhesion_mu or wr.adhesion_limited:
            raise ValueError("@wheel_rail.adhesion_mu: a rigidly coupled train's adhesion follows from its slip curve "
                             "(wheel_rail.conditions)")
        if self.track.grade_permille != 0:
            raise ValueError("@track.grade_permille: a rigidly coupled train takes no grade yet")
        table = [vt.resistance if isinstance(vt.resistance, TableResistance) else None for _, vt, _ in ex]
        ds = [vt.resistance.davis_n_for(m) if isinstance(vt.resistance, PerWeightResistance) else
              vt.resistance.davis_n() if vt.resistance is not None and t is None else (0.0, 0.0, 0.0)
              for (_, vt, m), t in zip(ex, table)]
        data: dict[str, Any] = {
            "model": "coupled", "mass_kg": [m for _, _, m in ex], "rigid": True,
            "davis": {"c0_n": [d[0] for d in ds], "c1_n_s_per_m": [d[1] for d in ds],
                      "c2_n_s2_per_m2": [d[2] for d in ds]},
            "curve_resistance_n": self.track.curve_resistance_n,
            "driven_axles": [_params(vt.wheels) if isinstance(vt.wheels, DrivenAxles) else None for _, vt, _ in ex],
            "wheel_rail": {"curve": wr.curve, "v_floor_mps": wr.v_floor_mps, "conditions": wr.conditions,
                           "base": wr.base, "windows": wr.windows},
            "vehicle_names": [name for name, _, _ in ex]}
        if any(t is not None for t in table):
            data["resistance_table"] = table
        return _validated(TrainConfig, data)

def _sets(data: Any, path: list[str]) -> bool:
    """Whether the nested mapping ``data`` gives a value at ``path`` (keys; list indices as digits)."""
    for part in path:
        if isinstance(data, dict) and part in data:
            data = data[part]
        elif isinstance(data, list) and part.isdigit() and int(part) < len(data):
            data = data[int(part)]
        else:
            return False
    return True


def _validated(cls: type[BaseModel], data: dict[str, Any]) -> Any:
    """``cls.model_validate(data)`` with its first problem as ``@path: message`` (the loader's
    convention; ed_brake's discriminator tags are left out of the path: ed_brake.max_decel_mps2)."""
    try:
        return cls.model_validate(data)
    except ValidationError as e:
        err = e.errors()[0]
        loc = ".".join(str(p) for p in err["loc"] if p not in ("per_mass", "envelope"))
        msg = "unknown key" if err["type"] == "extra_forbidden" else err["msg"]
        if msg.startswith("Value error, "):
            msg = msg[len("Value error, "):]
        if msg.startswith("@") and ": " in msg:
            sub, msg = msg[1:].split(": ", 1)
            loc = f"{loc}.{sub}" if loc else sub
        raise ValueError(f"@{loc}: {msg}" if loc else msg) from None


def vehicle_masses_kg(spec: TrainSpec) -> np.ndarray:
    """Masses (kg) per vehicle, front first."""
    return np.array([m for _, _, m in spec.expanded()], dtype=float)
