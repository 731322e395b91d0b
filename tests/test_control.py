"""Controller unit tests: chen2023, pi and the sliding-mode observer (no plant loop)."""
from __future__ import annotations

import math

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from canbrake.control.base import Observation, available, make_controller
from canbrake.control.chen import ChenConsensusController, barrier_gradient
from canbrake.control.observer import SlidingModeObserver
from canbrake.control.pi import PISpeedController

M = 20_000.0
A_REF = 3.5 / 3.6
V_REF = 25.0


def obs(i: int, v: np.ndarray, x: np.ndarray, age=None, *, tick=0, front=None, rear=None) -> Observation:
    n = len(v)
    return Observation(
        tick=tick,
        time_s=tick * 1e-3,
        speed_mps=float(v[i]),
        position_m=float(x[i]),
        ref_speed_mps=V_REF,
        ref_decel_mps2=A_REF,
        peer_speed_mps=np.asarray(v, dtype=float),
        peer_position_m=np.asarray(x, dtype=float),
        peer_age_s=np.zeros(n) if age is None else np.asarray(age, dtype=float),
        deflection_front_m=front,
        deflection_rear_m=rear,
    )


X_NOM = np.array([10.0, 20.0, 30.0, 40.0])


def chen(i: int = 1, n: int = 4, **kw) -> ChenConsensusController:
    kw.setdefault("nominal_spacing_m", -10.0)
    return ChenConsensusController(car_index=i, n_cars=n, mass_kg=M, dt_s=1e-3, **kw)


def test_registry_builds_both_controllers():
    assert {"chen2023", "pi"} <= set(available())
    c = make_controller("chen2023", {"k": 10.0}, car_index=0, n_cars=6, mass_kg=M, dt_s=1e-3)
    assert isinstance(c, ChenConsensusController) and c.k == 10.0
    p = make_controller("pi", {}, car_index=0, n_cars=6, mass_kg=M, dt_s=1e-3)
    assert isinstance(p, PISpeedController)
    from canbrake.control.base import ControllerError

    with pytest.raises(ControllerError) as e:  # checked against the constructor's signature
        make_controller("chen2023", {"no_such_gain": 1.0}, car_index=0, n_cars=6, mass_kg=M, dt_s=1e-3)
    assert e.value.param == "no_such_gain"
    with pytest.raises(ValueError):
        chen(deflection_source="telepathy")


def test_on_reference_and_undeflected_the_command_is_the_feedforward():
    v = np.full(4, V_REF)
    out = chen().step(obs(1, v, X_NOM))
    assert out.brake_force_n == pytest.approx(M * A_REF)
    assert set(out.diagnostics) == set(ChenConsensusController.diagnostic_names)


def test_consensus_and_tracking_signs():
    v = np.full(4, V_REF)
    v_fast = v.copy()
    v_fast[1] += 0.1  # car 1 faster than the reference and its peers
    out = chen().step(obs(1, v_fast, X_NOM))
    # u1 = m α1 Σ(v_i − v_j) = m·120·3·0.1; u3 = m(36·0.1 + a*)
    assert out.diagnostics["u_consensus_n"] == pytest.approx(M * 120 * 0.3)
    assert out.diagnostics["u_tracking_n"] == pytest.approx(M * (36 * 0.1 + A_REF))
    v_slow_peers = v.copy()
    v_slow_peers[[0, 2, 3]] -= 0.1
    assert chen().step(obs(1, v_slow_peers, X_NOM)).diagnostics["u_consensus_n"] > 0  # brake harder


def test_deflection_from_peer_positions_acts_like_the_coupler():
    # Table 2 orientation: Δl_1 = x_1 − x_2 − (−10). Car 1 closer to car 2 by 2 mm: Δl_1 = +2 mm
    x = X_NOM.copy()
    x[1] += 0.002
    v = np.full(4, V_REF)
    c = chen()
    out = c.step(obs(1, v, x))
    front, rear = out.diagnostics["deflection_front_m"], out.diagnostics["deflection_rear_m"]
    assert front == pytest.approx(-0.002) and rear == pytest.approx(0.002)
    # Σ_j b_ij (x_i − x_j − θ_ij) = Δl_1 − Δl_0 = 4 mm; the coupler pushes car 1 back by κ·4 mm too
    assert out.diagnostics["u_consensus_n"] == pytest.approx(M * 100 * 0.004)
    assert out.diagnostics["u_potential_n"] > 0
    # local deflection source gives the same result
    c_local = chen(deflection_source="local")
    out_local = c_local.step(obs(1, v, x, front=-0.002, rear=0.002))
    assert out_local.brake_force_n == pytest.approx(out.brake_force_n)


