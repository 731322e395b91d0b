"""Scenario files: the single source of truth for a run's parameters.

A scenario is YAML validated by the pydantic models below (unknown keys are errors). Units
are in the field names; km/h and km/h/s appear only here, at the edge, and are converted to SI
by the accessors (``*_mps``). A scenario may carry ``profiles:`` — named partial overrides that
are deep-merged over the base document when selected with ``profile:`` (or ``--profile``).

Nothing else in canbrake reads YAML.
"""
from __future__ import annotations

import copy
import math
import re
from pathlib import Path
from typing import Annotated, Any, Literal, Mapping, Union

import numpy as np
import yaml
from canbrake.arrays import per_car
from canbrake.bus.impair import ImpairmentSpec
from canbrake.bus.clock import ClockConfig
from canbrake.bus.txbuffer import TxBufferConfig
from canbrake.bus.segments import GatewayConfig, SegmentConfig
from canbrake.consist.base import _INF_OK, _non_finite, _raw_non_finite  # noqa: F401
from canbrake.consist.coupled import ActuatorConfig, PerCar, TrainConfig, _Model  # noqa: F401
from canbrake.consist.components import MOVED_TOP, TrainSpec
from pydantic import BaseModel, Field, ValidationError, field_validator, model_validator

KMH = 1.0 / 3.6  # m/s per km/h
from canbrake.consist.coupled import MAX_VEHICLES  # noqa: E402,F401 - most vehicles (and ECUs) a scenario may have


from canbrake.errors import ScenarioError  # noqa: E402 - defined below the layers (bus/ raises it too)


class InitialConfig(_Model):
    speed_kmh: PerCar
    position_m: list[float] | None = Field(None, description="default: car 1 in front, spaced by coupler.spacing_m or 10 m")

    @field_validator("speed_kmh")
    @classmethod
    def _forward(cls, v: PerCar) -> PerCar:
        for x in (v if isinstance(v, list) else [v]):
            if x < 0:
                raise ValueError(f"initial speeds must be >= 0 km/h (the train runs towards +x), got {x}")
        return v


class ReferenceConfig(_Model):
    """The virtual leader's speed v*(t) (and position x*(t)).

    ``kind: ramp`` (default): v*(t) = speed − decel·t until it reaches ``target_kmh`` (a negative
    ``decel_kmh_per_s`` ramps up), then constant. ``kind: table``: v* interpolated linearly in a CSV
    ``file`` (columns ``time_s,speed_kmh``, or ``position_m,speed_kmh`` with ``over: position``);
    a recorded speed curve is such a table. x*(0) = ``position_m``; x* is v* integrated.
    """

    kind: Literal["ramp", "table"] = "ramp"
    speed_kmh: float | None = Field(None, ge=0, description="ramp: v*(0)")
    decel_kmh_per_s: float | None = Field(None, description="ramp: rate of decrease of v* (negative: increase)")
    target_kmh: float = Field(0.0, ge=0, description="ramp: speed at which the ramp ends")
    file: str | None = Field(None, description="table: CSV file (relative to the scenario file)")
    over: Literal["time", "position"] = Field("time", description="table: the table's abscissa")
    position_m: float = Field(0.0, description="x*(0)")

    @model_validator(mode="after")
    def _kind_fields(self) -> "ReferenceConfig":
        if self.kind == "ramp":
            if self.speed_kmh is None or self.decel_kmh_per_s is None:
                raise ValueError("a ramp needs speed_kmh and decel_kmh_per_s")
            if self.decel_kmh_per_s > 0 and self.target_kmh > self.speed_kmh:
                raise ValueError(f"target_kmh ({self.target_kmh}) is above speed_kmh ({self.speed_kmh}) of a "
                                 f"decelerating ramp")
            if self.decel_kmh_per_s < 0 and self.target_kmh < self.speed_kmh:
                raise ValueError(f"target_kmh ({self.target_kmh}) is below speed_kmh ({self.speed_kmh}) of an "
                                 f"accelerating ramp (negative decel_kmh_per_s)")
        elif self.file is None:
            raise ValueError("a table reference needs file")
        return self

    @property
    def speed_mps(self) -> float:
        return (self.speed_kmh or 0.0) * KMH

    @property
    def decel_mps2(self) -> float:
        return (self.decel_kmh_per_s or 0.0) * KMH


class ControllerConfig(_Model):
    name: str = "chen2023"
    params: dict[str, Any] = Field(default_factory=dict, description="passed to the controller's constructor")


class PlacedEcu:
    """One ECU after expanding the placement (see :meth:`Scenario.placement`)."""

    __slots__ = ("name", "vehicle", "controller", "listens", "external")

    def __init__(self, name: str, vehicle: int, controller: "ControllerConfig", listens: Any,
                 external: bool = False) -> None:
        self.name, self.vehicle, self.controller, self.listens = name, vehicle, controller, listens
        self.external = external  # not started by canbrake: a foreign program or a real ECU on the bus

    def __repr__(self) -> str:
        return f"PlacedEcu({self.name!r}, vehicle={self.vehicle}, controller={self.controller.name!r})"


class EcuPlacement(_Model):
    """Where an ECU sits and what it runs. ``vehicle`` (1-based) places one ECU; ``vehicles: "2-106"``
    places one per vehicle of the range, named ``name`` with ``{v}`` replaced by the vehicle number
    (default ``ecu{v}``). ``listens``: whose STATE frames it receives (``all`` other ECUs, ``none``,
    ``neighbours``: the ECUs on the vehicles coupled to its own, or a list of ECU names); ``controller`` defaults to the scenario's top-level one."""

    name: str | None = Field(None, pattern=r"^[A-Za-z][A-Za-z0-9_{}]*$")
    vehicle: int | None = Field(None, ge=1)
    vehicles: str | None = Field(None, pattern=r"^\s*\d+\s*-\s*\d+\s*$")
    controller: ControllerConfig | None = None
    listens: Literal["all", "none", "neighbours"] | list[str] = "all"
    external: bool = Field(False, description="canbrake does not start this ECU: a foreign program or a real ECU "
                                              "sends its frames (docs/lockstep-protocol.md); its controller only "
                                              "defines its frames")

    @field_validator("listens", mode="before")
    @classmethod
    def _listens_word(cls, v: Any) -> Any:
        """A word that is none of the three (``neighbors``): one message, not one per member of
        the union (a list of names is checked by the placement)."""
        if isinstance(v, str) and v not in ("all", "none", "neighbours"):
            raise ValueError(f"expected all, none, neighbours or a list of ECU names, got {v!r}")
        return v

    @model_validator(mode="after")
    def _one_of(self) -> "EcuPlacement":
        if (self.vehicle is None) == (self.vehicles is None):
            raise ValueError("give exactly one of vehicle (one ECU) or vehicles (a range such as \"2-106\")")
        return self

    def vehicle_numbers(self) -> list[int]:
        if self.vehicle is not None:
            return [self.vehicle]
        a, b = (int(x) for x in str(self.vehicles).split("-"))
        if b < a:
            raise ValueError(f"vehicles {self.vehicles!r}: empty range")
        return list(range(a, b + 1))


