"""ControlStack: finite commands and statuses, safety teeth in pymunk, NaN handling, changing N,
episodes, stale and braked robots. The policy stage (tokens, runtimes, files): test_policy_stage.py."""

from __future__ import annotations

import numpy as np
import pytest
import torch
from hypothesis import given, settings
from hypothesis import strategies as st

from controllers.docking import DockingConfig
from controllers.mec import MecStatus
from controllers.policy import ActorConfig, build_actor
from controllers.safety import SafetyStatus, braking_acceleration
from controllers.scripted import ScriptedController
from sim.fleet import BatchedFleet, FleetState
from sim.pymunk_world import ModelError, PymunkWorld
from sim.scenario import clip_norm, make_scenario, transport_scenario
from stack.pipeline import (
    ControlStack,
    PolicyStatus,
    StackConfig,
    StackError,
    nominal_step,
    run_episode,
)

WEAK_ROBOTS = ModelError(gain=0.85, gain_spread=0.15, lag_tau=0.05, floor_friction=0.05)


def actor(seed: int = 0) -> torch.nn.Module:
    torch.manual_seed(seed)
    net = build_actor(ActorConfig(embed_dim=16, num_heads=2, hidden_sizes=(32,)), 3).eval()
    with torch.no_grad():   # large outputs so that the untrained policy actually moves robots
        for p in net.parameters():
            p.mul_(20.0)
    return net


def toward_nearest_neighbour(state: FleetState) -> np.ndarray:
    """Full thrust (1 m/s^2) of every robot at its nearest neighbour."""
    pos = state.positions
    d = np.linalg.norm(pos[:, None] - pos[None], axis=-1) + np.eye(len(pos)) * 1e9
    toward = pos[np.argmin(d, axis=1)] - pos
    return toward / np.linalg.norm(toward, axis=1, keepdims=True)


def test_tick_returns_finite_commands_statuses_and_timings():
    sc = make_scenario("paper-3")
    world = PymunkWorld(sc, WEAK_ROBOTS, seed=0)
    stack = ControlStack(sc, actor())
    state = world.reset(seed=0)
    for k in range(5):
        tick = stack.tick(state)
        for name in ("a_nom", "a_safe", "a_cmd"):
            arr = getattr(tick, name)
            assert arr.shape == (3, 2) and np.isfinite(arr).all(), name
        assert np.all(np.linalg.norm(tick.a_cmd, axis=1) <= sc.dynamics.accel_limit + 1e-12)
        assert tick.policy_status is PolicyStatus.OK
        assert isinstance(tick.safety_status, SafetyStatus)
        assert tick.mec_status is (MecStatus.RESET if k == 0 else tick.mec_status)
        assert isinstance(tick.mec_status, MecStatus)
        assert set(tick.timings_ns) == {"observe", "policy", "safety", "mec", "total"}
        parts = sum(v for key, v in tick.timings_ns.items() if key != "total")
        assert parts == tick.timings_ns["total"] and all(v >= 0 for v in tick.timings_ns.values())
        world.send_accelerations(tick.a_cmd)
        state = world.step()
    assert np.any(np.abs(tick.a_nom) > 0.05)   # the policy is not idle


def test_stages_off_pass_the_clipped_policy_command_through():
    sc = make_scenario("paper-3")
    stack = ControlStack(sc, lambda s: np.array([[3.0, 4.0], [0.3, 0.0], [0.0, -0.2]]),
                         StackConfig(safety=False, mec=False))
    tick = stack.tick(PymunkWorld(sc).reset(seed=1))
    np.testing.assert_allclose(tick.a_cmd, [[0.6, 0.8], [0.3, 0.0], [0.0, -0.2]])
    assert tick.safety_status is None and tick.mec_status is None and not tick.intervened


@pytest.mark.parametrize("scenario_name", ["paper-3", "paper-5"])
def test_filter_stops_adversarial_policy_in_pymunk_and_its_absence_collides(scenario_name):
    sc = make_scenario(scenario_name)
    world = PymunkWorld(sc, WEAK_ROBOTS)
    safe = run_episode(world, ControlStack(sc, toward_nearest_neighbour), seed=3, steps=60)
    assert not safe.collided, safe
    assert safe.interventions > 10                                   # the filter had work to do
    unsafe = run_episode(world, ControlStack(sc, toward_nearest_neighbour, StackConfig(safety=False)),
                         seed=3, steps=60)
    assert unsafe.collided and unsafe.robot_collisions >= 1          # teeth