def test_spacing_is_latched_when_not_given():
    c = ChenConsensusController(car_index=1, n_cars=4, mass_kg=M, dt_s=1e-3)
    v = np.full(4, V_REF)
    assert c.step(obs(1, v, X_NOM)).diagnostics["deflection_rear_m"] == 0.0
    x = X_NOM.copy()
    x[2] += 0.003
    assert c.step(obs(1, v, x, tick=1)).diagnostics["deflection_rear_m"] == pytest.approx(-0.003)


def test_barrier_is_zero_at_origin_odd_and_unbounded():
    for kind in ("inverse_square", "log"):
        assert barrier_gradient(0.0, -1.0, 1.0, kind) == 0.0
        assert barrier_gradient(0.5, -1.0, 1.0, kind) == pytest.approx(-barrier_gradient(-0.5, -1.0, 1.0, kind))
        assert barrier_gradient(0.5, -1.0, 1.0, kind) > 0
        near = barrier_gradient(0.998, -1.0, 1.0, kind, clip=0.999)
        assert near > 100 * barrier_gradient(0.5, -1.0, 1.0, kind)  # grows without bound at the limit
        # beyond the bound it stays at the clipped (large, finite, right-signed) value
        assert barrier_gradient(3.0, -1.0, 1.0, kind) == barrier_gradient(0.99, -1.0, 1.0, kind)
    # asymmetric bounds still give ∇U(0) = 0
    assert barrier_gradient(0.0, -0.5, 2.0) == 0.0


def test_the_scalar_barrier_equals_the_batch_form_bit_for_bit():
    """The compiled barrier_gradient and the numpy barrier_gradient_many are two implementations
    of one formula: the same floats, inside, at and beyond the bounds, for both kinds."""
    from canbrake.control.chen import barrier_gradient_many

    z = np.concatenate([np.linspace(-3.0, 3.0, 601), [-0.99, 0.99, -1.0, 1.0, 1e-300, -0.0]])
    for kind in ("inverse_square", "log"):
        for lo, hi, clip in ((-1.0, 1.0, 0.99), (-0.5, 2.0, 0.9), (-1.0, 1.0, 0.999)):
            many = barrier_gradient_many(z, lo, hi, kind, clip)
            one = np.array([barrier_gradient(float(x), lo, hi, kind, clip) for x in z])
            assert one.tobytes() == many.tobytes(), (kind, lo, hi, clip)
    with pytest.raises(ValueError):
        barrier_gradient(0.1, -1.0, 1.0, "cubic")


def test_the_compiled_step_reads_its_gains_at_every_call_and_checks_its_arrays():
    """step (compiled) reads the controller's parameters when called, so a gain changed on the
    object (as chen2023_compensated schedules them) acts at once; peer arrays of another dtype
    give the floats of float arrays; arrays shorter than the train raise, never read past their end."""
    x = X_NOM + np.array([0.0, 0.002, -0.001, 0.0])
    v = np.array([25.0, 25.1, 24.9, 25.0])
    changed, built = chen(), chen(alpha1=240.0, delta=3.0, k=20.0)
    changed.alpha1, changed.delta, changed.k = 240.0, 3.0, 20.0
    for t in range(5):
        a, b = changed.step(obs(1, v, x, tick=t)), built.step(obs(1, v, x, tick=t))
        assert a.brake_force_n == b.brake_force_n and a.diagnostics == b.diagnostics
    ints, floats = chen(), chen()
    vi, xi = np.array([25, 26, 24, 25]), np.array([10, 20, 30, 40])
    for t in range(3):
        o = obs(1, vi, xi, tick=t)
        oi = Observation.of(**{**o.__dict__, "peer_speed_mps": vi, "peer_position_m": xi})
        assert ints.step(oi).brake_force_n == floats.step(o).brake_force_n
    short = Observation.of(**{**obs(1, v, x).__dict__, "peer_speed_mps": v[:1]})
    with pytest.raises(IndexError):
        chen().step(short)
    short = Observation.of(**{**obs(3, v, x).__dict__, "peer_position_m": x[:2]})
    with pytest.raises(IndexError):
        chen(i=2).step(short)


