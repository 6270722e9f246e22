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


def test_robots_and_discs_close_exactly_the_cells_within_their_reach():
    """The free cells of a plan are those of every grid centre measured against every robot and
    disc (the brute force), for robots and discs anywhere, partly outside the arena too."""
    d = detour()
    rng = np.random.default_rng(0)
    closing = 0
    for _ in range(100):
        others = rng.uniform(-0.1, 1.1, (int(rng.integers(0, 6)), 2))
        k = int(rng.integers(0, 30))
        discs = np.column_stack([rng.uniform(-0.2, 1.2, (k, 2)), rng.uniform(0.0, 0.2, k)])
        want = d.static_free.copy()
        for c in others:
            want &= np.linalg.norm(d.centres - c, axis=1) >= 2 * R + CLEARANCE
        for x, y, radius in discs:
            want &= np.hypot(d.centres[:, 0] - x, d.centres[:, 1] - y) >= R + radius + CLEARANCE
        got = d.static_free.copy()
        for c in others:
            d._block(got, c[0], c[1], 2 * R + CLEARANCE)
        for x, y, radius in discs:
            d._block(got, x, y, R + radius + CLEARANCE)
        np.testing.assert_array_equal(got, want)
        closing += int(want.sum() < d.static_free.sum())
    assert closing >= 80          # the draws do close cells


@pytest.mark.parametrize("case", ["stuck", "jittering", "not movable", "near a target", "moving", "not pushed"])
def test_a_robot_detours_once_held_still_for_after_s_away_from_every_target(case):
    """One robot at (0.15, 0.15), its target at (0.85, 0.15) past a robot in the way; the
    policy pushes it at 0.5 m/s^2 into that robot. Held 20 ticks (1 s) within 2 cm of where it
    was, it detours from the 20th call on: up through the gap; also when it jitters in place at
    6 cm/s (1.5 mm back and forth a tick), which a 2 cm/s speed threshold never held. Not movable,
    within 12 cm of a target, moving on at 2.5 cm/s, or not pushed, it never does."""
    d = detour()
    pos = np.array([[0.15, 0.15], [0.5, 0.15]])
    targets = np.array([[0.85, 0.15], [0.15, 0.6]])
    vel = np.zeros((2, 2))
    a_nom = np.array([[0.5, 0.0], [0.0, 0.0]])
    movable = np.array([True, False])
    ids = ("a", "b")
    if case == "not movable":
        movable[0] = False
    elif case == "near a target":
        targets[1] = [0.2, 0.2]
    elif case == "not pushed":
        a_nom[0] = [0.1, 0.0]
    flags = []
    for k in range(25):
        if case == "moving":                    # 2.5 cm/s: 2.5 cm from where it was in a second
            vel[0] = [0.025, 0.0]
            pos[0, 0] = 0.15 + 0.025 * SC.dynamics.dt * k
        elif case == "jittering":
            vel[0] = [0.06 * (-1) ** k, 0.0]
            pos[0, 0] = 0.15 + 0.0015 * (k % 2)
        out, flag = d(ids, pos.copy(), vel.copy(), targets, a_nom, movable)
        flags.append(bool(flag[0]))
        assert not flag[1:].any()
    if case not in ("stuck", "jittering"):
        assert not any(flags) and np.array_equal(out, a_nom)
        return
    assert flags.index(True) == 19 and all(flags[19:])
    assert out[0, 1] > 0.0 and np.linalg.norm(out[0]) <= SC.dynamics.accel_limit + 1e-12


@pytest.mark.parametrize("speed", [0.0, 0.2])
def test_a_robot_on_the_move_is_left_to_the_filter_not_planned_round(speed):
    """Robot a, held at (0.15, 0.15), bound for (0.85, 0.2); b sits on its target in the way at
    (0.5, 0.15); c stands in the gap above b, at (0.5, 0.27). Standing, c closes the gap: a's path
    goes over the object (1.53 m, up to y = 0.725). Moving at 0.2 m/s, c will be elsewhere: the
    path takes the gap (0.78 m, below y = 0.27; the straight line through the gap is 0.73). Planned round, the second of two robots
    detouring in single file down one corridor found no path."""
    d = detour()
    pos = np.array([[0.15, 0.15], [0.5, 0.15], [0.5, 0.27]])
    vel = np.array([[0.0, 0.0], [0.0, 0.0], [speed, 0.0]])
    targets = np.array([[0.85, 0.2], [0.5, 0.15], [0.5, 0.3]])
    a_nom = np.array([[0.5, 0.0], [0.0, 0.0], [0.0, 0.0]])
    for _ in range(20):
        _, flag = d(("a", "b", "c"), pos, vel, targets, a_nom, np.array([True, False, False]))
    assert flag.tolist() == [True, False, False]
    path = d._paths["a"][0]
    if speed == 0.0:
        assert 1.4 < length(path) < 1.7 and path[:, 1].max() > 0.65 + R + CLEARANCE
    else:
        assert 0.73 <= length(path) < 0.85 and path[:, 1].max() < 0.35 - R
