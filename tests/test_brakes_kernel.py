"""The compiled brake equipment of the coupled train (physics/_brakes_kernel.pyx) against an
interpreted oracle: the vectorised numpy forms it replaced (ED/friction blending, the dump valve
with its watchdog, Cai's creep force per axle and the backward-Euler step of wheelsets and bodies,
the Coulomb brake without wheelsets), kept here only as the reference. The kernel must give the
same bits on random states, locked wheels and NaN commands included; plus a physics invariant
(without brake and forces a rolling car keeps its speed and its wheels roll without slip)."""
from __future__ import annotations

import math

import numpy as np
import pytest

from canbrake.physics.actuator import BrakeActuator
from canbrake.physics.brakes import BrakeBlending, Wheelsets
from canbrake.physics.rail import RailConditions
from canbrake.physics.resistance import DavisResistance
from canbrake.physics.train import TrainPlant
from canbrake.physics.wheel_adhesion import RailCondition

CURVE = RailCondition(b1=1.786, b2=40.0, b3=10.0, c1=0.040, c2=3.78, c3=33.3, peak_mu0=0.35)


# ------------------------------------------------------------------ the oracle (former numpy code)
def _creep(ws: Wheelsets, w, v, mu_peak):
    c, R, floor = ws.curve, ws.R, ws.v_floor
    vv = v[:, None]
    wr = w * R
    awr, av = np.abs(wr), np.abs(vv)
    den = np.maximum(np.maximum(awr, av), floor)
    lam = (wr - vv) / den
    use_wr = (awr >= av) & (awr >= floor)
    use_v = ~use_wr & (av >= floor)
    safe_wr2 = np.where(use_wr, wr * wr, 1.0)
    dlam_dw = np.where(use_wr, R * av / safe_wr2, R / den)
    dlam_dv = np.where(use_v, -wr / (den * den), -1.0 / den)
    scale = (c.c1 + c.c2 / (c.c3 + av)) / ws._mu0 * (mu_peak[:, None] / ws._peak_curve)
    a = np.abs(lam)
    ex = np.exp(-c.b2 * a)
    sn = scale * ws.N
    f = np.sign(lam) * sn * (c.b1 * (1.0 - ex) - a / c.b3)
    dmu = sn * (c.b1 * c.b2 * ex - 1.0 / c.b3)
    return lam, f, dmu * dlam_dw, dmu * dlam_dv


def _wheels_step(ws: Wheelsets, omega, h_s, v0, mass_kg, other_n, brake_torque_nm, drive_torque_nm, mu_peak):
    """Former Wheelsets.step: returns (v, ω, F, λ)."""
    R, J = ws.R, ws.J
    w0 = omega
    _, f0, _, _ = _creep(ws, w0, v0, mu_peak)
    spin = drive_torque_nm - f0 * R
    at_zero = w0 == 0.0
    locked = at_zero & (np.abs(spin) <= brake_torque_nm)
    s = np.where(at_zero, np.sign(spin), np.sign(w0))
    tb = brake_torque_nm * s
    w, v = np.where(locked, 0.0, w0), v0.copy()
    for _attempt in range(2):
        free = ~locked
        for _ in range(ws.iters):
            lam, f, fw, fv = _creep(ws, w, v, mu_peak)
            r_w = J * (w - w0) - h_s * (drive_torque_nm - tb - f * R)
            a = J + h_s * R * fw
            a = np.where(a > 0.1 * J, a, J)
            a = np.where(free, a, 1.0)
            r_w = np.where(free, r_w, 0.0)
            b = np.where(free, h_s * R * fv, 0.0)
            cc = np.where(free, -h_s * fw, 0.0)
            r_v = mass_kg * (v - v0) - h_s * (f.sum(axis=1) + other_n)
            d = mass_kg - h_s * fv.sum(axis=1)
            dv = (-r_v + (cc * r_w / a).sum(axis=1)) / (d - (cc * b / a).sum(axis=1))
            w = w + (-r_w - b * dv[:, None]) / a
            v = v + dv
        over = free & (w * s < 0.0)
        if not over.any():
            break
        locked = locked | over
        w = np.where(locked, 0.0, w)
    lam, f, _, _ = _creep(ws, w, v, mu_peak)
    return v, w, f, lam