def test_nan_policy_output_brakes_with_a_status_and_never_emits_nan():
    sc = make_scenario("paper-3")
    vel = np.array([[0.2, 0.0], [0.0, -0.1], [0.05, 0.05]])
    state = FleetState(time=0.0, step=0, positions=sc.starts, velocities=vel, targets=sc.targets,
                       object_pose=np.array([0.5, 0.5, 0.0]))
    half_nan = lambda s: np.array([[np.nan, 0.0], [0.1, 0.1], [np.inf, 1.0]])  # noqa: E731
    for config in (StackConfig(safety=False, mec=False), StackConfig()):
        tick = ControlStack(sc, half_nan, config).tick(state)
        assert tick.policy_status is PolicyStatus.NON_FINITE_OUTPUT and tick.braking
        assert "not finite" in tick.brake_reason
        assert np.isfinite(tick.a_cmd).all() and np.isfinite(tick.a_nom).all()
        np.testing.assert_allclose(tick.a_nom, braking_acceleration(vel, sc.dynamics))
    # braking by hand: c v - v / dt = 0.5 * 0.2 - 0.2 / 0.05 = -3.9 -> clipped to -1 along x
    tick = ControlStack(sc, half_nan, StackConfig(safety=False, mec=False)).tick(state)
    np.testing.assert_allclose(tick.a_cmd[0], [-1.0, 0.0])


def test_nan_network_output_and_nan_state_brake():
    sc = make_scenario("paper-3")
    net = actor()
    with torch.no_grad():
        for p in net.parameters():
            p.fill_(float("nan"))
    state = PymunkWorld(sc).reset(seed=0)
    tick = ControlStack(sc, net).tick(state)
    assert tick.policy_status is PolicyStatus.NON_FINITE_OUTPUT and np.isfinite(tick.a_cmd).all()
    bad = FleetState(time=0.0, step=0, positions=state.positions,
                     velocities=np.array([[np.nan, 0.0], [0.0, 0.0], [0.0, 0.0]]), targets=state.targets,
                     object_pose=state.object_pose)
    stack = ControlStack(sc, actor())
    tick = stack.tick(bad)                  # robot 0 never seen: nowhere to put it, nobody moves
    assert tick.policy_status is PolicyStatus.INVALID_STATE
    assert tick.stale.tolist() == [True, False, False]
    np.testing.assert_allclose(tick.a_nom, 0.0)          # braking from rest
    np.testing.assert_allclose(tick.a_cmd[0], 0.0)       # BRAKE, not 0 - d_hat
    assert np.isfinite(tick.a_cmd).all()
    # once seen, a robot whose state turns non-finite stands in at its last state, an obstacle
    stack.reset()
    moving = FleetState(time=0.0, step=0, positions=state.positions,
                        velocities=np.array([[0.2, 0.0], [0.0, 0.1], [0.0, 0.0]]), targets=state.targets,
                        object_pose=state.object_pose)
    sent = stack.tick(moving).a_cmd[0]
    bad.time = 0.05
    tick = stack.tick(bad)
    assert tick.policy_status is PolicyStatus.OK and tick.stale.tolist() == [True, False, False]
    # BRAKE at its last velocity carried through what it may have acted on since: its pending
    # count unknown, the h = 4 ticks the bound allows, the command sent to it the newest of them
    dyn, v = sc.dynamics, moving.velocities[:1].copy()
    for u in (0.0, 0.0, 0.0, sent):
        v = v + dyn.dt * (u - dyn.damping * v)
    np.testing.assert_allclose(tick.a_cmd[0], braking_acceleration(v, dyn)[0], rtol=0, atol=1e-12)


