"""Observation layouts, defined once and used by training, the ControlStack and exported policies.

Entity tokens (layout version :data:`LAYOUT_VERSION`)
-----------------------------------------------------
Robot i of N sees ``T = 2N + 1`` tokens of ``TOKEN_DIM = 4`` features each, in this order::

    token                     type           features (metres, m/s; arena centred at (W/2, H/2))
    0        self             SELF   (0)     [p_x - W/2, p_y - H/2, v_x, v_y]
    1..N     target k         TARGET (1)     [g_k - p, 0, 0]
    N+1..2N-1 other robot j   ROBOT  (2)     [q_j - p, u_j - v]        (j != i, ascending j)
    2N       object           OBJECT (3)     [c - p, s - p]            c: object centroid,
                                                                       s: nearest point of its boundary

Own target (an actor with ``own_target``): robot i's own target ``k = sigma_i``, where sigma is
the team's one-to-one assignment of least total squared path length round the object
(:func:`own_assignment` on :func:`own_target_paths`: Turpin et al.'s CAPT rule, whose straight
paths do not cross, on the ways the robots can go), carries a mark in its spare features, ``[g_k - p, m]`` with ``m = (g_k - p) min(1, 0.1 m / |g_k - p|)``
(:func:`mark_own_targets`). The reward's assigned terms then judge the robot by that same
target. Without it a policy has to work out which target is its own from the whole scene, and
two robots of a team larger than any it trained on were seen to claim one slot.

``token_types(N)`` gives the (T,) type of each token and ``tokens()`` returns
``(E, N, T, 4)`` features plus an ``(E, N, T)`` validity mask (all true in the simulator; the
fleet bridge clears it for robots that dropped out). A policy built on tokens works for any N.

Flat vector (the paper's Figure 1, for fixed-N baselines)
---------------------------------------------------------
``[P(2), V(2), G_1..G_N (g_k - p), R_1..R_{N-1} (q_j - p)]`` -> ``4N + 2`` features.
"""

from __future__ import annotations

from collections import OrderedDict
from functools import cache

import numpy as np
import torch

from sim.geometry import DetourDistance, DetourField, Frame, Polygon, others_index
from sim.metrics import optimal_assignment

LAYOUT_VERSION = 1
TOKEN_DIM = 4
SELF, TARGET, ROBOT, OBJECT = 0, 1, 2, 3
NUM_TOKEN_TYPES = 4


def num_tokens(n: int) -> int:
    return 2 * n + 1


def token_types(n: int, device: torch.device | str = "cpu") -> torch.Tensor:
    """(2N+1,) long tensor of token types for N robots."""
    return torch.tensor([SELF] + [TARGET] * n + [ROBOT] * (n - 1) + [OBJECT], dtype=torch.long,
                        device=device)


def _check(pos: torch.Tensor, vel: torch.Tensor, targets: torch.Tensor) -> None:
    if pos.dim() != 3 or pos.shape[-1] != 2:
        raise ValueError(f"pos must have shape (num_envs, num_robots, 2), got {tuple(pos.shape)}")
    if vel.shape != pos.shape:
        raise ValueError(f"vel must have the shape of pos {tuple(pos.shape)}, got {tuple(vel.shape)}")
    if targets.shape != pos.shape:
        raise ValueError(f"targets must have the shape of pos {tuple(pos.shape)}, got {tuple(targets.shape)}")


def tokens(pos: torch.Tensor, vel: torch.Tensor, targets: torch.Tensor, poly: torch.Tensor | Polygon,
           arena: tuple[float, float]) -> tuple[torch.Tensor, torch.Tensor]:
    """Entity tokens of every robot.

    Args:
        pos, vel: (E, N, 2) positions [m] and velocities [m/s].
        targets: (E, N, 2) target slots [m].
        poly: (M, 2) object polygon [m] (or a :class:`sim.geometry.Polygon`).
        arena: (W, H) [m].

    Returns:
        tokens: (E, N, 2N+1, 4), mask: (E, N, 2N+1) bool.
    """
    _check(pos, vel, targets)
    if not isinstance(poly, Polygon):
        poly = Polygon(poly.to(pos))
    return frame_tokens(Frame(pos, vel, targets, poly), arena, _centroid(poly.vertices))


