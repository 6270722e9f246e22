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


class DetourDistance:
    """Shortest distance from robot centres to targets *around* a convex object (the taut string).

    The object is inflated by ``margin`` (a robot radius plus clearance): its vertices are pushed
    out along the angle bisectors so every edge moves out by ``margin``. A robot-target pair whose
    segment misses the inflated polygon gets the straight distance; otherwise the path runs
    robot -> visible corner c_j -> along the perimeter -> corner c_i -> target::

        d(p, g_k) = min_j ( |p - c_j| [c_j visible from p] + h[j, k] ),
        h[j, k]   = min_i ( D[j, i] + |c_i - g_k| [g_k visible from c_i] ),

    with D the perimeter distance between corners; ``h`` depends only on the targets, so it is
    computed once. Visibility is the Cyrus-Beck clip of a segment against the convex polygon
    (shrunk by 1e-6 m so that grazing a corner counts as visible). A centre inside the inflated
    polygon is first moved to its nearest boundary point q (``d = |p - q| + d(q, g)``, continuous
    across the boundary). Non-convex objects get the straight distance.
    """

    def __init__(self, polygon: Polygon, targets: torch.Tensor, margin: float):
        self.enabled = polygon.convex_ccw
        v = polygon.vertices
        self.targets = targets                                   # (N, 2)
        if not self.enabled:
            return
        ex, ey = polygon.ex, polygon.ey
        length = (ex * ex + ey * ey).sqrt()
        nx, ny = ey / length, -ex / length                       # outward normals (CCW polygon)
        self.nx, self.ny = nx, ny
        # edge k runs v_k -> v_{k+1}; vertex k joins edges k-1 and k
        pnx, pny = torch.roll(nx, 1), torch.roll(ny, 1)
        bis = torch.stack((nx + pnx, ny + pny), -1)
        cos_half2 = (bis * bis).sum(-1) / 4                       # cos^2 of half the turn angle
        self.corners = v + bis / 2 * (margin / cos_half2).unsqueeze(-1)   # (M, 2)
        self.inflated = Polygon(self.corners)
        # offsets of the edge lines for the visibility test, slightly inside the inflated polygon
        self.edge_offset = (v[:, 0] * nx + v[:, 1] * ny) + margin - 1e-6   # n . x <= offset inside
        m = len(v)
        side = (torch.roll(self.corners, -1, 0) - self.corners).norm(dim=-1)   # corner k -> k+1
        cum = torch.cat((side.new_zeros(1), side.cumsum(0)))
        perimeter = cum[-1]
        fwd = (cum[:m].unsqueeze(0) - cum[:m].unsqueeze(1)) % perimeter
        self.perimeter_d = torch.minimum(fwd, perimeter - fwd)   # (M, M)
        vis_cg = self.visible(self.corners.unsqueeze(1), targets.unsqueeze(0))   # (M, N)
        d_cg = (self.corners.unsqueeze(1) - targets.unsqueeze(0)).norm(dim=-1)
        d_cg = torch.where(vis_cg, d_cg, torch.full_like(d_cg, float("inf")))
        self.h = (self.perimeter_d.unsqueeze(-1) + d_cg.unsqueeze(0)).min(1).values   # (M, N)

    def visible(self, a: torch.Tensor, b: torch.Tensor) -> torch.Tensor:
        """Segments a -> b (broadcast shapes (..., 2)) that miss the inflated polygon: (...,) bool."""
        a, b = torch.broadcast_tensors(a, b)
        dx, dy = (b - a).unbind(-1)
        ax, ay = a.unbind(-1)
        num = self.edge_offset - (ax.unsqueeze(-1) * self.nx + ay.unsqueeze(-1) * self.ny)   # (..., M)
        den = dx.unsqueeze(-1) * self.nx + dy.unsqueeze(-1) * self.ny
        ratio = num / torch.where(den == 0, torch.ones_like(den), den)
        inf = torch.full_like(ratio, float("inf"))
        t_enter = torch.where(den < 0, ratio, -inf).amax(-1).clamp_min(0.0)
        t_exit = torch.where(den > 0, ratio, inf).amin(-1).clamp_max(1.0)
        outside_parallel = ((den == 0) & (num < 0)).any(-1)
        return outside_parallel | (t_enter >= t_exit)

    def __call__(self, points: torch.Tensor) -> torch.Tensor:
        """(..., 2) points -> (..., K) detour distances to each of the K targets [m]."""
        straight = (points.unsqueeze(-2) - self.targets).norm(dim=-1)                   # (..., K)
        if not self.enabled:
            return straight
        sd, nx, ny = self.inflated.signed_distance_xy(points[..., 0], points[..., 1])
        inside = (sd < 0).unsqueeze(-1)
        points = torch.where(inside, torch.stack((nx, ny), -1), points)
        lead_in = torch.where(inside, -sd.unsqueeze(-1), torch.zeros_like(sd).unsqueeze(-1))
        straight_q = (points.unsqueeze(-2) - self.targets).norm(dim=-1)
        direct = self.visible(points.unsqueeze(-2), self.targets)                       # (..., K)
        d_pc = (points.unsqueeze(-2) - self.corners).norm(dim=-1)                       # (..., M)
        vis_pc = self.visible(points.unsqueeze(-2), self.corners)
        d_pc = torch.where(vis_pc, d_pc, torch.full_like(d_pc, float("inf")))
        around = (d_pc.unsqueeze(-1) + self.h).min(-2).values                           # (..., K)
        out = torch.where(direct, straight_q, around)
        return torch.where(torch.isinf(out), straight, out + lead_in)


