import itertools
import math

import numpy as np
import pytest
import torch
from hypothesis import given, settings
from hypothesis import strategies as st

from sim.geometry import Polygon
from sim.metrics import (
    collision_events,
    distance_matrix,
    episode_outcome,
    optimal_assignment,
    swept_contacts,
)
from sim.scenario import make_scenario

SC = make_scenario("paper-3")
POLY = torch.as_tensor(SC.polygon)


def _events(points):
    return collision_events(torch.tensor([points], dtype=torch.float64), POLY, 0.04, (1.0, 1.0))


def test_robot_robot_contact_at_two_radii():
    ev = _events([[0.2, 0.2], [0.279, 0.2], [0.8, 0.8]])     # 0.079 < 0.08: touching
    assert ev.robot[0].tolist() == [True, True, False]
    ev = _events([[0.2, 0.2], [0.281, 0.2], [0.8, 0.8]])     # 0.081: clear
    assert not ev.robot.any()


def test_robot_object_contact():
    # box right edge is x = 0.6: a centre at 0.639 overlaps by 1 mm, at 0.641 is clear
    assert _events([[0.639, 0.5], [0.2, 0.2], [0.2, 0.8]]).object[0].tolist() == [True, False, False]
    assert not _events([[0.641, 0.5], [0.2, 0.2], [0.2, 0.8]]).object.any()


def test_robot_wall_contact():
    ev = _events([[0.039, 0.5], [0.5, 0.961], [0.2, 0.2]])
    assert ev.wall[0].tolist() == [True, True, False]
    assert ev.any[0].tolist() == [True, True, False]


def test_assignment_picks_the_optimum_not_the_greedy_choice():
    # Greedy (robot 0 takes its nearest target 0) costs 1 + 10 = 11; the optimum is 2 + 2 = 4.
    cost = torch.tensor([[[1.0, 2.0], [2.0, 10.0]]])
    assert optimal_assignment(cost).tolist() == [[1, 0]]


@settings(max_examples=60, deadline=None)
@given(st.integers(1, 6), st.integers(0, 2**31 - 1), st.sampled_from(["auto", "enumerate", "scipy"]))
def test_every_solver_matches_brute_force_and_scipy(n, seed, method):
    from scipy.optimize import linear_sum_assignment

    cost = torch.rand(3, n, n, generator=torch.Generator().manual_seed(seed), dtype=torch.float64)
    got = optimal_assignment(cost, method)
    for b in range(3):
        assert sorted(got[b].tolist()) == list(range(n))
        best = min(itertools.permutations(range(n)), key=lambda p: sum(cost[b, i, p[i]] for i in range(n)))
        got_cost = cost[b, torch.arange(n), got[b]].sum()
        assert got_cost == pytest.approx(sum(cost[b, i, best[i]] for i in range(n)))
        r, c = linear_sum_assignment(cost[b].numpy())
        assert got_cost == pytest.approx(cost[b].numpy()[r, c].sum())


def test_large_n_uses_scipy_and_is_a_permutation():
    cost = torch.rand(2, 12, 12, generator=torch.Generator().manual_seed(1))
    got = optimal_assignment(cost)
    assert sorted(got[0].tolist()) == list(range(12))


def test_assignment_shape_error():
    with pytest.raises(ValueError, match=r"shape \(B, N, N\)"):
        optimal_assignment(torch.zeros(2, 3))
    with pytest.raises(ValueError, match="method"):
        optimal_assignment(torch.zeros(1, 2, 2), "greedy")


def test_success_and_final_distance_by_hand():
    targets = torch.tensor([[[0.3, 0.4], [0.3, 0.6]]])
    # robot 0 sits 0.04 right of target 1, robot 1 sits 0.03 below target 0: swapped assignment
    pos = torch.tensor([[[0.34, 0.6], [0.3, 0.37]]])
    out = episode_outcome(pos, targets, torch.tensor([False]), 0.05)
    assert out.assignment.tolist() == [[1, 0]]
    assert out.final_distance.item() == pytest.approx(0.035)
    assert out.max_distance.item() == pytest.approx(0.04)
    assert out.success.tolist() == [True]
    # the same positions after a collision during the episode: failure
    assert episode_outcome(pos, targets, torch.tensor([True]), 0.05).success.tolist() == [False]
    # one robot 0.051 away: failure
    far = torch.tensor([[[0.351, 0.6], [0.3, 0.37]]])
    assert episode_outcome(far, targets, torch.tensor([False]), 0.05).success.tolist() == [False]


def test_distance_matrix_orientation():
    pos = torch.tensor([[[0.0, 0.0], [1.0, 0.0]]])
    tgt = torch.tensor([[[0.0, 1.0], [3.0, 0.0]]])
    assert np.allclose(distance_matrix(pos, tgt)[0].numpy(), [[1.0, 3.0], [np.sqrt(2), 2.0]])


def _dense_min_d2(p0: np.ndarray, d: np.ndarray) -> float:
    s = np.linspace(0.0, 1.0, 4001)[:, None]
    q = p0 + s * d
    return float((q * q).sum(-1).min())


@settings(max_examples=300, deadline=None)
@given(st.lists(st.floats(-0.1, 0.1), min_size=4, max_size=4),
       st.lists(st.floats(-0.03, 0.03), min_size=4, max_size=4))
def test_swept_robot_contacts_are_those_of_the_densely_sampled_path(start, move):
    r = 0.04
    start = np.array(start).reshape(2, 2) + [[0.3, 0.5], [0.4, 0.5]]
    end = start + np.array(move).reshape(2, 2)
    dense = math.sqrt(_dense_min_d2(start[0] - start[1], (end - start)[0] - (end - start)[1]))
    if abs(dense - 2 * r) < 1e-4:        # the sampling's resolution
        return
    as_t = lambda a: torch.tensor(a[None])  # noqa: E731
    robot, _ = swept_contacts(as_t(start), as_t(end), r, torch.tensor([[0.0, 0.0], [0.01, 0.0], [0.0, 0.01]]))
    assert robot[0].tolist() == [dense < 2 * r] * 2


@settings(max_examples=300, deadline=None)
@given(st.floats(0.30, 0.70), st.floats(0.25, 0.75), st.floats(0, 2 * math.pi), st.floats(0.0, 0.0195))
def test_swept_object_contacts_are_those_of_the_densely_sampled_path(x, y, heading, length):
    # any step no longer than the speed limit allows, against the paper's box (0.4..0.6, 0.35..0.65)
    r, sc = 0.04, make_scenario("paper-3")
    poly = torch.tensor(sc.polygon)
    start = np.array([x, y])
    end = start + length * np.array([math.cos(heading), math.sin(heading)])
    path = torch.tensor(start + np.linspace(0, 1, 2001)[:, None] * (end - start))
    sd = Polygon(poly).signed_distance_xy(path[:, 0], path[:, 1])[0]
    if (sd - r).abs().min().item() < 2e-5:     # the sampling's resolution
        return
    ends = torch.tensor(np.stack([start, end])[None])
    at_ends = bool(collision_events(ends, poly, r, sc.arena, eps=0.0).object.any())
    _, obj = swept_contacts(ends[:, :1], ends[:, 1:], r, poly, eps=0.0)
    assert (bool(obj[0, 0]) or at_ends) == bool((sd < r).any())