def frame_tokens(frame: Frame, arena: tuple[float, float],
                 centroid: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """Entity tokens from a precomputed :class:`sim.geometry.Frame`; see :func:`tokens`.

    Tokens are assembled as rows of 4 with one concatenation along the token axis: on the
    CPU that is far cheaper than interleaving feature planes.
    """
    e, n = frame.px.shape
    offset = frame.state.new_tensor([arena[0] / 2, arena[1] / 2, 0.0, 0.0])
    self_tok = (frame.state - offset).unsqueeze(2)                                 # (E,N,1,4)
    tgt_tok = frame.target_tokens                                                 # (E,N,N,4)
    obj_tok = torch.stack((centroid[0] - frame.px, centroid[1] - frame.py,
                           frame.obj_nx - frame.px, frame.obj_ny - frame.py), -1).unsqueeze(2)
    toks = torch.cat((self_tok, tgt_tok, frame.others, obj_tok), 2)
    mask = _all_valid(e, n, frame.px.device)
    return toks, mask


OWN_TARGET_REACH = 0.1       # [m] the own-target mark is the offset to it, clipped to this length
OWN_TARGET_CLEARANCE = 0.03  # [m] beyond the robot radius: the detour the assignment measures


def own_assignment(path: torch.Tensor) -> torch.Tensor:
    """(E, N) long: the target each robot is told is its own, from (E, N, N) robot-target path
    lengths [m] (:func:`own_target_paths`): the one-to-one assignment of least total squared
    length (Turpin et al.'s CAPT rule, on the ways round the object; ties:
    :func:`sim.metrics.optimal_assignment`'s)."""
    return optimal_assignment(path.square())


def own_target_paths(polygon: Polygon, targets: torch.Tensor, radius: float) -> DetourDistance:
    """The path lengths :func:`own_assignment` is solved on, exactly: the detour round the object
    inflated by ``radius + OWN_TARGET_CLEARANCE`` (:class:`sim.geometry.DetourDistance`; the
    training reward's with its default clearance). The worlds tabulate it
    (:class:`sim.geometry.DetourField`, within 3.5 mm), as the reward does."""
    return DetourDistance(polygon, targets, radius + OWN_TARGET_CLEARANCE)


class FleetOwnTargets:
    """:func:`own_assignment` for one fleet in numpy, as the ControlStack needs it every tick:
    ``(pos (N, 2), targets (N, 2)) -> (N,)`` int, read from the tabulated paths of the batched
    world (:meth:`sim.geometry.DetourField.lookup_np`) and solved by training's own solver
    (:func:`sim.metrics.optimal_assignment`), so a tie goes as it went in training. A target's column
    of the table (its path lengths from every grid node) takes ~20-100 ms to build and depends on
    that target alone, so columns are kept per target (the last ``KEPT_COLUMNS``): a robot that
    leaves or rejoins reorders the set but costs no rebuild inside the tick (it cost 90 ms, past
    the 50 ms period). ``targets`` given here (the scenario's) are tabulated now, not at the
    first tick; other targets when first seen."""

    KEPT_COLUMNS = 64

    def __init__(self, polygon: np.ndarray, radius: float, arena: tuple[float, float],
                 targets: np.ndarray | None = None):
        self.polygon = Polygon(torch.as_tensor(np.asarray(polygon), dtype=torch.float64))
        self.radius, self.arena = float(radius), arena
        self._key: bytes | None = None
        self._table: np.ndarray | None = None                      # (nodes, N) of the set in _key
        self._columns: OrderedDict[bytes, np.ndarray] = OrderedDict()  # per target, (nodes,)
        self._grid: DetourField | None = None                      # the grid (one for all targets)
        if targets is not None:
            self._tabulate(np.ascontiguousarray(targets, dtype=np.float64))

    def _tabulate(self, targets: np.ndarray) -> None:
        keys = [t.tobytes() for t in targets]
        missing = [k for k, key in enumerate(keys) if key not in self._columns]
        if missing:
            field = DetourField(own_target_paths(self.polygon, torch.from_numpy(targets[missing]), self.radius),
                                self.arena)
            table = field.table.numpy()
            for j, k in enumerate(missing):
                self._columns[keys[k]] = np.ascontiguousarray(table[:, j])
            self._grid = field
        for key in keys:
            self._columns.move_to_end(key)
        self._table = np.stack([self._columns[key] for key in keys], 1)
        while len(self._columns) > max(self.KEPT_COLUMNS, len(keys)):
            self._columns.popitem(last=False)
        self._key = targets.tobytes()

    def __call__(self, pos: np.ndarray, targets: np.ndarray) -> np.ndarray:
        targets = np.ascontiguousarray(targets, dtype=np.float64)
        if self._key != targets.tobytes():
            self._tabulate(targets)
        path = self._table[self._grid.nodes_np(np.asarray(pos, dtype=np.float64))]
        return optimal_assignment(torch.from_numpy(path * path)[None])[0].numpy()


def mark_own_targets(toks: torch.Tensor, sigma: torch.Tensor, reach: float = OWN_TARGET_REACH) -> torch.Tensor:
    """Tokens (E, N, 2N+1, 4) with each robot's own target marked: robot i's token ``1 + sigma_i``
    (features ``[d, 0, 0]``, ``d = g - p``) becomes ``[d, d * min(1, reach / |d|)]``.

    ``sigma`` (E, N) long is the team's robot-to-target assignment (a permutation per row). The
    mark is a vector in the arena frame like every feature pair, so quarter turns of the scene
    turn it along (:func:`controllers.policy.layers.formation_turn`), and it needs no new
    token feature, width or type: the same networks and exported graphs read it.
    """
    e, n = sigma.shape
    if toks.shape[:3] != (e, n, 2 * n + 1) or sigma.dtype != torch.long:
        raise ValueError(f"mark_own_targets needs tokens (E, N, 2N+1, 4) and a long assignment (E, N); "
                         f"got {tuple(toks.shape)} and {tuple(sigma.shape)} {sigma.dtype}")
    index = (1 + sigma).view(e, n, 1, 1).expand(e, n, 1, toks.shape[-1])
    d = toks.gather(2, index)[..., 0:2]
    mark = d * (reach / torch.linalg.vector_norm(d, dim=-1, keepdim=True).clamp_min(reach))
    return toks.scatter(2, index, torch.cat((d, mark), -1))


def mark_own_targets_np(toks: np.ndarray, sigma: np.ndarray, reach: float = OWN_TARGET_REACH) -> np.ndarray:
    """:func:`mark_own_targets` of one fleet's tokens (N, 2N+1, 4) in place; returns them."""
    rows = np.arange(len(sigma))
    d = toks[rows, 1 + sigma, 0:2].astype(np.float64)
    scale = reach / np.maximum(np.sqrt(np.einsum("id,id->i", d, d)), reach)
    toks[rows, 1 + sigma, 2:4] = d * scale[:, None]
    return toks


def _all_valid(e: int, n: int, device) -> torch.Tensor:
    return torch.ones(1, 1, 1, dtype=torch.bool, device=device).expand(e, n, 2 * n + 1)


def _centroid(poly: torch.Tensor) -> torch.Tensor:
    x, y = poly[:, 0], poly[:, 1]
    xn, yn = torch.roll(x, -1), torch.roll(y, -1)
    cross = x * yn - xn * y
    area = 0.5 * cross.sum()
    return torch.stack(((x + xn).mul(cross).sum(), (y + yn).mul(cross).sum())) / (6 * area)


def flat(pos: torch.Tensor, vel: torch.Tensor, targets: torch.Tensor) -> torch.Tensor:
    """The paper's flat per-robot vector: (E, N, 2) inputs -> (E, N, 4N + 2)."""
    _check(pos, vel, targets)
    e, n, _ = pos.shape
    rel_g = (targets.unsqueeze(1) - pos.unsqueeze(2)).reshape(e, n, 2 * n)
    rel_p = (pos[:, others_index(n, pos.device)] - pos.unsqueeze(2)).reshape(e, n, 2 * (n - 1))
    return torch.cat((pos, vel, rel_g, rel_p), -1)


def flat_dim(n: int) -> int:
    return 4 * n + 2


def fleet_tokens_np(pos: np.ndarray, vel: np.ndarray, targets: np.ndarray, polygon: np.ndarray,
                    arena: tuple[float, float], out: np.ndarray | None = None) -> np.ndarray:
    """The same token layout for one fleet in numpy: (N, 2) arrays -> (N, 2N+1, 4).

    For the control tick (N of a few robots) this is several times cheaper than the batched
    torch path, which is built for thousands of environments; a test holds the two equal.
    Every entry is computed in float64 and written into ``out`` (N, 2N+1, 4) when given (any
    float dtype, e.g. a reused float32 buffer: one cast, no temporary copy), else into a new
    float64 array; ``out`` is returned. The polygon's per-edge constants and centroid are
    cached by its vertices.
    """
    n = len(pos)
    shape = (n, 2 * n + 1, TOKEN_DIM)
    if out is None:
        out = np.empty(shape)
    elif out.shape != shape:
        raise ValueError(f"out must have shape (N, 2N+1, {TOKEN_DIM}) = {shape}, got {out.shape}")
    centroid, edges = _polygon_constants(polygon)
    state = np.concatenate((pos, vel), axis=1)                                    # (N, 4)
    out[:, 0] = state - (arena[0] / 2, arena[1] / 2, 0.0, 0.0)
    out[:, 1:n + 1, :2] = targets[None] - pos[:, None]
    out[:, 1:n + 1, 2:] = 0.0
    if n > 1:
        out[:, n + 1:2 * n] = state[_others_np(n)] - state[:, None]
    out[:, 2 * n, :2] = centroid - pos
    out[:, 2 * n, 2:] = _nearest_offset(pos, edges)
    return out


@cache
def _others_np(n: int) -> np.ndarray:
    return others_index(n).numpy()


_POLYGON_CACHE: dict[bytes, tuple[np.ndarray, tuple[np.ndarray, ...]]] = {}


def _polygon_constants(polygon: np.ndarray) -> tuple[np.ndarray, tuple[np.ndarray, ...]]:
    """Centroid (2,) and per-edge rows ``(a_x, a_y, e_x, e_y, 1/|e|^2)`` (1, M) of a polygon,
    cached by the vertices' bytes (the polygon is fixed between re-posings)."""
    poly = np.asarray(polygon, dtype=np.float64)
    key = poly.tobytes() + str(poly.shape).encode()
    hit = _POLYGON_CACHE.get(key)
    if hit is None:
        if len(_POLYGON_CACHE) >= 64:
            _POLYGON_CACHE.clear()
        edge = np.roll(poly, -1, axis=0) - poly
        rows = (poly[:, 0][None].copy(), poly[:, 1][None].copy(), edge[:, 0][None].copy(),
                edge[:, 1][None].copy(), 1.0 / (edge * edge).sum(-1)[None])
        lo, hi = poly.min(axis=0), poly.max(axis=0)
        cross = edge[:, 0] * np.roll(edge[:, 1], -1) - edge[:, 1] * np.roll(edge[:, 0], -1)
        box = (len(poly) == 4 and bool((cross > 0).all())
               and bool(((poly == lo) | (poly == hi)).all()))
        if box:   # axis-aligned box: the closed form of sim.geometry.Polygon (centre, half size)
            rows = (*rows, (lo + hi) / 2, (hi - lo) / 2)
        hit = (_centroid_np(poly), rows)
        _POLYGON_CACHE[key] = hit
    return hit


def object_token_constants(polygon: np.ndarray) -> tuple:
    """The object's constants of the token layout as flat arrays, for compiled code:
    ``(centroid (2,), a_x, a_y, e_x, e_y, 1/|e|^2 (M,), box, box centre (2,), box half size (2,))``
    (``box``: an axis-aligned box, whose clamp gives the nearest point; see :func:`_nearest_offset`)."""
    centroid, edges = _polygon_constants(polygon)
    box = len(edges) == 7
    centre, half = (edges[5], edges[6]) if box else (np.zeros(2), np.zeros(2))
    return (np.ascontiguousarray(centroid, dtype=np.float64), *(np.ascontiguousarray(e[0]) for e in edges[:5]),
            box, np.ascontiguousarray(centre, dtype=np.float64), np.ascontiguousarray(half, dtype=np.float64))


def _nearest_offset(points: np.ndarray, edges: tuple[np.ndarray, ...]) -> np.ndarray:
    """(K, 2) ``s - p``: from each of the (K, 2) points to its nearest polygon boundary point.

    An axis-aligned box (``edges`` then carries its centre and half size) takes the closed form
    of :meth:`sim.geometry.Polygon.signed_distance_xy` while every point is outside: the point
    clamped to the box. Points inside (or any other polygon) take the nearest edge projection.
    """
    if len(edges) == 7:
        centre, half = edges[5], edges[6]
        rel = points - centre
        clamped = np.minimum(np.maximum(rel, -half), half)
        offset = clamped - rel
        if offset.any(axis=1).all():                           # every point strictly outside
            return offset
    ax, ay, ex, ey, inv_len2 = edges[:5]
    rx, ry = points[:, :1] - ax, points[:, 1:] - ay                              # (K, M)
    t = np.minimum(np.maximum((rx * ex + ry * ey) * inv_len2, 0.0), 1.0)
    dx, dy = t * ex - rx, t * ey - ry                                            # foot - point
    flat = np.arange(len(points)) * ax.shape[1] + (dx * dx + dy * dy).argmin(axis=1)
    return np.stack((dx.take(flat), dy.take(flat)), axis=1)


def _centroid_np(poly: np.ndarray) -> np.ndarray:
    return _centroid(torch.from_numpy(np.asarray(poly, dtype=np.float64))).numpy()


def nearest_boundary_point_np(points: np.ndarray, polygon: np.ndarray) -> np.ndarray:
    """(K, 2) nearest points on the boundary of an (M, 2) polygon to (K, 2) points."""
    return points + _nearest_offset(points, _polygon_constants(polygon)[1])
