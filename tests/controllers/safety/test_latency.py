"""Latency prediction and tightening: hand-worked numbers, soundness of the bounds, fixed robots."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from controllers.safety import SafetyFilter, SafetyStatus
from controllers.safety.latency import (
    LatencyConfig,
    LatencyConfigError,
    LatencyPredictor,
    Prediction,
    horizon_ticks,
    row_sums,
)
from sim.scenario import Dynamics, make_scenario, transport_scenario

DYN = Dynamics()            # dt 0.05 s, damping 0.5 1/s, accel limit 1, speed limit 0.4


def test_horizon_counts_the_state_age_and_the_command_delay_in_ticks():
    # (0 + 0.15) / 0.05 = 3; (0.05 + 0.15) / 0.05 = 4; 0.02 s of age still costs a whole tick
    np.testing.assert_array_equal(horizon_ticks(np.array([0.0, 0.05, 0.02]), 0.15, 0.05), [3, 4, 4])
    np.testing.assert_array_equal(horizon_ticks(np.array([0.0]), 0.0, 0.05), [0])


def test_prediction_runs_the_recorded_commands_and_grows_by_the_hand_worked_bounds():
    cfg = LatencyConfig(command_delay_s=0.1, accel_uncertainty=0.1, position_noise=0.002,
                        velocity_noise=0.01, spread_weight=1.0)
    pred = LatencyPredictor(DYN, cfg)
    ids = ("a",)
    u1, u2 = np.array([[0.4, 0.0]]), np.array([[0.4, 0.3]])
    pred.record(ids, u1)
    pred.record(ids, u2)
    pos, vel = np.array([[0.5, 0.5]]), np.array([[0.1, 0.0]])
    out = pred.predict(ids, pos, vel, np.zeros(1), np.array([[0.4, 0.3]]))
    p, v = DYN.step_np(*DYN.step_np(pos, vel, u1), u2)          # oldest first, h = 0.1 / 0.05 = 2
    np.testing.assert_allclose(out.pos, p)
    np.testing.assert_allclose(out.vel, v)
    assert out.horizon.tolist() == [2]
    # window {u1, u2, a_nom}: box diagonal 0.3 -> A = 0.3 + 0.1 = 0.4 m/s^2, h = 2
    # e_p = A dt^2 h (h + 1) / 2 + sigma_v dt h + sigma_p = 0.4 * 0.0025 * 3 + 0.01 * 0.1 + 0.002
    # e_v = A dt h + sigma_v = 0.4 * 0.1 + 0.01
    np.testing.assert_allclose(out.grow, [0.003 + 0.001 + 0.002])
    np.testing.assert_allclose(out.closing, [0.04 + 0.01])
    assert not out.fixed.any()
    # two standard deviations of a measured velocity noise of 0.02 m/s join the approach allowance
    # (and not the bound on the velocity's error the post-check reads: 3 sigma of it there already)
    noisy = pred.predict(ids, pos, vel, np.zeros(1), np.array([[0.4, 0.3]]), velocity_noise=np.array([0.02]))
    np.testing.assert_allclose(noisy.closing, [0.04 + 0.01 + 2 * 0.02])
    np.testing.assert_allclose(noisy.grow, out.grow)
    np.testing.assert_allclose(noisy.velocity_error, [0.04 + 0.01 + 3 * 0.02])
    off = LatencyPredictor(DYN, dataclasses.replace(cfg, measured_velocity_sigmas=0.0))
    off.record(ids, u1)
    off.record(ids, u2)
    quiet = off.predict(ids, pos, vel, np.zeros(1), np.array([[0.4, 0.3]]), velocity_noise=np.array([0.02]))
    np.testing.assert_allclose(quiet.closing, out.closing)


def test_history_is_keyed_by_robot_id_and_a_new_robot_holds_no_command():
    pred = LatencyPredictor(DYN, LatencyConfig(command_delay_s=0.05, accel_uncertainty=0.0))
    pred.record(("a", "b"), np.array([[1.0, 0.0], [0.0, 1.0]]))
    pos, vel = np.zeros((2, 2)) + 0.5, np.zeros((2, 2))
    out = pred.predict(("b", "c"), pos, vel, np.zeros(2), np.zeros((2, 2)))
    np.testing.assert_allclose(out.vel[0], [0.0, DYN.dt * 1.0])        # b ran its own command
    np.testing.assert_allclose(out.vel[1], [0.0, 0.0])                 # c: none yet


@settings(max_examples=80, deadline=None)
@given(seed=st.integers(0, 10_000))
def test_the_bounds_hold_for_any_order_of_the_window_commands(seed):
    """With spread weight 1 the tightening bounds what it claims: whichever commands of the
    window (the last h sent and the new one) acted at each of the h ticks, in any order and with
    repeats (a delay that jitters, a held command), plus any model error within delta_a, the robot
    ends within ``grow`` of the prediction and its velocity within ``closing``. (Robots stay
    below the speed limit here; the clip only shrinks differences.)"""
    rng = np.random.default_rng(seed)
    cfg = LatencyConfig(command_delay_s=0.15, accel_uncertainty=0.05, spread_weight=1.0)
    dyn = Dynamics(speed_limit=10.0)
    scale = rng.uniform(0, 1)
    window = list(rng.uniform(-1, 1, (3, 1, 2)) * scale)
    a_nom = rng.uniform(-1, 1, (1, 2)) * scale
    pred = LatencyPredictor(dyn, cfg)
    for u in window:
        pred.record(("r",), u)
    pos, vel = rng.uniform(0.3, 0.7, (1, 2)), rng.uniform(-0.2, 0.2, (1, 2))
    out = pred.predict(("r",), pos, vel, np.zeros(1), a_nom)
    assert out.horizon.tolist() == [3]
    choices = window + [a_nom]
    p, v = pos.copy(), vel.copy()
    for _ in range(3):
        error = rng.normal(size=2)
        error *= cfg.accel_uncertainty * rng.uniform(0, 1) / np.linalg.norm(error)
        p, v = dyn.step_np(p, v, choices[int(rng.integers(len(choices)))] + error)
    assert np.linalg.norm(p - out.pos) <= out.grow[0] + 1e-12
    assert np.linalg.norm(v - out.vel) <= out.closing[0] + 1e-12


def test_row_sums_follow_the_barrier_row_layout():
    x = np.array([1.0, 2.0, 4.0])
    pi, pj = np.triu_indices(3, 1)
    np.testing.assert_allclose(row_sums(x, pi, pj), [3, 5, 6, 1, 2, 4, 1, 1, 1, 1, 2, 2, 2, 2, 4, 4, 4, 4])


def test_a_fixed_robot_is_an_obstacle_not_a_decision_variable():
    """Robot 1 is not listening: the filter cannot move it (a_safe = 0) and makes robot 0 brake
    before its grown disc, which a filter that could count on robot 1 would not."""
    sc = transport_scenario(2)
    filt = SafetyFilter(sc)
    pos = np.array([[0.3, 0.9], [0.45, 0.9]])
    vel = np.array([[0.3, 0.0], [0.0, 0.0]])
    a_nom = np.array([[1.0, 0.0], [0.0, 0.0]])
    listening = Prediction(pos, vel, np.zeros(2), np.zeros(2), np.zeros(2, dtype=bool), np.zeros(2, int))
    deaf = Prediction(pos, vel, np.array([0.0, 0.02]), np.zeros(2), np.array([False, True]), np.zeros(2, int))
    both = filt.filter(pos, vel, a_nom, prediction=listening)
    alone = filt.filter(pos, vel, a_nom, prediction=deaf)
    np.testing.assert_allclose(alone.a_safe[1], 0.0)
    assert alone.status is not SafetyStatus.UNCHANGED
    assert alone.a_safe[0, 0] < both.a_safe[0, 0] - 0.1               # it brakes harder alone
    # two fixed robots: their row is dropped, nothing to solve
    none = filt.filter(pos, vel, np.zeros((2, 2)),
                       prediction=Prediction(pos, vel, np.zeros(2), np.zeros(2), np.ones(2, bool), np.zeros(2, int)))
    assert none.terms.bound[0] == -np.inf


def test_bad_latency_settings_name_the_field():
    with pytest.raises(LatencyConfigError, match="latency.command_delay_s"):
        LatencyConfig(command_delay_s=-0.1)
    with pytest.raises(LatencyConfigError, match="latency.stale_after_s"):
        LatencyConfig(stale_after_s=0.0)
    with pytest.raises(LatencyConfigError, match="latency.measured_velocity_sigmas"):
        LatencyConfig(measured_velocity_sigmas=-1.0)
    with pytest.raises(LatencyConfigError, match="latency.cover_merge must be a positive"):
        LatencyConfig(cover_merge=0.0)
    for bad in (0, 2.5, True):
        with pytest.raises(LatencyConfigError, match="latency.cover_discs must be a whole number >= 1"):
            LatencyConfig(cover_discs=bad)


def test_covers_become_fixed_rows_after_the_commanded_ones():
    """Row 1 (fixed, at rest) covered by three discs: it takes the first, the other two follow
    the three rows as fixed obstacles at rest with their row's approach allowance."""
    pred = Prediction(pos=np.zeros((3, 2)), vel=np.ones((3, 2)), grow=np.array([0.001, 0.05, 0.002]),
                      closing=np.array([0.01, 0.02, 0.03]), fixed=np.array([False, True, False]),
                      horizon=np.array([3, 0, 3]), brake_vel=np.ones((3, 2)), velocity_error=np.array([0.1, 0.2, 0.3]),
                      unsure=np.array([True, False, False]),
                      covers=((1, np.array([[0.1, 0.2], [0.15, 0.2], [0.2, 0.2]]), np.array([0.011, 0.012, 0.013])),))
    out = pred.with_covers()
    np.testing.assert_array_equal(out.pos, [[0, 0], [0.1, 0.2], [0, 0], [0.15, 0.2], [0.2, 0.2]])
    np.testing.assert_array_equal(out.grow, [0.001, 0.011, 0.002, 0.012, 0.013])
    np.testing.assert_array_equal(out.closing, [0.01, 0.02, 0.03, 0.02, 0.02])
    np.testing.assert_array_equal(out.velocity_error, [0.1, 0.2, 0.3, 0.02, 0.02])
    np.testing.assert_array_equal(out.fixed, [False, True, False, True, True])
    np.testing.assert_array_equal(out.unsure, [True, False, False, False, False])
    np.testing.assert_array_equal(out.horizon, [3, 0, 3, 0, 0])
    np.testing.assert_array_equal(out.vel[3:], 0.0)
    np.testing.assert_array_equal(out.brake_vel[3:], 0.0)
    assert out.covers == () and pred.with_covers() is not pred
    plain = Prediction(pos=pred.pos, vel=pred.vel, grow=pred.grow, closing=pred.closing, fixed=pred.fixed,
                       horizon=pred.horizon)
    assert plain.with_covers() is plain