def test_literal_readings_are_available():
    v = np.full(4, V_REF)
    out = chen(feedforward="velocity").step(obs(1, v, X_NOM))
    assert out.brake_force_n == pytest.approx(M * V_REF)  # the printed m(k v_e + v*)
    v2 = v.copy()
    v2[0] += 0.1
    scaled = chen().step(obs(1, v2, X_NOM)).diagnostics["u_consensus_n"]
    raw = chen(mass_scaled=False).step(obs(1, v2, X_NOM)).diagnostics["u_consensus_n"]
    assert scaled == pytest.approx(M * raw)


def test_ablation_flags_remove_their_terms():
    x = X_NOM.copy()
    x[1] += 0.002
    v = np.full(4, V_REF)
    v[0] += 0.1
    out = chen(potential_field=False, consensus=False, observer=False).step(obs(1, v, x))
    assert out.diagnostics["u_potential_n"] == 0.0
    assert out.diagnostics["u_consensus_n"] == 0.0
    assert out.diagnostics["u_observer_n"] == 0.0
    assert out.brake_force_n == pytest.approx(M * A_REF)


def test_a_peer_position_one_period_old_drives_the_barrier_to_its_clip_unless_extrapolated():
    """Why Chen's controller diverges in realtime runs at 1 ms (docs/performance.md, session 21):
    it takes a coupler's deflection as the difference of the two cars' broadcast positions, so a
    neighbour's state one period late (its frame missed the ECU's compute deadline) is off by
    v * T = 25 m/s * 1 ms = 2.5 cm, 2.5x the +-1 cm bound: with ``hold`` the barrier gradient is
    taken at its clip and the command is ~1e11 N; ``extrapolate`` moves the position on by its
    age and the potential term stays that of the true deflection (zero here)."""
    v = np.full(4, V_REF)
    x = X_NOM.copy()
    x[0] -= V_REF * 1e-3 - 0.5 * A_REF * 1e-6  # car 0's position as sent one period ago (it decelerates)
    age = np.array([1e-3, 0.0, 0.0, 0.0])
    hold = chen(stale_policy="hold").step(obs(1, v, x, age))
    assert abs(hold.diagnostics["deflection_front_m"]) > 0.02  # 2.5 cm seen where there is none
    assert abs(hold.diagnostics["u_potential_n"]) > 1e10
    ext = chen(stale_policy="extrapolate").step(obs(1, v, x, age))
    assert abs(ext.diagnostics["deflection_front_m"]) < 1e-9
    assert abs(ext.diagnostics["u_potential_n"]) < 1e-3


def test_stale_policies():
    v = np.full(4, V_REF)
    v[3] += 1.0
    age = np.array([0.0, 0.0, 0.0, 0.5])
    hold = chen(stale_policy="hold").step(obs(1, v, X_NOM, age)).diagnostics["u_consensus_n"]
    drop = chen(stale_policy="drop", stale_timeout_s=0.1).step(obs(1, v, X_NOM, age)).diagnostics["u_consensus_n"]
    assert hold == pytest.approx(M * 120 * -1.0)
    assert drop == 0.0
    ext = chen(stale_policy="extrapolate").step(obs(1, v, X_NOM, age)).diagnostics["u_consensus_n"]
    assert ext == pytest.approx(M * 120 * -(1.0 - A_REF * 0.5))
    # NaN = never received: ignored by every policy, also for deflection
    v_nan = np.full(4, V_REF)
    v_nan[3] = math.nan
    x_nan = X_NOM.copy()
    x_nan[2] = math.nan
    out = chen().step(obs(1, v_nan, x_nan, [0, 0, math.inf, math.inf]))
    assert math.isnan(out.diagnostics["deflection_rear_m"])
    assert np.isfinite(out.brake_force_n)


def test_observer_converges_to_a_constant_disturbance():
    m, dt, d = 20_000.0, 1e-3, 3_000.0  # +3 kN pushing forward: φ/m = 0.15 m/s²
    ob = SlidingModeObserver(m, dt)
    v, x, force = 25.0, 0.0, 15_000.0
    est = []
    for _ in range(100):
        ob.update(x, v)
        est.append(ob.phi_hat_mps2)
        ob.predict(force)
        v += dt * (-force + d) / m
        x += dt * v
    est = np.array(est)
    assert est[-1] == pytest.approx(d / m, rel=0.01)
    assert np.all(np.abs(est[30:] - d / m) < 0.02 * d / m)  # within 2 % after 30 ms


