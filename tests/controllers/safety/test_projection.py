"""controllers/safety/projection.py: the filter's QP in closed form when its broken rows share no
robot, held to hand-worked cases and to an exact active-set solver (DAQP) on random problems."""

from __future__ import annotations

import math

import numpy as np
import pytest
import qpsolvers
from hypothesis import given, settings
from hypothesis import strategies as st

from controllers.safety.barrier import BarrierTerms
from controllers.safety.projection import (
    inside_octagon,
    project_octagon,
    projected_optimum,
    separable_answer,
)

WALLS = np.array([[1.0, 0.0], [-1.0, 0.0], [0.0, 1.0], [0.0, -1.0]])


def row_robots(n: int) -> tuple[np.ndarray, np.ndarray]:
    """The robots of every row of N robots and a convex object (:meth:`BarrierTerms.row_robots`)."""
    pi, pj = np.triu_indices(n, 1)
    k = len(pi) + 5 * n
    terms = BarrierTerms(pair_i=pi, pair_j=pj, pair_normal=np.zeros((len(pi), 2)), object_normal=np.zeros((n, 2)),
                         wall_normal=WALLS, h=np.zeros(k), drift=np.zeros(k), bound=np.zeros(k))
    return terms.row_robots()


def test_one_pair_row_moves_both_robots_apart_by_half_the_deficit_each():
    normals = np.zeros((1 + 5 * 2, 2))
    normals[0] = (1.0, 0.0)                                    # n . (u_0 - u_1) >= 0.2
    lower = np.full(len(normals), -np.inf)
    lower[0] = 0.2
    a = np.zeros((2, 2))
    values = np.zeros(len(normals))
    u = separable_answer(normals, *row_robots(2), values, lower, a, a_box=1.0)
    assert u == pytest.approx(np.array([[0.1, 0.0], [-0.1, 0.0]]), abs=1e-11)


def test_rows_that_share_a_robot_are_left_to_the_solver():
    normals = np.zeros((3 + 5 * 3, 2))
    normals[:2] = (1.0, 0.0)                                   # pairs (0, 1) and (0, 2) both broken
    lower = np.full(len(normals), -np.inf)
    lower[:2] = 0.2
    assert separable_answer(normals, *row_robots(3), np.zeros(len(normals)), lower, np.zeros((3, 2)), 1.0) is None


def test_octagon_projection_by_hand():
    """c = 1: the edges are |x|, |y| <= 1 and |x +- y| <= sqrt(2) (vertices at (1, sqrt(2) - 1), ...)."""
    points = np.array([[2.0, 0.0], [1.0, 1.0], [0.3, -0.2], [0.0, -5.0], [-1.5, 1.5]])
    h = math.sqrt(2.0) / 2                                     # the foot on x + y = sqrt(2) from (1, 1)
    want = np.array([[1.0, 0.0], [h, h], [0.3, -0.2], [0.0, -1.0], [-h, h]])
    got = project_octagon(points, 1.0)
    assert got == pytest.approx(want, abs=1e-12)
    assert inside_octagon(got, 1.0).all()
    assert inside_octagon(points, 1.0).tolist() == [False, False, True, False, False]


def exact_qp(terms: BarrierTerms, a: np.ndarray, lower: np.ndarray, a_box: float) -> np.ndarray:
    """The filter's QP on DAQP (exact active set): min |u - a|^2 over the rows and octagons."""
    n = len(a)
    rows = terms.dense(n)
    keep = np.isfinite(lower)
    octagon = np.zeros((8 * n, 2 * n))
    limits = np.zeros(8 * n)
    for i in range(n):
        for k, (cx, cy, lim) in enumerate([(1, 0, a_box), (-1, 0, a_box), (0, 1, a_box), (0, -1, a_box),
                                           (1, 1, math.sqrt(2) * a_box), (-1, -1, math.sqrt(2) * a_box),
                                           (1, -1, math.sqrt(2) * a_box), (-1, 1, math.sqrt(2) * a_box)]):
            octagon[8 * i + k, 2 * i], octagon[8 * i + k, 2 * i + 1], limits[8 * i + k] = cx, cy, lim
    g = np.vstack([-rows[keep], octagon])
    h = np.concatenate([-lower[keep], limits])
    u = qpsolvers.solve_qp(2 * np.eye(2 * n), -2 * a.ravel(), g, h, solver="daqp")
    assert u is not None
    return u.reshape(n, 2)


def make_problem(rng: np.random.Generator, n: int, broken: int, met: int):
    """Random rows (unit normals) for N robots, a nominal in [-1, 1]^2 (often outside the
    octagon), ``broken`` rows it breaks and ``met`` rows it meets, some tightly."""
    pair_i, pair_j = np.triu_indices(n, 1)
    angle = rng.uniform(0, 2 * np.pi, len(pair_i) + n)
    normals = np.stack([np.cos(angle), np.sin(angle)], 1)
    zeros = np.zeros(len(pair_i) + 5 * n)
    terms = BarrierTerms(pair_i, pair_j, normals[:len(pair_i)], normals[len(pair_i):], WALLS, zeros, zeros, zeros)
    a = rng.uniform(-1.0, 1.0, (n, 2))
    values = terms.rows_times(a)
    lower = np.full(len(values), -np.inf)
    rows = rng.choice(len(values), size=broken + met, replace=False)
    lower[rows[:broken]] = values[rows[:broken]] + rng.uniform(0.0, 0.8, broken)
    lower[rows[broken:]] = values[rows[broken:]] - rng.uniform(0.0, 0.5, met)
    return terms, a, lower


A_BOX = 0.95


def accepted(terms: BarrierTerms, a: np.ndarray, lower: np.ndarray) -> np.ndarray | None:
    """The projection when it passes the filter's acceptance test (every row, every octagon)."""
    return projected_optimum(terms, terms.rows_times(a), lower, a, A_BOX)


@settings(max_examples=300, deadline=None)
@given(st.integers(2, 5), st.integers(0, 3), st.integers(0, 4), st.integers(0, 2**32 - 1))
def test_an_accepted_projection_is_the_qps_optimum(n, broken, met, seed):
    """Whenever the answer passes the filter's acceptance test it equals the exact solver's
    optimum (a wrong step, or rows sharing a robot moved independently, fail here)."""
    terms, a, lower = make_problem(np.random.default_rng(seed), n, broken, met)
    u = accepted(terms, a, lower)
    if u is not None:
        assert np.abs(u - exact_qp(terms, a, lower, A_BOX)).max() <= 1e-6


def test_the_acceptance_test_lets_through_a_good_share_with_robots_pulled_into_the_octagon():
    """The property above is not vacuous: over a seeded sweep, answers are accepted with broken
    rows moved and with free robots pulled into their octagon, each equal to the optimum."""
    rng = np.random.default_rng(11)
    moved = octagon = 0
    for _ in range(400):
        n = int(rng.integers(2, 6))
        terms, a, lower = make_problem(rng, n, int(rng.integers(1, 3)), int(rng.integers(0, 4)))
        u = accepted(terms, a, lower)
        if u is None:
            continue
        assert np.abs(u - exact_qp(terms, a, lower, A_BOX)).max() <= 1e-6
        moved += 1
        octagon += int((~inside_octagon(a, A_BOX) & inside_octagon(u, A_BOX)).any())
    assert moved >= 40 and octagon >= 10, (moved, octagon)