class RailEvent(_Model):
    """Rail condition change between start_s and stop_s (per car)."""

    type: Literal["rail"]
    start_s: float = Field(..., ge=0)
    stop_s: float | None = Field(None, ge=0)
    brake_factor: PerCar = Field(1.0, description="share of the braking force that reaches the rail (0..1)")
    adhesion_mu: PerCar | None = Field(None, description="adhesion limit μ during the event (realistic actuator)")

    @field_validator("brake_factor")
    @classmethod
    def _share(cls, v: PerCar) -> PerCar:
        for x in (v if isinstance(v, list) else [v]):
            if not 0.0 <= x <= 1.0:
                raise ValueError(f"brake_factor is a share of the braking force: 0..1, got {x}")
        return v

    @model_validator(mode="after")
    def _order(self) -> "RailEvent":
        if self.stop_s is not None and self.stop_s < self.start_s:
            raise ValueError(f"stop_s ({self.stop_s}) is before start_s ({self.start_s})")
        return self


class DisturbanceEvent(_Model):
    """External force on each car, + along the direction of travel (+x):
    F = bias + amplitude sin(2π f (t - start) + phase)."""

    type: Literal["disturbance"]
    start_s: float = Field(..., ge=0)
    stop_s: float | None = Field(None, ge=0)
    amplitude_n: PerCar = 0.0
    frequency_hz: float = Field(0.5, ge=0)
    phase_rad: float = 0.0
    bias_n: PerCar = 0.0


Event = Annotated[Union[RailEvent, DisturbanceEvent], Field(discriminator="type")]


class DbcPageMap(_Model):
    """One message of the user's DBC carrying (part of) a role: ``signals`` maps canbrake's signal
    names (speed_mps, brake_force_n, ... ; tick, ref_speed_mps, node_state for the plant's
    roles) onto the DBC's signal names; ``crc`` / ``counter`` / ``status``: the E2E CRC, the
    alive counter and the ECU status signals (STATE and command frames need crc and counter);
    ``multiplexer``: the page of a multiplexed message. In ``each_ecu``, ``{i}`` in any name is
    the ECU's index (1-based), ``{vehicle}`` its vehicle and ``{name}`` its name."""

    message: str = Field(min_length=1)
    multiplexer: int | None = Field(None, ge=0)
    signals: dict[str, str] = Field(default_factory=dict)
    crc: str | None = None
    counter: str | None = None
    status: str | None = None

    def filled(self, subst: Mapping[str, str]) -> dict[str, Any]:
        def f(x: str | None) -> str | None:
            if x is None:
                return None
            for k, v in subst.items():
                x = x.replace("{" + k + "}", v)
            return x
        return {"message": f(self.message), "multiplexer": self.multiplexer,
                "signals": {k: f(v) for k, v in self.signals.items()},
                "crc": f(self.crc), "counter": f(self.counter), "status": f(self.status)}


class DbcEcuMap(_Model):
    """One ECU's roles in the user's DBC: its sensor inputs (from the plant), state broadcast,
    commands (one message, or a list of messages when the role needs several) and heartbeat."""

    sensors: DbcPageMap | list[DbcPageMap] | None = None
    state: DbcPageMap | list[DbcPageMap] | None = None
    commands: DbcPageMap | list[DbcPageMap] | None = None
    heartbeat: DbcPageMap | None = None

    def filled(self, subst: Mapping[str, str]) -> dict[str, Any]:
        out: dict[str, Any] = {}
        for role in ("sensors", "state", "commands"):
            v = getattr(self, role)
            if v is not None:
                out[role] = [p.filled(subst) for p in (v if isinstance(v, list) else [v])]
        if self.heartbeat is not None:
            out["heartbeat"] = self.heartbeat.filled(subst)
        return out


class DbcMapConfig(_Model):
    """The user's own DBC (``bus.dbc``): canbrake's roles mapped onto its messages and signals
    (docs/your-own-train.md, "Your own DBC"). Roles left out keep canbrake's generated messages;
    canbrake checks the whole mapping before a run (canbrake.bus.userdbc)."""

    file: str = Field(min_length=1, description="the DBC, relative to the scenario's folder")
    sync: DbcPageMap | None = Field(None, description="SYNC: signals {tick: ...}")
    reference: DbcPageMap | None = Field(None, description="REFERENCE: signals {ref_speed_mps, ref_decel_mps2}")
    reference_position: DbcPageMap | None = Field(None, description="REFERENCE_POS: signals {ref_position_m}")
    plant_heartbeat: DbcPageMap | None = Field(None, description="the plant's heartbeat: signals {node_state}")
    each_ecu: DbcEcuMap | None = Field(None, description="template for every ECU not in ecus ({i}, {vehicle}, {name})")
    ecus: dict[str, DbcEcuMap] = Field(default_factory=dict, description="per ECU name")

    def resolved(self, ecus: list[tuple[str, int, int]]) -> dict[str, Any]:
        """The mapping for :func:`canbrake.bus.userdbc.mapped_layout`; ``ecus``: (name, index, vehicle)."""
        out: dict[str, Any] = {k: getattr(self, k).filled({}) for k in
                               ("sync", "reference", "reference_position", "plant_heartbeat")
                               if getattr(self, k) is not None}
        per: dict[str, Any] = {}
        for name, index, vehicle in ecus:
            m = self.ecus.get(name, self.each_ecu)
            if m is not None:
                per[name] = m.filled({"i": str(index), "vehicle": str(vehicle), "name": name})
        for name in self.ecus:
            if name not in per:
                per[name] = self.ecus[name].filled({})
        out["ecus"] = per
        return out



