"""The compiled plant kernels (canbrake/physics/_*_kernel.pyx) against closed forms and independent
evaluations of the same equations.

The kernels perform the operations of the numpy code they replaced in the same order, so a run is
bit-identical to the former one (checked when they were written: signals.csv and frames.log of
the shipped scenarios byte-equal to the numpy version's). A test cannot run deleted code, so these
tests check what must hold whatever the implementation: a stack's rows are their own plants bit
for bit, the draft gear follows its loading curve, a cylinder fills along its first-order lag and
the air brake's force is eq. (10), the wheels' backward-Euler equations are solved.
"""
from __future__ import annotations

import math

import numpy as np
import pytest

from canbrake.physics import heavy_haul as hh
from canbrake.physics._train_kernel import CoupledKernel, nan_as_zero
from canbrake.physics.actuator import BrakeActuator
from canbrake.physics.rail import DisturbanceForce, RailConditions, RailEvent
from canbrake.physics.train import END_STOP_TRANSITION_MPS, TrainPlant, stack_plants
from canbrake.physics.wheel_adhesion import RailCondition, WheelSet

M = np.array([18000, 21000, 19500, 20000, 19700, 22000.0])
X0 = np.array([10, 20, 30, 40, 50, 60.0])


def _plant(i: int, **kw) -> TrainPlant:
    rail = RailConditions(0.15, [RailEvent(0.3, 0.6, adhesion_mu=0.05, brake_effectiveness=[1, 0.5, 1, 0.3, 1, 1])])
    dist = [DisturbanceForce(amplitude_n=[500, 0, 300, 0, 0, 100], frequency_hz=1.3, start_s=0.1, offset_n=200)]
    return TrainPlant(M * (1 + 0.05 * i), X0, np.array([0.5, 0.0, 0.4, 0.45, 0.0, 0.6]) * (1 + i),
                      coupler_stiffness_n_per_m=80000 * (1 + i), rail=rail, disturbances=dist,
                      grade_rad=0.002 * i, **kw)


@pytest.mark.parametrize("actuator", [BrakeActuator.ideal(adhesion_limited=True), BrakeActuator.realistic()],
                         ids=["ideal", "realistic"])
def test_stack_rows_equal_their_plants_through_standstill_traction_and_rail_events(actuator):
    singles = [_plant(i, actuator=actuator) for i in range(3)]
    stack = stack_plants([_plant(i, actuator=actuator) for i in range(3)])
    rng = np.random.default_rng(3)
    stopped = 0
    for k in range(800):  # brake and traction at random: cars stop, stay, and start again
        cmd = np.stack([rng.normal(0.3, 1.0, 6) * M * (1 + 0.05 * i) for i in range(3)])
        for i, p in enumerate(singles):
            p.step(0.001, cmd[i])
        stack.step(0.001, cmd)
        stopped += sum(int((p.speed_mps == 0.0).sum()) for p in singles)
        for i, p in enumerate(singles):
            for name in ("position_m", "speed_mps", "accel_mps2"):
                assert np.array_equal(getattr(stack, name)[i], getattr(p, name)), (k, i, name)
            assert np.array_equal(np.broadcast_to(stack.applied_force_n, (3, 6))[i], p.applied_force_n)
    assert stopped > 20  # the standstill branch was taken


def test_a_stack_of_one_point_keeps_its_points_axis():
    single, stack = _plant(1), stack_plants([_plant(1)])
    for _ in range(50):
        single.step(0.001, M * 0.5)
        stack.step(0.001, (M * 0.5)[None, :])
    assert stack.position_m.shape == stack.speed_mps.shape == stack.accel_mps2.shape == (1, 6)
    assert np.array_equal(stack.speed_mps[0], single.speed_mps)
    assert np.array_equal(stack.position_m[0], single.position_m)


def test_friction_stops_a_car_exactly_and_holds_it():
    p = TrainPlant([20000.0], [0.0], [0.3], actuator=BrakeActuator.ideal())
    for _ in range(200):
        p.step(0.01, np.array([20000.0]))  # 1 m/s2: stops within 0.3 s
    x = p.position_m.copy()
    assert p.speed_mps[0] == 0.0 and p.accel_mps2[0] == 0.0
    for _ in range(50):
        p.step(0.01, np.array([20000.0]))
    assert p.speed_mps[0] == 0.0 and np.array_equal(p.position_m, x)
    # distance: v0²/(2 a) for the brake plus the resistance, within the trapezoid's exactness
    a = (20000.0 + p.resistance.c0_n[0]) / 20000.0
    assert x[0] == pytest.approx(0.3 ** 2 / (2 * a), rel=2e-2)


