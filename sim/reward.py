"""Dense reward shared by every learner (so comparisons are fair).

Per step and per robot i (all distances in metres; ``d(p, g)`` is the detour distance around
the object, :class:`sim.geometry.DetourDistance` or its tabulated :class:`sim.geometry.DetourField`,
or the straight one when none is given)::

    cover   = 1/2 * ( mean_k min_i d(p_i, g_k)  +  mean_i min_k d(p_i, g_k) )     (team term)
    arrived = 1/N * #{k : min_i |g_k - p_i| <= tol}                               (team term)
    r_i     = - w_dist * cover
              + w_arrive * arrived
              - w_robot * [robot i touches another robot]
              - w_object * [robot i touches the object]
              - w_wall * [robot i touches a wall]
              - w_onset * [robot i starts a new contact this step]

The detour distance keeps the gradient of ``cover`` pointing around the object instead of into
it (with straight distances the shortest way to a target runs through the object, a local
optimum that costs a learner thousands of episodes to escape).

``cover`` is zero exactly when every target holds a robot and every robot sits on a target,
which (targets farther apart than twice the tolerance) means a one-to-one assignment with
zero distance; it needs no assignment solve per step, so it stays cheap in the batched world.
Collision indicators come from :func:`sim.metrics.collision_events`.
"""

from __future__ import annotations

from dataclasses import dataclass

import torch

from sim.geometry import DetourDistance, DetourField
from sim.metrics import CollisionEvents, distance_matrix


@dataclass(frozen=True)
class RewardWeights:
    """Weights of the dense reward terms (see the module docstring)."""

    w_dist: float = 1.0
    w_arrive: float = 0.1
    w_robot: float = 0.5
    w_object: float = 0.5
    w_wall: float = 0.2
    w_onset: float = 0.0     # one-off cost of each new contact (0: off; needs the onset flags)


def formation_reward(pos: torch.Tensor, targets: torch.Tensor, events: CollisionEvents,
                     tolerance: float, weights: RewardWeights = RewardWeights(),
                     detour: DetourDistance | DetourField | None = None) -> torch.Tensor:
    """(E, N, 2) positions and targets -> (E, N) per-robot reward of this step."""
    d = distance_matrix(pos, targets)
    return reward_from_distances(d, events, tolerance, weights,
                                 None if detour is None else detour(pos))


def reward_from_distances(d: torch.Tensor, events: CollisionEvents, tolerance: float,
                          weights: RewardWeights = RewardWeights(),
                          d_detour: torch.Tensor | None = None,
                          onsets: torch.Tensor | None = None) -> torch.Tensor:
    """(E, N robots, N targets) straight (and detour) distances -> (E, N) per-robot reward."""
    path = d if d_detour is None else d_detour
    to_target = _min_over(path, -2)                        # (E, N targets)
    to_robot = _min_over(path, -1)                         # (E, N robots)
    cover = 0.5 * (to_target.mean(-1) + to_robot.mean(-1))  # (E,)
    arrived = (_min_over(d, -2) <= tolerance).float().mean(-1)   # (E,)
    team = -weights.w_dist * cover + weights.w_arrive * arrived
    own = (weights.w_robot * events.robot.float() + weights.w_object * events.object.float()
           + weights.w_wall * events.wall.float())
    if onsets is not None and weights.w_onset:
        own = own + weights.w_onset * onsets.float()
    return team.unsqueeze(-1) - own


def _min_over(x: torch.Tensor, dim: int) -> torch.Tensor:
    """``x.min(dim).values`` as a chain of elementwise minima: for the small N of this task that
    is several times faster on the CPU than a reduction over a short dimension."""
    if x.shape[dim] > 8:
        return x.min(dim).values
    parts = x.unbind(dim)
    out = parts[0]
    for p in parts[1:]:
        out = torch.minimum(out, p)
    return out
