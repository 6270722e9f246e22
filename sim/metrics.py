"""Task metrics, one implementation used by every world, learner and report.

* Collision events at one instant, per robot (:func:`collision_events`):
  robot-robot when two centres are closer than ``2 r``; robot-object when the disc
  overlaps the object polygon (signed distance of the centre < ``r``); robot-wall when the
  disc crosses a wall (centre closer than ``r`` to it). A tolerance ``eps`` (1e-6 m) keeps
  resting contact from counting.
* Collisions in mid-step (:func:`swept_contacts`): the same discs along the straight path of a
  step, for the contacts a world that moves in whole steps would miss between two instants.
* Assignment (:func:`optimal_assignment`): the one-to-one matching of robots to targets that
  minimises the sum of distances, solved exactly: by enumeration of the N! matchings, batched in
  torch, for N <= 4, and with scipy's ``linear_sum_assignment`` (Jonker-Volgenant, O(N^3)) per
  environment above, where it is the faster (1024 environments, one thread: N = 4 0.7 against
  1.6 ms, N = 5 4.0 against 1.8 ms, N = 6 29 against 2.2 ms, N = 8 2.8 ms by scipy).
* Success (:func:`episode_outcome`): under that assignment every robot is within
  ``target_tolerance`` of its target at the end *and* no collision happened in the episode.
* Final distance: the mean assigned distance at the end (the paper's Figures 11-13).
"""

from __future__ import annotations

import itertools
from dataclasses import dataclass
from functools import cache

import numpy as np
import torch

from sim.geometry import Frame, Polygon

CONTACT_EPS = 1e-6
_ENUMERATE_MAX_N = 4


@dataclass
class CollisionEvents:
    """Per-robot collision indicators at one instant, each (..., N) bool."""

    robot: torch.Tensor
    object: torch.Tensor
    wall: torch.Tensor

    @property
    def any(self) -> torch.Tensor:
        return self.robot | self.object | self.wall


def collision_events(pos: torch.Tensor, poly: torch.Tensor | Polygon, radius: float,
                     arena: tuple[float, float], eps: float = CONTACT_EPS) -> CollisionEvents:
    """Collisions of (E, N, 2) robot centres with each other, the object polygon (M, 2) and walls."""
    if not isinstance(poly, Polygon):
        poly = Polygon(poly.to(pos))
    return frame_collisions(Frame(pos, torch.zeros_like(pos), pos, poly), radius, arena, eps)


def frame_collisions(frame: Frame, radius: float, arena: tuple[float, float],
                     eps: float = CONTACT_EPS) -> CollisionEvents:
    """Collision events of a precomputed :class:`sim.geometry.Frame` (see the module docstring)."""
    contact = 2 * radius - eps
    close = frame.others_d2 < contact * contact
    lim = radius - eps
    wall = (frame.px < lim) | (frame.py < lim) | (frame.px > arena[0] - lim) | (frame.py > arena[1] - lim)
    return CollisionEvents(robot=close.any(-1), object=frame.obj_sd < lim, wall=wall)


def swept_contacts(start: torch.Tensor, end: torch.Tensor, radius: float, vertices: torch.Tensor,
                   eps: float = CONTACT_EPS) -> tuple[torch.Tensor, torch.Tensor]:
    """Contacts made *during* a step of straight-line motion from (E, N, 2) ``start`` to ``end``
    centres [m], among the robots and with the object's (M, 2) ``vertices``; returns (E, N) bool
    ``(robot, object)``: ``robot`` includes the contacts at the ends, ``object`` is the path's
    pass round a vertex (a touch of an edge at an end is :func:`frame_collisions`'s to see).

    Two robots' relative position moves along ``p(s) = p0 + s d``, ``d = p1 - p0``, s in [0, 1];
    its closest approach is at ``s* = clamp(-p0.d / d.d, 0, 1)`` and they touch when
    ``|p(s*)| < 2 r - eps``. Along a straight path the distance to an edge's line is linear, so
    the path comes closer to the object in mid-step than at its ends only round a vertex or by
    crossing an edge; a crossing takes a path of at least ``2 r`` between two points clear of
    the object (longer than a step: 2 cm at 0.4 m/s and 20 Hz against 8 cm), so the object
    counts as touched when the path passes within ``r - eps`` of a vertex. Walls are straight
    lines: the ends decide.
    """
    def closest_d2(px, py, dx, dy):            # x and y planes of p0 and d, broadcast
        s = (-(px * dx + py * dy) / (dx * dx + dy * dy).clamp_min(1e-30)).clamp(0.0, 1.0)
        qx, qy = px + s * dx, py + s * dy
        return qx * qx + qy * qy

    x0, y0 = start[..., 0], start[..., 1]
    mx, my = end[..., 0] - x0, end[..., 1] - y0
    d2 = closest_d2(x0.unsqueeze(-1) - x0.unsqueeze(-2), y0.unsqueeze(-1) - y0.unsqueeze(-2),
                    mx.unsqueeze(-1) - mx.unsqueeze(-2), my.unsqueeze(-1) - my.unsqueeze(-2))   # (E, N, N)
    n = start.shape[-2]
    others = ~torch.eye(n, dtype=torch.bool, device=start.device)
    contact = 2 * radius - eps
    robot = ((d2 < contact * contact) & others).any(-1)
    v = vertices.to(start)
    lim = radius - eps
    obj = (closest_d2(x0.unsqueeze(-1) - v[:, 0], y0.unsqueeze(-1) - v[:, 1],
                      mx.unsqueeze(-1), my.unsqueeze(-1)) < lim * lim).any(-1)         # (E, N, M) -> (E, N)
    return robot, obj


