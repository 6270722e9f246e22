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
              - w_own * min_k d(p_i, g_k)                                         (own term)
              - w_assigned * d(p_i, g_sigma(i))     sigma: min-sum one-to-one assignment (own term)
              + w_own_arrive * [|p_i - g_sigma(i)| <= tol]                          (own term)
              - w_near * near_i

    near_i  = sum_j ramp(|p_i - p_j| - 2r) + ramp(sd_object(p_i) - r) + sum_walls ramp(gap_wall)
    ramp(g) = clamp(1 - g / near_margin, 0, 1)     (1 at contact, 0 beyond ``near_margin``)

With ``contact_margin`` m > 0 the collision indicators of the reward (not the episode's success,
not the collision statistics) are those of discs of radius r + m: a learner penalised for
coming within m of anything keeps that margin, so a deterministic policy does not graze the
object the way a policy trained on the exact contact does (it sits right at the edge).

With ``assignment_power`` 2 sigma minimises the sum of *squared* detour distances (Turpin et al.'s
CAPT assignment): where robots queue along one path to targets along it, the linear sums tie
and the leader may be charged for the nearest target, which then blocks the follower's way to
the far one; the squared sum sends the leader to the far target (a^2 + (b + s)^2 >
(a + s)^2 + b^2 for a leader at a < b).

With ``assignment_hysteresis`` h > 0 the batched world keeps each episode's assignment sigma
from step to step and switches to the optimal one only when that is shorter in total by more
than h (in the assignment's cost, metres to the ``assignment_power``): the optimum flips back and
forth between near-equal assignments as robots move (two trained 3-robot policies saw 4.4 and 5.6
flips per episode on average), and each flip moves a robot's target,
its distance term and its arrival bonus to another robot.

``own`` and ``assigned`` give each robot credit for its own approach (the team terms reward every robot
alike for what any of them did); ``near`` is a soft barrier that costs proximity before contact,
so a learner is pushed off a collision course while the push is still a gradient, not a cliff.
Nearest-target terms (``cover``, ``own``) have a local optimum where two robots share a target
and a third waits between slots; the assignment term pulls every robot to a distinct target
(the exact min-sum assignment of :func:`sim.metrics.optimal_assignment`, by enumeration for N <= 4
and scipy above).

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

from sim.geometry import DetourDistance, DetourField, Frame
from sim.metrics import CollisionEvents, distance_matrix, optimal_assignment


@dataclass(frozen=True)
class RewardWeights:
    """Weights of the dense reward terms (see the module docstring)."""

    w_dist: float = 1.0
    w_arrive: float = 0.1
    w_robot: float = 0.5
    w_object: float = 0.5
    w_wall: float = 0.2
    w_onset: float = 0.0     # one-off cost of each new contact (0: off; needs the onset flags)
    w_own: float = 0.0       # per-robot distance to its nearest target (0: off)
    w_assigned: float = 0.0  # per-robot distance to its assigned target (0: off)
    w_own_arrive: float = 0.0  # per-robot bonus for sitting on its assigned target (0: off)
    w_near: float = 0.0      # soft proximity cost (0: off; needs the proximity ramp)
    near_margin: float = 0.03  # gap [m] at which the proximity cost starts
    detour_clearance: float = 0.01  # gap [m] the detour path keeps from the object
    contact_margin: float = 0.0     # the penalties count a gap below this [m] as contact
    assignment_hysteresis: float = 0.0  # keep sigma until another is cheaper by more than this [m^power]
    assignment_power: float = 1.0   # sigma minimises sum_i d(p_i, g_sigma(i)) ** power


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
                          onsets: torch.Tensor | None = None,
                          near: torch.Tensor | None = None,
                          sigma: torch.Tensor | None = None,
                          penalty_scale: float = 1.0) -> torch.Tensor:
    """(E, N robots, N targets) straight (and detour) distances -> (E, N) per-robot reward.

    ``sigma`` (E, N) long: the assignment of the ``assigned`` and ``own_arrive`` terms; None
    solves it for this step on :func:`assignment_cost` of ``d_detour`` (else ``d``). ``penalty_scale``
    multiplies the contact terms (``w_robot``, ``w_object``, ``w_wall``, ``w_onset``)."""
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
    if penalty_scale != 1.0:
        own = own * penalty_scale
    if weights.w_own:
        own = own + weights.w_own * to_robot
    if weights.w_assigned or weights.w_own_arrive:
        if sigma is None:
            sigma = optimal_assignment(assignment_cost(path, weights.assignment_power))
        sigma = sigma.unsqueeze(-1)                                         # (E, N, 1)
        if weights.w_assigned:
            own = own + weights.w_assigned * torch.gather(path, -1, sigma).squeeze(-1)
        if weights.w_own_arrive:
            on_target = torch.gather(d, -1, sigma).squeeze(-1) <= tolerance
            own = own - weights.w_own_arrive * on_target.float()
    if near is not None and weights.w_near:
        own = own + weights.w_near * near
    return team.unsqueeze(-1) - own


def assignment_cost(path: torch.Tensor, power: float) -> torch.Tensor:
    """(E, N, N) robot-target distances -> the cost whose min-sum assignment is sigma: ``d ** power``."""
    return path if power == 1 else path ** power


def proximity_ramp(frame: Frame, radius: float, arena: tuple[float, float], margin: float) -> torch.Tensor:
    """(E, N) ``near_i`` of the module docstring: summed ramps of the gaps to the other robots,
    the object and the four walls, each 1 at contact and 0 at a gap of ``margin`` [m] or more."""
    if margin <= 0:
        raise ValueError(f"near_margin must be > 0, got {margin!r}")
    inv = 1.0 / margin
    gap_rr = frame.others_d2.sqrt() - 2 * radius                  # (E, N, N-1)
    near = (1 - gap_rr * inv).clamp(0, 1).sum(-1)
    near = near + (1 - (frame.obj_sd - radius) * inv).clamp(0, 1)
    for gap in (frame.px - radius, frame.py - radius, arena[0] - radius - frame.px, arena[1] - radius - frame.py):
        near = near + (1 - gap * inv).clamp(0, 1)
    return near


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
