"""Randomised forward invariance: adversarial commands never collide through the filter, and do without it.

The plant is a numpy loop of the damped double integrator of :class:`sim.scenario.Dynamics`
(clip the command, semi-implicit Euler, clip the speed), with no wall clamping and no contact
forces, so every overlap at a tick counts. Each robot keeps one adversarial mode per episode:
full thrust towards its nearest neighbour, the object centre, the nearest wall, a fixed random
direction, or a fresh random direction every tick.
"""

from __future__ import annotations

import numpy as np

from controllers.mec import ModelErrorCompensator
from controllers.safety import SafetyFilter, SafetyStatus, analytic_distances
from sim.scenario import transport_scenario

EPISODES, STEPS = 12, 60
WALL_DIRS = np.array([[-1.0, 0.0], [1.0, 0.0], [0.0, -1.0], [0.0, 1.0]])


def initial_state(rng, scenario, filt):
    """Robots placed one by one with 0.03 m clearance; velocities scaled into the safe set h >= 0."""
    n, r = scenario.num_robots, scenario.robot_radius
    pos = np.zeros((0, 2))
    while len(pos) < n:
        cand = np.vstack([pos, rng.uniform(0.05, 0.95, (1, 2))])
        if analytic_distances(cand, r, scenario.arena, scenario.polygon).min_clearance() >= 0.03:
            pos = cand
    vel = rng.normal(0.0, 0.2, (n, 2))
    while filt.barrier(pos, vel).h.min() < 0:
        vel *= 0.8
    return pos, vel


def adversarial(rng, pos, modes, fixed_dirs, scenario):
    n = len(pos)
    d = np.linalg.norm(pos[:, None] - pos[None], axis=-1) + np.eye(n) * 1e9
    walls = np.stack([pos[:, 0], 1 - pos[:, 0], pos[:, 1], 1 - pos[:, 1]], 1)
    toward = np.stack([
        pos[np.argmin(d, axis=1)] - pos,                 # nearest neighbour
        scenario.object_center - pos,                    # the object
        WALL_DIRS[np.argmin(walls, axis=1)],             # the nearest wall
        fixed_dirs,                                      # one random direction
        rng.normal(size=(n, 2)),                         # a fresh random direction
    ])[modes, np.arange(n)]
    return toward / np.linalg.norm(toward, axis=1, keepdims=True) * scenario.dynamics.accel_limit


def plant_step(pos, vel, acc, dyn, gain):
    a = acc * np.minimum(1.0, dyn.accel_limit / np.maximum(np.linalg.norm(acc, axis=1), 1e-12))[:, None]
    v = vel + dyn.dt * (gain[:, None] * a - dyn.damping * vel)
    v *= np.minimum(1.0, dyn.speed_limit / np.maximum(np.linalg.norm(v, axis=1), 1e-12))[:, None]
    return pos + dyn.dt * v, v


def run(seed, *, filtered, model_error=False):
    """Returns (collision ticks, status counts, min clearance) of one episode."""
    rng = np.random.default_rng(seed)
    scenario = transport_scenario(3 + seed % 6)          # N = 3..8
    n, dyn = scenario.num_robots, scenario.dynamics
    filt = SafetyFilter(scenario)
    mec = ModelErrorCompensator(dyn) if model_error else None
    pos, vel = initial_state(rng, scenario, filt)
    modes = rng.integers(0, 5, n)
    fixed_dirs = rng.normal(size=(n, 2))
    gain = rng.uniform(0.7, 1.0, n) if model_error else np.ones(n)
    collisions, statuses, min_clear = 0, {}, np.inf
    for _ in range(STEPS):
        acc = adversarial(rng, pos, modes, fixed_dirs, scenario)
        if filtered:
            result = filt.filter(pos, vel, acc)
            statuses[result.status] = statuses.get(result.status, 0) + 1
            acc = result.a_safe
        if mec is not None:
            acc = mec.step(vel, acc).a_cmd
        pos, vel = plant_step(pos, vel, acc, dyn, gain)
        clearance = analytic_distances(pos, scenario.robot_radius, scenario.arena,
                                       scenario.polygon).min_clearance()
        min_clear = min(min_clear, clearance)
        collisions += clearance < 0
    return collisions, statuses, min_clear


def test_filter_keeps_adversarial_robots_collision_free_and_unfiltered_ones_collide():
    totals: dict = {}
    for seed in range(EPISODES):
        collisions, statuses, min_clear = run(seed, filtered=True)
        assert collisions == 0, f"seed {seed}: {collisions} collision ticks, min clearance {min_clear}"
        for k, v in statuses.items():
            totals[k] = totals.get(k, 0) + v
    assert totals.get(SafetyStatus.INTERVENED, 0) > EPISODES * STEPS // 2   # it had work to do
    collided = sum(run(seed, filtered=False)[0] > 0 for seed in range(EPISODES))
    assert collided >= EPISODES - 2                                         # teeth


def test_filter_with_mec_survives_weak_actuators():
    """Robots achieving only 70-100 % of the command, compensated by the MEC, still never collide."""
    for seed in range(EPISODES // 2):
        collisions, _, min_clear = run(seed, filtered=True, model_error=True)
        assert collisions == 0, f"seed {seed}: min clearance {min_clear}"
    collided = sum(run(seed, filtered=False, model_error=True)[0] > 0 for seed in range(EPISODES // 2))
    assert collided >= EPISODES // 2 - 1
