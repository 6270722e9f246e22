"""Batched planar geometry in torch (and numpy wrappers): discs, simple polygons, walls.

All functions broadcast over leading batch dimensions. Distances are in metres. The hot
paths work on x and y as separate planes: on the CPU that is several times faster than
broadcasting over a trailing dimension of size 2.
"""

from __future__ import annotations

from functools import cache

import numpy as np
import torch


class Polygon:
    """A simple polygon (M, 2) with precomputed edges, for batched signed distances.

    The signed distance is negative inside. Convex counter-clockwise polygons use the
    half-plane test (inside iff left of every edge); others the crossing-number test.
    """

    def __init__(self, vertices: torch.Tensor):
        if vertices.dim() != 2 or vertices.shape[-1] != 2 or vertices.shape[0] < 3:
            raise ValueError(f"polygon vertices must have shape (M >= 3, 2), got {tuple(vertices.shape)}")
        self.vertices = vertices
        a = vertices
        b = torch.roll(vertices, -1, dims=0)
        self.ax, self.ay = a[:, 0], a[:, 1]
        self.bx, self.by = b[:, 0], b[:, 1]
        self.ex, self.ey = self.bx - self.ax, self.by - self.ay
        self.inv_len2 = 1.0 / (self.ex * self.ex + self.ey * self.ey)
        cross_next = self.ex * torch.roll(self.ey, -1) - self.ey * torch.roll(self.ex, -1)
        self.convex_ccw = bool((cross_next > 0).all())
        lo, hi = vertices.min(0).values, vertices.max(0).values
        on_box = ((vertices == lo) | (vertices == hi)).all(-1)
        self.axis_aligned_box = len(vertices) == 4 and self.convex_ccw and bool(on_box.all())
        self.box_center, self.box_half = (lo + hi) / 2, (hi - lo) / 2

    def signed_distance_xy(self, px: torch.Tensor, py: torch.Tensor):
        """Signed distance and nearest boundary point of points given as x and y planes (...,).

        Returns ``(signed (...,), nearest_x (...,), nearest_y (...,))``.
        """
        if self.axis_aligned_box:
            return self._box_distance_xy(px, py)
        rx = px.unsqueeze(-1) - self.ax            # (..., M)
        ry = py.unsqueeze(-1) - self.ay
        t = ((rx * self.ex + ry * self.ey) * self.inv_len2).clamp_(0.0, 1.0)
        dx = rx - t * self.ex
        dy = ry - t * self.ey
        d2 = dx * dx + dy * dy
        d2min, idx = d2.min(-1)
        if self.convex_ccw:
            inside = ((self.ex * ry - self.ey * rx) > 0).all(-1)
        else:
            straddles = (self.ay > py.unsqueeze(-1)) != (self.by > py.unsqueeze(-1))
            safe_ey = torch.where(self.ey == 0, torch.ones_like(self.ey), self.ey)
            x_cross = self.ax + (py.unsqueeze(-1) - self.ay) * self.ex / safe_ey
            inside = ((straddles & (px.unsqueeze(-1) < x_cross)).sum(-1) % 2) == 1
        ti = torch.gather(t, -1, idx.unsqueeze(-1)).squeeze(-1)
        nx = self.ax[idx] + ti * self.ex[idx]
        ny = self.ay[idx] + ti * self.ey[idx]
        dist = d2min.sqrt()
        return torch.where(inside, -dist, dist), nx, ny


    def _box_distance_xy(self, px: torch.Tensor, py: torch.Tensor):
        """Closed form for an axis-aligned box: with ``q = |p - c| - h`` (per axis),
        ``sd = |max(q, 0)| + min(max(q_x, q_y), 0)``; the nearest point is ``p`` clamped to the box
        outside, and ``p`` moved onto the nearer side inside."""
        cx, cy = self.box_center[0], self.box_center[1]
        hx, hy = self.box_half[0], self.box_half[1]
        rx, ry = px - cx, py - cy
        qx, qy = rx.abs() - hx, ry.abs() - hy
        ox, oy = qx.clamp_min(0), qy.clamp_min(0)
        inner = torch.maximum(qx, qy).clamp_max(0)
        sd = (ox * ox + oy * oy).sqrt() + inner
        nx = rx.clamp(-hx, hx)
        ny = ry.clamp(-hy, hy)
        inside = inner < 0
        snap_x = inside & (qx >= qy)
        snap_y = inside & (qx < qy)
        nx = torch.where(snap_x, torch.copysign(hx.expand_as(rx), rx), nx)
        ny = torch.where(snap_y, torch.copysign(hy.expand_as(ry), ry), ny)
        return sd, nx + cx, ny + cy


def closest_point_on_polygon(points: torch.Tensor, poly: torch.Tensor | Polygon):
    """Signed distance and closest boundary point of points to a simple polygon.

    Args:
        points: (..., 2) query points.
        poly: (M, 2) polygon vertices (simple, not self-intersecting) or a :class:`Polygon`.

    Returns:
        signed: (...,) distance to the boundary, negative inside the polygon.
        closest: (..., 2) the nearest point on the boundary.
    """
    if not isinstance(poly, Polygon):
        poly = Polygon(poly.to(points))
    sd, nx, ny = poly.signed_distance_xy(points[..., 0], points[..., 1])
    return sd, torch.stack((nx, ny), -1)