class BusConfig(_Model):
    backend: Literal["memory", "socketcan", "virtual"] = "memory"
    channel: str | None = Field(None, description="default: a fresh in-memory channel, or vcan0 for socketcan")
    interface: str | None = Field(None, description="any python-can interface name; overrides backend")
    bitrate_bps: int = Field(500000, gt=0, le=1_000_000,
                             description="classic CAN bit rate: the timing model's and bus load's; passed to a "
                                         "python-can adapter interface as `bitrate` (a SocketCAN device's is set "
                                         "with `ip link`)")
    interface_args: dict[str, Any] = Field(
        default_factory=dict, description="extra keyword arguments for can.Bus with --interface NAME "
                                          "(python-can's interface options, e.g. {fd: false, serial: 123})")
    timing: Literal["ideal", "model"] = Field(
        "ideal", description="ideal: frames arrive within the period (the papers' assumption); model: the CAN "
                             "timing model (stuffing, arbitration, queueing) decides when each frame arrives (lockstep)")
    plant_io_on_bus: bool = Field(False, description="count the plant's sensor frames as bus traffic "
                                                     "(false: they stand in for each car's local wiring)")
    impairments: list[ImpairmentSpec] = Field(default_factory=list,
                                              description="see canbrake.bus.impair (delay, jitter, loss, ...)")
    log_format: Literal["log", "asc", "blf", "trc", "mf4"] = Field(
        "log", description="format of the run's frame log frames.<log_format>, written by python-can: "
                           "log (candump -L), asc (Vector ASCII), blf (Vector binary), trc (PEAK), mf4 (ASAM MDF, "
                           "needs asammdf: pip install 'canbrake[mf4]')")
    tx_buffers: list[TxBufferConfig] = Field(default_factory=list,
                                             description="transmit buffer per node for the timing model and the "
                                                         "analysis (canbrake.bus.txbuffer); default: priority-ordered")
    segments: list[SegmentConfig] = Field(default_factory=list,
                                          description="bus segments (name, bit rate, nodes) joined by gateways, "
                                                      "lockstep (canbrake.bus.segments); empty: one bus")
    gateways: list[GatewayConfig] = Field(default_factory=list,
                                          description="gateways joining two segments each, with a forwarding delay")
    dbc: DbcMapConfig | None = Field(None, description="run on the user's own DBC: canbrake's roles mapped onto its "
                                                       "messages and signals (docs/your-own-train.md)")


class PlantConfig(_Model):
    coupler_sensors: bool = Field(False, description="send COUPLER_Ci frames (locally measured deflection)")
    substeps: int = Field(1, ge=1, le=1000, description="integration sub-steps per control period")
    trace_every: int = Field(1, ge=1, description="write every n-th control period (and the last) to "
                                                  "signals.csv; a long train's full trace is large")


class SafetyConfig(_Model):
    """What each car's brake unit does when its brake commands stop arriving intact (E2E checked):
    after ``command_timeout_s`` without a valid command it brakes on its own at
    ``failsafe_decel_mps2`` (force = that x the car's mass). Off by default: the papers assume
    commands always arrive, and the plant then holds the last command however old it is."""

    command_timeout_s: float | None = Field(None, gt=0, description="no valid command for this long "
                                                                    "-> fail-safe brake (null: off)")
    failsafe_decel_mps2: float = Field(1.2, gt=0, description="fail-safe braking force per unit mass (m/s^2)")
    latch: bool = Field(True, description="true: a car stays in fail-safe until the end of the run; false: "
                                          "the next valid command releases it")
    failsafe_commands: dict[str, float] | None = Field(
        None, description="the plant commands a brake unit in fail-safe applies instead of the fail-safe "
                          "force, e.g. {ecp_demand: 1.0} (an ECP wagon's full application); null: "
                          "brake_force_n = failsafe_decel_mps2 x mass")
    max_abs_deflection_m: float | None = Field(None, gt=0, description="coupler deflection bound for the verdict "
                                               "(default: the controller's theta bounds, if any)")
    max_speed_kmh: float | None = Field(None, gt=0, description="speed bound for the verdict (null: none)")
    peer_hold_periods: int | None = Field(None, ge=1, description="an ECU holds a peer's last good value for "
                                                                  "this many periods, then drops it and runs on its "
                                                                  "own sensors (null: hold forever)")


class SecurityConfig(_Model):
    """SecOC-style authentication (canbrake.bus.secoc): 24-bit truncated AES-CMAC on brake commands
    and simulation-control frames, freshness = (session, tick). The key never lives in the repository."""

    key_file: str = Field(..., min_length=1, description="file with the AES-128 key (32 hex digits or 16 bytes)")
    session: int = Field(0, ge=0, le=0xFFFFFFFF, description="trip counter in the freshness value; increase it "
                                                            "per run so frames of earlier runs fail")


class CrashFault(_Model):
    """Fault injection: the ECU process of ``car`` raises an error at ``at_s`` (tests supervision)."""

    car: int = Field(..., ge=1)
    at_s: float = Field(..., ge=0)


class EcuConfig(_Model):
    heartbeat_period_s: float = Field(0.1, gt=0)
    per_process: int = Field(1, ge=1, le=1024,
                             description="ECUs hosted per OS process (1: one process per ECU, the default; "
                                         "more for long trains on few cores; frames are identical)")
    crash: CrashFault | None = Field(None, description="inject a crash of one ECU process")
    realtime_compute_deadline: float = Field(0.5, gt=0, lt=1,
                                             description="realtime: fraction of the period an ECU waits for peers")
    lockstep_deadline: float = Field(0.5, gt=0, lt=1,
                                     description="lockstep: fraction of the period within which a state frame "
                                                 "must arrive to be used in the same tick")
    clocks: list[ClockConfig] = Field(default_factory=list,
                                      description="clock drift (ppm) and timer jitter per ECU, simulated time with "
                                                  "bus.timing: model (canbrake.bus.clock)")
    external_start_timeout_s: float = Field(30.0, gt=0, description="external ECUs (ecus.*.external): how long "
                                            "the run waits for each one's first heartbeat (wall s)")
    external_timeout_s: float = Field(1.0, gt=0, description="lockstep: how long (wall s) the plant and the ECUs "
                                      "wait for an external ECU's frames of a period once everything else is in; "
                                      "then the period goes on without them and the ECU counts as silent until its "
                                      "frames are on time again")