def test_observer_anti_windup_after_a_skid():
    m, dt = 20_000.0, 1e-3
    ob = SlidingModeObserver(m, dt)
    v = 25.0
    for k in range(1500):  # 1 s skid: commanded 50 kN, rail takes 5 kN; then 0.5 s normal
        ob.update(0.0, v)
        ob.predict(50_000.0)
        applied = 5_000.0 if k < 1000 else 50_000.0
        v += dt * (-applied) / m
    assert abs(ob.phi_hat_mps2) < 0.01  # not pinned at +γ2 after adhesion returns
    with pytest.raises(ValueError):
        SlidingModeObserver(m, dt, gamma2_mps2=50.0, boundary_vel_mps=0.01)  # unstable when sampled


def test_saturation_limits_the_command_and_drives_the_observer():
    v = np.full(4, V_REF + 1.0)
    c = chen(brake_force_max_n=1.5 * M)
    assert c.step(obs(1, v, X_NOM)).brake_force_n == 1.5 * M


def test_pi_feedforward_and_antiwindup():
    p = PISpeedController(0, 1, M, 1e-3, kp=2.0, ki=1.0, brake_force_max_n=1.5 * M)
    o = obs(0, np.array([V_REF]), np.array([0.0]))
    assert p.step(o).brake_force_n == pytest.approx(M * A_REF)
    fast = obs(0, np.array([V_REF + 5.0]), np.array([0.0]))
    for _ in range(1000):
        out = p.step(fast)
    assert out.brake_force_n == 1.5 * M
    assert p.integral_m == 0.0  # frozen while saturated in the error's direction
    slow = obs(0, np.array([V_REF - 0.1]), np.array([0.0]))
    p.step(slow)
    assert p.integral_m == pytest.approx(-0.1e-3)


def test_observer_defaults_adapt_to_a_10ms_period():
    c = ChenConsensusController(car_index=0, n_cars=4, mass_kg=M, dt_s=0.01, nominal_spacing_m=-10.0)
    assert c._obs.dt_s * c._obs.gamma2_mps2 / c._obs.boundary_vel_mps <= 0.5
    assert c._obs.error_limit_mps == pytest.approx(5 * c._obs.boundary_vel_mps)
    out = c.step(obs(0, np.full(4, V_REF), X_NOM))
    assert out.brake_force_n == pytest.approx(M * A_REF)


def test_per_mass_ratings_scale_with_the_car():
    c = chen(brake_rating_mps2=1.4, traction_rating_mps2=1.0)
    assert c.brake_force_max_n == pytest.approx(1.4 * M) and c.traction_force_max_n == pytest.approx(M)
    p = PISpeedController(0, 1, 18_000.0, 1e-3, brake_rating_mps2=1.4, brake_force_max_n=20_000.0)
    assert p.brake_force_max_n == 20_000.0  # the tighter limit wins


