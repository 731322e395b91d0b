"""Plant tests against closed-form physics (canbrake.physics)."""
from __future__ import annotations

import math

import numpy as np
import pytest

from canbrake.physics import (
    BrakeActuator,
    DavisResistance,
    DisturbanceForce,
    RailConditions,
    RailEvent,
    TrainPlant,
    davis_1926,
)

DT = 1e-3


def run(plant: TrainPlant, cmd, seconds: float, dt: float = DT) -> None:
    cmd = np.asarray(cmd, dtype=float)
    for _ in range(int(round(seconds / dt))):
        plant.step(dt, cmd)


def test_single_car_constant_brake_matches_analytic_solution():
    # m dv/dt = -(F + c0 + c1 v)  ->  v(t) = (v0 + b/a) e^{-a t} - b/a,  a = c1/m, b = (F + c0)/m
    m, v0, F, c0, c1 = 20_000.0, 25.0, 20_000.0, 650.0, 40.0
    plant = TrainPlant([m], [0.0], [v0], resistance=DavisResistance.uniform(1, c0, c1, 0.0))
    run(plant, [F], 5.0)
    a, b = c1 / m, (F + c0) / m
    v_exact = (v0 + b / a) * math.exp(-a * 5.0) - b / a
    x_exact = (v0 + b / a) * (1 - math.exp(-a * 5.0)) / a - b / a * 5.0
    assert plant.speed_mps[0] == pytest.approx(v_exact, abs=2e-3)
    assert plant.position_m[0] == pytest.approx(x_exact, abs=2e-2)
    # instantaneous acceleration = -(F + f(v))/m
    assert plant.accel_mps2[0] == pytest.approx(-(F + c0 + c1 * plant.speed_mps[0]) / m, rel=1e-3)


def test_quadratic_resistance_and_grade_in_acceleration():
    m, v0 = 20_000.0, 20.0
    res = davis_1926([m])
    theta = 0.01  # uphill towards +x
    plant = TrainPlant([m], [0.0], [v0], resistance=res, grade_rad=theta)
    plant.step(DT, [5_000.0])
    v = plant.speed_mps[0]
    expected = -(5_000.0 + res.magnitude_n(np.array([v0]))[0] + m * 9.81 * math.sin(theta)) / m
    assert (v - v0) / DT == pytest.approx(expected, rel=1e-6)


@pytest.mark.parametrize("front_is_higher_index", [True, False])
def test_coupler_force_sign_and_symmetry(front_is_higher_index):
    m = np.array([18_000.0, 22_000.0])
    if front_is_higher_index:  # Chen Table 2: car 1 at x=10, car 2 at x=20, travelling to +x
        x_nom = np.array([10.0, 20.0])
        x = np.array([10.0, 20.05])  # gap 5 cm longer than nominal: stretched
        rear, front = 0, 1
    else:
        x_nom = np.array([20.0, 10.0])
        x = np.array([20.05, 10.0])
        rear, front = 1, 0
    plant = TrainPlant(
        m, x, [10.0, 10.0], coupler_spacing_m=x_nom[0] - x_nom[1], resistance=DavisResistance.zero(2)
    )
    dl = 0.05 if not front_is_higher_index else -0.05
    assert plant.deflection_m[0] == pytest.approx(dl)
    phi = plant.coupler_force_n[0]
    assert phi == pytest.approx(80_000 * (1 - 0.5 * 0.05**2) * dl)
    plant.step(DT, [0.0, 0.0])
    acc = plant.accel_mps2
    assert acc[rear] > 0.0, "stretched coupler pulls the rear car forward"
    assert acc[front] < 0.0, "and the front car back"
    assert m[0] * acc[0] == pytest.approx(-m[1] * acc[1], rel=1e-9), "equal and opposite"
    assert abs(m[0] * acc[0]) == pytest.approx(abs(phi), rel=1e-3)


def test_initial_deflection_zero_for_table2_positions():
    plant = TrainPlant([2e4] * 6, [10, 20, 30, 40, 50, 60], [25.0] * 6)
    np.testing.assert_allclose(plant.coupler_spacing_m, -10.0)
    np.testing.assert_allclose(plant.deflection_m, 0.0)


@pytest.mark.parametrize("brake_n", [0.0, 30_000.0])
def test_two_cars_at_rest_stay_at_rest(brake_n):
    plant = TrainPlant([20_000.0, 21_000.0], [10.0, 20.0], [0.0, 0.0], actuator=BrakeActuator.realistic())
    run(plant, [brake_n, brake_n], 2.0)
    assert np.all(plant.speed_mps == 0.0)
    np.testing.assert_array_equal(plant.position_m, [10.0, 20.0])


