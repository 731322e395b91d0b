"""Build physics, controllers and nodes from a validated :class:`~canbrake.scenario.Scenario`.

The one place where scenario fields (edge units) are mapped onto the constructors of the
physics, control and node layers (SI).
"""
from __future__ import annotations

import math
from pathlib import Path
from typing import Any

import numpy as np

from canbrake.bus import dbc
from canbrake.bus.codec import FrameCodec
from canbrake.control.base import Controller, make_controller
from canbrake.nodes.base import Node, PassThrough, SendPath
from canbrake.scenario import Scenario, per_car


def reference_fn(scn: Scenario):
    """v*(t) = max(v0 - a* t, 0) and a* while v* > 0 (m/s, m/s²)."""
    v0, a = scn.reference.speed_mps, scn.reference.decel_mps2

    def ref(t_s: float) -> tuple[float, float]:
        v = v0 - a * t_s
        return (v, a) if v > 0 else (0.0, 0.0)

    return ref


def build_plant_model(scn: Scenario):
    """The physics plant of ``scn`` (a :class:`canbrake.physics.train.TrainPlant`)."""
    from canbrake.physics.actuator import BrakeActuator
    from canbrake.physics.rail import DisturbanceForce, RailConditions, RailEvent
    from canbrake.physics.resistance import DavisResistance
    from canbrake.physics.train import TrainPlant

    n = scn.n_cars
    t = scn.train
    resistance = None
    if t.davis is not None:
        resistance = DavisResistance(per_car(t.davis.c0_n, n, "c0"), per_car(t.davis.c1_n_s_per_m, n, "c1"),
                                     per_car(t.davis.c2_n_s2_per_m2, n, "c2"))
    a = scn.actuator
    inf = math.inf
    if a.model == "ideal":
        actuator = BrakeActuator(kind="ideal", adhesion_limited=a.adhesion_limited,
                                 brake_rating_mps2=a.max_brake_decel_mps2 or inf,
                                 traction_rating_mps2=inf if a.max_traction_accel_mps2 is None else a.max_traction_accel_mps2)
    else:
        actuator = BrakeActuator(kind="realistic", time_constant_s=a.lag_s,
                                 jerk_limit_mps3=a.jerk_limit_mps3 or inf,
                                 brake_rating_mps2=a.max_brake_decel_mps2 or inf,
                                 traction_rating_mps2=inf if a.max_traction_accel_mps2 is None else a.max_traction_accel_mps2,
                                 adhesion_limited=a.adhesion_limited)
    rail_events = []
    disturbances = []
    for ev in scn.events:
        end = inf if ev.stop_s is None else ev.stop_s
        if ev.type == "rail":
            rail_events.append(RailEvent(start_s=ev.start_s, end_s=end,
                                         adhesion_mu=None if ev.adhesion_mu is None else per_car(ev.adhesion_mu, n, "mu"),
                                         brake_effectiveness=per_car(ev.brake_factor, n, "brake_factor")))
        else:
            disturbances.append(DisturbanceForce(amplitude_n=per_car(ev.amplitude_n, n, "amplitude"),
                                                 frequency_hz=ev.frequency_hz, start_s=ev.start_s, end_s=end,
                                                 offset_n=per_car(ev.bias_n, n, "bias"), phase_rad=ev.phase_rad))
    c = t.coupler
    return TrainPlant(
        t.mass_kg, scn.initial_position_m(), scn.initial_speed_mps(),
        coupler_stiffness_n_per_m=c.stiffness_n_per_m if n > 1 else [],
        coupler_nonlinearity_per_m2=c.epsilon_per_m2 if n > 1 else [],
        coupler_spacing_m=c.spacing_m, end_stop_m=c.end_stop_m,
        resistance=resistance, grade_rad=math.atan(t.grade_permille / 1000.0),
        curve_resistance_n=per_car(t.curve_resistance_n, n, "curve"),
        actuator=actuator, rail=RailConditions(base_adhesion_mu=per_car(a.adhesion_mu, n, "mu"), events=rail_events),
        disturbances=disturbances, max_substep_s=scn.control_period_s / scn.plant.substeps,
    )


def needs_barrier(scn: Scenario) -> bool:
    """Lockstep needs the *_DONE barrier frames only when a frame can be lost, delayed or late."""
    return bool(scn.bus.impairments) or scn.bus.timing == "model"


def build_controller(scn: Scenario, car: int) -> Controller:
    """Controller of car ``car`` (1-based)."""
    return make_controller(scn.controller.name, scn.controller.params, car_index=car - 1, n_cars=scn.n_cars,
                           mass_kg=scn.train.mass_kg[car - 1], dt_s=scn.control_period_s)


def build_send_path(scn: Scenario, node: str) -> SendPath:
    """The impairment chain of one sending node (pass-through when none applies)."""
    if not scn.bus.impairments:
        return PassThrough()
    from canbrake.bus.sendpath import build_send_path as _build

    return _build(scn, node)


def build_rx_path(scn: Scenario, node: str) -> Any:
    """Per-link impairments on what ``node`` receives (specs with ``receivers``), or None."""
    if not any(getattr(s, "receivers", None) and node in s.receivers for s in scn.bus.impairments):
        return None
    from canbrake.bus.impair import build_impairments

    return build_impairments(scn.bus.impairments, scn.seed, node, direction="rx")