# ---------------------------------------------------------------- the batch form (canbrake.batch)
@pytest.mark.parametrize("car", [0, 2, 5])
@pytest.mark.parametrize("kw", [
    {},
    {"nominal_spacing_m": None, "barrier": "log", "velocity_graph": "neighbours"},
    {"observer_cancellation": "kd", "brake_rating_mps2": 1.2, "traction_rating_mps2": 0.8,
     "observer_actuator_lag_s": 0.3, "feedforward": "velocity"},
    {"consensus": False, "potential_field": False, "observer": False},
])
def test_step_batch_equals_step_point_by_point(car, kw):
    """step_batch on P points at once gives every point the floats its own controller's step gives,
    over 300 ticks of noisy, partly missing peer data (NaN, which delays the spacing latch) and
    deflections beyond the barrier's bounds and the ratings (so every branch is taken)."""
    n, P, dt = 6, 7, 1e-3
    kw = {"nominal_spacing_m": -10.0, **kw}
    rng = np.random.default_rng(car)
    mk = lambda: ChenConsensusController(car_index=car, n_cars=n, mass_kg=M, dt_s=dt, **kw)  # noqa: E731
    batch, singles = mk(), [mk() for _ in range(P)]
    assert batch.batchable()
    x0 = np.arange(n) * 10.0 + 10.0
    for k in range(300):
        v = 25.0 - 0.001 * k + rng.normal(0, 0.05, (P, n))
        x = x0 + 25.0 * k * dt + rng.normal(0, 0.008 * (1 + k % 3), (P, n))
        px = x.copy()
        px[rng.random((P, n)) < (0.6 if k < 20 else 0.1)] = np.nan
        pv = np.where(np.isnan(px), np.nan, v)
        pv[:, car], px[:, car] = v[:, car], x[:, car]
        age = np.where(np.isnan(px), np.inf, 0.0)
        vr = np.full(P, V_REF) - 0.01 * k
        ar = np.full(P, A_REF)
        out = batch.step_batch(Observation(tick=k, time_s=k * dt, speed_mps=v[:, car], position_m=x[:, car],
                                           ref_speed_mps=vr, ref_decel_mps2=ar, peer_speed_mps=pv,
                                           peer_position_m=px, peer_age_s=age))
        for p, ctrl in enumerate(singles):
            ref = ctrl.step(Observation(tick=k, time_s=k * dt, speed_mps=float(v[p, car]), position_m=float(x[p, car]),
                                        ref_speed_mps=float(vr[p]), ref_decel_mps2=float(ar[p]), peer_speed_mps=pv[p],
                                        peer_position_m=px[p], peer_age_s=age[p]))
            assert np.float64(out.brake_force_n[p]).tobytes() == np.float64(ref.brake_force_n).tobytes(), (k, p)
            for name in ChenConsensusController.diagnostic_names:
                got = np.broadcast_to(out.diagnostics[name], (P,))[p]
                assert got == ref.diagnostics[name] or (math.isnan(got) and math.isnan(ref.diagnostics[name])), \
                    (k, p, name)


@pytest.mark.parametrize("kw", [
    {},
    {"nominal_spacing_m": None, "barrier": "log", "velocity_graph": "neighbours"},
    {"observer_cancellation": "kd", "brake_rating_mps2": 1.2, "traction_rating_mps2": 0.8,
     "observer_actuator_lag_s": 0.3, "feedforward": "velocity"},
])
def test_slots_stepped_as_one_group_equal_their_own_controllers(kw):
    """ChenBatch over every car of the train (different masses) and P points, flattened point-major,
    gives each element the floats of its own car's controller, bit for bit: the first and last cars'
    missing neighbour and the peers outside the velocity graph contribute exact zeros."""
    from canbrake.control.chen import ChenBatch

    n, P, dt = 6, 4, 1e-3
    kw = {"nominal_spacing_m": -10.0, **kw}
    masses = [18000.0, 21000.0, 19500.0, 20000.0, 19700.0, 22000.0]
    rng = np.random.default_rng(7)
    mk = lambda i: ChenConsensusController(car_index=i, n_cars=n, mass_kg=masses[i], dt_s=dt, **kw)  # noqa: E731
    group = [mk(i) for i in range(n)]
    assert len({ChenConsensusController.group_key(c) for c in group}) == 1
    grp = ChenConsensusController.batch_group(group, P)
    assert isinstance(grp, ChenBatch)
    singles = [[mk(i) for i in range(n)] for _ in range(P)]
    x0 = -np.arange(n) * 10.0 + 60.0
    for k in range(200):
        v = 25.0 - 0.001 * k + rng.normal(0, 0.05, (P, n))
        x = x0 + 25.0 * k * dt + rng.normal(0, 0.008 * (1 + k % 3), (P, n))
        px = np.repeat(x[:, None, :], n, axis=1)                 # (P, receiver, sender)
        px[rng.random((P, n, n)) < (0.6 if k < 20 else 0.1)] = np.nan
        pv = np.where(np.isnan(px), np.nan, np.repeat(v[:, None, :], n, axis=1))
        for i in range(n):
            px[:, i, i], pv[:, i, i] = x[:, i], v[:, i]
        age = np.where(np.isnan(px), np.inf, 0.0)
        vr, ar = V_REF - 0.01 * k, A_REF
        N = P * n
        out = grp.step(Observation(tick=k, time_s=k * dt, speed_mps=v.reshape(N), position_m=x.reshape(N),
                                   ref_speed_mps=np.full(N, vr), ref_decel_mps2=np.full(N, ar),
                                   peer_speed_mps=pv.reshape(N, n), peer_position_m=px.reshape(N, n),
                                   peer_age_s=age.reshape(N, n)))
        for p in range(P):
            for i in range(n):
                ref = singles[p][i].step(Observation(
                    tick=k, time_s=k * dt, speed_mps=float(v[p, i]), position_m=float(x[p, i]), ref_speed_mps=vr,
                    ref_decel_mps2=ar, peer_speed_mps=pv[p, i], peer_position_m=px[p, i], peer_age_s=age[p, i]))
                e = p * n + i
                assert np.float64(out.brake_force_n[e]).tobytes() == np.float64(ref.brake_force_n).tobytes(), (k, p, i)
                for name in ChenConsensusController.diagnostic_names:
                    got = np.broadcast_to(out.diagnostics[name], (N,))[e]
                    want = ref.diagnostics[name]
                    assert np.float64(got).tobytes() == np.float64(want).tobytes() or (
                        math.isnan(got) and math.isnan(want)), (k, p, i, name)


