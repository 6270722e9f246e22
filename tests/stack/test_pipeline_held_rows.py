"""ControlStack: robots that do not listen stay fixed obstacles on every path of a tick.

Hand-built cases, one per path: the latency prediction switched off, the compensated command's
re-check, an infinitely old state, two tracker sightings of one robot, and an object that moved
and came back. Each failed before its fix (the numbers in the comments are the old outputs).
"""

from __future__ import annotations

import numpy as np
import pytest

import stack.pipeline as pipeline
from controllers.docking import DockingConfig
from controllers.safety.latency import LatencyConfig
from sim.fleet import FleetState, Obstacles, SilentRobots
from sim.scenario import clip_norm, transport_scenario
from stack.pipeline import ControlStack, StackConfig

SCENARIO = transport_scenario(2)
POSE = np.array([*SCENARIO.object_center, 0.0])
NO_LATENCY = StackConfig(mec=False, estimated_position=False, latency=LatencyConfig(enabled=False),
                         docking=DockingConfig(enabled=False))


def state(positions, velocities, ids=("a", "b"), **kw) -> FleetState:
    n = len(positions)
    return FleetState(time=kw.pop("time", 1.0), step=kw.pop("step", 20), positions=positions, velocities=velocities,
                      targets=[[0.1, 0.9], [0.9, 0.9]][:n], object_pose=kw.pop("object_pose", POSE),
                      robot_ids=ids, **kw)


def braking_alone(stack: ControlStack, pos, vel) -> float:
    """x-command of robot a closing on a robot held still at 0.33 (filter alone, the other fixed)."""
    from controllers.safety.prediction import Prediction
    pos, vel = np.asarray(pos, dtype=float), np.asarray(vel, dtype=float)
    held = Prediction.as_measured(pos, vel, np.array([False, True]))
    return float(stack.safety.filter(pos, vel, np.array([[1.0, 0.0], [0.0, 0.0]]), prediction=held).a_safe[0, 0])


@pytest.mark.parametrize("how", ["silent", "stale"])
def test_without_the_latency_prediction_a_robot_not_listening_is_still_held_fixed(how):
    """Robot a at 0.35 m/s, 9 cm from b. Held fixed, b cannot take its share of the avoidance, so a
    brakes harder than it would with b free (the QP split it before: -0.56 and -0.74 m/s^2)."""
    stack = ControlStack(SCENARIO, lambda s: np.tile([1.0, 0.0], (s.num_robots, 1)), NO_LATENCY)
    pos, vel = [[0.2, 0.15], [0.33, 0.15]], [[0.35, 0.0], [0.0, 0.0]]
    if how == "silent":
        given = state(pos[:1], vel[:1], ids=("a",), silent=SilentRobots(("b",), pos[1:], vel[1:], [1.0]))
    else:
        given = state(pos, vel, state_age_s=[0.0, 0.5])
    result = stack.tick(given)
    fixed = braking_alone(stack, pos, vel)
    assert fixed < -0.9
    assert result.a_cmd[0, 0] == pytest.approx(fixed, abs=1e-6)
    if how == "stale":
        assert result.stale.tolist() == [False, True]
        assert np.allclose(result.a_safe[1], 0.0)         # b's plan: held, not asked to move away