def test_brake_holds_against_grade_and_compressed_coupler_but_not_beyond_its_capacity():
    m = 20_000.0
    theta = -0.02  # downhill towards +x: gravity pushes forward, 3.9 kN
    held = TrainPlant([m], [0.0], [0.0], grade_rad=theta)
    run(held, [10_000.0], 1.0)
    assert held.speed_mps[0] == 0.0
    free = TrainPlant([m], [0.0], [0.0], grade_rad=theta)
    run(free, [0.0], 1.0)  # c0 ≈ 640 N < 3.9 kN: rolls forward, never backward
    assert free.speed_mps[0] > 0.0
    expected = (m * 9.81 * math.sin(-theta) - free.resistance.c0_n[0]) / m
    assert free.speed_mps[0] == pytest.approx(expected * 1.0, rel=0.02)


def test_braking_to_standstill_stops_exactly_no_reverse():
    plant = TrainPlant([20_000.0, 20_000.0], [0.0, -10.0], [1.0, 1.0])
    run(plant, [40_000.0, 40_000.0], 2.0)
    assert np.all(plant.speed_mps == 0.0)
    x_stop = plant.position_m.copy()
    run(plant, [40_000.0, 40_000.0], 1.0)
    np.testing.assert_array_equal(plant.position_m, x_stop)
    # traction at standstill does start the car
    run(plant, [-10_000.0, -10_000.0], 0.5)
    assert np.all(plant.speed_mps > 0.0)


def test_internal_forces_conserve_momentum_and_energy():
    m = np.array([18_000.0, 21_000.0, 19_500.0, 20_000.0])
    v0 = np.array([25.0, 26.0, 24.0, 25.5])
    plant = TrainPlant(m, [10, 20, 30, 40], v0, resistance=DavisResistance.zero(4))
    p0 = float(m @ v0)
    e0 = 0.5 * float(m @ v0**2) + plant.coupler_energy_j()
    run(plant, np.zeros(4), 5.0)
    assert float(m @ plant.speed_mps) == pytest.approx(p0, rel=1e-12)
    e1 = 0.5 * float(m @ plant.speed_mps**2) + plant.coupler_energy_j()
    assert e1 == pytest.approx(e0, rel=1e-5)
    assert np.max(np.abs(plant.deflection_m)) > 0.05  # the couplers did work


def test_realistic_lag_reaches_63_percent_in_one_time_constant():
    m, tau, F = 20_000.0, 0.3, 5_000.0
    act = BrakeActuator.realistic(time_constant_s=tau, jerk_limit_mps3=math.inf)
    plant = TrainPlant([m], [0.0], [20.0], actuator=act, resistance=DavisResistance.zero(1))
    run(plant, [F], tau)
    assert plant.brake_effort_n[0] / F == pytest.approx(1 - math.exp(-1), abs=2e-3)
    assert plant.applied_force_n[0] == pytest.approx(plant.brake_effort_n[0])


def test_realistic_jerk_limit_respected():
    m, jerk = 20_000.0, 1.0
    act = BrakeActuator.realistic(jerk_limit_mps3=jerk)
    plant = TrainPlant([m], [0.0], [20.0], actuator=act)
    efforts = []
    for _ in range(1500):
        plant.step(DT, [1.5 * m])
        efforts.append(plant.brake_effort_n[0])
    rate = np.diff(np.concatenate([[0.0], efforts])) / DT / m
    assert rate.max() <= jerk + 1e-9
    assert rate.max() == pytest.approx(jerk, rel=1e-9)  # and it binds for a 1.5 m/s² step
    assert efforts[999] == pytest.approx(1.0 * m, rel=1e-6)  # linear ramp for the first second


def test_saturation_at_rating_and_adhesion():
    m = 20_000.0
    act = BrakeActuator.realistic(time_constant_s=0.01, jerk_limit_mps3=math.inf, brake_rating_mps2=1.5)
    rail = RailConditions(base_adhesion_mu=0.3, events=[RailEvent(1.0, 2.0, adhesion_mu=0.05)])
    plant = TrainPlant([m], [0.0], [25.0], actuator=act, rail=rail)
    run(plant, [5 * m], 0.5)
    assert plant.applied_force_n[0] == pytest.approx(1.5 * m, rel=1e-6)  # rating below μ m g = 2.94 m
    run(plant, [5 * m], 1.0)  # now in the skid
    assert plant.applied_force_n[0] == pytest.approx(0.05 * m * 9.81, rel=1e-9)
    run(plant, [5 * m], 1.0)  # recovered
    assert plant.applied_force_n[0] == pytest.approx(1.5 * m, rel=1e-6)