class Scenario(_Model):
    name: str
    description: str = ""
    seed: int = Field(0, ge=0)
    duration_s: float = Field(..., gt=0)
    control_period_s: float = Field(0.001, gt=0, le=1.0,
                                    description="lockstep/realtime control period, s; at least the wire time of the "
                                                "SYNC frame that starts every period (95 bit times: 4 data bytes, "
                                                "worst-case stuffing, interframe space) at the slowest bit rate "
                                                "(bus.bitrate_bps, bus.segments), i.e. 95 us at 1 Mbit/s, 190 us at "
                                                "500 kbit/s")
    mode: Literal["lockstep", "realtime"] = "lockstep"
    time_scale: float = Field(1.0, gt=0, le=100, description="realtime: simulated seconds per wall second "
                                                             "(0.5: half speed for slow hardware)")
    profile: str | None = None
    profiles: dict[str, dict[str, Any]] = Field(default_factory=dict)
    train: TrainSpec = Field(description="the train: vehicle types composed of components (canbrake.consist.components)")
    initial: InitialConfig
    reference: ReferenceConfig
    controller: ControllerConfig = ControllerConfig()
    ecus: list[EcuPlacement] = Field(default_factory=list, description="ECU placement (default: one per vehicle)")
    events: list[Event] = Field(default_factory=list)
    bus: BusConfig = BusConfig()
    plant: PlantConfig = PlantConfig()
    ecu: EcuConfig = EcuConfig()
    safety: SafetyConfig = SafetyConfig()
    security: SecurityConfig | None = Field(None, description="authentication of commands and simulation control "
                                                             "(null: off)")

    @model_validator(mode="before")
    @classmethod
    def _moved(cls, data: Any) -> Any:
        """Keys that moved into ``train:`` (the component schema) say where they went."""
        if isinstance(data, dict):
            for k, why in MOVED_TOP.items():
                if k in data:
                    raise ValueError(f"@{k}: {why}")
        return data

    @property
    def consist(self) -> Any:
        """The train as its physics kernel takes it (internal; assembled from ``train``'s components)."""
        return self.train.kernel

    @property
    def actuator(self) -> ActuatorConfig:
        """Every car's brake/traction equipment of a coupled (Chen-coupler) train, as the kernel
        takes it (the brake component and train.wheel_rail); the default for other trains."""
        return getattr(self.consist, "actuator", None) or ActuatorConfig()

    @model_validator(mode="after")
    def _per_car_lengths(self) -> "Scenario":
        n = self.n_cars
        checks: list[tuple[str, Any, int]] = [("initial.speed_kmh", self.initial.speed_kmh, n)]
        self._check_placement()
        if not isinstance(self.consist, TrainConfig):
            if self.initial.position_m is not None:
                checks.append(("initial.position_m", self.initial.position_m, n))
            for name, value, k in checks:
                per_car(value, k, name)
            return self._check_times()
        checks += [
            ("train.track.curve_resistance_n", self.train.track.curve_resistance_n, n),
            ("train.wheel_rail.adhesion_mu", self.train.wheel_rail.adhesion_mu, n),
        ]
        if self.initial.position_m is not None:
            checks.append(("initial.position_m", self.initial.position_m, n))
        self._check_easing()
        if self.consist.rigid and self.events:
            raise ValueError("@events.0: a rigidly coupled train (coupler: {model: rigid}) takes no events yet (its "
                             "rail conditions over time are train.wheel_rail.windows)")
        for i, ev in enumerate(self.events):
            for fname in ("brake_factor", "adhesion_mu", "amplitude_n", "bias_n"):
                if hasattr(ev, fname) and getattr(ev, fname) is not None:
                    checks.append((f"events.{i}.{fname}", getattr(ev, fname), n))
        wrong = [(name, len(value)) for name, value, k in checks if isinstance(value, list) and len(value) != k]
        lengths = {m for _, m in wrong}
        if wrong and len(lengths) == 1 and len(wrong) >= 2:
            # every per-car list agrees on another train length: the mass list is the odd one out
            m = lengths.pop()
            raise ValueError(f"@train.vehicles: has {n} cars, but {', '.join(nm for nm, _ in wrong)} "
                             f"{'have' if len(wrong) > 1 else 'has'} {m} values: fix the mass list or those")
        for name, value, k in checks:
            per_car(value, k, name)
        self._check_spacing()
        return self._check_times()

    def _check_easing(self) -> None:
        """Easing anticipates the brake's lag: its time constant must be longer (canbrake.control.brake_functions)."""
        b = self.consist.brakes
        if b is None or b.easing is None:
            return
        from canbrake.consist.brakes import car_easing_lag_s, easing_lag_s

        if b.cars is not None:  # each car's easing anticipates its own lag
            for i, c in enumerate(b.cars):
                if c.easing is None:
                    continue
                lag = car_easing_lag_s(b, self.actuator, i)
                if not c.easing.time_constant_s > lag:
                    raise ValueError(f"@train.vehicle_types.{c.vehicle_type}.brake.easing.time_constant_s: must exceed "
                                     f"the brake lag it anticipates ({lag:g} s: brake.lag_s + "
                                     f"brake.blending.friction_lag_s, or easing.lag_s), got {c.easing.time_constant_s:g}")
            return

        lag = easing_lag_s(b, self.actuator)
        if not b.easing.time_constant_s > lag:
            raise ValueError(f"@train.every_vehicle.brake.easing.time_constant_s: must exceed the brake lag it "
                             f"anticipates ({lag:g} s: brake.lag_s + brake.blending.friction_lag_s, or easing.lag_s), "
                             f"got {b.easing.time_constant_s:g}")

    def _check_spacing(self) -> None:
        """Initial positions and a given coupler spacing must agree: a coupler that would start
        deflected by more than its own spacing means the positions list the cars in the other order."""
        sp, pos = self.consist.coupler.spacing_m, self.initial.position_m
        if sp is None or pos is None or self.n_cars < 2:
            return
        s = per_car(sp, self.n_cars - 1, "spacing")
        dl = np.asarray(pos[:-1], dtype=float) - np.asarray(pos[1:], dtype=float) - s
        bad = np.flatnonzero(np.abs(dl) > np.abs(s))
        if bad.size:
            j = int(bad[0])
            raise ValueError(f"initial.position_m: coupler {j + 1} (cars {j + 1}-{j + 2}) would start deflected by "
                             f"{dl[j]:g} m, more than its spacing {s[j]:g} m (the vehicle types' length_m, with car 1 "
                             f"leading); list the positions with car 1 in front or fix the lengths")

    def min_control_period_s(self) -> tuple[float, str]:
        """The shortest control period (s) a CAN bus can carry, and the field of the bit rate it
        follows from: every period begins with the plant's SYNC frame, so a period lasts at least
        that frame's wire time (worst-case stuffing and the interframe space, bus/timing.py) at
        the slowest bit rate the SYNC crosses (``bus.bitrate_bps``, ``bus.segments``). Whether the
        rest of a period's traffic fits is the bus load's business (the ``overloaded`` finding)."""
        from canbrake.bus.dbc import SYNC_DLC, SYNC_ID
        from canbrake.bus.timing import frame_bits

        rates = [(self.bus.bitrate_bps, "bus.bitrate_bps")] + [
            (sg.bitrate_bps, f"bus.segments.{i}.bitrate_bps") for i, sg in enumerate(self.bus.segments)
            if sg.bitrate_bps is not None]
        rate, field = min(rates)
        return frame_bits(SYNC_ID, False, SYNC_DLC, stuffing="worst") / rate, field

    def _check_times(self) -> "Scenario":
        t_min, rate_field = self.min_control_period_s()
        if self.control_period_s < t_min:
            from canbrake.bus.dbc import SYNC_DLC

            rate = min(r for r in [self.bus.bitrate_bps, *(sg.bitrate_bps for sg in self.bus.segments)] if r)
            raise ValueError(f"@control_period_s: {self.control_period_s:g} s is shorter than the SYNC frame that "
                             f"begins every period takes on the bus: {round(t_min * rate)} bit times ({SYNC_DLC} "
                             f"data bytes, worst-case stuffing, interframe space) = {t_min * 1e6:g} us at "
                             f"{rate / 1e3:g} kbit/s ({rate_field}); the control period must be at least "
                             f"{t_min * 1e6:g} us")
        if self.time_scale != 1.0 and self.mode != "realtime":
            raise ValueError("@time_scale: only used in realtime mode (mode: realtime, --mode realtime)")
        t_out = self.safety.command_timeout_s
        if t_out is not None and t_out < self.control_period_s:
            raise ValueError(f"safety.command_timeout_s ({t_out}) is shorter than one control period "
                             f"({self.control_period_s} s)")
        if self.duration_s < self.control_period_s:
            raise ValueError(f"@duration_s: {self.duration_s:g} s is shorter than one control period "
                             f"({self.control_period_s:g} s)")
        if self.duration_s / self.control_period_s > 10_000_000:
            raise ValueError(f"@duration_s: {self.duration_s:g} s / control_period_s {self.control_period_s:g} s "
                             f"exceeds 10 million ticks")
        return self

    def _check_placement(self) -> None:
        placed = self.placement()
        n = self.n_cars
        names = [p.name for p in placed]
        for p in placed:
            if not 1 <= p.vehicle <= n:
                raise ValueError(f"ecus: ECU {p.name} is on vehicle {p.vehicle}, the train has {n}")
            if isinstance(p.listens, list):
                unknown = [x for x in p.listens if x not in names]
                if unknown:
                    raise ValueError(f"ecus: ECU {p.name} listens to unknown ECU(s) {', '.join(unknown)} "
                                     f"(ECUs: {', '.join(names)})")
        if len(set(names)) != len(names):
            dup = sorted({x for x in names if names.count(x) > 1})
            raise ValueError(f"ecus: ECU name(s) used twice: {', '.join(dup)}")
        veh = [p.vehicle for p in placed]
        if len(set(veh)) != len(veh):
            dup = sorted({x for x in veh if veh.count(x) > 1})
            raise ValueError(f"ecus: more than one ECU on vehicle(s) {', '.join(map(str, dup))}")
        check = getattr(self.consist, "check_ecus", None)  # what the kernel's vehicles can take
        if check is not None:
            check(placed, dt_s=self.control_period_s)
        if self.ecu.crash is not None and self.ecu.crash.car not in veh:
            raise ValueError(f"ecu.crash.car: no ECU on vehicle {self.ecu.crash.car}")
        if self.safety.failsafe_commands:
            from canbrake.control.base import controller_class
            sent = set()
            for p in placed:
                sent.update(getattr(controller_class(p.controller.name), "command_names", ("brake_force_n",)))
            unknown = sorted(set(self.safety.failsafe_commands) - sent)
            if unknown:
                raise ValueError(f"safety.failsafe_commands: {', '.join(unknown)} is not a command of any ECU "
                                 f"(commands: {', '.join(sorted(sent))})")

    def placement(self) -> list["PlacedEcu"]:
        """Every ECU of the run in identifier-plan order (index 1..): name, vehicle, controller, listens."""
        if not self.ecus:
            return [PlacedEcu(f"ecu{v}", v, self.controller, "all") for v in range(1, self.n_cars + 1)]
        out: list[PlacedEcu] = []
        for i, e in enumerate(self.ecus):
            try:
                vs = e.vehicle_numbers()
            except ValueError as err:
                raise ValueError(f"ecus.{i}.vehicles: {err}") from None
            for v in vs:
                name = (e.name or "ecu{v}").replace("{v}", str(v))
                if e.vehicles is not None and e.name is not None and "{v}" not in e.name and len(vs) > 1:
                    raise ValueError(f"ecus.{i}.name: a range of vehicles needs {{v}} in the name")
                out.append(PlacedEcu(name, v, e.controller or self.controller, e.listens, e.external))
        return out

    # --- SI accessors -------------------------------------------------------------------
    @property
    def n_cars(self) -> int:
        """Number of vehicles of the consist."""
        return int(self.consist.vehicle_count())

    @property
    def n_ecus(self) -> int:
        return len(self.placement())

    def vehicle_masses_kg(self) -> np.ndarray:
        return np.asarray(self.consist.vehicle_masses_kg(), dtype=float)

    @property
    def n_ticks(self) -> int:
        """Number of control periods simulated."""
        return int(round(self.duration_s / self.control_period_s))

    def initial_speed_mps(self) -> np.ndarray:
        return per_car(self.initial.speed_kmh, self.n_cars, "initial.speed_kmh") * KMH

    def initial_position_m(self) -> np.ndarray:
        if self.initial.position_m is not None:
            return np.asarray(self.initial.position_m, dtype=float)
        sp = self.consist.coupler.spacing_m
        spacing = per_car(10.0 if sp is None else sp, max(self.n_cars - 1, 0), "spacing")
        # car 1 leads: x_1 > x_2 > ... with x_i - x_{i+1} = spacing_i
        x = np.zeros(self.n_cars)
        for i in range(1, self.n_cars):
            x[i] = x[i - 1] - spacing[i - 1]
        return x - x[-1]

    #: folder of the scenario file: data files named in it are relative to it (None: the cwd)
    base_dir: str | None = Field(None, description="set by the loader: folder the data files are relative to")

    def data_dir(self) -> Path | None:
        return None if self.base_dir is None else Path(self.base_dir)

    def to_yaml(self) -> str:
        """Resolved scenario (defaults filled in) as YAML."""
        data = self.model_dump(mode="json")
        return yaml.safe_dump(data, sort_keys=False)