@pytest.mark.parametrize("delay", [0, 1, 2, 3])
def test_with_the_pending_count_the_prediction_is_the_state_where_the_new_command_acts(delay):
    """A pymunk robot with a fixed command delay reports how many commands it has yet to act on;
    through exactly those the prediction lands on the state in which the new command starts
    acting (to rounding), whatever the configured bound."""
    from sim.pymunk_world import ModelError, PymunkWorld
    sc = make_scenario("paper-3")
    world = PymunkWorld(sc, ModelError(delay_ticks=delay))
    pred = LatencyPredictor(sc.dynamics, LatencyConfig(command_delay_s=0.15))
    rng = np.random.default_rng(delay)
    state, ids, predicted, measured = world.reset(seed=delay), ("a", "b", "c"), [], []
    for _ in range(12):
        u = rng.uniform(-0.3, 0.3, (3, 2))
        out = pred.predict(ids, state.positions, state.velocities, state.ages(), u,
                           pending=state.commands_pending)
        assert state.commands_pending.tolist() == [min(delay, state.step)] * 3
        predicted.append(out.pos)
        measured.append(state.positions)
        pred.record(ids, u)
        world.send_accelerations(u)
        state = world.step()
    # the command of tick k acts from tick k + delay on (before tick `delay`, fewer were in flight)
    checked = range(delay, len(measured) - delay)
    for k in checked:
        np.testing.assert_allclose(predicted[k], measured[k + delay], atol=1e-9)
    assert len(checked) >= 6
    assert world.collision_counts.any is False


