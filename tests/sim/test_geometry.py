import functools
import math

import numpy as np
import pytest
import torch
from hypothesis import assume, given, settings
from hypothesis import strategies as st

from sim.geometry import Polygon, closest_point_on_polygon, pairwise_distances

BOX = torch.tensor([[0.4, 0.35], [0.6, 0.35], [0.6, 0.65], [0.4, 0.65]], dtype=torch.float64)
L_SHAPE = torch.tensor([[0.2, 0.2], [0.8, 0.2], [0.8, 0.4], [0.4, 0.4], [0.4, 0.8], [0.2, 0.8]],
                       dtype=torch.float64)


def test_box_signed_distance_by_hand():
    pts = torch.tensor([[0.7, 0.5],      # right of the box: 0.1
                        [0.5, 0.5],      # centre: inside, nearest side at 0.1 -> -0.1
                        [0.7, 0.75],     # beyond the corner (0.6, 0.65): hypot(0.1, 0.1)
                        [0.5, 0.36]],    # inside near the bottom: -0.01
                       dtype=torch.float64)
    sd, nearest = closest_point_on_polygon(pts, BOX)
    assert torch.allclose(sd, torch.tensor([0.1, -0.1, math.hypot(0.1, 0.1), -0.01], dtype=torch.float64))
    assert torch.allclose(nearest[2], torch.tensor([0.6, 0.65], dtype=torch.float64))
    assert torch.allclose(nearest[3], torch.tensor([0.5, 0.35], dtype=torch.float64))


def _generic(poly: torch.Tensor) -> Polygon:
    p = Polygon(poly)
    p.convex_ccw = False      # force the crossing-number path
    p.axis_aligned_box = False
    return p


def _convex(poly: torch.Tensor) -> Polygon:
    p = Polygon(poly)
    p.axis_aligned_box = False   # force the half-plane path
    return p


def test_default_box_takes_the_closed_form():
    assert Polygon(BOX).axis_aligned_box
    assert not Polygon(L_SHAPE).axis_aligned_box


@settings(max_examples=300, deadline=None)
@given(st.floats(0, 1), st.floats(0, 1))
def test_box_closed_form_matches_the_general_projection(x, y):
    pts = torch.tensor([[x, y]], dtype=torch.float64)
    box = Polygon(BOX).signed_distance_xy(pts[:, 0], pts[:, 1])
    gen = _convex(BOX).signed_distance_xy(pts[:, 0], pts[:, 1])
    assert torch.allclose(box[0], gen[0], atol=1e-12)
    # the nearest point may differ only where two sides are equally near (inside, on a diagonal)
    nb = torch.stack(box[1:]).squeeze(-1)
    assert torch.allclose(((nb - pts[0]) ** 2).sum().sqrt(), box[0].abs(), atol=1e-12)


@settings(max_examples=200, deadline=None)
@given(st.floats(0, 1), st.floats(0, 1))
def test_convex_fast_path_matches_crossing_number(x, y):
    pts = torch.tensor([[x, y]], dtype=torch.float64)
    fast = _convex(BOX).signed_distance_xy(pts[:, 0], pts[:, 1])
    slow = _generic(BOX).signed_distance_xy(pts[:, 0], pts[:, 1])
    for a, b in zip(fast, slow, strict=True):
        assert torch.allclose(a, b)


def test_non_convex_polygon():
    poly = Polygon(L_SHAPE)
    assert not poly.convex_ccw
    pts = torch.tensor([[0.6, 0.5],   # in the notch: nearest is (0.6, 0.4) on the inner edge
                        [0.3, 0.3],   # inside the L: nearest edge 0.1 away
                        [0.6, 0.3]],  # inside the foot: nearest is y=0.2 or y=0.4, 0.1 away
                       dtype=torch.float64)
    sd, nx, ny = poly.signed_distance_xy(pts[:, 0], pts[:, 1])
    assert torch.allclose(sd, torch.tensor([0.1, -0.1, -0.1], dtype=torch.float64))
    assert torch.allclose(torch.stack((nx[0], ny[0])), torch.tensor([0.6, 0.4], dtype=torch.float64))


@settings(max_examples=100, deadline=None)
@given(st.lists(st.tuples(st.floats(0, 1), st.floats(0, 1)), min_size=2, max_size=6))
def test_pairwise_distances_match_numpy(points):
    pos = torch.tensor(points, dtype=torch.float64)
    ref = np.linalg.norm(np.asarray(points)[:, None] - np.asarray(points)[None], axis=-1)
    assert np.allclose(pairwise_distances(pos).numpy(), ref)