def test_brake_effectiveness_and_disturbance():
    m = 20_000.0
    rail = RailConditions(events=[RailEvent(0.0, 1.0, brake_effectiveness=[0.5, 1.0])])
    dist = [DisturbanceForce(amplitude_n=[1000.0, 0.0], frequency_hz=0.0, offset_n=[0.0, 2000.0])]
    plant = TrainPlant([m, m], [0.0, -1000.0], [20.0, 20.0], coupler_stiffness_n_per_m=0.0,
                       resistance=DavisResistance.zero(2), rail=rail, disturbances=dist)
    plant.step(DT, [10_000.0, 10_000.0])
    np.testing.assert_allclose(plant.applied_force_n, [5_000.0, 10_000.0])
    np.testing.assert_allclose(plant.accel_mps2, [-5_000.0 / m, (-10_000.0 + 2000.0) / m], rtol=1e-9)
    d = DisturbanceForce(amplitude_n=3.0, frequency_hz=2.0, start_s=6.0)
    assert d.force_n(6.125, 2) == pytest.approx([3.0, 3.0])
    assert d.force_n(5.9, 2) == pytest.approx([0.0, 0.0])


def test_ideal_actuator_passes_any_sign_and_davis_values():
    plant = TrainPlant([20_000.0], [0.0], [20.0])
    plant.step(DT, [-4_000.0])
    assert plant.applied_force_n[0] == -4_000.0
    r = davis_1926([20_000.0])
    assert r.c0_n[0] == pytest.approx(643.5, abs=1.0)
    assert r.c1_n_per_mps[0] == pytest.approx(6.58, abs=0.01)
    assert r.c2_n_per_mps2[0] == pytest.approx(0.896, abs=0.005)


def test_softening_coupler_past_its_reversal_point_raises_instead_of_nan():
    from canbrake.physics import PlantDiverged

    plant = TrainPlant([20_000.0, 20_000.0], [0.0, 10.0], [20.0, 25.0], resistance=DavisResistance.zero(2))
    with pytest.raises(PlantDiverged), np.errstate(over="ignore", invalid="ignore"):
        run(plant, [0.0, 0.0], 20.0)
    # with an end stop the same impact is survivable
    stopped = TrainPlant([20_000.0, 20_000.0], [0.0, 10.0], [20.0, 25.0], resistance=DavisResistance.zero(2),
                         end_stop_m=0.1)
    run(stopped, [0.0, 0.0], 5.0)
    assert np.all(np.isfinite(stopped.speed_mps))
    assert np.max(np.abs(stopped.deflection_m)) < 0.3  # 0.1 m + ≈ v·sqrt(μ/k_stop) = 0.11 m overrun


# ---------------------------------------------------------------- stacked plants (the batch engine)
def test_a_stack_of_plants_steps_each_row_as_its_own_plant():
    """stack_plants: P plants with different masses, couplers and commands stepped as one give every
    row the floats of its own plant, bit for bit, including cars stopping under friction and a
    point that diverges (flagged, parked, its neighbours untouched)."""
    from canbrake.physics.train import PlantDiverged, TrainPlant, stack_plants

    rng = np.random.default_rng(3)
    P, n = 5, 6
    mk = lambda p: TrainPlant(18000 + 500 * p + 100 * np.arange(n), 10.0 * np.arange(n),  # noqa: E731
                              2.0 + rng.normal(0, 0.3, n), coupler_stiffness_n_per_m=80_000 + 1000 * p,
                              grade_rad=0.001 * p)
    singles = [mk(p) for p in range(P)]
    st = stack_plants([TrainPlant(s.mass_kg, s._x0, s._v0, coupler_stiffness_n_per_m=s.coupler_stiffness_n_per_m,
                                  grade_rad=0.001 * p) for p, s in enumerate(singles)])
    assert st is not None
    dead = None
    with np.errstate(all="ignore"):
        _step_both(st, singles, rng, P, n)


def _step_both(st, singles, rng, P, n):
    from canbrake.physics.train import PlantDiverged

    dead = None
    for k in range(3000):
        cmd = rng.normal(20_000, 15_000, (P, n))
        if k == 1500:
            cmd[3, 0] = -1e9  # traction on one car drives point 3's softening couplers past their peak
        st.step(1e-3, cmd)
        for p, s in enumerate(singles):
            if p == dead:
                continue
            try:
                s.step(1e-3, cmd[p])
            except PlantDiverged:
                dead = p
                assert st.diverged_rows[p]
                continue
            for name in ("position_m", "speed_mps", "accel_mps2", "applied_force_n"):
                assert getattr(s, name).tobytes() == getattr(st, name)[p].tobytes(), (k, p, name)
    assert dead == 3 and st.diverged_rows.tolist() == [False, False, False, True, False]
    assert (st.speed_mps[[0, 1, 2, 4]] == 0.0).any()  # some cars stopped under friction (the other branch)