def mark_external(data: dict[str, Any], names: list[str], source: str = "--external") -> dict[str, Any]:
    """Scenario mapping ``data`` with the ECUs ``names`` made external (``--external ecu3``). A
    scenario without ``ecus:`` gets Chen's placement written out (ecu1..ecuN, one per vehicle)."""
    data = copy.deepcopy(data)
    if not names:
        return data
    if not data.get("ecus"):
        try:
            n = Scenario.model_validate(data).n_cars
        except ValidationError:
            return data  # the scenario's own error is reported by resolve()
        data["ecus"] = [{"name": f"ecu{v}", "vehicle": v} for v in range(1, n + 1)]
    entries = data["ecus"]
    known = []
    for name in names:
        hit = None
        for e in entries:
            if not isinstance(e, dict):
                continue
            own = e.get("name") or ("ecu{v}" if e.get("vehicles") else f"ecu{e.get('vehicle')}")
            if e.get("vehicle") is not None:
                own = own.replace("{v}", str(e["vehicle"]))
            if own == name:
                hit = e
            known.append(own)
        if hit is None:
            raise ScenarioError(f"{source} {name}: no ECU of that name in the placement (ECUs: "
                                f"{', '.join(dict.fromkeys(known))}); an ECU of a vehicle range is made external "
                                f"in the scenario file (ecus: ... external: true)")
        hit["external"] = True
    return data


