"""Obstacles a tracker sees (sim.fleet.Obstacles): the filter keeps robots clear of them, in
pymunk with two ticks of command delay and sightings two ticks old."""

from __future__ import annotations

import numpy as np
import pytest

from controllers.safety.prediction import Prediction
from controllers.scripted import ScriptedController
from sim.fleet import Obstacles
from sim.intruders import scattered_boxes
from sim.pymunk_world import ModelError, PymunkWorld
from sim.scenario import make_scenario
from stack.pipeline import ControlStack, StackConfig

BARE = StackConfig(safety=False, mec=False)


def test_obstacles_are_checked_by_name():
    with pytest.raises(ValueError, match="Obstacles.radii must be 1 finite values > 0"):
        Obstacles(("o",), [[0.5, 0.5]], [0.0], [0.0], [0.0])
    with pytest.raises(ValueError, match="Obstacles.positions"):
        Obstacles(("o", "p"), [[0.5, 0.5]], [0.1, 0.1], [0.0, 0.0], [0.0, 0.0])
    with pytest.raises(ValueError, match="Obstacles.speed"):
        Obstacles(("o",), [[0.5, 0.5]], [0.1], [0.0], [-1.0])


def test_an_obstacle_is_a_fixed_row_grown_by_how_far_it_may_move():
    """R = 0.06 m, robot radius 0.04, seen 0.1 s ago, 0.15 s of latency, one 0.05 s tick, at
    most 0.2 m/s: a fixed disc at its sighting, grown by 0.02 + 0.2 * 0.3 = 0.08 m, closing at
    0.2 m/s."""
    base = Prediction(pos=np.zeros((2, 2)), vel=np.ones((2, 2)), grow=np.full(2, 0.01), closing=np.full(2, 0.02),
                      fixed=np.zeros(2, dtype=bool), horizon=np.full(2, 3))
    p = base.with_obstacles(np.array([[0.5, 0.6]]), np.array([0.06]), np.array([0.3]), np.array([0.2]), 0.04)
    np.testing.assert_allclose(p.pos[2], [0.5, 0.6])
    np.testing.assert_allclose(p.vel[2], [0.0, 0.0])
    assert p.grow[2] == pytest.approx(0.08) and p.closing[2] == pytest.approx(0.2)
    assert p.fixed.tolist() == [False, False, True] and p.horizon[2] == 0
    np.testing.assert_array_equal(p.grow[:2], base.grow)
    assert base.with_obstacles(np.zeros((0, 2)), np.zeros(0), np.zeros(0), np.zeros(0), 0.04) is base


def _episode(config: StackConfig, start: tuple[float, float], velocity: tuple[float, float],
             radius: float = 0.05, age_ticks: int = 2, delay_ticks: int = 2):
    """Scripted paper-3 in pymunk (commands delayed ``delay_ticks``), an obstacle of ``radius``
    moving from ``start`` at ``velocity`` [m/s], reported to the stack ``age_ticks`` late.
    Returns (smallest gap between a robot and the obstacle [m], the largest speed at which a
    robot moved towards it while touching it [m/s], success)."""
    sc = make_scenario("paper-3")
    world = PymunkWorld(sc, ModelError(delay_ticks=delay_ticks))
    state = world.reset(seed=0)
    stack = ControlStack(sc, ScriptedController(sc), config)
    dt, speed = sc.dynamics.dt, float(np.hypot(*velocity))
    gap, towards = np.inf, -np.inf
    for k in range(sc.dynamics.episode_steps):
        seen = np.asarray(start) + np.asarray(velocity) * max(k - age_ticks, 0) * dt
        obstacle = Obstacles(("o",), seen[None], [radius], [min(k, age_ticks) * dt], [speed])
        world.send_accelerations(stack.tick(state.replaced(obstacles=obstacle)).a_cmd)
        state = world.step()
        centre = np.asarray(start) + np.asarray(velocity) * (k + 1) * dt
        true = world.true_state()
        offset = centre - true.positions
        dist = np.linalg.norm(offset, axis=1)
        gap = min(gap, float((dist - radius - sc.robot_radius).min()))
        for i in np.flatnonzero(dist < radius + sc.robot_radius):
            towards = max(towards, float(true.velocities[i] @ offset[i] / dist[i]))
    return gap, towards, bool(world.outcome().success[0])


