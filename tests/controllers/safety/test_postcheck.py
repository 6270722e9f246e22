"""One-tick sweep check: hand-worked cases, agreement with the batched world, soundness."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from controllers.safety import CollisionScene, analytic_distances, predict_step
from controllers.safety.postcheck import (
    SweepChecker,
    braking_acceleration,
    segment_origin_distance,
)
from sim.batched_env import BatchedFormationEnv
from sim.scenario import transport_scenario

SCENARIO = transport_scenario(3)      # box [0.4, 0.6] x [0.35, 0.65]
DYN = SCENARIO.dynamics
R = SCENARIO.robot_radius


def checker_for(pos):
    scene = CollisionScene(SCENARIO, len(pos))
    scene.update(pos)
    return SweepChecker(scene.object_parts, R, SCENARIO.arena, DYN), scene.distances().object_distance


def test_segment_origin_distance_by_hand():
    start = np.array([[-1.0, 1.0], [1.0, 0.0], [3.0, 4.0], [-3.0, -4.0]])
    end = np.array([[1.0, 1.0], [2.0, 0.0], [3.0, 4.0], [3.0, 4.0]])
    np.testing.assert_allclose(segment_origin_distance(start, end), [1.0, 1.0, 5.0, 0.0])


def test_predict_step_matches_the_batched_world():
    rng = np.random.default_rng(0)
    env = BatchedFormationEnv(SCENARIO, 1, dtype=torch.float64)
    pos = np.array([[0.2, 0.2], [0.8, 0.3], [0.3, 0.8]])
    for _ in range(10):
        vel = rng.normal(0, 0.3, (3, 2))
        acc = rng.normal(0, 1.5, (3, 2))
        env.set_state(torch.from_numpy(pos)[None], torch.from_numpy(vel)[None])
        env.step(torch.from_numpy(acc)[None])
        end, bulge = predict_step(pos, vel, acc, DYN)
        np.testing.assert_allclose(end, env.pos[0].numpy(), atol=1e-12)
        assert np.all(bulge <= 0.5 * DYN.dt**2 * (DYN.accel_limit + DYN.damping * 0.3 * 5))


def test_head_on_pair_is_braked_and_unavoidable_touch_is_reported():
    # gap 0.01 m, closing at 0.8 m/s: even full braking (v' = 0.4 - 0.05 * 1.2 = 0.34 m/s,
    # 0.017 m each) closes more than the gap
    pos = np.array([[0.30, 0.2], [0.39, 0.2], [0.8, 0.9]])
    vel = np.array([[0.4, 0.0], [-0.4, 0.0], [0.0, 0.0]])
    checker, clearance = checker_for(pos)
    out = checker.check(pos, vel, np.zeros((3, 2)), clearance)
    np.testing.assert_array_equal(out.braked, [True, True, False])
    np.testing.assert_array_equal(out.contact, [True, True, False])
    np.testing.assert_allclose(out.acc[:2], [[-1.0, 0.0], [1.0, 0.0]])
    np.testing.assert_allclose(out.acc[2], [0.0, 0.0])


def test_slow_pair_is_saved_by_braking():
    # gap 0.008 m closing at 0.2 m/s: coasting travels 2 * 0.0975 * 0.05 = 0.00975 m > gap;
    # braking (a = -1) gives v' = 0.0475 m/s: 0.00475 m plus widening 2 * 0.0013125 m < 0.008 m
    pos = np.array([[0.30, 0.2], [0.388, 0.2], [0.8, 0.9]])
    vel = np.array([[0.1, 0.0], [-0.1, 0.0], [0.0, 0.0]])
    checker, clearance = checker_for(pos)
    out = checker.check(pos, vel, np.zeros((3, 2)), clearance)
    np.testing.assert_array_equal(out.braked, [True, True, False])
    assert not out.contact.any()


def test_sweep_catches_a_corner_that_both_end_points_clear():
    """Passing the box corner (0.4, 0.35) on a chord 0.0395 m from it, ends 0.04075 m from it."""
    corner = np.array([0.4, 0.35])
    direction = np.array([1.0, -1.0]) / math.sqrt(2)
    middle = corner + 0.0395 * np.array([-1.0, -1.0]) / math.sqrt(2)
    start = middle - 0.01 * direction
    vel = 0.4 * direction                        # 0.02 m per tick at the speed limit
    acc = DYN.damping * vel                      # holds the speed: no widening
    pos = np.array([start, [0.9, 0.9], [0.1, 0.9]])
    vels = np.array([vel, [0, 0], [0, 0]])
    accs = np.array([acc, [0, 0], [0, 0]])
    end, bulge = predict_step(pos, vels, accs, DYN)
    assert bulge[0] == pytest.approx(0.0, abs=1e-15)
    ends = analytic_distances(np.array([start, end[0]]), R, SCENARIO.arena, SCENARIO.polygon)
    assert np.all(ends.object_distance > 0.0007)             # both end points are clear
    checker, clearance = checker_for(pos)
    assert checker.failing(pos, vels, accs, clearance)[0]     # the swept capsule is not
    out = checker.check(pos, vels, accs, clearance)
    assert out.braked[0] and not out.braked[1:].any()
    np.testing.assert_allclose(out.acc[0], braking_acceleration(vels, DYN)[0])


def test_wall_approach_is_braked():
    pos = np.array([[0.05, 0.5], [0.5, 0.9], [0.9, 0.1]])
    vel = np.array([[-0.4, 0.0], [0.0, 0.0], [0.0, 0.0]])
    checker, clearance = checker_for(pos)
    out = checker.check(pos, vel, np.array([[-1.0, 0.0], [0, 0], [0, 0]]), clearance)
    np.testing.assert_array_equal(out.braked, [True, False, False])


def test_braking_stops_slow_robots_without_reversing():
    vel = np.array([[0.01, 0.0], [0.0, -0.4], [0.0, 0.0]])
    a = braking_acceleration(vel, DYN)
    v_next = vel + DYN.dt * (a - DYN.damping * vel)
    np.testing.assert_allclose(v_next[0], 0.0, atol=1e-15)     # stops exactly
    np.testing.assert_allclose(a[1], [0.0, 1.0])               # full thrust against v
    np.testing.assert_allclose(a[2], 0.0)
    assert np.all(np.isfinite(braking_acceleration(np.array([[np.nan, 1.0]]), DYN)))


def test_passing_the_check_means_no_contact_along_the_tick():
    """Soundness: robots the check lets through touch nothing on the continuous path or at the end."""
    rng = np.random.default_rng(7)
    passed = flagged = 0
    times = np.linspace(0.0, DYN.dt, 41)
    for _ in range(400):
        pos = rng.uniform(0.03, 0.97, (3, 2))
        start = analytic_distances(pos, R, SCENARIO.arena, SCENARIO.polygon)
        if not 0 <= start.min_clearance() < 0.02:          # near contact: where the check matters
            continue
        vel = rng.uniform(-0.4, 0.4, (3, 2))
        acc = rng.uniform(-1.5, 1.5, (3, 2))
        checker, clearance = checker_for(pos)
        bad = checker.failing(pos, vel, acc, clearance)
        flagged += int(bad.sum())
        a = acc * np.minimum(1.0, DYN.accel_limit / np.linalg.norm(acc, axis=1))[:, None]
        a_eff = a - DYN.damping * vel
        end, _ = predict_step(pos, vel, acc, DYN)
        paths = [pos + vel * t + 0.5 * a_eff * t**2 for t in times] + [end]
        for p in paths:
            d = analytic_distances(p, R, SCENARIO.arena, SCENARIO.polygon)
            touching = d.object_distance < 0
            touching |= (d.wall_distance < 0).any(axis=1)
            for k in np.flatnonzero(d.pair_distance < 0):
                touching[d.pair_i[k]] = touching[d.pair_j[k]] = True
            assert not np.any(touching & ~bad)
        passed += int((~bad).sum())
    assert passed > 100 and flagged > 20                 # both outcomes were exercised