class DetourField:
    """:class:`DetourDistance` tabulated on a grid over the arena, read back at the nearest node.

    The exact detour costs a few segment clips per robot-target pair; the field costs one gather.
    The detour distance is 1-Lipschitz, so the lookup error is at most ``resolution / sqrt(2)``
    (3.5 mm at the default 5 mm) away from the object's inflated corners, where the detour
    itself switches sides.
    """

    def __init__(self, detour: DetourDistance, arena: tuple[float, float], resolution: float = 0.005):
        self.res = resolution
        self.nx = int(round(arena[0] / resolution)) + 1
        self.ny = int(round(arena[1] / resolution)) + 1
        t = detour.targets
        xs = torch.arange(self.nx, dtype=t.dtype, device=t.device) * resolution
        ys = torch.arange(self.ny, dtype=t.dtype, device=t.device) * resolution
        grid = torch.stack(torch.meshgrid(ys, xs, indexing="ij")[::-1], -1).reshape(-1, 2)
        self.table = detour(grid).contiguous()                      # (ny * nx, K), row = iy * nx + ix
        self._table_np: np.ndarray | None = None

    def __call__(self, pos: torch.Tensor) -> torch.Tensor:
        """(E, N, 2) centres -> (E, N, K) detour distances to the K targets [m]."""
        e, n, _ = pos.shape
        ix = (pos[..., 0] / self.res).round().clamp(0, self.nx - 1)
        iy = (pos[..., 1] / self.res).round().clamp(0, self.ny - 1)
        node = (iy * self.nx + ix).long().reshape(-1)
        return self.table.index_select(0, node).view(e, n, -1)

    def lookup_np(self, pos: np.ndarray) -> np.ndarray:
        """:meth:`__call__` for one fleet in numpy, (N, 2) -> (N, K): one gather, no torch call
        (the control tick's own-target assignment reads it)."""
        if self._table_np is None:
            self._table_np = self.table.numpy()
        return self._table_np[self.nodes_np(pos)]

    def nodes_np(self, pos: np.ndarray) -> np.ndarray:
        """(N,) int64 the table row of the grid node nearest each of (N, 2) centres [m]."""
        ix = np.clip(np.rint(pos[:, 0] / self.res), 0, self.nx - 1)
        iy = np.clip(np.rint(pos[:, 1] / self.res), 0, self.ny - 1)
        return (iy * self.nx + ix).astype(np.int64)