def test_step_batch_is_offered_only_where_it_is_exact():
    assert not chen(stale_policy="extrapolate").batchable()
    assert not chen(deflection_source="local").batchable()
    from canbrake.control.chen_compensated import ChenCompensatedController

    assert not ChenCompensatedController(1, 12, M, 1e-3, nominal_spacing_m=-10.0).batchable()  # > 9 cars


@pytest.mark.parametrize("kw", [{}, {"ki": 0.3, "kp": 1.5, "brake_rating_mps2": 1.0, "traction_rating_mps2": 0.5},
                                {"ki": 2.0, "feedforward": False, "brake_force_max_n": 5000.0}])
def test_pi_step_batch_equals_step_point_by_point(kw):
    """The PI controller's batch form: every point's force, error and integral equal its own
    controller's, through saturation in both directions (the integral frozen there)."""
    P, dt = 9, 0.01
    rng = np.random.default_rng(7)
    batch = PISpeedController(2, 6, M, dt, **kw)
    singles = [PISpeedController(2, 6, M, dt, **kw) for _ in range(P)]
    assert batch.batchable()
    for k in range(400):
        v = V_REF + rng.normal(0, 2.0, P) + 3 * math.sin(k / 40)
        vr, ar = np.full(P, V_REF), np.full(P, A_REF)
        out = batch.step_batch(Observation(tick=k, time_s=k * dt, speed_mps=v, position_m=np.zeros(P),
                                           ref_speed_mps=vr, ref_decel_mps2=ar, peer_speed_mps=np.zeros((P, 6)),
                                           peer_position_m=np.zeros((P, 6)), peer_age_s=np.zeros((P, 6))))
        for p, c in enumerate(singles):
            ref = c.step(obs(0, np.array([v[p]]), np.zeros(1), tick=k))
            assert out.brake_force_n[p] == ref.brake_force_n and out.diagnostics["integral_m"][p] == c.integral_m


@pytest.mark.parametrize("kw", [{}, {"speed_alignment": "reference", "predict": False, "command_latency_s": 0.004},
                                {"align": False, "gain_schedule": False, "observer_delay": False},
                                {"barrier": "log", "delay_margin": 0.3, "latency_decay_s": 0.05}])
@pytest.mark.parametrize("car", [0, 3])
def test_compensated_step_batch_equals_step_point_by_point(kw, car):
    """chen2023_compensated's batch form: per point the same latency estimate, scheduled gains
    (the barrier clip's bisection included), time-aligned peers and delayed observer input as its
    own controller, bit for bit, with peer ages that jump between 0 and 30 periods and lost peers."""
    from canbrake.control.chen_compensated import ChenCompensatedController

    n, P, dt = 6, 6, 1e-3
    rng = np.random.default_rng(11 + car)
    mk = lambda: ChenCompensatedController(car, n, M, dt, nominal_spacing_m=-10.0, **kw)  # noqa: E731
    batch, singles = mk(), [mk() for _ in range(P)]
    assert batch.batchable()
    x0 = np.arange(n) * 10.0 + 10.0
    for k in range(400):
        v = 25.0 - 0.001 * k + rng.normal(0, 0.02, (P, n))
        x = x0 + 25.0 * k * dt + rng.normal(0, 0.004, (P, n))
        lag = rng.integers(0, 30, (P, n)) * (rng.random((P, n)) < 0.5)
        age = lag * dt
        px, pv = x.copy(), v.copy()
        lost = rng.random((P, n)) < 0.1
        px[lost], pv[lost], age[lost] = np.nan, np.nan, np.inf
        px[:, car], pv[:, car], age[:, car] = x[:, car], v[:, car], 0.0
        ar = np.full(P, A_REF)
        out = batch.step_batch(Observation(tick=k, time_s=k * dt, speed_mps=x[:, car] * 0 + v[:, car],
                                           position_m=x[:, car], ref_speed_mps=np.full(P, V_REF), ref_decel_mps2=ar,
                                           peer_speed_mps=pv, peer_position_m=px, peer_age_s=age))
        for p, c in enumerate(singles):
            ref = c.step(Observation(tick=k, time_s=k * dt, speed_mps=float(v[p, car]), position_m=float(x[p, car]),
                                     ref_speed_mps=V_REF, ref_decel_mps2=A_REF, peer_speed_mps=pv[p],
                                     peer_position_m=px[p], peer_age_s=age[p]))
            assert np.float64(out.brake_force_n[p]).tobytes() == np.float64(ref.brake_force_n).tobytes(), (k, p)
            for name in ("latency_estimate_s", "gain_scale", "u_potential_n", "observer_accel_mps2"):
                got = np.broadcast_to(out.diagnostics[name], (P,))[p]
                assert got == ref.diagnostics[name] or (math.isnan(got) and math.isnan(ref.diagnostics[name])), \
                    (k, p, name)


