"""Detours round what holds a robot (controllers/detour.py): the grid path and when it is taken."""

from __future__ import annotations

import math

import numpy as np
import pytest

from controllers.detour import CLEARANCE, Detour
from sim.scenario import make_scenario

SC = make_scenario("paper-3")            # box [0.4, 0.6] x [0.35, 0.65], r = 0.04, 1 x 1 arena
R = SC.robot_radius


def detour(after_s: float = 1.0) -> Detour:
    return Detour(R, SC.dynamics.accel_limit, SC.arena, SC.polygon, SC.dynamics.dt, after_s, 0.12)


def length(path: np.ndarray) -> float:
    return float(np.linalg.norm(np.diff(path, axis=0), axis=1).sum())


def test_a_path_passes_a_robot_in_the_way_through_the_gap_it_leaves():
    """Along the bottom from (0.15, 0.15) to (0.85, 0.15), a robot at (0.5, 0.15) in the way.
    Below it there is no room (a centre within 0.11 of it and 0.07 of the wall: none); above,
    between it and the object, centres from 0.26 to 0.28 up. The shortest way through that gap
    is two straight lines via (0.5, 0.26), 2 sqrt(0.35^2 + 0.11^2) = 0.734 m; an 8-connected
    grid of 1 cm adds at most 8 % to a line."""
    path = detour().plan(np.array([0.15, 0.15]), np.array([0.85, 0.15]), np.array([[0.5, 0.15]]))
    np.testing.assert_allclose(path[0], [0.155, 0.155])
    np.testing.assert_allclose(path[-1], [0.85, 0.15])
    assert np.linalg.norm(path[:-1] - [0.5, 0.15], axis=1).min() >= 2 * R + CLEARANCE
    assert 0.26 <= path[:, 1].max() <= 0.28
    assert 2 * math.hypot(0.35, 0.11) <= length(path) <= 2 * math.hypot(0.35, 0.11) * 1.09


def test_a_robot_higher_up_is_passed_below_and_a_held_target_has_no_path():
    """The robot in the way at (0.5, 0.2): no room above it (centres from 0.31, the object
    wants them below 0.28), room below (0.07 to 0.09 up). A robot standing on the target: no
    free cell within reach of it, so no path."""
    path = detour().plan(np.array([0.15, 0.15]), np.array([0.85, 0.15]), np.array([[0.5, 0.2]]))
    assert 0.07 <= path[:, 1].min() <= 0.09 and path[:, 1].max() <= 0.16
    assert detour().plan(np.array([0.15, 0.15]), np.array([0.85, 0.15]),
                         np.array([[0.5, 0.15], [0.85, 0.17]])) is None


def test_the_filter_discs_are_kept_clear_like_robots():
    """A fixed disc of radius 0.1 at (0.5, 0.15) (a silent robot bounded by 6 cm of what is not
    known of it) closes the bottom corridor: the path goes round the top of the object."""
    path = detour().plan(np.array([0.15, 0.15]), np.array([0.85, 0.15]), np.zeros((0, 2)),
                         discs=np.array([[0.5, 0.15, 0.1]]))
    assert np.linalg.norm(path - [0.5, 0.15], axis=1).min() >= R + 0.1 + CLEARANCE
    assert path[:, 1].max() >= 0.65 + R + CLEARANCE


@pytest.mark.parametrize("case", ["stuck", "not movable", "near a target", "moving", "not pushed"])
def test_a_robot_detours_once_held_still_for_after_s_away_from_every_target(case):
    """One robot at (0.15, 0.15), its target at (0.85, 0.15) past a robot in the way; the
    policy pushes it at 0.5 m/s^2 into that robot. Held still 20 ticks (1 s), it detours from
    the 20th call on: up through the gap. Not movable, within 12 cm of a target, moving, or not
    pushed, it never does."""
    d = detour()
    pos = np.array([[0.15, 0.15], [0.5, 0.15]])
    targets = np.array([[0.85, 0.15], [0.15, 0.6]])
    vel = np.zeros((2, 2))
    a_nom = np.array([[0.5, 0.0], [0.0, 0.0]])
    movable = np.array([True, False])
    if case == "not movable":
        movable[0] = False
    elif case == "near a target":
        targets[1] = [0.2, 0.2]
    elif case == "moving":
        vel[0] = [0.05, 0.0]
    elif case == "not pushed":
        a_nom[0] = [0.1, 0.0]
    flags = []
    for _ in range(25):
        out, flag = d(("a", "b"), pos, vel, targets, a_nom, movable)
        flags.append(bool(flag[0]))
        assert not flag[1]
    if case != "stuck":
        assert not any(flags) and np.array_equal(out, a_nom)
        return
    assert flags.index(True) == 19 and all(flags[19:])
    assert out[0, 1] > 0.0 and np.linalg.norm(out[0]) <= SC.dynamics.accel_limit + 1e-12
