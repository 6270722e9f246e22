"""Batched planar geometry in torch (and numpy wrappers): discs, simple polygons, walls.

All functions broadcast over leading batch dimensions. Distances are in metres.
"""

from __future__ import annotations

import numpy as np
import torch


def closest_point_on_polygon(points: torch.Tensor, poly: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """Signed distance and closest boundary point of points to a simple polygon.

    Args:
        points: (..., 2) query points.
        poly: (M, 2) polygon vertices (any orientation, simple, not self-intersecting).

    Returns:
        signed: (...,) distance to the boundary, negative inside the polygon.
        closest: (..., 2) the nearest point on the boundary.
    """
    a = poly                                     # (M, 2)
    b = torch.roll(poly, -1, dims=0)             # (M, 2)
    ab = b - a
    ap = points.unsqueeze(-2) - a                # (..., M, 2)
    t = ((ap * ab).sum(-1) / (ab * ab).sum(-1)).clamp(0.0, 1.0)
    proj = a + t.unsqueeze(-1) * ab              # (..., M, 2)
    d2 = ((points.unsqueeze(-2) - proj) ** 2).sum(-1)
    d2min, idx = d2.min(-1)
    closest = torch.gather(proj, -2, idx[..., None, None].expand(*idx.shape, 1, 2)).squeeze(-2)
    # Crossing-number point-in-polygon test, vectorised over edges.
    py = points[..., 1:2]
    px = points[..., 0:1]
    ay, by = a[:, 1], b[:, 1]
    straddles = (ay > py) != (by > py)
    x_cross = a[:, 0] + (py - ay) * (b[:, 0] - a[:, 0]) / torch.where(by == ay, torch.ones_like(by), by - ay)
    inside = ((straddles & (px < x_cross)).sum(-1) % 2) == 1
    dist = d2min.sqrt()
    return torch.where(inside, -dist, dist), closest


def point_polygon_signed_distance_np(points: np.ndarray, poly: np.ndarray) -> np.ndarray:
    """numpy wrapper of :func:`closest_point_on_polygon`: (K, 2), (M, 2) -> (K,) signed distances."""
    sd, _ = closest_point_on_polygon(torch.as_tensor(points, dtype=torch.float64),
                                     torch.as_tensor(poly, dtype=torch.float64))
    return sd.numpy()


def pairwise_distances(pos: torch.Tensor) -> torch.Tensor:
    """(..., N, 2) positions -> (..., N, N) centre distances (diagonal is 0)."""
    diff = pos.unsqueeze(-2) - pos.unsqueeze(-3)
    return (diff * diff).sum(-1).clamp_min(0).sqrt()


def wall_clearance(pos: torch.Tensor, arena: tuple[float, float]) -> torch.Tensor:
    """(..., N, 2) centres -> (..., N, 4) distances from the centre to the walls x=0, x=W, y=0, y=H."""
    w, h = arena
    return torch.stack((pos[..., 0], w - pos[..., 0], pos[..., 1], h - pos[..., 1]), dim=-1)