def test_brake_functions_easing_batch_form_equals_step():
    """Easing around a batch-capable controller: the cap (speeds near and at rest) per point as the
    scalar wrapper applies it; WSP has no batch form."""
    from canbrake.control.brake_functions import BrakeFunctions

    P = 8
    mk = lambda: BrakeFunctions(PISpeedController(1, 4, M, 0.01, kp=3.0), easing_tau_s=1.0, lag_s=0.3)  # noqa: E731
    batch, singles = mk(), [mk() for _ in range(P)]
    assert batch.batchable() and not BrakeFunctions(PISpeedController(1, 4, M, 0.01), wsp=object()).batchable()
    v = np.array([0.0, 5e-4, 0.2, 0.5, 1.0, 3.0, 10.0, np.nan])
    for k in range(50):
        vr = np.full(P, 2.0 - 0.04 * k)
        out = batch.step_batch(Observation(tick=k, time_s=k * 0.01, speed_mps=v, position_m=np.zeros(P),
                                           ref_speed_mps=vr, ref_decel_mps2=np.full(P, 1.0),
                                           peer_speed_mps=np.zeros((P, 4)), peer_position_m=np.zeros((P, 4)),
                                           peer_age_s=np.zeros((P, 4))))
        for p, c in enumerate(singles):
            ref = c.step(Observation(tick=k, time_s=k * 0.01, speed_mps=float(v[p]), position_m=0.0,
                                     ref_speed_mps=float(vr[p]), ref_decel_mps2=1.0, peer_speed_mps=np.zeros(4),
                                     peer_position_m=np.zeros(4), peer_age_s=np.zeros(4)))
            for a, b in ((out.brake_force_n[p], ref.brake_force_n),
                         (out.diagnostics["easing_cap_n"][p], ref.diagnostics["easing_cap_n"])):
                assert a == b or (math.isnan(a) and math.isnan(b)), (k, p)


# --- the compiled stale policies against the Python law they replaced (session 24) -------------
def _ref_peer_ok(c, j, o):
    age = o.peer_age_s[j]
    if not (o.peer_position_m[j] == o.peer_position_m[j]):
        return False
    return not (c.stale_policy == "drop" and age > c.stale_timeout_s)


def _ref_peer_position(c, j, o):
    x = float(o.peer_position_m[j])
    if c.stale_policy == "extrapolate":
        age = float(o.peer_age_s[j])
        if age > 0 and math.isfinite(age):
            x += float(o.peer_speed_mps[j]) * age - 0.5 * o.ref_decel_mps2 * age * age
    return x


def _ref_deflections(c, o, spacing):
    """(front, rear) as ChenConsensusController._deflections computed them; ``spacing`` the
    [front, rear, latched] state, updated as the controller's."""
    i, n, x = c.car_index, c.n_cars, o.position_m
    if not spacing[2]:
        if not ((i == 0 or _ref_peer_ok(c, i - 1, o)) and (i == n - 1 or _ref_peer_ok(c, i + 1, o))):
            return None, None
        if i > 0:
            spacing[0] = _ref_peer_position(c, i - 1, o) - x
        if i < n - 1:
            spacing[1] = x - _ref_peer_position(c, i + 1, o)
        spacing[2] = True
    front = rear = None
    if i > 0 and _ref_peer_ok(c, i - 1, o):
        front = _ref_peer_position(c, i - 1, o) - x - spacing[0]
    if i < n - 1 and _ref_peer_ok(c, i + 1, o):
        rear = x - _ref_peer_position(c, i + 1, o) - spacing[1]
    return front, rear


