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


class Reference:
    """v*(t), a*(t) (a* > 0 slows down) and x*(t) of the scenario's reference, SI.

    Calling it gives ``(v*, a*)`` at ``t_s``; :meth:`position` gives x*. A ramp is exact; a table
    is interpolated linearly in time (``over: position`` tables are first turned into a time table
    by integrating dt = dx / v on a fine grid) and x* is its exact integral (trapezoids)."""

    def __init__(self, scn: Scenario) -> None:
        r = scn.reference
        self.kind = r.kind
        self.x0 = float(r.position_m)
        if r.kind == "ramp":
            self.v0, self.a = r.speed_mps, r.decel_mps2
            self.v_end = r.target_kmh / 3.6
            self.t_end = abs(self.v0 - self.v_end) / abs(self.a) if self.a != 0 else math.inf
            return
        from canbrake.consist.base import DataFileError, load_table

        try:
            if r.over == "time":
                tab = load_table(r.file, ("time_s", "speed_kmh"), scn.data_dir())  # type: ignore[arg-type]
                t, v = tab["time_s"], tab["speed_kmh"] / 3.6
            else:
                tab = load_table(r.file, ("position_m", "speed_kmh"), scn.data_dir())  # type: ignore[arg-type]
                x, vx = tab["position_m"], tab["speed_kmh"] / 3.6
                if np.any(np.diff(x) <= 0) or np.any(vx <= 0):
                    raise DataFileError(f"{r.file}: position_m must increase and speed_kmh be > 0 for a "
                                        f"reference over position")
                dt = np.diff(x) * 2.0 / (vx[1:] + vx[:-1])
                t, v = np.concatenate([[0.0], np.cumsum(dt)]), vx
                self.x0 = float(x[0]) if r.position_m == 0.0 else self.x0
        except DataFileError as e:
            raise ValueError(f"reference.file: {e}") from None
        if t.size < 2 or np.any(np.diff(t) <= 0):
            raise ValueError(f"reference.file: {r.file}: time_s must increase (at least two rows)")
        if np.any(v < 0):
            raise ValueError(f"reference.file: {r.file}: negative speed")
        self.t, self.v = t - t[0], v
        self.slope = np.diff(v) / np.diff(self.t)
        self.cumx = np.concatenate([[0.0], np.cumsum(0.5 * (v[1:] + v[:-1]) * np.diff(self.t))])

    def __call__(self, t_s: float) -> tuple[float, float]:
        if self.kind == "ramp":
            if t_s >= self.t_end:
                return self.v_end, 0.0
            return self.v0 - self.a * t_s, self.a
        i = int(np.searchsorted(self.t, t_s, side="right")) - 1
        if i >= self.t.size - 1:
            return float(self.v[-1]), 0.0
        i = max(i, 0)
        return float(self.v[i] + self.slope[i] * (t_s - self.t[i])), float(-self.slope[i])

    def position(self, t_s: float) -> float:
        """x*(t_s) (m)."""
        if self.kind == "ramp":
            te = min(t_s, self.t_end)
            x = self.v0 * te - 0.5 * self.a * te * te
            return self.x0 + x + self.v_end * max(0.0, t_s - self.t_end)
        i = int(np.searchsorted(self.t, t_s, side="right")) - 1
        if i >= self.t.size - 1:
            return self.x0 + float(self.cumx[-1] + self.v[-1] * (t_s - self.t[-1]))
        i = max(i, 0)
        dt = t_s - self.t[i]
        return self.x0 + float(self.cumx[i] + self.v[i] * dt + 0.5 * self.slope[i] * dt * dt)


def reference_fn(scn: Scenario) -> Reference:
    """The scenario's reference (callable: t -> (v*, a*); ``.position(t)`` -> x*)."""
    return Reference(scn)


def build_plant_model(scn: Scenario) -> Any:
    """The physics plant of ``scn``: an object following :class:`canbrake.physics.contract.PlantModel`."""
    return scn.train.assemble(scn, scn.data_dir())


def build_coupled_plant(scn: Scenario) -> "CoupledPlant":
    """The coupled (Chen) plant of ``scn`` behind the plant contract."""
    return CoupledPlant(_train_plant(scn))