def _deep_merge(base: dict[str, Any], override: dict[str, Any]) -> dict[str, Any]:
    out = copy.deepcopy(base)
    for k, v in override.items():
        if isinstance(v, dict) and isinstance(out.get(k), dict):
            out[k] = _deep_merge(out[k], v)
        else:
            out[k] = copy.deepcopy(v)
    return out


def _label(key: str, labels: Mapping[str, str] | None) -> str:
    """How the user gave the override ``key``: ``--set KEY`` unless ``labels`` names it (a
    command-line flag such as ``--duration``, or an API keyword argument)."""
    return (labels or {}).get(key) or f"--set {key}"


def _set_dotted(data: dict[str, Any], dotted: str, value: Any, labels: Mapping[str, str] | None = None) -> None:
    keys = dotted.split(".")
    label = _label(dotted, labels)
    cur: Any = data
    for depth, k in enumerate(keys):
        last = depth == len(keys) - 1
        if isinstance(cur, list):
            if not k.isdigit() or int(k) >= len(cur):
                raise ScenarioError(f"{label}: {k!r} is not an index of a list of {len(cur)}")
            if last:
                cur[int(k)] = value
            else:
                cur = cur[int(k)]
        elif isinstance(cur, dict):
            if last:
                cur[k] = value
            else:
                cur = cur.setdefault(k, {})
        else:
            raise ScenarioError(f"{label}: {'.'.join(keys[:depth])} is not a mapping or list")


def _check_new_vehicle_types(data: dict[str, Any], types_before: Mapping[str, Any], overrides: Mapping[str, Any],
                             labels: Mapping[str, str] | None) -> None:
    """A vehicle type an override creates (``--set train.vehicle_types.NAME.…`` with a NAME the
    scenario lacks) that no vehicle uses: most often a misspelt type name, which would otherwise
    change nothing at all. (A file may keep unused types; only an override's new one is refused.)"""
    train = data.get("train")
    if not isinstance(train, dict) or not isinstance(train.get("vehicles"), list):
        return
    used = {v.get("type") for v in train["vehicles"] if isinstance(v, dict)}
    for k in overrides:
        m = re.fullmatch(r"train\.vehicle_types\.([^.]+)(\..*)?", k)
        if m and m[1] not in types_before and m[1] not in used:
            known = ", ".join(sorted(str(t) for t in types_before)) or "none"
            raise ScenarioError(f"{_label(k, labels)}: the scenario has no vehicle type {m[1]!r} (its types: {known}) "
                                f"and no vehicle in train.vehicles is of that type, so it would change nothing")


def format_validation_error(source: str, err: ValidationError) -> str:
    """One readable message per problem: ``file: field.path: what is wrong``."""
    lines = []
    for e in err.errors():
        tags = {"rail", "disturbance"}
        loc = ".".join(str(p) for p in e["loc"] if not (isinstance(p, str) and p in tags))
        msg = e["msg"]
        if e["type"] == "extra_forbidden":
            msg = "unknown key"
        if msg.startswith("Value error, "):
            msg = msg[len("Value error, "):]
        if msg.startswith("@") and ": " in msg:  # a model validator naming the field it rejects
            sub, msg = msg[1:].split(": ", 1)
            loc = f"{loc}.{sub}" if loc else sub
        lines.append(f"{source}: {loc}: {msg}" if loc else f"{source}: {msg}")
    return "\n".join(lines)