def test_plants_that_cannot_be_stacked_are_refused():
    from canbrake.physics.train import TrainPlant, stack_plants

    a = TrainPlant([1e4, 1e4], [0.0, 10.0], [1.0, 1.0])
    b = TrainPlant([1e4, 1e4], [0.0, 10.0], [1.0, 1.0], end_stop_m=0.08)
    assert stack_plants([a, a]) is not None
    assert stack_plants([a, b]) is None


def test_a_stack_with_blending_a_lagged_actuator_and_end_stops_steps_as_its_plants():
    """The equipped path stacked: ED/friction blending, a realistic (lagged, jerk-limited, rated)
    actuator and draft-gear end stops whose own step never refines the 1 ms sub-step; each row
    equals its plant bit for bit while traction on one car drives couplers into their stops and
    the train brakes to a stand (the ED fade and friction at rest). An end stop that can refine
    the sub-step (it would depend on each point's state) is not stacked."""
    from canbrake.physics.actuator import BrakeActuator
    from canbrake.physics.brakes import BrakeBlending
    from canbrake.physics.train import TrainPlant, stack_plants

    P, n = 4, 5
    act = BrakeActuator.realistic(time_constant_s=0.3, jerk_limit_mps3=2.0, brake_rating_mps2=1.4,
                                  traction_rating_mps2=1.0, adhesion_limited=True)
    mk = lambda p: TrainPlant(30000 + 2000 * p + 500 * np.arange(n), 15.0 * np.arange(n), 4.0 - 0.3 * p,  # noqa: E731
                              actuator=act, blending=BrakeBlending(friction_lag_s=0.2), end_stop_m=0.02,
                              end_stop_stiffness_n_per_m=5e6, end_stop_absorption=0.5, max_substep_s=1e-3)
    singles = [mk(p) for p in range(P)]
    st = stack_plants([mk(p) for p in range(P)])
    assert st is not None
    rng = np.random.default_rng(5)
    stops = 0
    for k in range(1500):
        cmd = np.full((P, n), 30000.0) + rng.normal(0, 3000, (P, n))
        if k < 300:
            cmd[:, 0] = -60000.0  # traction on the last car: the couplers close onto their stops
        st.step(0.01, cmd)
        for p, s in enumerate(singles):
            s.step(0.01, cmd[p])
            for name in ("position_m", "speed_mps", "accel_mps2", "applied_force_n"):
                assert getattr(s, name).tobytes() == getattr(st, name)[p].tobytes(), (k, p, name)
            assert s.equipment_measurements()["friction_brake_n"].tobytes() == \
                st.equipment_measurements()["friction_brake_n"][p].tobytes()
        stops += int((np.abs(st.deflection_m) > 0.02).any())
    assert stops > 0 and (st.speed_mps == 0.0).all()
    coarse = TrainPlant([3e4, 3e4], [0.0, 15.0], [4.0, 4.0], end_stop_m=0.02, end_stop_stiffness_n_per_m=5e6,
                        max_substep_s=0.01)
    assert stack_plants([coarse, coarse]) is None


@pytest.mark.parametrize("equipped", [False, True])
def test_a_stacked_point_that_diverges_is_reported_as_its_own_plant(equipped):
    """The divergence text of a stack's row is the PlantDiverged message its own plant raises
    (the equipped step words it without the softening-coupler hint), at the same time."""
    from canbrake.physics.brakes import BrakeBlending
    from canbrake.physics.train import PlantDiverged, TrainPlant, stack_plants

    mk = lambda: TrainPlant([2e4, 2e4, 2e4], [0.0, 10.0, 20.0], [5.0, 5.0, 5.0],  # noqa: E731
                            blending=BrakeBlending() if equipped else None)
    single, st = mk(), stack_plants([mk(), mk()])
    cmd = np.array([-1e9, 0.0, 0.0])
    with np.errstate(all="ignore"), pytest.raises(PlantDiverged) as err:
        for _ in range(1000):
            st.step(1e-3, np.stack([cmd, np.zeros(3)]))
            single.step(1e-3, cmd)
    assert st.diverged_rows.tolist() == [True, False]
    assert st.diverged_text(float(st.diverged_dl_m[0])) == str(err.value)