def test_the_compensated_command_is_rechecked_with_a_stale_robot_held_still(monkeypatch):
    """A steady push on b that the MEC has learned, then b's states stop (it is held still). The
    MEC's -d_hat for b must not make up, in the re-check, for a row that a's compensated command
    breaks: b is braked, not compensated (before: margin -0.30 judged as +0.20, at tick 24)."""
    dyn = SCENARIO.dynamics
    seen = []
    original = pipeline.recheck

    def spy(terms, a_safe, a_cmd, keep):
        out = original(terms, a_safe, a_cmd, keep)
        seen.append((terms, a_safe.copy(), out.copy()))
        return out

    monkeypatch.setattr(pipeline, "recheck", spy)
    stack = ControlStack(SCENARIO, lambda s: np.array([[1.0, 0.0], [0.0, 0.0]]),
                         StackConfig(estimated_position=False, docking=DockingConfig(enabled=False)))
    pos, vel = np.array([[0.10, 0.15], [0.45, 0.15]]), np.zeros((2, 2))
    push = np.array([[-0.3, 0.0], [-0.5, 0.0]])
    frozen, worst, stale_ticks = None, np.inf, 0
    for k in range(60):
        t = 1.0 + k * dyn.dt
        if k == 20:
            frozen = (pos[1].copy(), t)
        reported, ages = pos.copy(), np.zeros(2)
        if frozen is not None:
            reported[1], ages[1] = frozen[0], t - frozen[1]
        seen.clear()
        result = stack.tick(state(reported, np.where(np.arange(2)[:, None] == 1, 0.0, vel) if frozen else vel,
                                  time=t, step=k, state_age_s=ages))
        if result.stale[1] and seen:
            terms, a_safe, out = seen[-1]
            held = np.vstack([out[:1], np.zeros((len(a_safe) - 1, 2))])
            floor = np.minimum(terms.bound, terms.rows_times(a_safe)) - 1e-9
            worst = min(worst, float((terms.rows_times(held) - floor).min()))
            stale_ticks += 1
        accel = clip_norm(result.a_cmd, dyn.accel_limit) + push
        if frozen is not None:
            accel[1], vel[1] = 0.0, 0.0
        pos, vel = dyn.step_np(pos, vel, accel)
    assert stale_ticks > 20
    assert worst >= 0.0


def test_an_infinitely_old_state_makes_its_robot_an_obstacle_not_an_error():
    stack = ControlStack(SCENARIO, lambda s: np.zeros((s.num_robots, 2)), StackConfig())
    pos, vel = [[0.2, 0.2], [0.3, 0.8]], [[0.0, 0.0], [0.1, 0.0]]
    stack.tick(state(pos, vel, state_age_s=[0.0, 0.0]))
    result = stack.tick(state(pos, vel, time=1.05, step=21, state_age_s=[0.0, np.inf]))   # raised OverflowError
    assert result.stale.tolist() == [False, True]
    assert np.isfinite(result.a_cmd).all()
    assert result.a_cmd[1].tolist() == pytest.approx(stack.brake(np.array(vel))[1].tolist())


def test_two_sightings_of_one_robot_never_hold_it():
    """A tracker that gave robot a a second track before ending the first: both are a, so neither
    is an obstacle (before, the older one held a where it stood: a braked to 0)."""
    policy = lambda s: np.array([[1.0, 0.0], [0.0, 0.0]])    # noqa: E731
    given = state([[0.2, 0.15], [0.2, 0.6]], np.zeros((2, 2)))
    twice = Obstacles(("#1", "#2"), [[0.20, 0.15], [0.201, 0.15]], [0.04, 0.04], [0.0, 0.0], [0.0, 0.0],
                      robots=("a", "a"))
    result = ControlStack(SCENARIO, policy, StackConfig()).tick(given.replaced(obstacles=twice))
    assert result.a_cmd[0].tolist() == pytest.approx([1.0, 0.0])


def test_an_object_back_at_its_own_pose_is_filtered_where_it_is():
    """Robot at 0.30 heading +x at 0.3 m/s for the object's left face (x = 0.4): braked. After
    one tick with the object 0.3 m to the right, the same tick at the object's own pose must
    brake again (before, the filter kept the moved object and let it drive on at +0.64)."""
    one = transport_scenario(1)
    home = np.array([*one.object_center, 0.0])
    config = StackConfig(mec=False, estimated_position=False, docking=DockingConfig(enabled=False))

    def tick(stack, t, pose):
        return stack.tick(FleetState(time=t, step=int(round(t / 0.05)), positions=[[0.30, 0.5]],
                                     velocities=[[0.3, 0.0]], targets=[[0.1, 0.9]], object_pose=pose,
                                     robot_ids=("a",)))

    fresh = tick(ControlStack(one, lambda s: np.array([[1.0, 0.0]]), config), 1.0, home)
    stack = ControlStack(one, lambda s: np.array([[1.0, 0.0]]), config)
    tick(stack, 1.0, home + [0.3, 0.0, 0.0])
    back = tick(stack, 1.05, home)
    assert fresh.a_cmd[0, 0] < 0.0
    assert back.a_cmd[0].tolist() == pytest.approx(fresh.a_cmd[0].tolist())