def test_without_the_pending_count_a_short_delay_is_predicted_off_by_the_commands_counted_twice():
    """The teeth of the test above: one tick of delay under a 3-tick bound, the pending count
    not told, predicts through three commands of which two had already acted."""
    from sim.pymunk_world import ModelError, PymunkWorld
    sc = make_scenario("paper-3")
    world = PymunkWorld(sc, ModelError(delay_ticks=1))
    pred = LatencyPredictor(sc.dynamics, LatencyConfig(command_delay_s=0.15))
    state, ids, predicted, worst = world.reset(seed=1), ("a", "b", "c"), [], 0.0
    for _ in range(8):
        u = np.tile([0.6, 0.0], (3, 1))
        predicted.append(pred.predict(ids, state.positions, state.velocities, state.ages(), u).pos)
        pred.record(ids, u)
        world.send_accelerations(u)
        state = world.step()
        if state.step >= 2:                        # u_k acts from tick k + 1
            worst = max(worst, float(np.abs(predicted[state.step - 1] - state.positions).max()))
    assert worst > 1e-3


def test_a_robot_whose_pending_commands_outrun_the_bound_is_an_obstacle():
    """Fresh state, but 5 commands not acted on under a 3-tick bound: its command link is down."""
    pred = LatencyPredictor(DYN, LatencyConfig(command_delay_s=0.15))
    pos, vel = np.array([[0.3, 0.5], [0.6, 0.5]]), np.array([[0.1, 0.0], [0.0, 0.0]])
    out = pred.predict(("a", "b"), pos, vel, np.zeros(2), np.zeros((2, 2)), pending=np.array([5, 3]))
    assert out.fixed.tolist() == [True, False]
    assert pred.late(np.zeros(2), np.array([4, 3])).tolist() == [True, False]
    assert pred.late(np.array([0.1, 0.0]), np.array([4, 3])).tolist() == [False, False]  # 2 ticks old