def hosted_babblers(scn: Scenario) -> list[SendPath]:
    """Send paths of babbling nodes that are not ECUs (e.g. a rogue device): the plant hosts them,
    releasing their frames at each tick start."""
    if not scn.bus.impairments:
        return []
    from canbrake.bus.impair import babbling_nodes

    real = {f"ecu{c}" for c in range(1, scn.n_cars + 1)}
    return [build_send_path(scn, name) for name in babbling_nodes(scn.bus.impairments) if name not in real]


class PlantAdapter:
    """Presents a :class:`TrainPlant` as the plant node's :class:`~canbrake.nodes.plant.PlantModel`."""

    def __init__(self, plant: Any) -> None:
        self.plant = plant
        self.n_cars = plant.n_cars

    def step(self, dt_s: float, brake_force_cmd_n: np.ndarray) -> None:
        self.plant.step(dt_s, brake_force_cmd_n)

    def measurements(self) -> dict[str, np.ndarray]:
        s = self.plant.snapshot()
        return {"position_m": s.position_m, "speed_mps": s.speed_mps, "accel_mps2": s.accel_mps2,
                "applied_brake_n": s.applied_force_n, "deflection_m": s.deflection_m,
                "coupler_force_n": s.coupler_force_n}


def failsafe_of(scn: Scenario) -> Any:
    """The plant's fail-safe reaction from ``safety`` (None when off)."""
    from canbrake.nodes.plant import FailSafe

    sf = scn.safety
    if sf.command_timeout_s is None:
        return None
    mass = np.asarray(scn.train.mass_kg, dtype=float)
    return FailSafe(timeout_ticks=max(1, int(round(sf.command_timeout_s / scn.control_period_s))),
                    force_n=mass * sf.failsafe_decel_mps2, latch=sf.latch)


def build_node(scn: Scenario, role: str, *, car: int = 0, run_dir: Path | None, channel: str = "can0",
               progress: Any = None, codec: FrameCodec | None = None, bus_timing: Any = "build") -> Node:
    """One node of the run: ``role`` is "plant", "ecu" (with ``car``) or "recorder"."""
    codec = codec or FrameCodec(dbc.build_database(scn.n_cars))
    if role == "plant":
        from canbrake.nodes.plant import PlantNode

        return PlantNode(PlantAdapter(build_plant_model(scn)), codec, dt_s=scn.control_period_s,
                         n_ticks=scn.n_ticks, reference=reference_fn(scn), mode=scn.mode,
                         coupler_sensors=scn.plant.coupler_sensors, heartbeat_period_s=scn.ecu.heartbeat_period_s,
                         out_dir=run_dir, progress=progress, hosted=hosted_babblers(scn),
                         barrier=needs_barrier(scn), failsafe=failsafe_of(scn))
    if role == "ecu":
        from canbrake.nodes.ecu import EcuNode

        if bus_timing == "build":
            from canbrake.bus.schedule import build_bus_timing

            bus_timing = build_bus_timing(scn)
        return EcuNode(car, scn.n_cars, build_controller(scn, car), codec, dt_s=scn.control_period_s,
                       bus_timing=bus_timing, barrier=needs_barrier(scn), rx_path=build_rx_path(scn, f"ecu{car}"),
                       mode=scn.mode, send_path=build_send_path(scn, f"ecu{car}"),
                       heartbeat_period_s=scn.ecu.heartbeat_period_s,
                       compute_deadline=scn.ecu.realtime_compute_deadline, out_dir=run_dir,
                       lockstep_deadline=scn.ecu.lockstep_deadline,
                       crash_at_tick=(int(round(scn.ecu.crash.at_s / scn.control_period_s))
                                      if scn.ecu.crash is not None and scn.ecu.crash.car == car else None))
    if role == "recorder":
        from canbrake.nodes.recorder import RecorderNode

        return RecorderNode(scn.n_cars, dt_s=scn.control_period_s, bitrate_bps=scn.bus.bitrate_bps, mode=scn.mode,
                            plant_io_on_bus=scn.bus.plant_io_on_bus, barrier=needs_barrier(scn),
                            log_path=None if run_dir is None else run_dir / f"frames.{scn.bus.log_format}",
                            channel=channel)
    raise ValueError(f"unknown node role {role!r}")


def build_nodes(scn: Scenario, run_dir: Path | None, channel: str = "can0") -> list[Node]:
    """Every node of a run, plant last (it starts the first tick)."""
    from canbrake.bus.schedule import build_bus_timing

    codec = FrameCodec(dbc.build_database(scn.n_cars))
    timing = build_bus_timing(scn)  # one replica serves every node of an in-process run
    nodes: list[Node] = [build_node(scn, "recorder", run_dir=run_dir, channel=channel, codec=codec)]
    nodes += [build_node(scn, "ecu", car=c, run_dir=run_dir, codec=codec, bus_timing=timing)
              for c in range(1, scn.n_cars + 1)]
    nodes.append(build_node(scn, "plant", run_dir=run_dir, codec=codec))
    return nodes