class _Oracle:
    """The former TrainPlant._step_equipped's equipment part for one plant, with its own state."""

    def __init__(self, plant: TrainPlant) -> None:
        self.p = plant
        self.friction = np.zeros(plant.n_cars)
        self.ed = np.zeros(plant.n_cars)
        self.valve = np.zeros(plant.n_cars)
        self.vent = np.zeros(plant.n_cars)
        self.omega = None if plant.wheels is None else plant.wheels.omega.copy()

    def substep(self, h, effort, v, f, r, mu, eff, wsp):
        pl, bl = self.p, self.p.blending
        total = effort
        if bl is not None:
            s = np.abs(v)
            fade = np.clip((s - bl.fade_end_mps) / (bl.fade_start_mps - bl.fade_end_mps), 0.0, 1.0)
            with np.errstate(divide="ignore"):
                per_kg = np.minimum(bl.ed_max_decel_mps2, bl.ed_power_w_per_kg / np.maximum(s, 1e-9))
            demand = np.maximum(effort, 0.0)
            self.ed = np.minimum(demand, pl.mass_kg * per_kg * fade)
            share = demand - self.ed
            if bl.friction_lag_s > 0.0:
                self.friction = self.friction + (share - self.friction) * (1.0 - math.exp(-h / bl.friction_lag_s))
            else:
                self.friction = share
            total = self.ed + self.friction + np.minimum(effort, 0.0)
        brake = np.maximum(total, 0.0) * eff
        traction = np.minimum(total, 0.0)
        if wsp is not None:
            want = np.clip(np.where(np.isnan(wsp), 0.0, wsp), 0.0, 1.0)
            self.vent = np.where(want > 0.5, self.vent + h, 0.0)
            want = np.where(self.vent > pl.wsp_max_vent_s, 0.0, want)
            target = np.clip(np.where(np.isnan(want), 0.0, want), 0.0, 1.0)
            lag = pl.wsp_valve_lag_s
            self.valve = target if lag <= 0.0 else self.valve + (target - self.valve) * (1.0 - math.exp(-h / lag))
            brake = brake * (1.0 - self.valve)
        ws = pl.wheels
        if ws is not None:
            other = f - np.sign(v) * r
            per_axle = ws.R / ws.p
            v_new, self.omega, force, _ = _wheels_step(
                ws, self.omega, h, v, pl.mass_kg, other, np.repeat((brake * per_axle)[:, None], ws.p, 1),
                np.repeat((-traction * per_axle)[:, None], ws.p, 1), mu)
            v_new = np.where((v != 0.0) & (v_new * v < 0.0), 0.0, v_new)
            return v_new, -force.sum(axis=1)
        rail = brake + traction
        if pl.actuator.adhesion_limited:
            cap = mu * pl.mass_kg * pl.gravity_mps2
            rail = np.minimum(np.maximum(rail, -cap), cap)
        f = f - np.minimum(rail, 0.0)
        rr = np.maximum(rail, 0.0) + r
        moving = v != 0.0
        sgn = np.where(moving, np.sign(v), np.sign(f))
        breakaway = moving | (np.abs(f) > rr)
        v_new = v + np.where(breakaway, (h / pl.mass_kg) * (f - sgn * rr), 0.0)
        return np.where(moving & (v_new * v < 0.0), 0.0, v_new), rail


def _plant(rng, wheels: bool, blending: bool, lag: float = 0.2, adhesion: bool = False) -> TrainPlant:
    n = 5
    m = rng.uniform(3e4, 5e4, n)
    v0 = rng.uniform(0.0, 25.0, n)
    ws = Wheelsets(m, 4, 0.42, 120.0, v0, curve=CURVE) if wheels else None
    bl = BrakeBlending(ed_max_decel_mps2=0.9, ed_power_w_per_kg=rng.choice([math.inf, 20.0]),
                       friction_lag_s=lag) if blending else None
    act = BrakeActuator.ideal(adhesion_limited=True) if adhesion else None
    return TrainPlant(m, -20.0 * np.arange(n), v0, blending=bl, wheels=ws, actuator=act, wsp_max_vent_s=0.05,
                      rail=RailConditions(base_adhesion_mu=0.12))


def _random_inputs(rng, n):
    effort = rng.uniform(-3e4, 6e4, n)
    effort[rng.random(n) < 0.2] = 0.0
    v = rng.uniform(-0.5, 25.0, n)
    v[rng.random(n) < 0.2] = 0.0
    f = rng.normal(0.0, 5e3, n)
    r = rng.uniform(0.0, 3e3, n)
    mu = rng.uniform(0.03, 0.3, n)
    eff = rng.choice([1.0, 0.7], n)
    wsp = rng.choice([np.nan, 0.0, 0.3, 1.0, 1.4, -0.2], n)
    return effort, v, f, r, mu, eff, wsp


