"""A tracker's sightings as the stack takes them (stack/seen.py): a robot's own sighting never
holds it, and a silent robot the tracker sees at rest is bounded by that sighting instead of
every place it might have stopped."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from controllers.scripted import ScriptedController
from sim.fleet import Obstacles
from sim.intruders import IntruderFleet, RobotSightings
from sim.pymunk_world import ModelError, PymunkWorld
from sim.scenario import make_scenario
from stack.pipeline import ControlStack, StackConfig
from stack.seen import robot_sightings
from tests.frozen_neighbour import beside_a_frozen_robot


def test_robot_sightings_hand_worked():
    """r1 seen 50 ms ago as a 45 mm disc (robot radius 40 mm) moving at most 0.02 m/s, with a
    reach of 0.25 s beyond its age: grown by 5 mm + 0.02 * 0.3 = 11 mm, taken at t = 1.95 s. A
    disc of robot r9 (not in this fleet) and an anonymous one stay obstacles."""
    obs = Obstacles(("#0", "#1", "#2"), [[0.3, 0.4], [0.5, 0.5], [0.7, 0.7]], [0.045, 0.1, 0.05],
                    [0.05, 0.1, 0.0], [0.02, 0.0, 0.3], ("r1", None, "r9"))
    seen, rest = robot_sightings(obs, ("r0", "r1"), now=2.0, reach_s=0.25, robot_radius=0.04)
    assert list(seen) == [1]
    np.testing.assert_allclose(seen[1].centre, [0.3, 0.4])
    assert seen[1].grow == pytest.approx(0.011) and seen[1].closing == pytest.approx(0.02)
    assert seen[1].taken_at == pytest.approx(1.95)
    assert rest.ids == ("#1", "#2") and rest.robots == (None, "r9")
    np.testing.assert_allclose(rest.age_s, [0.1, 0.0])
    only_robots = Obstacles(("#0",), [[0.3, 0.4]], [0.045], [0.05], [0.02], ("r0",))
    assert robot_sightings(only_robots, ("r0",), 2.0, 0.25, 0.04)[1] is None
    with pytest.raises(ValueError, match="Obstacles.robots must name 1 robots"):
        Obstacles(("#0",), [[0.3, 0.4]], [0.045], [0.05], [0.02], ("r0", "r1"))


def _commands(sc, fleet, steps: int) -> list[np.ndarray]:
    stack = ControlStack(sc, ScriptedController(sc), StackConfig())
    state, out = fleet.reset(seed=3), []
    stack.reset()
    for _ in range(steps):
        result = stack.tick(state)
        out.append(result.a_cmd)
        fleet.send_accelerations(result.a_cmd)
        state = fleet.step()
    return out


class _Anonymous(IntruderFleet):
    """The same tracker with the robots' identity withheld: each robot a plain obstacle."""

    def _seen(self, state):
        state = super()._seen(state)
        return state.replaced(obstacles=dataclasses.replace(state.obstacles, robots=()))


def test_a_robot_is_never_held_by_its_own_sighting():
    """Scripted paper-3 in pymunk, every robot seen by the tracker (5 mm, 2 cm/s, one tick late):
    every command is the one sent without a tracker. The teeth: the same discs given as plain
    obstacles hold each robot against its own picture, and the commands differ."""
    sc = make_scenario("paper-3")
    plain = _commands(sc, PymunkWorld(sc), 40)
    seen = _commands(sc, IntruderFleet(PymunkWorld(sc), (), 1, RobotSightings()), 40)
    np.testing.assert_array_equal(np.array(seen), np.array(plain))
    blind = _commands(sc, _Anonymous(PymunkWorld(sc), (), 1, RobotSightings()), 40)
    assert np.abs(np.array(blind) - np.array(plain)).max() > 0.5


def _beside_a_frozen_robot(tracked: bool, safety: bool = True) -> tuple[float, float]:
    """:func:`tests.frozen_neighbour.beside_a_frozen_robot` with robot 1's goal at (0.2, 0.78):
    108 mm from where robot 0 stops, 84 mm from where it would have stopped had it braked at
    once; with ``tracked`` a tracker sees both robots (5 mm, one tick late)."""
    def wrap(world):
        return IntruderFleet(world, (), sighting_delay_ticks=1, robots=RobotSightings()) if tracked else world

    return beside_a_frozen_robot((0.2, 0.78), StackConfig(safety=safety), 100, wrap)


def test_a_neighbour_docks_beside_a_frozen_robot_the_tracker_sees_at_rest():
    """Without a tracker the frozen robot's cover keeps room for every place it may have
    stopped, and robot 1 ends 34 mm off its goal; a tracker that sees it at rest lets robot 1
    onto its goal (0.1 mm), 34 mm clear of the frozen robot; bare (no filter) reaches it too."""
    covered, gap_covered = _beside_a_frozen_robot(tracked=False)
    seen, gap_seen = _beside_a_frozen_robot(tracked=True)
    bare, _ = _beside_a_frozen_robot(tracked=False, safety=False)
    assert covered > 0.03 and seen < 0.002 and bare < 0.002
    assert gap_covered > 0.03 and gap_seen > 0.03


@pytest.mark.parametrize("seed", range(4))
def test_a_frozen_robot_seen_at_rest_is_bounded_more_tightly_and_still_held(seed):
    """Scripted paper-3/4/5 in pymunk, a robot frozen at a random tick, the tracker one tick
    late: its sighting narrows the robot's bound only once its branches are all at rest, and
    the discs hold its true centre at every tick they are predicted for."""
    sc = make_scenario(("paper-3", "paper-4", "paper-5")[seed % 3])
    rng = np.random.default_rng(seed)
    robot, tick = int(rng.integers(sc.num_robots)), int(rng.integers(8, 30))
    world = PymunkWorld(sc, ModelError(freeze=(robot, tick)))
    fleet = IntruderFleet(world, (), sighting_delay_ticks=1, robots=RobotSightings(seed=seed))
    stack = ControlStack(sc, ScriptedController(sc), StackConfig())
    calls = []
    predict = stack.predictor.predict
    stack.predictor.predict = lambda *a, **k: calls.append((predict(*a, **k), k.get("seen"))) or calls[-1][0]
    state, narrowed, due, misses = fleet.reset(seed=seed), [], {}, 0
    stack.reset()
    ahead = int(round(stack.config.latency.command_delay_s / sc.dynamics.dt))
    for k in range(tick + 40):
        result = stack.tick(state)
        prediction, seen = calls[-1]
        if result.stale[robot]:
            covers = [(c, r) for row, c, r in prediction.covers if row == robot]
            centres, radii = covers[0] if covers else (prediction.pos[robot][None], prediction.grow[robot:robot + 1])
            sighting = seen[robot]
            paths = stack.predictor._paths[state.robot_ids[robot]]
            at_rest = paths.seen_at_rest(sighting.taken_at)
            narrowed.append(at_rest)
            due[k + ahead] = (centres.copy(), radii.copy())
        fleet.send_accelerations(result.a_cmd)
        state = fleet.step()
        if k + 1 in due:
            centres, radii = due.pop(k + 1)
            true = world.true_state().positions[robot]
            misses += bool((np.linalg.norm(true - centres, axis=1) - radii).min() > 1e-9)
    assert narrowed[0] is False and narrowed[-1] is True
    assert narrowed == sorted(narrowed)                 # once at rest, always
    assert misses == 0