def test_a_robot_that_acts_on_no_new_command_is_braked_though_its_state_is_fresh():
    """Its STATE keeps naming a command 5 ticks old under the 3-tick default bound (its command
    link is down): BRAKE, an obstacle to the others; the same robot with 3 pending is commanded."""
    sc = make_scenario("paper-3")
    state = PymunkWorld(sc).reset(seed=0)
    state.velocities = np.array([[0.2, 0.0], [0.0, 0.1], [0.0, 0.0]])
    stack = ControlStack(sc, ScriptedController(sc))
    state.commands_pending = np.array([5, 0, 0])
    tick = stack.tick(state)
    assert tick.stale.tolist() == [True, False, False]
    np.testing.assert_allclose(tick.a_cmd[0], braking_acceleration(state.velocities, sc.dynamics)[0])
    stack.reset()
    state.commands_pending = np.array([3, 0, 0])
    tick = stack.tick(state)
    assert not tick.stale.any() and np.linalg.norm(tick.a_cmd[0] - braking_acceleration(
        state.velocities, sc.dynamics)[0]) > 1e-3


def test_a_repeated_state_is_no_news_and_a_robot_away_keeps_its_last_state():
    """A dropped update repeats the old measurement with a larger age: the MEC must not take it
    again; a robot missing from a tick and back with a non-finite state stands in at its last one."""
    from stack.last_known import LastKnown

    known = LastKnown()
    ids, pos, vel = ("a", "b"), np.array([[0.1, 0.2], [0.3, 0.4]]), np.array([[0.1, 0.0], [0.0, 0.1]])
    assert known.new_measurement(ids, np.zeros(2), 1.0).tolist() == [True, True]
    known.update(ids, pos, vel, np.zeros(2), 1.0, np.zeros(2, dtype=bool))
    # b's update was lost: the same measurement, 0.05 s older, at 1.05 s
    assert known.new_measurement(ids, np.array([0.0, 0.05]), 1.05).tolist() == [True, False]
    known.update(ids, pos, vel, np.array([0.0, 0.05]), 1.05, np.zeros(2, dtype=bool))
    known.new_measurement(("a",), np.zeros(1), 1.1)                 # b away for a tick
    known.update(("a",), pos[:1], vel[:1], np.zeros(1), 1.1, np.zeros(1, dtype=bool))
    bad = np.full((2, 2), np.nan)
    unknown = np.array([True, True])
    known.new_measurement(("b", "c"), np.zeros(2), 1.2)
    p, v, ages, unplaced = known.update(("b", "c"), bad, bad, np.zeros(2), 1.2, unknown)
    np.testing.assert_allclose(p[0], pos[1])
    np.testing.assert_allclose(v[0], vel[1])
    assert ages[0] == pytest.approx(0.2)                            # measured at 1.0 s
    assert unplaced.tolist() == [False, True]                       # c was never seen


def _filter_sees(stack: ControlStack) -> list:
    """Record the prediction the stack's filter is given each tick."""
    seen, judge = [], stack.safety.filter

    def recorded(*args, prediction=None, **kwargs):
        seen.append(prediction)
        return judge(*args, prediction=prediction, **kwargs)
    stack.safety.filter = recorded
    return seen


def _exact_link_with_robot_0_lost(moving: np.ndarray, push: np.ndarray, lost_from: int, ticks: int):
    """transport-3 in pymunk on an exact link (no delay, no noise), robot 0 starting at 0.2 m/s,
    the others at rest, the policy asking ``push`` (3, 2) every tick; robot 0's states from tick
    ``lost_from`` on are lost (its last delivered row repeated, older, a command more pending
    each tick). Yields (tick, the stack's TickResult, robot 0's true state, the prediction)."""
    sc = transport_scenario(3)
    world = PymunkWorld(sc)
    world.reset(seed=0)
    world.set_state(np.array([[0.25, 0.2], [0.8, 0.85], [0.8, 0.15]]), moving)
    state = world.read_state()
    stack = ControlStack(sc, lambda s: push)
    seen = _filter_sees(stack)
    for k in range(ticks):
        if k < lost_from:
            delivered = state.positions[0].copy(), state.velocities[0].copy()
        else:
            state.positions[0], state.velocities[0] = delivered
            state.state_age_s = np.array([(k - lost_from + 1) * sc.dynamics.dt, 0.0, 0.0])
            state.commands_pending = np.array([k - lost_from + 1, 0, 0])
        tick = stack.tick(state)
        yield k, tick, world.true_state(), seen[-1]
        world.send_accelerations(tick.a_cmd)
        state = world.step()


