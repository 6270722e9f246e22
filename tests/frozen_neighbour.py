"""One scene shared by the silent-robot tests: a robot freezes at speed beside a neighbour that
a PD law drives to a goal, everything through a :class:`stack.pipeline.ControlStack`."""

from __future__ import annotations

from collections.abc import Callable

import numpy as np

from sim.fleet import Fleet
from sim.pymunk_world import ModelError, PymunkWorld
from sim.scenario import transport_scenario
from stack.pipeline import ControlStack, StackConfig


def beside_a_frozen_robot(goal: tuple[float, float], config: StackConfig, ticks: int,
                          wrap: Callable[[PymunkWorld], Fleet] = lambda world: world) -> tuple[float, float]:
    """Two robots of ``transport_scenario(2)`` in pymunk: robot 0 starts at rest at (0.1, 0.85),
    thrusts along +x at 1 m/s^2 and freezes at tick 8 (x = 0.182, 0.36 m/s; held two ticks by
    its watchdog, then braked, it comes to rest at x = 0.282); robot 1 starts at (0.35, 0.7) and
    is driven to ``goal`` [m] by ``a = 4 (goal - p) - 3 v``. ``wrap`` may put the world in another
    fleet (a tracker's). Returns robot 1's final distance to ``goal`` and the smallest gap between
    the two discs over ``ticks`` ticks [m], both from pymunk's true state."""
    sc = transport_scenario(2)
    world = PymunkWorld(sc, ModelError(freeze=(0, 8)))
    fleet = wrap(world)
    fleet.reset(seed=0)
    world.set_state(np.array([[0.1, 0.85], [0.35, 0.7]]), np.zeros((2, 2)))
    state, target = fleet.read_state(), np.asarray(goal)

    def policy(s):
        return np.array([[1.0, 0.0], 4.0 * (target - s.positions[1]) - 3.0 * s.velocities[1]])

    stack, gap = ControlStack(sc, policy, config), np.inf
    for _ in range(ticks):
        result = stack.tick(state)
        fleet.send_accelerations(result.a_cmd)
        state = fleet.step()
        true = world.true_state().positions
        gap = min(gap, float(np.linalg.norm(true[0] - true[1])) - 2 * sc.robot_radius)
    return float(np.linalg.norm(world.true_state().positions[1] - target)), gap