def _controller_name(data: dict[str, Any]) -> Any:
    """The top-level controller's name in a scenario mapping (ControllerConfig's default if none)."""
    c = data.get("controller")
    default = ControllerConfig.model_fields["name"].default
    if c is None:
        return default
    return c.get("name", default) if isinstance(c, dict) else c  # not a mapping: validation says so


def _kept_params(old: Any, new: Any, params: dict[str, Any]) -> dict[str, Any]:
    """:func:`canbrake.control.base.inherited_params` (none for an unknown name: reported when the
    scenario is checked)."""
    from canbrake.control.base import inherited_params

    try:
        return inherited_params(old, new, params)
    except (ValueError, TypeError):  # ControllerError: unknown or broken; a name that is no string
        return {}


def _switch_controller(data: dict[str, Any], old: Any, name: Any, holder: dict[str, Any] | None = None) -> None:
    """Make ``name`` the top-level controller of ``data`` (or of ``holder``, an entry of ``ecus``)
    in place of ``old``, without ``old``'s
    parameters (:func:`_kept_params`). The scenario's deflection bound stays: when ``old``'s barrier
    bounds ``theta_lower_m``/``theta_upper_m`` were the bound (no ``safety.max_abs_deflection_m``)
    and do not carry over, they become ``safety.max_abs_deflection_m``, so every controller is judged
    against the same bound."""
    holder = data if holder is None else holder
    cur = holder.get("controller")
    params = cur.get("params") if isinstance(cur, dict) else None
    params = params if isinstance(params, dict) else {}
    kept = _kept_params(old, name, params) if params else {}
    lo, hi = params.get("theta_lower_m"), params.get("theta_upper_m")
    if "theta_lower_m" not in kept and all(isinstance(x, (int, float)) and not isinstance(x, bool) for x in (lo, hi)):
        safety = data.get("safety")
        if safety is None:
            safety = data["safety"] = {}
        if isinstance(safety, dict) and safety.get("max_abs_deflection_m") is None:
            safety["max_abs_deflection_m"] = float(min(abs(lo), abs(hi)))
    holder["controller"] = {"name": name, **({"params": kept} if kept else {})}


def _drop_stale_profile_params(data: dict[str, Any], written_for: Any) -> None:
    """Profiles' ``controller`` sections that name no controller hold parameters of the controller
    the document was written for (``written_for``): once the scenario runs an unrelated one
    (:func:`_kept_params`), they can never apply, and are dropped (a profile selected later must not
    bring them back)."""
    profiles = data.get("profiles")
    now = _controller_name(data)
    if now == written_for or not isinstance(profiles, dict):
        return
    for body in profiles.values():
        c = body.get("controller") if isinstance(body, dict) else None
        if isinstance(c, dict) and "name" not in c and isinstance(c.get("params"), dict):
            kept = _kept_params(written_for, now, c["params"])
            if kept:
                c["params"] = kept
            else:
                c.pop("params")
            if not c:
                body.pop("controller")


def resolve(data: dict[str, Any], source: str = "<scenario>", profile: str | None = None,
            overrides: dict[str, Any] | None = None, external: list[str] | None = None,
            labels: Mapping[str, str] | None = None) -> Scenario:
    """Validate a scenario mapping, applying a profile and dotted-key overrides. ``labels``: how
    the user gave an override, by its key (``{"duration_s": "--duration"}``), for the messages;
    default ``--set KEY``.

    Switching the controller by name (a profile's ``controller.name``, ``--set controller.name=X``)
    drops the previous controller's parameters (a controller derived from it keeps those it
    accepts); parameters given with the switch (the profile's, ``--set controller.params.K=V``)
    stay, and the profiles' parameters of the previous controller are dropped from the result
    (:func:`_switch_controller`, :func:`_drop_stale_profile_params`)."""
    if not isinstance(data, dict):
        raise ScenarioError(f"{source}: expected a mapping at the top level, got {type(data).__name__}")
    data = copy.deepcopy(data)
    written_for = _controller_name(data)
    profile = profile or data.get("profile")
    profiles = data.get("profiles") or {}
    if profile is not None:
        if not isinstance(profiles, dict) or profile not in profiles:
            known = ", ".join(sorted(profiles)) if isinstance(profiles, dict) and profiles else "none"
            raise ScenarioError(f"{source}: profile {profile!r} is not defined (profiles: {known})")
        if not isinstance(profiles[profile], dict):
            raise ScenarioError(f"{source}: profiles.{profile}: expected a mapping")
        pc = profiles[profile].get("controller")
        if isinstance(pc, dict) and "name" in pc and pc["name"] != written_for:
            _switch_controller(data, written_for, pc["name"])
        data = _deep_merge(data, profiles[profile])
        data["profile"] = profile
    overrides = overrides or {}
    before = _controller_name(data)
    ecus_before = {}  # an ECU's own controller switched by name (--set ecus.N.controller.name=X): as below
    for k in overrides:
        m = re.fullmatch(r"ecus\.(\d+)\.controller\.name", k)
        entries = data.get("ecus")
        if m and isinstance(entries, list) and int(m[1]) < len(entries) and isinstance(entries[int(m[1])], dict) \
                and isinstance(entries[int(m[1])].get("controller"), dict):
            ecus_before[int(m[1])] = entries[int(m[1])]["controller"].get("name")
    train0 = data.get("train") if isinstance(data.get("train"), dict) else {}
    types0 = dict(train0["vehicle_types"]) if isinstance(train0.get("vehicle_types"), dict) else {}
    for k, v in overrides.items():
        _set_dotted(data, k, v, labels)
    _check_new_vehicle_types(data, types0, overrides, labels)
    after = _controller_name(data)
    if after != before and "controller" not in overrides and isinstance(data.get("controller"), dict):
        given = {k: v for k, v in overrides.items() if k == "controller.params" or k.startswith("controller.params.")}
        _switch_controller(data, before, after)
        for k, v in given.items():
            _set_dotted(data, k, v, labels)
    for i, old_name in ecus_before.items():
        entry = data["ecus"][i]
        new_name = entry["controller"].get("name") if isinstance(entry.get("controller"), dict) else None
        if new_name != old_name and f"ecus.{i}.controller" not in overrides:
            given = {k: v for k, v in overrides.items() if k.startswith(f"ecus.{i}.controller.params")}
            _switch_controller(data, old_name, new_name, holder=entry)
            for k, v in given.items():
                _set_dotted(data, k, v, labels)
    _drop_stale_profile_params(data, written_for)
    if external:
        data = mark_external(data, list(external))
    try:
        scn = Scenario.model_validate(data)
    except ValidationError as e:
        raise ScenarioError(blame_overrides(format_validation_error(source, e), source, overrides or {},
                                            labels)) from None
    unused = [k for k in overrides if k == "controller" or k.startswith("controller.")]
    if unused and scn.ecus and all(e.controller is not None for e in scn.ecus):  # it would change nothing
        label = (labels or {}).get(unused[0], f"--set {unused[0]}")
        raise ScenarioError(f"{label}: no ECU of {source} runs the top-level controller: every entry of ecus "
                            f"has its own (set ecus.0.controller.{unused[0].partition('.')[2] or 'name'} instead)")
    return scn