@cache
def _permutations(n: int, device: str) -> torch.Tensor:
    return torch.tensor(list(itertools.permutations(range(n))), dtype=torch.long, device=device)


def distance_matrix(pos: torch.Tensor, targets: torch.Tensor) -> torch.Tensor:
    """(..., N, 2) robots, (..., N, 2) targets -> (..., N robots, N targets) distances."""
    dx = pos[..., :, None, 0] - targets[..., None, :, 0]
    dy = pos[..., :, None, 1] - targets[..., None, :, 1]
    return (dx * dx + dy * dy).sqrt()


def optimal_assignment(cost: torch.Tensor, method: str = "auto") -> torch.Tensor:
    """Min-sum one-to-one assignment for a batch of square cost matrices.

    Args:
        cost: (B, N, N) cost[b, i, k] of giving robot i target k.
        method: ``"enumerate"`` (all N! matchings, batched), ``"scipy"`` (per environment) or
            ``"auto"``: enumeration for N <= 4, scipy above (module docstring).

    Returns:
        (B, N) long tensor: the target index of each robot.
    """
    if cost.dim() != 3 or cost.shape[-1] != cost.shape[-2]:
        raise ValueError(f"cost must have shape (B, N, N), got {tuple(cost.shape)}")
    if method not in ("auto", "enumerate", "scipy"):
        raise ValueError(f"method must be 'auto', 'enumerate' or 'scipy', got {method!r}")
    b, n, _ = cost.shape
    if method == "enumerate" or (method == "auto" and n <= _ENUMERATE_MAX_N):
        return _enumerated(cost)
    from scipy.optimize import linear_sum_assignment

    out = np.empty((b, n), dtype=np.int64)
    cost_np = cost.detach().cpu().double().numpy()
    for i in range(b):
        r, c = linear_sum_assignment(cost_np[i])
        out[i, r] = c
    return torch.from_numpy(out).to(cost.device)


def _enumerated(cost: torch.Tensor) -> torch.Tensor:
    b, n, _ = cost.shape
    perms = _permutations(n, str(cost.device))          # (P, N)
    rows = torch.arange(n, device=cost.device)
    chunk = max(1, 2_000_000 // (perms.shape[0] * n))
    best = []
    for start in range(0, b, chunk):
        c = cost[start:start + chunk]                   # (b', N, N)
        totals = c[:, rows, perms].sum(-1)              # (b', P)
        best.append(perms[totals.argmin(-1)])
    return torch.cat(best, 0) if best else torch.empty(0, n, dtype=torch.long, device=cost.device)


@dataclass
class EpisodeOutcome:
    """Per-environment outcome of finished episodes, each (B,)."""

    success: torch.Tensor          # bool
    final_distance: torch.Tensor   # mean assigned distance [m]
    max_distance: torch.Tensor     # worst assigned distance [m]
    assignment: torch.Tensor       # (B, N) target index per robot


def episode_outcome(pos: torch.Tensor, targets: torch.Tensor, collided: torch.Tensor,
                    tolerance: float) -> EpisodeOutcome:
    """Success and final distance of (B, N, 2) final positions against (B, N, 2) targets.

    ``collided`` is a (B,) bool telling whether any collision happened during the episode.
    """
    dist = distance_matrix(pos, targets)
    assign = optimal_assignment(dist)
    assigned = torch.gather(dist, -1, assign.unsqueeze(-1)).squeeze(-1)  # (B, N)
    final = assigned.mean(-1)
    worst = assigned.max(-1).values
    success = (worst <= tolerance) & ~collided
    return EpisodeOutcome(success=success, final_distance=final, max_distance=worst, assignment=assign)