def test_a_lost_state_is_carried_on_from_its_measurement_exactly_on_a_link_that_keeps_its_delay():
    """Robot 0's states of ticks 3 and 4 are lost: the tick-2 row arrives again, older, with
    more commands pending. Without delay, where the new command acts is where the robot is now,
    and the filter must judge it there, to rounding: the position estimator gives its position
    and the MEC its velocity as of that measurement, and the latency prediction carries both
    through the commands sent since. The MEC's prediction to now already held those commands;
    carried through them again, the robot was judged 28 and 54 mm/s and 1.4 and 5.4 mm off
    (``bench/safety.py`` jitter, noise and drops at once, seed 292: one tick after the start,
    a robot coasting at 0.175 m/s towards a wall 4 cm off was judged at 0.084 m/s and let
    accelerate into it)."""
    moving = np.array([[0.0, 0.2], [0.0, 0.0], [0.0, 0.0]])
    push = np.array([[0.0, -0.5], [0.0, 0.0], [0.0, 0.0]])
    judged = 0
    for k, tick, true, prediction in _exact_link_with_robot_0_lost(moving, push, lost_from=3, ticks=5):
        assert not tick.stale[0]
        np.testing.assert_allclose(prediction.pos[0], true.positions[0], rtol=0, atol=1e-12)
        np.testing.assert_allclose(prediction.vel[0], true.velocities[0], rtol=0, atol=1e-12)
        judged += k >= 3
    assert judged == 2


def test_a_robot_gone_stale_is_braked_from_the_velocity_its_commands_in_flight_gave_it():
    """Robot 0, at 0.2 m/s along +y, is pushed along -x at full thrust, and its states are lost
    from tick 1 on: from tick 3 its row is stale, an obstacle sent BRAKE, which a pymunk robot
    takes as the acceleration to achieve. On an exact link its last state carried through the
    commands it was sent since (the pushes, then the brakes already sent) is its true velocity,
    so every BRAKE is the braking law at it and the robot comes to rest. Braked from its last
    measured velocity, it got (0, -1) m/s^2 every tick: never braked along x, reversed along y."""
    moving = np.array([[0.0, 0.2], [0.0, 0.0], [0.0, 0.0]])
    push = np.array([[-1.0, 0.0], [0.0, 0.0], [0.0, 0.0]])
    dyn, stale, last = transport_scenario(3).dynamics, [], None
    for k, tick, true, _ in _exact_link_with_robot_0_lost(moving, push, lost_from=1, ticks=9):
        if tick.stale[0]:
            stale.append(k)
            brake = braking_acceleration(true.velocities[:1], dyn)[0]
            np.testing.assert_allclose(tick.a_cmd[0], brake, rtol=0, atol=1e-12)
        if last is not None:
            assert true.velocities[0] @ last >= 0.0                   # never turned round
        last = true.velocities[0]
    assert stale == [3, 4, 5, 6, 7, 8]
    assert np.hypot(*last) < 1e-12                                  # at rest


def test_robot_count_can_change_between_ticks():
    sc = make_scenario("paper-3")
    stack = ControlStack(sc, actor())
    # estimates are keyed by robot id: only a team of robots never seen starts afresh
    for n, expect_reset in ((3, True), (3, False), (5, False), (8, False), (3, False)):
        state = PymunkWorld(transport_scenario(n)).reset(seed=n)
        tick = stack.tick(state)
        assert tick.a_cmd.shape == (n, 2) and np.isfinite(tick.a_cmd).all()
        assert (tick.mec_status is MecStatus.RESET) == expect_reset
    with pytest.raises(StackError, match="shape"):
        ControlStack(sc, lambda s: np.zeros((2, 2))).tick(PymunkWorld(sc).reset(seed=0))


def test_nominal_step_by_hand():
    dyn = make_scenario("paper-3").dynamics
    p, v = nominal_step(np.zeros((1, 2)), np.array([[0.1, 0.0]]), np.array([[2.0, 0.0]]), dyn)
    # a clipped to 1; v' = 0.1 + 0.05 (1 - 0.5 * 0.1) = 0.1475; p' = 0.05 * 0.1475
    np.testing.assert_allclose(v, [[0.1475, 0.0]])
    np.testing.assert_allclose(p, [[0.007375, 0.0]])