def test_a_stale_robot_is_braked_from_its_state_carried_through_the_commands_in_flight():
    """Robot "a" was measured at 0.2 m/s along +y four ticks ago and sent four commands since
    (all pending): a push along -x, then three brakes. Stale, it is an obstacle whose BRAKE is
    to cancel the velocity those commands give it: its measurement run through them, by hand.
    With more pending commands than the history holds, the disc's own velocity stays."""
    pred = LatencyPredictor(DYN)
    ids = ("a", "b")
    pos, vel = np.array([[0.3, 0.3], [0.7, 0.7]]), np.array([[0.0, 0.2], [0.0, 0.0]])
    sent = [np.array([-1.0, 0.0]), np.array([0.6, -0.8]), np.array([0.3, -0.4]), np.array([0.0, -0.5])]
    for u in sent:
        pred.record(ids, np.array([u, [0.0, 0.0]]), braking=np.array([u[1] < 0, False]))
    ages = np.array([4 * DYN.dt, 0.0])
    out = pred.predict(ids, pos, vel, ages, np.zeros((2, 2)), pending=np.array([4, 0]), now=1.0)
    assert out.fixed.tolist() == [True, False]
    v = vel[0].copy()
    for u in sent:
        v = v + DYN.dt * (u - DYN.damping * v)
    np.testing.assert_allclose(out.braking_velocity()[0], v, rtol=0, atol=1e-15)
    assert np.abs(out.braking_velocity()[0] - out.vel[0]).max() > 0.01     # not the disc's
    beyond = pred.predict(ids, pos, vel, np.array([10 * DYN.dt, 0.0]), np.zeros((2, 2)),
                          pending=np.array([pred.depth + 1, 0]), now=1.0)
    np.testing.assert_array_equal(beyond.braking_velocity()[0], beyond.vel[0])


def test_a_robot_whose_delay_changes_gets_the_jitter_weight_for_a_while():
    """Spread 0.3 m/s^2 over h = 2 ticks: grow = w * 0.3 * dt^2 * h (h + 1) / 2, w = 0.25 while the
    observed delay holds, 0.5 from the tick it changes and for ``depth`` ticks after."""
    cfg = LatencyConfig(command_delay_s=0.1, accel_uncertainty=0.0)
    pred = LatencyPredictor(DYN, cfg)
    ids, one = ("a",), np.array([1])
    pos, vel = np.array([[0.5, 0.5]]), np.zeros((1, 2))
    grow = []
    for k, pending in enumerate([1, 1, 2] + [2] * pred.depth):
        pred.record(ids, np.array([[0.4, 0.3 * (k % 2)]]))
        out = pred.predict(ids, pos, vel, np.zeros(1), np.array([[0.4, 0.0]]), pending=one * pending)
        grow.append(float(out.grow[0]))
    unit = 0.3 * DYN.dt**2 * 3
    np.testing.assert_allclose(grow[1], 0.25 * unit)
    np.testing.assert_allclose(grow[2:2 + pred.depth], 0.5 * unit)
    np.testing.assert_allclose(grow[-1], 0.25 * unit)