def point_polygon_signed_distance_np(points: np.ndarray, poly: np.ndarray) -> np.ndarray:
    """numpy wrapper of :func:`closest_point_on_polygon`: (K, 2), (M, 2) -> (K,) signed distances."""
    sd, _ = closest_point_on_polygon(torch.as_tensor(points, dtype=torch.float64),
                                     torch.as_tensor(poly, dtype=torch.float64))
    return sd.numpy()


def pairwise_distances(pos: torch.Tensor) -> torch.Tensor:
    """(..., N, 2) positions -> (..., N, N) centre distances (diagonal is 0)."""
    dx = pos[..., None, :, 0] - pos[..., :, None, 0]
    dy = pos[..., None, :, 1] - pos[..., :, None, 1]
    return (dx * dx + dy * dy).sqrt()


def wall_clearance(pos: torch.Tensor, arena: tuple[float, float]) -> torch.Tensor:
    """(..., N, 2) centres -> (..., N, 4) distances from the centre to the walls x=0, x=W, y=0, y=H."""
    w, h = arena
    return torch.stack((pos[..., 0], w - pos[..., 0], pos[..., 1], h - pos[..., 1]), dim=-1)


class Frame:
    """The geometry of one instant, computed once and shared by collisions, reward and tokens.

    Attributes (E environments, N robots; ``[e, i, ...]`` is seen from robot i):
        pos: (E, N, 2) robot centres [m]; px, py: its (E, N) planes.
        state: (E, N, 4) ``[p, v]`` per robot.
        others: (E, N, N-1, 4) ``[q_j - p_i, u_j - v_i]`` for the other robots j != i, ascending j.
        others_d2: (E, N, N-1) squared centre distance to each other robot [m^2].
        target_tokens: (E, N, N, 4) ``[g_k - p_i, 0, 0]`` for target k; d_rg: (E, N, N) ``|g_k - p_i|``.
        obj_sd: (E, N) signed distance of the centre to the object [m] (negative inside).
        obj_nx, obj_ny: (E, N) the object's nearest boundary point [m].
    """

    def __init__(self, pos: torch.Tensor, vel: torch.Tensor, targets: torch.Tensor, polygon: Polygon):
        # Differences are taken between two index_select gathers of the same shape: on the CPU
        # that is ~2x faster than broadcasting over the small robot dimensions.
        e, n, _ = pos.shape
        self.pos = pos
        self.px, self.py = pos[..., 0], pos[..., 1]
        self.state = torch.cat((pos, vel), -1)
        if n > 1:
            idx, rep = others_flat_index(n, pos.device)
            self.others = (self.state.index_select(1, idx) - self.state.index_select(1, rep)).view(e, n, n - 1, 4)
        else:
            self.others = self.state.new_zeros(e, n, 0, 4)
        ox, oy = self.others[..., 0], self.others[..., 1]
        self.others_d2 = ox * ox + oy * oy
        tile, row = target_flat_index(n, pos.device)
        pos4 = torch.nn.functional.pad(pos, (0, 2))
        if targets.dim() == 3 and targets.stride(0) == 0:      # one target set for every env
            tgt4 = torch.nn.functional.pad(targets[0], (0, 2)).index_select(0, tile)
        else:
            tgt4 = torch.nn.functional.pad(targets, (0, 2)).index_select(1, tile)
        self.target_tokens = (tgt4 - pos4.index_select(1, row)).view(e, n, n, 4)   # [g_k - p_i, 0, 0]
        gx, gy = self.target_tokens[..., 0], self.target_tokens[..., 1]
        self.d_rg = (gx * gx + gy * gy).sqrt()
        self.obj_sd, self.obj_nx, self.obj_ny = polygon.signed_distance_xy(self.px, self.py)


def others_index(n: int, device: torch.device | str = "cpu") -> torch.Tensor:
    """(N, N-1) indices of the other robots for each robot, ascending."""
    idx = torch.arange(n, device=device)
    keep = ~torch.eye(n, dtype=torch.bool, device=device)
    return idx.unsqueeze(0).expand(n, n)[keep].view(n, n - 1)


@cache
def others_flat_index(n: int, device: torch.device | str = "cpu") -> tuple[torch.Tensor, torch.Tensor]:
    """Flat (N*(N-1),) indices: the other robot j and the robot i itself, row by row."""
    rows = torch.arange(n, device=device).repeat_interleave(n - 1)
    return others_index(n, device).reshape(-1), rows


@cache
def target_flat_index(n: int, device: torch.device | str = "cpu") -> tuple[torch.Tensor, torch.Tensor]:
    """Flat (N*N,) indices: target k and robot i for every (i, k), row by row."""
    ar = torch.arange(n, device=device)
    return ar.repeat(n), ar.repeat_interleave(n)