def test_run_episode_metrics_on_both_worlds():
    sc = make_scenario("paper-3")
    off = StackConfig(safety=False, mec=False)
    batched = run_episode(BatchedFleet(sc), ControlStack(sc, ScriptedController(sc), off), seed=0)
    assert batched.success and not batched.collided and batched.steps == sc.dynamics.episode_steps
    assert batched.tracking_error < 1e-12            # the batched world is the nominal model
    perfect = run_episode(PymunkWorld(sc), ControlStack(sc, ScriptedController(sc), off), seed=0)
    assert perfect.success and perfect.tracking_error < 1e-9
    weak = ModelError(gain=0.7, lag_tau=0.05, floor_friction=0.1)
    without = run_episode(PymunkWorld(sc, weak), ControlStack(sc, ScriptedController(sc), off), seed=0)
    with_mec = run_episode(PymunkWorld(sc, weak),
                           ControlStack(sc, ScriptedController(sc), StackConfig(safety=False)), seed=0)
    assert with_mec.tracking_error < 0.6 * without.tracking_error


def test_run_episode_reports_the_first_tick_the_team_stands_on_its_targets():
    from sim.metrics import episode_outcome

    sc = make_scenario("paper-3")
    off = StackConfig(safety=False, mec=False)
    fleet, states = BatchedFleet(sc), []
    step = fleet.step
    fleet.step = lambda: states.append(step()) or states[-1]
    m = run_episode(fleet, ControlStack(sc, ScriptedController(sc), off), seed=0)
    within = [bool(episode_outcome(torch.from_numpy(s.positions)[None], torch.from_numpy(s.targets)[None],
                                   torch.tensor([False]), sc.target_tolerance).success[0]) for s in states]
    assert m.success and not within[0]
    assert m.arrival_step == within.index(True) + 1 < sc.dynamics.episode_steps
    idle = run_episode(BatchedFleet(sc), ControlStack(sc, lambda s: np.zeros((3, 2)), off), seed=0)
    assert idle.arrival_step is None and not idle.success


def test_the_policy_sees_a_frozen_robot_where_it_stopped_not_where_it_last_reported():
    """A pymunk robot pushed away from the object at full thrust freezes at the 0.4 m/s speed
    limit (silent and deaf, its watchdog braking it two ticks later) and stops 12 cm past its
    last report. Once it counts as stale, the policy (and docking) are shown the centre of its
    branches' disc, where it must have stopped: 11.6 mm from its true centre. Shown the last
    report instead, a neighbour judged its target taken by a robot no longer there, and the
    policy steered round a ghost (the frozen-robot condition of bench/safety.py)."""
    sc = make_scenario("paper-3")
    world = PymunkWorld(sc, ModelError(freeze=(0, 10)))
    state, seen = world.reset(seed=0), []
    push = np.zeros((3, 2))
    push[0] = (state.positions[0] - state.object_pose[:2]) / np.linalg.norm(state.positions[0] - state.object_pose[:2])

    def policy(s):
        seen.append(s.positions.copy())
        return push

    stack, stale_ticks = ControlStack(sc, policy), []
    for k in range(40):
        result = stack.tick(state)
        if result.stale[0]:
            stale_ticks.append(k)
        world.send_accelerations(result.a_cmd)
        state = world.step()
    rest = world.true_state().positions[0]
    assert stale_ticks[0] == 12 and stale_ticks[-1] == 39
    assert np.linalg.norm(state.positions[0] - rest) > 0.1          # the last report
    assert np.linalg.norm(seen[-1][0] - rest) < 0.02


