"""The adversary of the safety benchmarks: robots that try to collide, and starts inside h >= 0.

Every robot keeps one adversarial mode per episode: full thrust at its nearest neighbour, at the
object, at the nearest wall, along a fixed random direction, along a fresh random direction
every tick, the scripted controller, or (with a network) a trained policy.
"""

from __future__ import annotations

import dataclasses

import numpy as np

from controllers.docking import DockingConfig
from controllers.safety import SafetyFilter, analytic_distances
from controllers.scripted import ScriptedController
from sim.fleet import FleetState
from sim.pymunk_world import PymunkWorld
from stack.pipeline import ControlStack, StackConfig

WALL_DIRS = np.array([[-1.0, 0.0], [1.0, 0.0], [0.0, -1.0], [0.0, 1.0]])
MIN_ROBOTS, MAX_ROBOTS = 3, 16


class AdversarialPolicy:
    """FleetState -> (N, 2): each robot follows its own adversarial mode (module docstring)."""

    def __init__(self, scenario, rng: np.random.Generator, network=None):
        n = scenario.num_robots
        self.scenario, self.rng = scenario, rng
        self.modes = rng.integers(0, 7 if network is not None else 6, n)
        self.fixed = rng.normal(size=(n, 2))
        self.scripted = ScriptedController(scenario)
        self.network = ControlStack(scenario, network, StackConfig(safety=False, mec=False)) \
            if network is not None else None

    def reset(self) -> None:
        self.scripted.reset()

    def __call__(self, state: FleetState) -> np.ndarray:
        pos, n = state.positions, state.num_robots
        limit = self.scenario.dynamics.accel_limit
        d = np.linalg.norm(pos[:, None] - pos[None], axis=-1) + np.eye(n) * 1e9
        walls = np.stack([pos[:, 0], self.scenario.arena[0] - pos[:, 0], pos[:, 1],
                          self.scenario.arena[1] - pos[:, 1]], 1)
        thrust = np.stack([pos[np.argmin(d, axis=1)] - pos, self.scenario.object_center - pos,
                           WALL_DIRS[np.argmin(walls, axis=1)], self.fixed,
                           self.rng.normal(size=(n, 2))])
        thrust = thrust / np.maximum(np.linalg.norm(thrust, axis=-1, keepdims=True), 1e-12) * limit
        out = thrust[np.minimum(self.modes, 4), np.arange(n)]
        scripted = self.modes == 5
        if scripted.any():
            out[scripted] = self.scripted(state)[scripted]
        if self.network is not None and (self.modes == 6).any():
            out[self.modes == 6] = self.network.tick(state).a_nom[self.modes == 6]
        return out


def without_docking(config: StackConfig) -> StackConfig:
    """``config`` with docking off: near a free target docking would take a robot over from the
    adversary, whose commands are the point of an adversarial episode."""
    return dataclasses.replace(config, docking=DockingConfig(enabled=False))


def in_delayed_safe_set(barrier: SafetyFilter, pos: np.ndarray, vel: np.ndarray, coast_ticks: int) -> bool:
    """``h >= 0`` at the state and at every state the robots coast to, with no command, over the
    next ``coast_ticks`` ticks: where a filter that allows for that much command delay can start
    (a robot cannot brake before its first command arrives)."""
    dyn = barrier.dynamics
    for _ in range(coast_ticks + 1):
        if barrier.barrier(pos, vel).h.min() < 0:
            return False
        pos, vel = dyn.step_np(pos, vel, np.zeros_like(vel))
    return True


def random_start(world: PymunkWorld, barrier: SafetyFilter, rng: np.random.Generator,
                 coast_ticks: int = 3) -> FleetState:
    """Random positions with >= 0.03 m clearance, random velocities scaled into the safe set
    ``h >= 0`` of the default latency bound (3 ticks, :func:`in_delayed_safe_set`)."""
    sc = world.scenario
    n, r = sc.num_robots, sc.robot_radius
    pos = np.zeros((0, 2))
    while len(pos) < n:
        cand = np.vstack([pos, rng.uniform(r, 1 - r, (1, 2))])
        if analytic_distances(cand, r, sc.arena, sc.polygon).min_clearance() >= 0.03:
            pos = cand
    vel = rng.normal(0.0, 0.15, (n, 2))
    while not in_delayed_safe_set(barrier, pos, vel, coast_ticks):
        vel *= 0.8
    world.set_state(pos, vel)
    return world.read_state()