def blame_overrides(message: str, source: str, overrides: dict[str, Any],
                    labels: Mapping[str, str] | None = None) -> str:
    """A problem in a field set with ``--set KEY=VALUE`` names ``--set KEY``, not the file (or
    the flag or keyword that set it, from ``labels``: ``--duration: must be > 0``)."""
    out: list[str] = []
    for line in message.splitlines():
        rest = line[len(source) + 2:] if line.startswith(f"{source}: ") else line
        field = rest.split(": ", 1)[0]
        # train.every_vehicle is merged over every vehicle type: its problems show in each type
        per_type = re.fullmatch(r"train\.vehicle_types\.[^.]+\.(.+)", field)
        every = f"train.every_vehicle.{per_type.group(1)}" if per_type else None
        key = next((k for k in sorted(overrides, key=len, reverse=True)
                    if field == k or field.startswith(k + ".") or k.startswith(field + ".")
                    or (every is not None and (every == k or every.startswith(k + ".")))), None)
        if key is None:  # not a field an override set; one in the same section may still have caused it
            near = [_label(k, labels) for k in overrides if k.split(".", 1)[0] == field.split(".", 1)[0]]
            text = f"{line} (with {', '.join(near)})" if near and line.startswith(f"{source}: ") else line
        elif key != field and not (every is not None and every == key):
            text = f"{_label(key, labels)}: {rest}"
        else:
            text = f"{_label(key, labels)}: {rest.split(': ', 1)[1] if ': ' in rest else rest}"
        if text not in out:  # the same override's problem once, not once per vehicle type
            out.append(text)
    return "\n".join(out)


class DuplicateKeyError(yaml.constructor.ConstructorError):
    """A mapping that names a key twice (``key``, 1-based ``first_line`` and ``line``)."""

    def __init__(self, key: Any, first_line: int, node: yaml.Node) -> None:
        super().__init__(None, None, f"duplicate key {key!r} (line {node.start_mark.line + 1}, first at "
                                     f"line {first_line})", node.start_mark)
        self.key, self.first_line, self.line = key, first_line, node.start_mark.line + 1


class StrictLoader(yaml.SafeLoader):
    """YAML's safe loader, strict: no anchors/aliases (a few hundred bytes of nested aliases
    expand to gigabytes, a "billion laughs", and a scenario has no need for them) and no key
    twice in one mapping (PyYAML keeps the last value silently; a scenario that says ``seed: 1``
    and later ``seed: 2`` is refused rather than guessed at). Every scenario, ``--set`` value
    and ``--grid`` value is read with it."""

    def compose_node(self, parent: Any, index: Any) -> Any:  # noqa: D102
        if self.check_event(yaml.AliasEvent):
            ev = self.peek_event()
            raise yaml.composer.ComposerError(None, None, f"YAML aliases (*{ev.anchor}) are not supported in "
                                              "scenarios; write the values out", ev.start_mark)
        return super().compose_node(parent, index)

    def construct_mapping(self, node: yaml.MappingNode, deep: bool = False) -> dict[Any, Any]:  # noqa: D102
        if isinstance(node, yaml.MappingNode):
            seen: dict[Any, int] = {}
            for key_node, _ in node.value:
                if key_node.tag == "tag:yaml.org,2002:merge":
                    continue  # `<<:` merges are overridden by the mapping's own keys, as YAML says
                key = self.construct_object(key_node, deep=True)
                try:
                    if key in seen:
                        raise DuplicateKeyError(key, seen[key], key_node)
                    seen[key] = key_node.start_mark.line + 1
                except TypeError:
                    continue  # an unhashable key: SafeConstructor reports it
        return super().construct_mapping(node, deep)


def load_yaml(text: str) -> Any:
    """``text`` parsed with :class:`StrictLoader` (raises yaml.YAMLError)."""
    return yaml.load(text, Loader=StrictLoader)  # noqa: S506 - a SafeLoader, stricter




def load_scenario(path: str | Path, profile: str | None = None,
                  overrides: dict[str, Any] | None = None, external: list[str] | None = None,
                  labels: Mapping[str, str] | None = None) -> Scenario:
    """Read and validate a scenario file, or the built-in scenario of that name
    (:func:`canbrake.builtin.find_scenario`); raises :class:`ScenarioError` with a clear message.
    ``labels``: how the user gave each override (:func:`resolve`)."""
    from canbrake.builtin import find_scenario

    p = find_scenario(path)
    try:
        text = p.read_text()
    except FileNotFoundError:
        raise ScenarioError(f"{p}: no such scenario file") from None
    except (OSError, UnicodeDecodeError) as e:
        raise ScenarioError(f"{p}: cannot read: {e}") from None
    try:
        data = load_yaml(text)
    except DuplicateKeyError as e:
        raise ScenarioError(f"{p}: line {e.line}: duplicate key {e.key!r}, first at line {e.first_line} "
                            f"(a key may appear once per mapping)") from None
    except yaml.YAMLError as e:
        mark = getattr(e, "problem_mark", None)
        where = f" (line {mark.line + 1}, column {mark.column + 1})" if mark else ""
        problem = getattr(e, "problem", None) or str(e).splitlines()[0]
        raise ScenarioError(f"{p}: malformed YAML{where}: {problem}") from None
    if isinstance(data, dict) and "base_dir" not in data:
        data["base_dir"] = str(p.resolve().parent)
    return resolve(data, str(p), profile, overrides, external, labels)