def _same(a, b) -> bool:
    a, b = np.asarray(a, dtype=float), np.asarray(b, dtype=float)
    return a.shape == b.shape and bool(np.all(a.view(np.int64) == b.view(np.int64)))


@pytest.mark.parametrize("wheels, blending, lag, adhesion", [
    (True, True, 0.2, False), (True, False, 0.2, False), (False, True, 0.2, False), (False, True, 0.0, False),
    (False, True, 0.2, True)])
def test_substep_bit_identical_to_the_numpy_form(wheels, blending, lag, adhesion) -> None:
    rng = np.random.default_rng(7)
    for trial in range(6):
        pl = _plant(rng, wheels, blending, lag, adhesion)
        ora = _Oracle(pl)
        kern = pl._equip_kernel()
        n = pl.n_cars
        fr, ed, valve, vent = np.zeros(n), np.zeros(n), np.zeros(n), np.zeros(n)
        ws = pl.wheels
        om = None if ws is None else ws.omega.copy()
        fo, sl = (None, None) if ws is None else (np.zeros_like(om), np.zeros_like(om))
        for k in range(40):
            h = [1e-3, 1e-2][k % 2]
            effort, v, f, r, mu, eff, wsp = _random_inputs(rng, n)
            if k % 3 == 0:
                wsp = None
            if ws is not None and k % 5 == 4:  # some wheels at rest: locking, breakaway
                om[rng.random(om.shape) < 0.4] = 0.0
                ora.omega = om.copy()
            bk = (1.0 - math.exp(-h / lag)) if lag > 0 else 0.0
            vk = 1.0 - math.exp(-h / pl.wsp_valve_lag_s)
            z = np.zeros(0)
            got_v, got_rail = kern.substep(h, np.array([bk]), np.array([vk]), effort, v, f, r, pl.mass_kg, mu, eff, wsp,
                                           fr if blending else z, ed if blending else z, valve, vent,
                                           z if ws is None else om.reshape(-1), z if ws is None else fo.reshape(-1),
                                           z if ws is None else sl.reshape(-1))
            want_v, want_rail = ora.substep(h, effort, v, f, r, mu, eff, wsp)
            assert _same(got_v, want_v), (trial, k)
            assert _same(got_rail, want_rail), (trial, k)
            if blending:
                assert _same(fr, ora.friction) and _same(ed, ora.ed)
            if wsp is not None:
                assert _same(valve, ora.valve) and _same(vent, ora.vent)
            if ws is not None:
                assert _same(om, ora.omega)


def test_wheelsets_step_bit_identical_with_locked_wheels() -> None:
    rng = np.random.default_rng(3)
    for _ in range(30):
        n, p = 3, int(rng.integers(1, 10))  # up to 9 axles: numpy's pairwise sum from 8 on
        m = rng.uniform(3e4, 5e4, n)
        ws = Wheelsets(m, p, 0.42, 120.0, rng.uniform(0, 20, n), curve=CURVE)
        ws.omega[rng.random((n, p)) < 0.3] = 0.0
        omega = ws.omega.copy()
        args = (1e-2, rng.uniform(0, 20, n), m, rng.normal(0, 4e3, n), rng.uniform(0, 8e3, (n, p)),
                rng.uniform(0, 2e3, (n, p)), rng.uniform(0.03, 0.3, n))
        want_v, want_w, want_f, want_lam = _wheels_step(ws, omega, *args)
        got_v = ws.step(*args)
        assert _same(got_v, want_v) and _same(ws.omega, want_w)
        assert _same(ws.force_n, want_f) and _same(ws.slip, want_lam)


def test_free_rolling_car_keeps_its_speed() -> None:
    """Invariant: no brake, no traction, no other force: no creep, the car and its wheels keep
    rolling at the same speed (ωR = v), exactly."""
    m = np.array([4e4, 4e4])
    ws = Wheelsets(m, 4, 0.42, 120.0, np.array([10.0, 20.0]), curve=CURVE)
    pl = TrainPlant(m, [0.0, -20.0], [10.0, 20.0], wheels=ws, blending=BrakeBlending(),
                    resistance=DavisResistance.zero(2), coupler_stiffness_n_per_m=0.0)
    for _ in range(100):
        pl.step(1e-3, np.zeros(2))
    assert np.array_equal(pl.speed_mps, [10.0, 20.0])
    assert np.allclose(ws.omega * ws.R, pl.speed_mps[:, None], rtol=0, atol=1e-12)
    assert np.all(ws.force_n == 0.0)