def test_a_robot_whose_delay_jitters_is_braked_from_its_measured_velocity():
    """Two robots at 2 cm/s along x, each with one command of 0.2 m/s^2 along x pending. "a" keeps
    its observed delay: it is braked from the prediction, 0.02 + dt (0.2 - c 0.02) = 0.0295 m/s.
    "b"'s delay changed this tick: its pending command may be overtaken and never act, so it is
    braked from the 0.02 m/s measured; with the rule off, from the prediction as "a". Both are slow
    enough to stop within a tick, so the brake spreads the stop over h + 1 ticks."""
    from controllers.safety import braking_acceleration
    ids, pos = ("a", "b"), np.array([[0.3, 0.3], [0.7, 0.7]])
    vel, push = np.array([[0.02, 0.0], [0.02, 0.0]]), np.array([[0.2, 0.0], [0.2, 0.0]])
    predicted_speed = 0.02 + DYN.dt * (0.2 - DYN.damping * 0.02)
    for rule, b_speed in ((True, 0.02), (False, predicted_speed)):
        pred = LatencyPredictor(DYN, LatencyConfig(jitter_brake_measured=rule))
        for pending in ([1, 1], [1, 2], [1, 1]):       # b's observed delay 1, 2, 1 ticks
            pred.record(ids, push)
            out = pred.predict(ids, pos, vel, np.zeros(2), push, pending=np.array(pending))
        np.testing.assert_allclose(out.vel[:, 0], predicted_speed)
        np.testing.assert_allclose(out.braking_velocity()[:, 0], [predicted_speed, b_speed])
        brake = braking_acceleration(out.vel, DYN, out)
        h = out.horizon + 1.0                        # slow robots stop over h + 1 ticks
        speeds = np.array([predicted_speed, b_speed])
        np.testing.assert_allclose(brake[:, 0], DYN.damping * speeds - speeds / (h * DYN.dt))
    with pytest.raises(LatencyConfigError, match="latency.jitter_brake_measured"):
        LatencyConfig(jitter_brake_measured=1)


@pytest.mark.parametrize("measured, pending", [(0.25, -1), (0.35, -1), (0.35, 6), (0.6, 11)])
def test_a_measured_delay_above_the_configured_one_predicts_as_if_it_were_configured(measured, pending):
    """The history was sized from command_delay_s alone and the kernel cut every horizon to it:
    at a measured 0.35 s (default 0.15 s bound) the robot was predicted 8 ticks ahead of 9, about
    2 cm short, and its disc grew 5.6 mm less than the bound asks."""
    dyn = Dynamics()
    ids, pos, vel, age = ("a",), np.array([[0.5, 0.5]]), np.array([[0.3, 0.0]]), np.array([0.1])

    def predicted(predictor, measured_s):
        predictor.predict(ids, pos, vel, age, np.zeros((1, 2)), measured_s)     # a first tick
        for k in range(40):
            predictor.record(ids, np.array([[0.5, 0.2 * (-1) ** k]]))
        return predictor.predict(ids, pos, vel, age, np.array([[0.5, 0.0]]), measured_s,
                                 pending=np.array([pending]))

    got = predicted(LatencyPredictor(dyn, LatencyConfig()), measured)
    want = predicted(LatencyPredictor(dyn, LatencyConfig(command_delay_s=measured)), None)
    assert got.horizon[0] == want.horizon[0] == int(np.ceil((age[0] + measured) / dyn.dt - 1e-9))
    for field in ("pos", "vel", "grow", "closing"):
        np.testing.assert_allclose(getattr(got, field), getattr(want, field), rtol=0, atol=1e-12, err_msg=field)