def _ref_speed_disagreement(c, o):
    pv = o.peer_speed_mps
    if c.stale_policy == "hold":  # peer by peer in index order (as the batch form sums)
        total, cnt = 0.0, 0
        for j in np.flatnonzero(c._adj_a):
            if pv[j] == pv[j]:
                total += float(pv[j])
                cnt += 1
        return 0.0 if cnt == 0 else cnt * o.speed_mps - total
    ok = c._adj_a & (pv == pv)
    if c.stale_policy == "drop":
        ok &= o.peer_age_s <= c.stale_timeout_s
    cnt = int(np.count_nonzero(ok))
    if cnt == 0:
        return 0.0
    total = float(pv[ok].sum())
    if c.stale_policy == "extrapolate":
        ages = o.peer_age_s[ok]
        ages = ages[np.isfinite(ages)]
        total -= o.ref_decel_mps2 * float(ages.sum())
    return cnt * o.speed_mps - total


_value = st.one_of(st.floats(-50, 50, allow_nan=False), st.sampled_from([0.0, -0.0, math.nan]))
_age = st.one_of(st.floats(0, 0.2), st.sampled_from([0.0, -0.0, 1e-3, math.inf, math.nan, 0.05]))


@settings(max_examples=150, deadline=None)
@given(n=st.sampled_from([2, 3, 6, 9, 17, 70, 140]), data=st.data(),
       policy=st.sampled_from(["extrapolate", "drop", "hold"]), graph=st.sampled_from(["all", "neighbours"]),
       latched=st.booleans())
def test_compiled_stale_policies_give_the_floats_of_the_python_law(n, data, policy, graph, latched):
    """Deflections and speed disagreement under every stale policy, computed by the compiled step,
    equal bit for bit what the Python law (kept here as the reference) computed: NaN peers, ages
    0, inf, NaN, stale or fresh, the spacing latched at the first usable positions or given, trains
    whose peer sums numpy makes pairwise (9 cars and more)."""
    i = data.draw(st.integers(0, n - 1))
    periods = data.draw(st.integers(1, 3))
    c = ChenConsensusController(car_index=i, n_cars=n, mass_kg=M, dt_s=1e-3, stale_policy=policy,
                                stale_timeout_s=0.03, velocity_graph=graph,
                                nominal_spacing_m=-10.0 if latched else None)
    spacing = [c._spacing_front, c._spacing_rear, c._latched]
    for k in range(periods):
        v = np.array(data.draw(st.lists(_value, min_size=n, max_size=n)))
        x = np.array(data.draw(st.lists(_value, min_size=n, max_size=n))) + 10.0 * np.arange(n)
        age = np.array(data.draw(st.lists(_age, min_size=n, max_size=n)))
        v[i] = abs(v[i]) if v[i] == v[i] else 20.0  # its own speed and position are measured
        x[i] = 10.0 * i
        o = obs(i, v, x, age, tick=k)
        front, rear = _ref_deflections(c, o, spacing)
        sd = _ref_speed_disagreement(c, o)
        d = c.step(o).diagnostics
        nan = math.nan
        assert np.array_equal(np.array([d["deflection_front_m"], d["deflection_rear_m"]]),
                              np.array([nan if front is None else front, nan if rear is None else rear]),
                              equal_nan=True)
        pos = 0.0
        if rear is not None:
            pos += rear
        if front is not None:
            pos -= front
        u1 = c._scale * (c.alpha1 * sd + c.alpha2 * pos)
        assert np.array_equal(np.array(d["u_consensus_n"]), np.array(c.brake_gain * u1), equal_nan=True)
        assert math.copysign(1.0, d["u_consensus_n"]) == math.copysign(1.0, c.brake_gain * u1) or u1 != u1
        assert (c._spacing_front, c._spacing_rear, c._latched) == tuple(spacing) or not all(
            s == s for s in spacing[:2] if s is not None)
