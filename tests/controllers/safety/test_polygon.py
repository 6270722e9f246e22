"""controllers/safety/polygon.py: the object as convex pieces, by hand and on random simple polygons."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from controllers.safety.geometry import point_polygon
from controllers.safety.polygon import convex_pieces, is_convex_ccw

L_SHAPE = np.array([[0.35, 0.35], [0.65, 0.35], [0.65, 0.45], [0.45, 0.45], [0.45, 0.65], [0.35, 0.65]])
U_SHAPE = np.array([[0.34, 0.35], [0.66, 0.35], [0.66, 0.65], [0.56, 0.65], [0.56, 0.45], [0.44, 0.45],
                    [0.44, 0.65], [0.34, 0.65]])


def area(poly: np.ndarray) -> float:
    x, y = poly[:, 0], poly[:, 1]
    return 0.5 * float(np.sum(x * np.roll(y, -1) - np.roll(x, -1) * y))


def test_a_convex_polygon_is_its_own_piece():
    box = np.array([[0.4, 0.35], [0.6, 0.35], [0.6, 0.65], [0.4, 0.65]])
    pieces = convex_pieces(box)
    assert len(pieces) == 1 and np.array_equal(pieces[0], box)


def test_a_straight_through_vertex_is_dropped_and_the_box_stays_one_piece():
    box = np.array([[0.0, 0.0], [0.5, 0.0], [1.0, 0.0], [1.0, 1.0], [0.0, 1.0]])   # (0.5, 0) is on an edge
    assert not is_convex_ccw(box)
    (piece,) = convex_pieces(box)
    assert sorted(map(tuple, piece)) == [(0.0, 0.0), (0.0, 1.0), (1.0, 0.0), (1.0, 1.0)]


@pytest.mark.parametrize(("shape", "count"), [(L_SHAPE, 2), (U_SHAPE, 3)])
def test_an_l_splits_in_two_and_a_u_in_three(shape, count):
    pieces = convex_pieces(shape)
    assert len(pieces) == count
    assert all(is_convex_ccw(p) for p in pieces)
    assert sum(area(p) for p in pieces) == pytest.approx(area(shape), abs=1e-12)


def star_polygon(radii: list[float], jitter: list[float]) -> np.ndarray:
    """A simple counter-clockwise polygon: vertices at increasing angles about (0.5, 0.5)."""
    k = len(radii)
    angles = 2 * np.pi * (np.arange(k) + 0.8 * np.asarray(jitter)) / k
    return 0.5 + np.asarray(radii)[:, None] * np.stack([np.cos(angles), np.sin(angles)], 1)


@settings(max_examples=150, deadline=None)
@given(data=st.data(), k=st.integers(3, 12))
def test_pieces_are_convex_and_tile_the_polygon(data, k):
    """Every piece strictly convex and counter-clockwise; the pieces' areas sum to the polygon's;
    every point inside a piece is inside the polygon and every point of the polygon is in a piece
    (so the least distance over the pieces is the distance to the polygon outside it)."""
    radii = data.draw(st.lists(st.floats(0.05, 0.4), min_size=k, max_size=k))
    jitter = data.draw(st.lists(st.floats(0.0, 1.0), min_size=k, max_size=k))
    poly = star_polygon(radii, jitter)
    pieces = convex_pieces(poly)
    assert all(is_convex_ccw(p) for p in pieces)
    assert sum(area(p) for p in pieces) == pytest.approx(area(poly), rel=1e-9, abs=1e-12)
    assert len(pieces) <= k - 2
    points = np.random.default_rng(k).uniform(0.0, 1.0, (200, 2))
    whole, _, _ = point_polygon(points, poly)
    per_piece = np.stack([point_polygon(points, p)[0] for p in pieces], 1)
    outside = whole > 1e-9
    np.testing.assert_allclose(per_piece.min(1)[outside], whole[outside], atol=1e-12)
    np.testing.assert_array_equal(per_piece.min(1) < -1e-9, whole < -1e-9)