def test_polygon_shape_error():
    import pytest

    with pytest.raises(ValueError, match=r"shape \(M >= 3, 2\)"):
        Polygon(torch.zeros(2, 2))


@functools.cache
def _detour():
    from sim.geometry import DetourDistance

    targets = torch.tensor([[0.33, 0.5], [0.33, 0.8]], dtype=torch.float64)
    return DetourDistance(Polygon(BOX), targets, margin=0.05)


def test_detour_corners_inflate_the_box():
    # box 0.4..0.6 x 0.35..0.65 inflated by 0.05 on every side
    assert torch.allclose(_detour().corners, torch.tensor(
        [[0.35, 0.30], [0.65, 0.30], [0.65, 0.70], [0.35, 0.70]], dtype=torch.float64))


def test_detour_distance_by_hand():
    d = _detour()(torch.tensor([[0.67, 0.5], [0.67, 0.9], [0.2, 0.5]], dtype=torch.float64))
    # (0.67, 0.5) -> (0.33, 0.5) is blocked: over the top via (0.65, 0.7) and (0.35, 0.7):
    # hypot(0.02, 0.2) + 0.3 + hypot(0.02, 0.2)
    assert d[0, 0].item() == pytest.approx(2 * math.hypot(0.02, 0.2) + 0.3)
    # (0.67, 0.5) -> (0.33, 0.8): to the corner (0.65, 0.7), then straight to the target
    assert d[0, 1].item() == pytest.approx(math.hypot(0.02, 0.2) + math.hypot(0.32, 0.1))
    # (0.67, 0.9) sees the upper target straight, but the line to (0.33, 0.5) cuts the inflated
    # box's upper-left corner: via (0.35, 0.7) instead
    assert d[1, 1].item() == pytest.approx(math.hypot(0.34, 0.1))
    assert d[1, 0].item() == pytest.approx(math.hypot(0.32, 0.2) + math.hypot(0.02, 0.2))
    assert d[2, 1].item() == pytest.approx(math.hypot(0.13, 0.3))


@settings(max_examples=100, deadline=None)
@given(st.floats(0.04, 0.96), st.floats(0.04, 0.96))
def test_detour_is_never_shorter_than_straight_and_the_field_matches(x, y):
    exact = _detour()
    p = torch.tensor([[x, y]], dtype=torch.float64)
    # the lookup bound holds outside the inflated object (inside, the lead-in to the nearest
    # boundary point switches sides along the diagonals)
    assume(exact.inflated.signed_distance_xy(p[:, 0], p[:, 1])[0].item() >= 0.005)
    d = exact(p)
    straight = (p.unsqueeze(-2) - exact.targets).norm(dim=-1)
    assert (d >= straight - 1e-12).all()
    assert torch.allclose(_field()(p.unsqueeze(0))[0], d, atol=0.005 / math.sqrt(2) + 1e-9)


@functools.cache
def _field():
    from sim.geometry import DetourField

    return DetourField(_detour(), (1.0, 1.0), resolution=0.005)


@settings(max_examples=30, deadline=None)
@given(st.integers(1, 8), st.integers(0, 2**31 - 1))
def test_the_fields_numpy_lookup_reads_the_same_nodes(n, seed):
    """:meth:`DetourField.lookup_np` (the control tick's) against the torch lookup, points off
    the arena included (clamped to its edge nodes) and points half a node apart (rounding)."""
    rng = np.random.default_rng(seed)
    pos = np.concatenate((rng.uniform(-0.1, 1.1, (n, 2)), (rng.integers(0, 200, (n, 2)) + 0.5) * 0.005))
    want = _field()(torch.from_numpy(pos)[None])[0].numpy()
    assert np.array_equal(_field().lookup_np(pos), want)


def test_detour_falls_back_to_straight_for_non_convex_objects():
    from sim.geometry import DetourDistance

    targets = torch.tensor([[0.1, 0.9]], dtype=torch.float64)
    dd = DetourDistance(Polygon(L_SHAPE), targets, 0.05)
    p = torch.tensor([[0.9, 0.1]], dtype=torch.float64)
    assert dd(p)[0, 0].item() == pytest.approx(math.hypot(0.8, 0.8))
