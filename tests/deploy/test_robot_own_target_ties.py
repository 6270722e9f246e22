"""The robot runtime's own target on ties: each robot of a team works its target out alone
(``RobotPolicy.act``), and the team must still hold the assignment training gives it
(:func:`sim.observations.own_assignment`, ties included), so no two robots take one target."""

from __future__ import annotations

import numpy as np
import pytest
import torch
from hypothesis import given, settings
from hypothesis import strategies as st

from deploy.robot import RobotPolicy, detour_distances, least_squares_assignment
from sim.observations import own_assignment
from sim.scenario import make_scenario

SCENARIO = make_scenario("paper-5")
MARGIN = 0.08                                  # [m] a policy file's own_target_margin
OFF_PATH = np.array([[0.10, 0.90], [0.15, 0.90], [0.15, 0.95], [0.10, 0.95]])   # in no robot's way


def _network(x, mask):
    """Stands in for the network (the npz kernel's call): (0, 0), valid."""
    return np.zeros((len(x), 2), dtype=np.float32), np.ones(len(x), dtype=bool)


def _policy() -> tuple[RobotPolicy, list]:
    """An own-target RobotPolicy with no file (only ``act``'s own path runs) and the list each
    target it works out is appended to."""
    policy = RobotPolicy.__new__(RobotPolicy)
    policy.path, policy.session = "no file", _network
    policy.own_target, policy.own_target_margin = True, MARGIN
    policy.robot_counts, policy._counts_text = frozenset(), ""
    found: list = []

    def own_target(*args):
        found.append(RobotPolicy._own_target(policy, *args))
        return found[-1]

    policy._own_target = own_target
    return policy, found


def marked_by_each_robot(pos: np.ndarray, targets: np.ndarray, polygon: np.ndarray) -> list[int]:
    """The target each robot marks when it acts alone, seeing the others in fleet order."""
    policy, found = _policy()
    for i in range(len(pos)):
        others = [j for j in range(len(pos)) if j != i]
        policy.act(pos[i], np.zeros(2), targets, pos[others], np.zeros((len(others), 2)), polygon,
                   SCENARIO.arena, index=i)
    return found


def training_rule(pos: np.ndarray, targets: np.ndarray, polygon: np.ndarray) -> list[int]:
    path = detour_distances(pos, targets, polygon, MARGIN)
    return own_assignment(torch.from_numpy(path)[None])[0].tolist()


TIES = {
    "two robots mirrored, targets on the mirror line":
        ([[0.25, 0.25], [0.25, 0.75]], [[0.75, 0.5], [0.875, 0.5]]),
    "two of three mirrored":
        ([[0.25, 0.25], [0.25, 0.75], [0.9, 0.1]], [[0.75, 0.5], [0.875, 0.5], [0.9, 0.2]]),
    "four on a square, targets on its centre lines":
        ([[0.25, 0.25], [0.25, 0.75], [0.75, 0.25], [0.75, 0.75]],
         [[0.5, 0.375], [0.5, 0.625], [0.375, 0.5], [0.625, 0.5]]),
    "six robots on one spot":
        ([[0.5, 0.5]] * 6, [[0.2 + 0.1 * k, 0.25] for k in range(6)]),
    "six robots, six targets on one spot":
        ([[0.2 + 0.1 * k, 0.25] for k in range(6)], [[0.5, 0.6]] * 6),
}


@pytest.mark.parametrize("name", list(TIES))
def test_tied_robots_take_the_targets_training_gives_them(name):
    """Before: each robot put itself first, and the Hungarian method broke ties its own way;
    the two mirrored robots both marked target 0 (and the six on one spot all did)."""
    pos, targets = (np.array(a, dtype=np.float64) for a in TIES[name])
    marked = marked_by_each_robot(pos, targets, OFF_PATH)
    assert marked == training_rule(pos, targets, OFF_PATH)
    assert sorted(marked) == list(range(len(pos)))


# paths from a handful of values (and whole rows or columns alike): ties everywhere
_values = st.sampled_from([0.0, 0.1, 0.2, 0.3, 0.25, 0.5, 0.7, 1.0, 1.5])


@st.composite
def tied_paths(draw) -> np.ndarray:
    n = draw(st.one_of(st.integers(1, 8), st.just(21)))
    path = np.array(draw(st.lists(st.lists(_values, min_size=n, max_size=n), min_size=n, max_size=n)))
    if draw(st.booleans()):
        path[:, draw(st.integers(0, n - 1))] = path[:, 0]
    if draw(st.booleans()):
        path[draw(st.integers(0, n - 1))] = path[0]
    return path


@settings(max_examples=400, deadline=None)
@given(tied_paths())
def test_the_assignment_breaks_ties_as_training_does(path):
    want = own_assignment(torch.from_numpy(path)[None])[0].numpy()
    assert np.array_equal(least_squares_assignment(path), want)


@settings(max_examples=300, deadline=None)
@given(st.integers(1, 21), st.integers(0, 2**31 - 1))
def test_the_assignment_is_trainings_on_random_paths(n, seed):
    path = np.random.default_rng(seed).uniform(0.0, 1.0, (n, n))
    assert np.array_equal(least_squares_assignment(path), own_assignment(torch.from_numpy(path)[None])[0].numpy())


_spot = st.sampled_from([0.125, 0.25, 0.375, 0.5, 0.625, 0.75, 0.875])
_points = st.tuples(_spot, _spot)


@settings(max_examples=150, deadline=None)
@given(st.integers(1, 7).flatmap(lambda n: st.tuples(st.lists(_points, min_size=n, max_size=n),
                                                      st.lists(_points, min_size=n, max_size=n))),
       st.booleans())
def test_every_robot_alone_marks_the_teams_assignment(team, round_the_object):
    """Robots and targets on a coarse lattice (coinciding, mirrored: tied costs), round
    paper-5's object or with it out of the way: what each robot marks alone is the training
    rule's assignment of the whole team, a permutation."""
    pos, targets = (np.array(a, dtype=np.float64) for a in team)
    polygon = np.asarray(SCENARIO.polygon) if round_the_object else OFF_PATH
    marked = marked_by_each_robot(pos, targets, polygon)
    assert marked == training_rule(pos, targets, polygon)
    assert sorted(marked) == list(range(len(pos)))


def test_an_index_outside_the_team_is_refused():
    with pytest.raises(ValueError, match="place among the 2 robots"):
        _policy()[0].act([0.2, 0.2], [0, 0], [[0.5, 0.5], [0.6, 0.6]], [[0.3, 0.3]], [[0, 0]], OFF_PATH,
                      SCENARIO.arena, index=2)