def test_a_target_passed_by_a_robot_that_froze_is_free_for_docking_once_that_robot_is_stale():
    """Robot 0 crosses above the object at full thrust and freezes at tick 25, 49 mm from
    robot 1's target; it stops 134 mm from it. Robot 1, pushed aside by the filter as robot 0
    passed, docks from tick 28 (robot 0 stale: seen where it stopped) and ends 26 mm from its
    target at tick 80. Judged by robot 0's last report the target stays taken: robot 1 never
    docks and ends 142 mm off."""
    from sim.scenario import Scenario
    sc = Scenario(name="dock-beside-a-frozen-robot", num_robots=2, start_slots=((0.9, 0.74), (0.5, 0.85)),
                  target_slots=((0.3, 0.8), (0.5, 0.8)), start_jitter=0.0)
    world = PymunkWorld(sc, ModelError(freeze=(0, 25)))
    state = world.reset(seed=0)
    stack, docked = ControlStack(sc, lambda s: np.array([[-1.0, 0.0], [0.0, 0.0]])), []
    for _ in range(80):
        result = stack.tick(state)
        docked.append(bool(result.docking[1]))
        world.send_accelerations(result.a_cmd)
        state = world.step()
    target = sc.targets[1]
    assert np.linalg.norm(state.positions[0] - target) < 0.09            # the last report: "taken"
    assert docked.index(True) == 28 and all(docked[28:])
    assert np.linalg.norm(world.true_state().positions[1] - target) < 0.03


def _predictions_round_a_braked_tick(mode: str) -> dict[int, np.ndarray]:
    """Robot 0 thrusts along +x from rest through a world that delays commands two ticks; on
    tick 5 it is sent the braking law instead. ``mode``: "asked" (the policy itself asks the
    brake), "raised" (the policy raises and the caller sends BRAKE to every row), "overridden"
    (the tick returns thrust and the caller sends robot 0 BRAKE in its place); "...-untold":
    the same without :meth:`ControlStack.sent_braking`. Returns the latency prediction of robot
    0 (centre and velocity, (4,)) on ticks 6-9, where the braked tick is still in flight."""
    sc = transport_scenario(2)
    world = PymunkWorld(sc, ModelError(delay_ticks=2))
    world.reset(seed=0)
    world.set_state(np.array([[0.1, 0.85], [0.8, 0.2]]), np.zeros((2, 2)))
    state, stack = world.read_state(), None

    def policy(s: FleetState) -> np.ndarray:
        if s.step == 5 and mode == "asked":
            return stack.brake(s.velocities)
        if s.step == 5 and mode.startswith("raised"):
            raise RuntimeError("controller fault")
        return np.array([[1.0, 0.0], [0.0, 0.0]])

    stack = ControlStack(sc, policy, StackConfig(mec=False))
    seen, predict = {}, stack.predictor.predict

    def kept(*args, **kwargs):
        p = predict(*args, **kwargs)
        seen[state.step] = np.concatenate([p.pos[0], p.vel[0]])
        return p

    stack.predictor.predict = kept
    for _ in range(10):
        try:
            command = stack.tick(state).a_cmd
        except RuntimeError:
            command = np.full((2, 2), np.nan)
        braked = np.array([state.step == 5 and mode != "asked"] * 2)
        braked[1] &= mode.startswith("raised")
        command = np.where(braked[:, None], stack.brake(state.velocities), command)
        if braked.any() and not mode.endswith("untold"):
            stack.sent_braking(state, braked)
        world.send_accelerations(command)
        state = world.step()
    return {k: seen[k] for k in range(6, 10)}


@pytest.mark.parametrize("mode", ["raised", "overridden"])
def test_a_brake_sent_in_place_of_the_stacks_command_is_what_it_predicts_through(mode):
    """Told of the BRAKE (:meth:`ControlStack.sent_braking`), the stack predicts robot 0 through
    its commands in flight exactly as if its policy had asked the brake; untold, its history
    holds the thrust (or, after a tick that raised, no entry: every older command one tick
    late) and the prediction is 5-10 mm and 0.1 m/s off for the two ticks the brake is in flight."""
    asked = _predictions_round_a_braked_tick("asked")
    told = _predictions_round_a_braked_tick(mode)
    untold = _predictions_round_a_braked_tick(f"{mode}-untold")
    for k in asked:
        assert np.allclose(told[k], asked[k], atol=1e-12), k
    off = [np.abs(untold[k] - asked[k]) for k in (6, 7)]
    assert all(d[:2].max() > 0.004 and d[2:].max() > 0.09 for d in off), off


def test_sent_braking_checks_its_mask():
    stack = ControlStack(transport_scenario(2), lambda s: np.zeros((s.num_robots, 2)))
    state = PymunkWorld(transport_scenario(2)).reset(seed=0)
    with pytest.raises(StackError, match=r"braking must have shape \(2,\)"):
        stack.sent_braking(state, np.ones(3, dtype=bool))