def test_a_box_on_the_way_is_kept_clear():
    """A 5 cm box above the object, on the way of the robots that go over it: the stack keeps
    them 12 mm clear, on an exact link (where every robot still reaches its target) and with
    two ticks of command delay and sightings two ticks old (where, held behind the box, they do
    not all arrive within the episode); without the filter they drive through it (53 mm deep)."""
    gap, _, success = _episode(StackConfig(), (0.5, 0.8), (0.0, 0.0), age_ticks=0, delay_ticks=0)
    assert gap > 0.005 and success
    gap, _, _ = _episode(StackConfig(), (0.5, 0.8), (0.0, 0.0))
    assert gap > 0.005
    gap_bare, _, _ = _episode(BARE, (0.5, 0.8), (0.0, 0.0), age_ticks=0, delay_ticks=0)
    assert gap_bare < -0.03


@pytest.mark.parametrize(("start", "velocity"), [((0.5, 0.95), (0.0, -0.1)), ((0.2, 0.95), (0.1, -0.3)),
                                                 ((0.9, 0.1), (-0.2, 0.2))])
def test_no_robot_drives_into_a_moving_obstacle(start, velocity):
    """A person-sized disc walking across the arena at 0.1-0.32 m/s. Braking cannot stop one
    that walks into a robot, and some do; but with the stack a robot touching it moves towards
    it at 1 cm/s at most (it was braked, and is hit), where robots without the filter drive into
    it at 7-24 cm/s."""
    gap, towards, _ = _episode(StackConfig(), start, velocity)
    assert gap > 0 or towards < 0.01, (gap, towards)
    gap_bare, towards_bare, _ = _episode(BARE, start, velocity)
    assert gap_bare < 0 and towards_bare > 0.05, (gap_bare, towards_bare)


def test_with_the_latency_prediction_off_an_obstacle_is_still_kept_clear():
    """The rows as measured (Prediction.as_measured) with the obstacle appended: the same box,
    an exact link, the latency prediction off."""
    from controllers.safety.latency import LatencyConfig

    gap, _, _ = _episode(StackConfig(latency=LatencyConfig(enabled=False)), (0.5, 0.8), (0.0, 0.0),
                         age_ticks=0, delay_ticks=0)
    assert gap > 0.0, gap


def test_a_cluttered_arena_gives_the_commands_of_the_filter_that_takes_every_disc():
    """100 boxes reported by a tracker, pymunk with two ticks of command delay: at every tick the
    stack's commands are those of a stack whose filter takes all 100 (1e-5 m/s^2), while its QP
    holds only the boxes near a robot (at most 60 here; the time it saves: bench/safety.py
    --only clutter); the boxes do change the commands (teeth)."""
    sc = make_scenario("paper-3")
    boxes = scattered_boxes(np.random.default_rng(3), sc.starts, sc.arena, sc.robot_radius, 100)
    world = PymunkWorld(sc, ModelError(delay_ticks=2))
    state = world.reset(seed=0)
    stacks = {name: ControlStack(sc, ScriptedController(sc), config) for name, config in
              (("pruned", StackConfig()), ("all", StackConfig(all_tracker_discs=True)), ("none", StackConfig()))}
    worst, moved_by_boxes = 0.0, 0.0
    for _ in range(80):
        cmd = {name: s.tick(state.replaced(obstacles=None if name == "none" else boxes)).a_cmd
               for name, s in stacks.items()}
        worst = max(worst, float(np.abs(cmd["pruned"] - cmd["all"]).max()))
        moved_by_boxes = max(moved_by_boxes, float(np.abs(cmd["pruned"] - cmd["none"]).max()))
        world.send_accelerations(cmd["pruned"])
        state = world.step()
    assert worst < 1e-5
    assert moved_by_boxes > 0.1
    assert max(stacks["pruned"].safety._problems) < 3 + 100 == max(stacks["all"].safety._problems)