def test_kernel_refuses_arrays_it_cannot_read():
    p = TrainPlant(M, X0, np.full(6, 20.0))
    p.step(0.001, np.zeros(6))  # builds the kernel
    k = p._kernel()
    assert isinstance(k, CoupledKernel)
    args = (p.position_m, p.speed_mps, np.zeros(6), np.zeros(6), np.zeros(6), p._mu, p._eff, 0.0, 1e-3, 1, True,
            True, 0.0)
    with pytest.raises(TypeError, match="float64"):
        k.step(p.position_m.astype(np.float32), *args[1:])
    with pytest.raises(ValueError, match=r"shape \(6,\)"):
        k.step(np.zeros(5), *args[1:])


def _numpy_couplers(p: TrainPlant, x: np.ndarray, v: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The plant's former numpy deflection_m / coupler_force_n (without draft gears): the oracle of
    CoupledKernel.couplers, same operations in the same order."""
    dl = x[..., :-1] - x[..., 1:] - p.coupler_spacing_m
    phi = p.coupler_stiffness_n_per_m * (1.0 + p.coupler_nonlinearity_per_m2 * dl * dl) * dl
    if p.end_stop_m is not None:
        rate = v[..., :-1] - v[..., 1:]
        over = np.abs(dl) - p.end_stop_m
        sgn = np.sign(dl)
        loading = np.clip(0.5 + sgn * rate / (2.0 * END_STOP_TRANSITION_MPS), 0.0, 1.0)
        share = 1.0 - p.end_stop_absorption * (1.0 - loading)
        with np.errstate(invalid="ignore"):
            phi = phi + np.where(over > 0.0, sgn * over * p.end_stop_stiffness_n_per_m * share, 0.0)
    return dl, phi


def _same_bits(a: np.ndarray, b: np.ndarray) -> bool:
    """Equal to the bit (signed zeros told apart), NaN where the other is NaN."""
    nan = np.isnan(a)
    return a.shape == b.shape and bool(np.array_equal(nan, np.isnan(b))) and bool(
        np.array_equal(a[~nan].view(np.int64), b[~nan].view(np.int64)))


@pytest.mark.parametrize("stops", [None, (0.08, 5e6, 0.5), ([0.08, None, 0.05, 0.1, None], [5e6, 2e7, 1e7, 5e6, 2e7],
                                                          [0.5, 0.0, 0.6, 0.3, 0.2])],
                         ids=["no-stop", "stop", "per-coupler"])
def test_the_kernels_couplers_are_the_numpy_formulas_bit_for_bit(stops):
    kw = {} if stops is None else dict(end_stop_m=stops[0], end_stop_stiffness_n_per_m=stops[1],
                                       end_stop_absorption=stops[2])
    p = TrainPlant(M, X0, np.full(6, 20.0), coupler_nonlinearity_per_m2=[-0.5, -0.3, 0.2, -0.5, 0.0],
                   coupler_stiffness_n_per_m=[8e4, 9e4, 7e4, 8.5e4, 6e4], **kw)
    rng = np.random.default_rng(11)
    kern = p._kernel()
    for k in range(400):  # deflections inside and beyond the stops, rates on both curves and across ±v_t
        x = X0 + rng.normal(0.0, 0.06, 6) * (10.0 ** rng.integers(-6, 1))
        v = 20.0 + rng.normal(0.0, 0.02, 6) * (10.0 ** rng.integers(-3, 2))
        if k % 50 == 0:  # exact zeros, a NaN and an infinity
            x = X0.copy()
            x[3] = [np.nan, np.inf, X0[3]][k // 50 % 3]
            v[2] = v[3]
        dl, phi = kern.couplers(x, v)
        ref_dl, ref_phi = _numpy_couplers(p, x, v)
        assert _same_bits(dl, ref_dl) and _same_bits(phi, ref_phi), k
    p.position_m, p.speed_mps = x, v
    assert _same_bits(p.coupler_force_n, ref_phi) and _same_bits(p.deflection_m, ref_dl)
    assert _same_bits(p.snapshot().coupler_force_n, ref_phi)


@pytest.mark.parametrize("stops", [None, (0.08, 5e6, 0.5)], ids=["no-stop", "stop"])
def test_the_steps_couplers_are_the_numpy_formulas_of_the_new_state(stops):
    # the compiled step returns the couplers of the state it reaches; couplers() serves them for that state
    kw = {} if stops is None else dict(end_stop_m=stops[0], end_stop_stiffness_n_per_m=stops[1],
                                       end_stop_absorption=stops[2])
    singles = [TrainPlant(M, X0, np.array([20.0, 20.3, 19.6, 20.1, 20.4, 19.8]) * (1 + 0.1 * i),
                          coupler_stiffness_n_per_m=8e4 * (1 + i), actuator=BrakeActuator.realistic(), **kw)
               for i in range(2)]
    stack = stack_plants([TrainPlant(M, X0, np.array([20.0, 20.3, 19.6, 20.1, 20.4, 19.8]) * (1 + 0.1 * i),
                                     coupler_stiffness_n_per_m=8e4 * (1 + i), **kw) for i in range(2)]) \
        if stops is None else None
    rng = np.random.default_rng(4)
    for k in range(300):
        for p in singles:
            p.step(0.001, rng.normal(0.5, 1.0, 6) * M)
            dl, phi = p.couplers()
            assert p.couplers()[1] is phi  # the step's own arrays
            ref_dl, ref_phi = _numpy_couplers(p, p.position_m, p.speed_mps)
            assert _same_bits(dl, ref_dl) and _same_bits(phi, ref_phi), k
        if stack is not None:
            stack.step(0.001, np.stack([rng.normal(0.5, 1.0, 6) * M] * 2))
            ref_dl, ref_phi = _numpy_couplers(stack, stack.position_m, stack.speed_mps)
            assert _same_bits(stack.couplers()[0], ref_dl) and _same_bits(stack.couplers()[1], ref_phi), k
    p = singles[0]
    p.position_m = p.position_m + 0.01  # a state the step did not reach: computed afresh
    assert _same_bits(p.couplers()[1], _numpy_couplers(p, p.position_m, p.speed_mps)[1])
    p.reset()
    assert _same_bits(p.couplers()[0], np.zeros(5))


def test_a_stacks_couplers_are_its_plants_and_one_car_has_none():
    plants = [_plant(i) for i in range(3)]
    for i, p in enumerate(plants):
        p.position_m = X0 + 0.01 * (i + 1) * np.arange(6)
        p.speed_mps = np.full(6, 10.0) - 0.1 * i * np.arange(6)
    stack = stack_plants(plants)
    dl, phi = stack.couplers()
    assert dl.shape == phi.shape == (3, 5)
    for i, p in enumerate(plants):
        assert _same_bits(dl[i], p.couplers()[0]) and _same_bits(phi[i], p.couplers()[1])
    with pytest.raises(ValueError, match="shape"):  # one row for a stack of three
        stack._kernel().couplers(X0, np.zeros(6))
    one = TrainPlant([20000.0], [0.0], [1.0])
    assert one.couplers()[0].shape == one.couplers()[1].shape == (0,)


def test_the_coupled_plants_measurements_of_a_state_outlive_the_next_step():
    # the measurements hold the plant's own state arrays (no copies): a step must replace them
    from canbrake.build import CoupledPlant

    for plant in (TrainPlant(M, X0, np.full(6, 20.0)),
                  TrainPlant(M, X0, np.full(6, 20.0), actuator=BrakeActuator.realistic(), end_stop_m=0.08)):
        cp = CoupledPlant(plant)
        cp.step(0.001, {"brake_force_n": M * 0.8})
        m = cp.measurements()
        kept = {k: a.copy() for k, a in m.items()}
        for _ in range(3):
            cp.step(0.001, {"brake_force_n": M * 0.5})
        assert all(np.array_equal(m[k], kept[k]) for k in kept)
        assert not np.array_equal(cp.measurements()["position_m"], kept["position_m"])


@pytest.mark.parametrize("name", ["chen2023_case1_fine_rail", "emu8_low_adhesion", "li2024_ecp_over_can",
                                  "cai2014_case1"])
def test_the_plant_models_keep_no_reference_to_the_commands(name):
    # the plant node passes its own command arrays (no copies) and updates them in place as frames
    # arrive: a model stepped with arrays scribbled over after each step must run as one stepped with copies
    from pathlib import Path

    from canbrake.build import build_plant_model
    from canbrake.scenario import load_scenario

    scn = load_scenario(Path(__file__).resolve().parent.parent / "scenarios" / f"{name}.yaml")
    a, b = build_plant_model(scn), build_plant_model(scn)
    rng = np.random.default_rng(2)
    n = a.n_vehicles
    for k in range(30):
        cmds = {c: rng.uniform(0.0, 1.0, n) * (2e4 if c == "brake_force_n" else 1e3 if "torque" in c else 1.0)
                for c in a.command_names}
        if "brake_force_n" in cmds:
            cmds["brake_force_n"][k % n] = np.nan
        a.step(scn.control_period_s, cmds)
        b.step(scn.control_period_s, {c: x.copy() for c, x in cmds.items()})
        ma = a.measurements()
        for x in cmds.values():
            x.fill(-7.0e6)  # the next frames, written into the node's arrays
        mb = b.measurements()
        assert set(ma) == set(mb)
        assert all(_same_bits(np.asarray(ma[m], dtype=float), np.asarray(mb[m], dtype=float)) for m in ma), k


def test_nan_as_zero_is_numpys_where_bit_for_bit():
    rng = np.random.default_rng(5)
    a = rng.normal(0.0, 1e4, (3, 6))
    a[0, 1], a[1, 2], a[2, 3], a[2, 4], a[0, 5] = np.nan, -0.0, np.inf, -np.inf, -np.nan
    for x in (a, a[1], a[:, 2], a.T, a[:0]):  # rows, a strided column, a transpose, nothing
        got = nan_as_zero(x)
        assert got is not x and got.shape == x.shape
        assert _same_bits(got, np.where(np.isnan(x), 0.0, x))
    with pytest.raises(TypeError, match="float64"):
        nan_as_zero(a.astype(np.float32))


# ------------------------------------------------------------------ heavy haul
MT2 = hh.DraftGear("MT-2", (0.0, 0.02, 0.05, 0.073, 0.083), (0.0, 3e5, 9e5, 1.8e6, 2.27e6), 0.25, 0.005, 2e8, 2e8, 0.0)


def test_a_gear_loaded_slowly_follows_its_loading_curve_and_unloads_inside_the_band():
    bank = hh.CouplerBank([MT2])
    stretch = np.linspace(0.0, 0.095, 2000)  # slack, the curve, then solid beyond the stroke
    for s in stretch:
        f = bank.step(np.array([s]), np.zeros(1))[0]
        d = max(s - MT2.slack_m, 0.0)
        if d <= MT2.curve_m[-1]:
            want = np.interp(d, MT2.curve_m, MT2.curve_n)
        else:
            want = MT2.curve_n[-1] + MT2.k_solid_n_per_m * (d - MT2.curve_m[-1])
        assert f == pytest.approx(want, rel=1e-9, abs=1e-6)
    for s in stretch[::-1][:1500]:  # unloading: between f_u = r_u f_l and f_l
        f = bank.step(np.array([s]), np.zeros(1))[0]
        d = max(s - MT2.slack_m, 0.0)
        fl = np.interp(d, MT2.curve_m, MT2.curve_n) if d <= MT2.curve_m[-1] else \
            MT2.curve_n[-1] + MT2.k_solid_n_per_m * (d - MT2.curve_m[-1])
        fu = MT2.unloading_ratio * min(fl, MT2.curve_n[-1]) + (fl - MT2.curve_n[-1] if d > MT2.curve_m[-1] else 0.0)
        assert fu * (1 - 1e-12) - 1e-6 <= f <= fl * (1 + 1e-12) + 1e-6
    f_neg = hh.CouplerBank([MT2]).step(np.array([-0.04]), np.zeros(1))[0]
    assert f_neg == pytest.approx(-np.interp(0.035, MT2.curve_m, MT2.curve_n), rel=1e-12)  # compression


def test_ecp_cylinders_fill_along_their_lag_and_brake_with_eq_10():
    c = hh.Consist(mass_kg=np.full(3, 1e5), length_m=np.full(3, 12.0), davis_a=np.zeros(3), davis_b=np.zeros(3),
                   davis_c=np.zeros(3), is_loco=np.zeros(3, bool))
    k_full = np.array([20.0, 25.0, 30.0])
    ab = hh.AirBrake(c, apply_wave_mps=200.0, release_wave_mps=36.0, cylinder_tau_s=2.0, beta_c=0.8,
                     block_force_kn=k_full, n_blocks=np.full(3, 8.0), friction_coef=np.full(3, 0.481),
                     cylinder_pressure_pa=np.full(3, 430e3), mode="ecp")
    ab.ecp_target = np.array([1.0, 0.5, 0.0])
    v = np.array([10.0, 5.0, 0.0])
    for k in range(1, 301):
        f = ab.step(0.01 * k, 0.01, v)
    fill = ab.ecp_target * (1.0 - math.exp(-0.01 / 2.0 * 300))  # 1 - (1-g)^k = 1 - e^(-t/τ)
    assert ab.fill == pytest.approx(fill, rel=1e-9)
    kk = k_full * ab.fill
    phi = hh.friction_coefficient(kk, v / hh.KMH, 0.481)
    assert f == pytest.approx(1000.0 * 0.8 * 8.0 * phi * kk, rel=1e-12)
    assert f[2] == 0.0


# ------------------------------------------------------------------ adhesion
@pytest.mark.parametrize("torque", [3000.0, -8000.0, 30000.0])
def test_the_wheels_backward_euler_equations_are_solved(torque):
    cond = RailCondition(b1=1.786, b2=40.0, b3=10.0, c1=0.040, c2=3.78, c3=33.3, peak_mu0=0.35)
    ws = WheelSet(np.full(4, 117600.0), 200.0, 0.625, np.full(4, 20.0 / 0.625) * (1 + 0.01 * np.arange(4)),
                  variant="physical")
    w0, v0, dt, m = ws.omega_radps.copy(), 20.0, 1e-3, 4.8e5
    davis = (2000.0, 40.0, 6.0)
    v, fa = ws.step_coupled(np.full(4, torque), v0, cond, dt, mass_kg=m, davis=davis, newton_iters=8)
    w = ws.omega_radps
    # the residuals of J (ω − ω0) = dt (T − F R), m (v − v0) = dt (Σ F − F_d(v)), F from numpy (adhesion())
    assert np.max(np.abs(200.0 * (w - w0) - dt * (torque - fa * 0.625))) < 1e-6 * abs(torque) * dt
    fd = 2000.0 * math.copysign(1.0, v) + 40.0 * v + 6.0 * v * abs(v)
    assert m * (v - v0) - dt * (fa.sum() - fd) == pytest.approx(0.0, abs=1e-6 * max(abs(fa.sum()), fd) * dt)
    # the same with the resistance as a callable
    ws2 = WheelSet(np.full(4, 117600.0), 200.0, 0.625, w0.copy(), variant="physical")
    v2, fa2 = ws2.step_coupled(np.full(4, torque), v0, cond, dt, mass_kg=m, newton_iters=8,
                               resistance=lambda u: (2000.0 * np.sign(u) + 40.0 * u + 6.0 * u * abs(u),
                                                     40.0 + 12.0 * abs(u)))
    assert v2 == v and np.array_equal(fa2, fa)


@pytest.mark.parametrize("variant", ["paper", "physical"])
def test_the_steps_adhesion_is_the_numpy_adhesion_bit_for_bit(variant):
    """The kernel evaluates (λ, μ, F_a) at the new state itself (the plant's measurements use it):
    exactly what WheelSet.adhesion (slip_ratio, adhesion_coefficient in numpy) gives there,
    through standstill (the floored slip denominator), traction, braking and wheel lock."""
    cond = RailCondition(b1=2.046, b2=15.0, b3=10.0, c1=0.060, c2=12.9, c3=72.2, peak_mu0=0.25)
    rng = np.random.default_rng(5)
    ws = WheelSet(np.array([117600.0, 115000.0, 120000.0]), 80.0, 0.495, np.zeros(3), variant=variant)
    v = 0.0
    for k in range(600):
        torque = rng.normal(0.0, 20000.0, 3) if k % 50 else np.array([-1e6, 0.0, 1e6])
        v, fa = ws.step_coupled(torque, v, cond, 1e-3, mass_kg=96000.0, davis=(407.0, 291.6, 6.7))
        lam, mu, fa_np = ws.adhesion(v, cond)
        got = ws.last_adhesion[3]
        assert all(a.tobytes() == b.tobytes() for a, b in zip(got, (lam, mu, fa_np)))
        assert fa is got[2] and ws.finite
        if k % 100 == 0:
            v = 0.0  # a body at rest under turning wheels