def _train_plant(scn: Scenario):
    """The :class:`canbrake.physics.train.TrainPlant` of a coupled-train scenario."""
    from canbrake.physics.actuator import BrakeActuator
    from canbrake.physics.rail import DisturbanceForce, RailConditions, RailEvent
    from canbrake.physics.resistance import DavisResistance
    from canbrake.physics.train import TrainPlant

    n = scn.n_cars
    t = scn.consist
    resistance = None
    if t.davis is not None:
        resistance = DavisResistance(per_car(t.davis.c0_n, n, "c0"), per_car(t.davis.c1_n_s_per_m, n, "c1"),
                                     per_car(t.davis.c2_n_s2_per_m2, n, "c2"))
    a = scn.actuator
    inf = math.inf
    if a.model == "ideal":
        actuator = BrakeActuator(kind="ideal", adhesion_limited=a.adhesion_limited,
                                 brake_rating_mps2=a.per_car("max_brake_decel_mps2"),
                                 traction_rating_mps2=a.per_car("max_traction_accel_mps2"))
    else:
        actuator = BrakeActuator(kind="realistic",
                                 time_constant_s=tuple(float(x) for x in a.lag_s) if isinstance(a.lag_s, list) else a.lag_s,
                                 jerk_limit_mps3=a.per_car("jerk_limit_mps3"),
                                 brake_rating_mps2=a.per_car("max_brake_decel_mps2"),
                                 traction_rating_mps2=a.per_car("max_traction_accel_mps2"),
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
    if t.rigid:  # one body (Cai 2014): the front vehicle's speed and position, driven axles, rail schedule
        x = scn.initial.position_m
        x0 = 0.0 if x is None else float(np.asarray(x, dtype=float).reshape(-1)[0])
        return TrainPlant(
            t.mass_kg, np.full(n, x0), scn.initial_speed_mps(), resistance=resistance,
            coupler_stiffness_n_per_m=c.stiffness_n_per_m if n > 1 else [],
            coupler_nonlinearity_per_m2=c.epsilon_per_m2 if n > 1 else [],
            curve_resistance_n=per_car(t.curve_resistance_n, n, "curve"),
            max_substep_s=scn.control_period_s / scn.plant.substeps,
            resistance_table=None if t.resistance_table is None else [
                None if r is None else (r.speed_mps, r.force_n) for r in t.resistance_table],
            rigid=True, driven_axles=None if t.driven_axles is None else [
                None if a is None else a.physics() for a in t.driven_axles],
            rail_schedule=t.wheel_rail.schedule(), adhesion_curve=t.wheel_rail.curve,
            adhesion_v_floor_mps=t.wheel_rail.v_floor_mps)
    blending, wheels, valve_lag = _brake_equipment(scn)
    li = _li_parts(scn)
    x0 = li.pop("position_m") if "position_m" in li else scn.initial_position_m()
    return TrainPlant(
        t.mass_kg, x0, scn.initial_speed_mps(),
        coupler_stiffness_n_per_m=c.stiffness_n_per_m if n > 1 else [],
        coupler_nonlinearity_per_m2=c.epsilon_per_m2 if n > 1 else [],
        coupler_spacing_m=c.spacing_m, end_stop_m=c.end_stop_m,
        end_stop_stiffness_n_per_m=c.end_stop_stiffness_n_per_m, end_stop_absorption=c.end_stop_absorption,
        resistance=resistance, grade_rad=math.atan(t.grade_permille / 1000.0),
        curve_resistance_n=per_car(t.curve_resistance_n, n, "curve"),
        actuator=actuator, rail=RailConditions(base_adhesion_mu=per_car(a.adhesion_mu, n, "mu"), events=rail_events),
        disturbances=disturbances,
        max_substep_s=t.max_substep_s if t.max_substep_s is not None else scn.control_period_s / scn.plant.substeps,
        blending=blending, wheels=wheels, wsp_valve_lag_s=valve_lag,
        wsp_max_vent_s=_per_car_wsp(t.brakes, "max_vent_s", math.inf, n),
        resistance_table=None if t.resistance_table is None else [
            None if r is None else (r.speed_mps, r.force_n) for r in t.resistance_table],
        traction_envelope=None if t.traction_envelope is None else [
            None if e is None else e.physics() for e in t.traction_envelope],
        draft_gears=None if t.coupler_gear is None else [
            None if g is None else t.draft_gears[g].physics(g) for g in t.coupler_gear],
        air_brake=t.air_brake_physics(),
        air_braked=None if t.air_rigging is None else [r is not None for r in t.air_rigging],
        **li,
    )


def _li_parts(scn: Scenario) -> dict[str, Any]:
    """The coupled plant's arguments for Li 2024's line and locomotive (TrainPlant: route, static
    couplers, electric brake, adhesion, δ, eq. 40), only those set; with a route also ``position_m``:
    the first car at ``start_position_m``, the others behind it at their nominal spacings."""
    t = scn.consist
    out: dict[str, Any] = {}
    if t.route is not None:
        if scn.initial.position_m is not None:
            raise ValueError("initial.position_m: a train on a route is placed by train.start_position_m (the first "
                             "vehicle's centre on the route, the others behind it)")
        out["route"] = t.route.load(scn.data_dir())
        out["line_rule"] = t.route.line_rule()
        sp = np.asarray(per_car(10.0 if t.coupler.spacing_m is None else t.coupler.spacing_m, max(t.n_cars - 1, 0),
                                "spacing"), dtype=float)
        out["position_m"] = t.start_position_m - np.concatenate([[0.0], np.cumsum(sp)])
    if t.static_couplers:
        out["static_couplers"] = True
    if t.electric_brake_envelope:
        out["electric_brake_envelope"] = True
    if t.loco_adhesion is not None:
        out["loco_adhesion"] = [None if a is None else a.physics() for a in t.loco_adhesion]
    if t.uncertainty != 0.0:
        out["uncertainty"] = t.uncertainty
    d = t.disturbance
    if d is not None and d.enabled:
        on = np.zeros(t.n_cars, dtype=bool)
        on[[v - 1 for v in d.vehicles]] = True
        out["li_disturbance_on"], out["li_disturbance_coef"] = on, (d.c0_mps2, d.c1_mps2, d.c2)
    return out


def _brake_equipment(scn: Scenario) -> tuple[Any, Any, float]:
    """(blending, wheelsets, dump-valve lag) of a coupled train's brake equipment (``scn.consist.brakes``; None where absent)."""
    b = scn.consist.brakes
    if b is None:
        return None, None, 0.05
    from canbrake.physics.brakes import BrakeBlending, Wheelsets
    from canbrake.physics.wheel_adhesion import RailCondition

    blending = wheels = None
    if b.blending is not None and b.cars is not None:
        blending = _blending_per_car(b)
    elif b.blending is not None:
        e = b.blending
        ed_max: Any = e.ed_max_decel_mps2
        ed_power: Any = math.inf if e.ed_power_kw_per_t is None else e.ed_power_kw_per_t
        envelope = None
        if e.per_car is not None:  # each car's own ED brake (vehicle_types.<type>.ed_brake)
            nan = (math.nan,) * 5
            cars = [(ed_max, ed_power, nan) if c is None else (0.0, math.inf, nan) if c.model == "none"
                    else (c.max_decel_mps2, math.inf if c.power_kw_per_t is None else c.power_kw_per_t, nan)
                    if c.model == "per_mass" else (0.0, math.inf, c.row_si()) for c in e.per_car]
            ed_max, ed_power = tuple(float(c[0]) for c in cars), tuple(float(c[1]) for c in cars)
            if any(c is not None and c.model == "envelope" for c in e.per_car):
                envelope = tuple(c[2] for c in cars)
        blending = BrakeBlending(ed_max_decel_mps2=ed_max, ed_power_w_per_kg=ed_power,
                                 fade_start_mps=e.fade_start_kmh / 3.6, fade_end_mps=e.fade_end_kmh / 3.6,
                                 friction_lag_s=e.friction_lag_s, envelope=envelope)
    if b.wheels is not None:
        w = b.wheels
        curve = RailCondition(b1=w.b1, b2=w.b2, b3=w.b3, c1=w.c1, c2=w.c2, c3=w.c3, peak_mu0=1.0)
        axles: Any = w.axles
        radius: Any = w.radius_m
        inertia: Any = w.inertia_kgm2
        floor: Any = w.v_floor_mps
        curves: Any = curve
        if b.wheels_per_car is not None:  # per car; 0 axles: a car without wheels (its curve unused)
            cars = [c or w for c in b.wheels_per_car]
            axles = [0 if c is None else c.axles for c in b.wheels_per_car]
            radius = [1.0 if c is None else c.radius_m for c in b.wheels_per_car]
            inertia = [1.0 if c is None else c.inertia_kgm2 for c in b.wheels_per_car]
            curves = [RailCondition(b1=c.b1, b2=c.b2, b3=c.b3, c1=c.c1, c2=c.c2, c3=c.c3, peak_mu0=1.0) for c in cars]
            floor = [c.v_floor_mps for c in cars]
        wheels = Wheelsets(scn.vehicle_masses_kg(), axles, radius, inertia, scn.initial_speed_mps(),
                           curve=curves, v_floor_mps=floor)
    return blending, wheels, _per_car_wsp(b, "valve_lag_s", 0.05, scn.n_cars)


def _per_car_wsp(b: Any, name: str, none: float, n: int) -> Any:
    """The dump valves' ``name`` (valve_lag_s, max_vent_s): the train's wsp's (``none`` without),
    or a tuple per car where the cars' wsp differ (a car without wsp takes the train's: its valve
    is never commanded)."""
    if b is None or b.wsp is None:
        return none
    first = getattr(b.wsp, name)
    if b.cars is None:
        return first
    vals = tuple(float(getattr(c.wsp, name)) if c.wsp is not None else float(first) for c in b.cars)
    return vals[0] if len(set(vals)) == 1 else vals


def _blending_per_car(b: Any) -> Any:
    """The blending of a train whose vehicle types differ in it (``b.cars``): per car its ED
    capacity (its ``ed_brake``, else its blending's ``ed_max_decel_mps2``/``ed_power_kw_per_t``; 0
    without blending), fade speeds and friction lag (0 without blending: friction only, at once)."""
    from canbrake.physics.brakes import BrakeBlending

    nan = (math.nan,) * 5
    first = b.blending
    per_car = first.per_car if first.per_car is not None else [None] * len(b.cars)
    ed_max, ed_power, env, fs, fe, lag = [], [], [], [], [], []
    for c, ed in zip(b.cars, per_car):
        e = c.blending
        if e is None:  # friction only: no ED force, the friction brake follows the demand at once
            row = (0.0, math.inf, nan, first.fade_start_kmh, first.fade_end_kmh, 0.0)
        elif ed is None:
            row = (e.ed_max_decel_mps2, math.inf if e.ed_power_kw_per_t is None else e.ed_power_kw_per_t, nan,
                   e.fade_start_kmh, e.fade_end_kmh, e.friction_lag_s)
        elif ed.model == "none":
            row = (0.0, math.inf, nan, e.fade_start_kmh, e.fade_end_kmh, e.friction_lag_s)
        elif ed.model == "per_mass":
            row = (ed.max_decel_mps2, math.inf if ed.power_kw_per_t is None else ed.power_kw_per_t, nan,
                   e.fade_start_kmh, e.fade_end_kmh, e.friction_lag_s)
        else:
            row = (0.0, math.inf, ed.row_si(), e.fade_start_kmh, e.fade_end_kmh, e.friction_lag_s)
        for out, x in zip((ed_max, ed_power, env, fs, fe, lag), row):
            out.append(x)
    return BrakeBlending(ed_max_decel_mps2=tuple(float(x) for x in ed_max),
                         ed_power_w_per_kg=tuple(float(x) for x in ed_power),
                         fade_start_mps=tuple(x / 3.6 for x in fs), fade_end_mps=tuple(x / 3.6 for x in fe),
                         friction_lag_s=tuple(float(x) for x in lag),
                         envelope=tuple(env) if any(r is not nan for r in env) else None)


def needs_barrier(scn: Scenario) -> bool:
    """Lockstep needs the *_DONE barrier frames only when a frame can be lost, delayed or late."""
    return bool(scn.bus.impairments) or scn.bus.timing == "model" or bool(external_ecus(scn))


def external_ecus(scn: Scenario) -> frozenset[int]:
    """Indices (1-based, placement order) of the ECUs canbrake does not start (``external: true``)."""
    return frozenset(i for i, p in enumerate(scn.placement(), start=1) if getattr(p, "external", False))


def ecu_specs(scn: Scenario) -> list[dbc.EcuSpec]:
    """The placement as the bus sees it: per ECU its sensors, commands, broadcasts and listeners."""
    placed = scn.placement()
    index = {p.name: i for i, p in enumerate(placed, start=1)}
    # built once: their signal names may depend on their parameters (e.g. cai2014's axles)
    ctrls = {i: build_controller(scn, i) for i in range(1, len(placed) + 1)}
    # an ECU that broadcasts nothing sends no STATE frame: nobody can wait for one (lockstep phase 1)
    silent = {i for i, c in ctrls.items() if not tuple(getattr(c, "broadcast_names", ("speed_mps", "position_m")))}
    listens: dict[int, tuple[int, ...]] = {}
    for i, p in enumerate(placed, start=1):
        if p.listens == "all":
            listens[i] = tuple(j for j in range(1, len(placed) + 1) if j != i and j not in silent)
        elif p.listens == "none":
            listens[i] = ()
        elif p.listens == "neighbours":  # the ECUs on the vehicles coupled to this one
            listens[i] = tuple(j for j, q in enumerate(placed, start=1)
                               if j != i and abs(q.vehicle - p.vehicle) == 1 and j not in silent)
        else:
            listens[i] = tuple(sorted(index[x] for x in p.listens if index[x] != i))
            quiet = [x for x in p.listens if index[x] in silent]
            if quiet:
                raise ValueError(f"ECU {p.name} listens to {quiet[0]}, whose controller "
                                 f"{placed[index[quiet[0]] - 1].controller.name} broadcasts nothing (no STATE frame)")
    specs = []
    for i, p in enumerate(placed, start=1):
        ctrl = ctrls[i]
        sensors = tuple(getattr(ctrl, "sensor_names", ("speed_mps", "position_m")))
        if scn.plant.coupler_sensors and scn.train.kernel_name == "coupled":
            sensors += tuple(x for x in ("deflection_front_m", "deflection_rear_m") if x not in sensors)
        listeners = tuple(j for j in range(1, len(placed) + 1) if i in listens[j])
        specs.append(dbc.EcuSpec(p.name, i, p.vehicle, sensors=sensors,
                                 commands=tuple(getattr(ctrl, "command_names", ("brake_force_n",))),
                                 broadcast=tuple(getattr(ctrl, "broadcast_names", ("speed_mps", "position_m"))),
                                 listeners=listeners, listens=listens[i]))
    return specs


def bus_layout(scn: Scenario) -> dbc.BusLayout:
    """Every message of the run (the DBC's source), from the placement.

    Memoised on the scenario's content: the plant, every ECU, its send path, the timing model and
    the recorder all ask for it, and building it builds every controller (106 for a 1 + 105 train).
    The layout is never modified after it is built."""
    key = repr(scn.model_dump())  # exact, inf included (JSON would turn it into null)
    layout = _LAYOUTS.get(key)
    if layout is None:
        if len(_LAYOUTS) >= 8:
            _LAYOUTS.pop(next(iter(_LAYOUTS)))
        layout = _LAYOUTS[key] = _build_layout(scn)
    return layout


_LAYOUTS: dict[str, dbc.BusLayout] = {}


def _build_layout(scn: Scenario) -> dbc.BusLayout:
    from canbrake.control.base import controller_class

    specs = ecu_specs(scn)
    ref_pos = any(getattr(controller_class(p.controller.name), "needs_ref_position", False) for p in scn.placement())
    layout = dbc.BusLayout(specs, period_ms=scn.control_period_s * 1000.0, ref_position=ref_pos,
                           heartbeat_ms=int(round(scn.ecu.heartbeat_period_s * 1000)),
                           secured=scn.security is not None)
    layout.n_vehicles = scn.n_cars  # type: ignore[attr-defined]
    if scn.security is not None:  # secured layouts: longer frames with a MAC (canbrake.bus.secoc)
        from canbrake.bus.secoc import secure_database

        plain = layout.database
        layout.database = lambda: secure_database(plain())  # type: ignore[method-assign]
    if scn.bus.dbc is not None:  # the user's own DBC: the mapped roles move onto its messages
        layout = _user_layout(scn, layout, specs)
    return layout


def user_dbc_path(scn: Scenario) -> Path | None:
    """The user's DBC of ``scn`` (``bus.dbc.file``, relative to the scenario's folder), or None."""
    if scn.bus.dbc is None:
        return None
    p = Path(scn.bus.dbc.file)
    return p if p.is_absolute() or scn.data_dir() is None else scn.data_dir() / p  # type: ignore[operator]


def _user_layout(scn: Scenario, base: dbc.BusLayout, specs: list[dbc.EcuSpec]) -> dbc.BusLayout:
    from canbrake.bus.userdbc import load_user_dbc, mapped_layout

    path = user_dbc_path(scn)
    mapping = scn.bus.dbc.resolved([(e.name, e.index, e.vehicle) for e in specs])  # type: ignore[union-attr]
    layout = mapped_layout(base, load_user_dbc(path), path, mapping,  # type: ignore[arg-type]
                           period_ms=scn.control_period_s * 1000.0, heartbeat_ms=scn.ecu.heartbeat_period_s * 1000.0)
    layout.n_vehicles = scn.n_cars  # type: ignore[attr-defined]
    return layout


def build_controller(scn: Scenario, ecu_index: int) -> Controller:
    """Controller of the ECU at ``ecu_index`` (1-based, placement order)."""
    p = scn.placement()[ecu_index - 1]
    ctrl = make_controller(p.controller.name, p.controller.params, car_index=ecu_index - 1, n_cars=scn.n_ecus,
                           mass_kg=float(scn.vehicle_masses_kg()[p.vehicle - 1]), dt_s=scn.control_period_s)
    brakes = getattr(scn.consist, "brakes", None)
    own = None if brakes is None else brakes.car(p.vehicle - 1)
    if own is not None and (own.easing is not None or (own.wsp is not None and own.wsp.enabled)):
        from canbrake.control.brake_functions import brake_functions_of

        ctrl = brake_functions_of(ctrl, brakes, scn.actuator, p.vehicle - 1)
    ecp = getattr(scn.consist, "ecp_unit_params", None)
    if ecp is not None and "brake_force_n" in ctrl.command_names and "ecp_demand" not in ctrl.command_names:
        unit = ecp(p.vehicle)  # None: not an ECP wagon (a locomotive, or a pneumatic train)
        if unit is not None:
            from canbrake.control.ecp import EcpUnit

            ctrl = EcpUnit(ctrl, **unit)
    return ctrl


def build_send_path(scn: Scenario, node: str) -> SendPath:
    """The impairment chain of one sending node (pass-through when none applies and no timing
    model latency has to be held back)."""
    if not scn.bus.impairments and not (scn.mode == "lockstep" and scn.bus.timing == "model"):
        return PassThrough()
    from canbrake.bus.sendpath import build_send_path as _build

    return _build(scn, node, bus_layout(scn))


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

    real = {p.name for p in scn.placement()}
    return [build_send_path(scn, name) for name in babbling_nodes(scn.bus.impairments) if name not in real]


class CoupledPlant:
    """A :class:`~canbrake.physics.train.TrainPlant` behind the plant contract: ``brake_force_n``
    (NaN = no command = no force), ``wsp_release`` (the dump valves of wheel-slide protection, with
    the wheels component) and, with air brakes, ``airbrake_apply`` (the driver's valve, read on the
    leading car) and ``ecp_demand`` (per car), as the heavy-haul plant takes them; an air-braked car
    without traction (a wagon) ignores ``brake_force_n``, as there. A rigidly coupled train with
    driven axles takes ``axle<j>_torque_nm`` instead and measures what
    :meth:`~canbrake.physics.train.TrainPlant.rigid_measurements` gives."""

    command_names: tuple[str, ...] = ("brake_force_n", "wsp_release")

    def __init__(self, plant: Any) -> None:
        from canbrake.physics._train_kernel import nan_as_zero

        self.plant = plant
        self._nan_as_zero = nan_as_zero  # NaN (not commanded) = no force, in one compiled call
        self.n_vehicles = plant.n_cars
        self.n_cars = plant.n_cars
        self.mass_kg = plant.mass_kg
        self._meas: dict[str, np.ndarray] | None = None  # of the current state; step() drops it
        self._wagons: np.ndarray | None = None  # air-braked cars without traction: no force equipment
        # line data for Li's driver rules: the coupled kernel's grade is constant, so a long downgrade
        # (steeper than 8 permille, heavy_haul.Route.long_downgrade_ahead) is always ahead or never
        g = plant._grade_force if plant._has_grade else None
        steep = g is not None and bool(np.all(g > plant.mass_kg * plant.gravity_mps2 * math.sin(math.atan(0.008))))
        self._downgrade = np.full(plant.n_cars, 1.0 if steep else 0.0)
        if plant.rigid:
            self.command_names = plant.axle_command_names
        if plant.air_brake is not None:
            self.command_names = ("brake_force_n", "wsp_release", "airbrake_apply", "ecp_demand")
            env = plant.traction_envelope
            powered = np.array([False] * plant.n_cars if env is None else [e is not None for e in env])
            self._wagons = plant.air_braked & ~powered

    def step(self, dt_s: float, commands: Any) -> None:
        self._meas = None
        if self.plant.rigid:  # driven axles: their torques
            self.plant.step(dt_s, None, axle_torque_nm=self.plant.axle_torques(commands))
            return
        f = commands.get("brake_force_n")
        f = np.zeros(self.n_vehicles) if f is None else np.asarray(f, dtype=float)
        if self._wagons is not None:
            f = np.where(self._wagons, np.nan, f)
            ap = commands.get("airbrake_apply")
            self.plant.command_air(None if ap is None else float(ap[0]), commands.get("ecp_demand"))
        wsp = commands.get("wsp_release")
        if wsp is None:
            self.plant.step(dt_s, self._nan_as_zero(f))
        else:
            self.plant.step(dt_s, self._nan_as_zero(f), wsp_release=np.asarray(wsp, dtype=float))

    def measurements(self) -> dict[str, np.ndarray]:
        """The contract's measurements, computed once per state (the plant node reads them for
        the sensor frames and for the trace; do not modify the arrays)."""
        if self._meas is None:
            self._meas = self._measure()
        return self._meas

    def _measure(self) -> dict[str, np.ndarray]:
        if self.plant.rigid:
            return self.plant.rigid_measurements()
        p = self.plant  # its state arrays as they are: a step replaces them, never writes into them
        dl, phi = p.couplers()
        out = {"position_m": p.position_m, "speed_mps": p.speed_mps, "accel_mps2": p.accel_mps2,
               "applied_brake_n": p.applied_force_n, "deflection_m": dl, "coupler_force_n": phi}
        if self.plant.blending is not None or self.plant.wheels is not None:
            out.update(self.plant.equipment_measurements())
        ab = self.plant.air_brake
        if ab is not None:  # the air-braked cars' brake (NaN on the others)
            on = self.plant.air_braked
            out["applied_brake_n"] = p.applied_force_n + ab.last_force_n
            out["air_brake_n"] = np.where(on, ab.last_force_n, np.nan)
            out["brake_cylinder_pressure_pa"] = np.where(on, ab.fill * ab.cylinder_pressure_pa, np.nan)
            if ab.pipe is not None:
                out["brake_pipe_pressure_pa"] = np.where(on, ab.pipe_pressure_pa, np.nan)
        if ab is not None or self.plant.draft_gears is not None:  # what Li 2024's controllers read
            out["passive_force_n"] = self.plant.passive_force_n(phi)
            out["downgrade_ahead"] = self._downgrade if getattr(self.plant, "route", None) is None else np.full(
                self.n_vehicles, float(self.plant.downgrade_ahead()))  # the route's line data
        return out


PlantAdapter = CoupledPlant  # the former name


def failsafe_of(scn: Scenario) -> Any:
    """The plant's fail-safe reaction from ``safety`` (None when off)."""
    from canbrake.nodes.plant import FailSafe

    sf = scn.safety
    if sf.command_timeout_s is None:
        return None
    mass = scn.vehicle_masses_kg()
    values = dict(sf.failsafe_commands or {})
    return FailSafe(timeout_ticks=max(1, int(round(sf.command_timeout_s / scn.control_period_s))),
                    force_n=mass * sf.failsafe_decel_mps2, latch=sf.latch, values=values)


def _error_timing(scn: Scenario) -> Any:
    """The recorder's own timing-model replica (lockstep with ``bus.timing: model``, else None):
    the frames' modelled wire times for the log's stamps, and the bus errors if it has any."""
    from canbrake.bus.schedule import build_bus_timing

    return build_bus_timing(scn, bus_layout(scn))


def _segments_of(scn: Scenario, layout: Any) -> Any:
    """The recorder's view of ``bus.segments`` (None on one bus; canbrake.bus.segments)."""
    from canbrake.bus.segments import topology_of

    topo = topology_of(scn, layout) if scn.mode == "lockstep" else None
    return None if topo is None else (topo, scn.ecu.lockstep_deadline * scn.control_period_s, scn.bus.tx_buffers)


def _realtime_clock(scn: Scenario, layout: Any, name: str) -> Any:
    """Realtime: the ECU's own timer from ``ecu.clocks`` (drift, jitter, phase), None otherwise."""
    if scn.mode != "realtime" or not scn.ecu.clocks:
        return None
    from canbrake.bus.schedule import clocks_of

    return clocks_of(scn, layout).get(name)


def _realtime_errors(scn: Scenario, name: str) -> Any:
    """Realtime: the ECU's own bit-error / faulty-transceiver injector (canbrake.bus.rt_errors)."""
    from canbrake.bus.rt_errors import realtime_errors_of

    return realtime_errors_of(scn, name)


def build_node(scn: Scenario, role: str, *, car: int = 0, run_dir: Path | None, channel: str = "can0",
               progress: Any = None, codec: FrameCodec | None = None, bus_timing: Any = "build",
               layout: dbc.BusLayout | None = None) -> Node:
    """One node of the run: ``role`` is "plant", "ecu" (``car``: the ECU's index, 1-based, in
    placement order) or "recorder"."""
    from canbrake.bus.secoc import secoc_of

    layout = layout or bus_layout(scn)
    codec = codec or FrameCodec(layout.database())
    secoc = secoc_of(scn)  # None unless `security:` is set
    if role == "plant":
        from canbrake.nodes.plant import PlantNode

        return PlantNode(build_plant_model(scn), codec, layout=layout, dt_s=scn.control_period_s,
                         n_ticks=scn.n_ticks, reference=reference_fn(scn), mode=scn.mode,
                         heartbeat_period_s=scn.ecu.heartbeat_period_s,
                         out_dir=run_dir, progress=progress, hosted=hosted_babblers(scn),
                         barrier=needs_barrier(scn), failsafe=failsafe_of(scn), secoc=secoc,
                         trace_every=scn.plant.trace_every, external=external_ecus(scn),
                         external_start_timeout_s=scn.ecu.external_start_timeout_s,
                         external_timeout_s=scn.ecu.external_timeout_s, time_scale=scn.time_scale)
    if role == "ecu":
        from canbrake.nodes.ecu import EcuNode

        if bus_timing == "build":
            from canbrake.bus.schedule import build_bus_timing

            bus_timing = build_bus_timing(scn, layout)
        spec = layout.ecus[car - 1]
        return EcuNode(spec, layout, build_controller(scn, car), codec, dt_s=scn.control_period_s,
                       bus_timing=bus_timing, barrier=needs_barrier(scn), rx_path=build_rx_path(scn, spec.name),
                       mode=scn.mode, send_path=build_send_path(scn, spec.name),
                       heartbeat_period_s=scn.ecu.heartbeat_period_s,
                       compute_deadline=scn.ecu.realtime_compute_deadline, out_dir=run_dir,
                       lockstep_deadline=scn.ecu.lockstep_deadline,
                       secoc=secoc, peer_hold_periods=scn.safety.peer_hold_periods, n_ticks=scn.n_ticks,
                       clock=_realtime_clock(scn, layout, spec.name), rt_errors=_realtime_errors(scn, spec.name),
                       external=external_ecus(scn), external_timeout_s=scn.ecu.external_timeout_s,
                       time_scale=scn.time_scale,
                       crash_at_tick=(int(round(scn.ecu.crash.at_s / scn.control_period_s))
                                      if scn.ecu.crash is not None and scn.ecu.crash.car == spec.vehicle else None))
    if role == "recorder":
        from canbrake.nodes.recorder import RecorderNode

        return RecorderNode(layout, dt_s=scn.control_period_s, bitrate_bps=scn.bus.bitrate_bps, mode=scn.mode,
                            plant_io_on_bus=scn.bus.plant_io_on_bus, barrier=needs_barrier(scn), secoc=secoc,
                            n_ticks=scn.n_ticks, bus_timing=_error_timing(scn), segments=_segments_of(scn, layout),
                            external=external_ecus(scn),
                            log_path=None if run_dir is None else run_dir / f"frames.{scn.bus.log_format}",
                            channel=channel)
    raise ValueError(f"unknown node role {role!r}")


def build_nodes(scn: Scenario, run_dir: Path | None, channel: str = "can0") -> list[Node]:
    """Every node of a run, plant last (it starts the first tick)."""
    from canbrake.bus.schedule import build_bus_timing

    layout = bus_layout(scn)
    codec = FrameCodec(layout.database())
    timing = build_bus_timing(scn, layout)  # one replica serves every node of an in-process run
    kw = dict(run_dir=run_dir, codec=codec, layout=layout)
    nodes: list[Node] = [build_node(scn, "recorder", channel=channel, **kw)]  # type: ignore[arg-type]
    nodes += [build_node(scn, "ecu", car=i, bus_timing=timing, **kw)  # type: ignore[arg-type]
              for i in range(1, scn.n_ecus + 1)]
    nodes.append(build_node(scn, "plant", **kw))  # type: ignore[arg-type]
    return nodes