_TICKS = ["ok", "override r0", "override r1", "override both", "raise"]


@settings(max_examples=40, deadline=None)
@given(ticks=st.lists(st.sampled_from(_TICKS), min_size=1, max_size=9),
       speeds=st.lists(st.floats(-0.3, 0.3), min_size=4, max_size=4))
def test_the_command_history_holds_what_was_sent_whatever_the_link_overrode(ticks, speeds):
    """Any sequence of ticks, some answered as computed, some with rows braked in place by the
    link, some where the stack raised and every row was braked: after each, the newest entries
    of the stack's command history are exactly what each robot was sent (the braking law at
    its velocity, flagged, where braked; the stack's command otherwise), tick for tick. Without
    :meth:`ControlStack.sent_braking` the history holds the stack's own commands and skips the
    ticks that raised."""
    sc = transport_scenario(2)
    pos = np.array([[0.2, 0.8], [0.8, 0.2]])
    vel = np.array(speeds).reshape(2, 2)
    kind = iter(ticks)
    current = {"kind": "ok"}

    def policy(s: FleetState) -> np.ndarray:
        if current["kind"] == "raise":
            raise RuntimeError("controller fault")
        return np.array([[0.5, -0.2], [-0.3, 0.4]])

    stack = ControlStack(sc, policy, StackConfig(mec=False, docking=DockingConfig(enabled=False)))
    sent, flags = [], []
    for step, current["kind"] in enumerate(kind):
        state = FleetState(time=step * 0.05, step=step, positions=pos + step * 0.05 * vel, velocities=vel,
                           targets=sc.targets, object_pose=np.array([*sc.object_center, 0.0]),
                           robot_ids=("r0", "r1"), commands_pending=np.zeros(2, dtype=np.int64))
        braked = np.array(["r0" in current["kind"] or "both" in current["kind"] or current["kind"] == "raise",
                           "r1" in current["kind"] or "both" in current["kind"] or current["kind"] == "raise"])
        try:
            command = stack.tick(state).a_cmd
        except RuntimeError:
            command = np.zeros((2, 2))
        brake = braking_acceleration(vel, sc.dynamics)
        sent.append(np.where(braked[:, None], brake, clip_norm(command, sc.dynamics.accel_limit)))
        flags.append(braked)
        if braked.any():
            stack.sent_braking(state, braked)
    depth = min(len(sent), stack.predictor.depth)
    history = stack.predictor._history[-depth:]
    np.testing.assert_allclose(history, np.array(sent[-depth:]), atol=1e-12)
    np.testing.assert_array_equal(stack.predictor._braked[-depth:], np.array(flags[-depth:]))


@pytest.mark.parametrize("excuse", [True, False])
def test_robots_parked_beside_the_object_leave_it(excuse, monkeypatch):
    """Three robots at rest 3 mm off the box's faces (a valid scenario, no jitter): the default
    stack brought none of them anywhere (every command braked by the post-check, the object
    unexcused) where bare they succeed; with the object's excuse they leave and arrive."""
    from controllers.safety import postcheck
    from sim.scenario import Scenario, rectangle

    if not excuse:
        monkeypatch.setattr(postcheck.SweepChecker, "object_excused", lambda self, *args: False)
    r, gap = 0.04, 0.003
    sc = Scenario(name="beside-object", num_robots=3,
                  start_slots=((0.5, 0.65 + r + gap), (0.6 + r + gap, 0.5), (0.5, 0.35 - r - gap)),
                  target_slots=((0.2, 0.85), (0.85, 0.85), (0.2, 0.15)),
                  object_vertices=rectangle((0.5, 0.5), (0.2, 0.3)), start_jitter=0.0)
    world = PymunkWorld(sc)
    metrics = run_episode(world, ControlStack(sc, ScriptedController(sc), StackConfig()), 0)
    moved = np.linalg.norm(world.true_state().positions - np.asarray(sc.starts), axis=1)
    assert not metrics.collided
    if excuse:
        assert metrics.success and moved.min() > 0.3
    else:
        assert moved.max() < 0.005
