"""The reward of one step of E environments, with what it remembers between steps.

:func:`sim.reward.reward_from_distances` is a function of one state; the training reward also
needs the step before: the contact *onsets* (of discs grown by ``contact_margin``, when it is
positive) and the *sticky* assignment (``assignment_hysteresis``), plus the tabulated detour
field and the curriculum's ``penalty_scale``. :class:`StepReward` holds that state, so the
batched training world (:class:`sim.batched_env.BatchedFormationEnv`, E environments) and the
PettingZoo env over pymunk (:class:`sim.pettingzoo_env.FormationParallelEnv`, E = 1) reward the
same thing: one object, one rule, equal rewards on equal states (tested).
"""

from __future__ import annotations

import torch

from sim.geometry import DetourDistance, DetourField, Frame, Polygon
from sim.metrics import CollisionEvents, frame_collisions, optimal_assignment
from sim.observations import OWN_TARGET_CLEARANCE, own_target_paths
from sim.reward import RewardWeights, assignment_cost, proximity_ramp, reward_from_distances
from sim.scenario import Scenario


def frame_contacts(frame: Frame, radius: float, arena: tuple[float, float],
                   touched: tuple[torch.Tensor, ...]) -> tuple[CollisionEvents, torch.Tensor]:
    """Collision events of discs of ``radius`` plus the touches of this step the instant does
    not show (``touched``: (E, N) wall, object and optionally robot: the stops at walls and the
    object, :func:`sim.metrics.swept_contacts`); returns the events and their (E, N, 3) stack
    (robot, object, wall)."""
    events = frame_collisions(frame, radius, arena)
    events.wall = events.wall | touched[0]
    events.object = events.object | touched[1]
    if len(touched) > 2:
        events.robot = events.robot | touched[2]
    return events, torch.stack((events.robot, events.object, events.wall), -1)


class StepReward:
    """(E, N) reward of each step of E environments of ``scenario`` (module docstring).

    Call it once per step with the frame of the state the step ended in, the contact events of
    the robots' own discs and their onsets this step; :meth:`reset` the environments that start
    a new episode. ``prev_near_contact`` (E, N, 3) and ``assignment`` (E, N, -1: none yet) are
    the remembered state (a checkpoint saves them).
    """

    def __init__(self, scenario: Scenario, num_envs: int, weights: RewardWeights, polygon: Polygon,
                 device: torch.device | str = "cpu"):
        self.scenario, self.weights = scenario, weights
        self.radius, self.arena = scenario.robot_radius, scenario.arena
        targets = polygon.vertices.new_tensor(scenario.targets)
        self.polygon, self.targets = polygon, targets
        self.detour = DetourField(DetourDistance(polygon, targets, self.radius + weights.detour_clearance), self.arena)
        n = scenario.num_robots
        self.prev_near_contact = torch.zeros(num_envs, n, 3, dtype=torch.bool, device=device)
        self.assignment = torch.full((num_envs, n), -1, dtype=torch.long, device=device)
        self.penalty_scale = 1.0   # multiplies the contact terms (a training curriculum sets it)

    def reset(self, ids: torch.Tensor | slice = slice(None)) -> None:
        self.prev_near_contact[ids] = False
        self.assignment[ids] = -1

    def __call__(self, frame: Frame, touched: tuple[torch.Tensor, torch.Tensor],
                 events: CollisionEvents, onsets: torch.Tensor, sigma: torch.Tensor | None = None) -> torch.Tensor:
        """``events`` of the robots' discs and their (E, N, 3) ``onsets`` this step; with a
        contact margin the reward judges discs grown by it instead (its own onsets). ``sigma``
        (E, N) long, when given, is the assignment of the ``assigned`` and ``own_arrive`` terms
        (the one the robots are told: :func:`sim.observations.own_assignment`); else the reward's
        own (sticky with ``assignment_hysteresis``)."""
        w = self.weights
        if w.contact_margin > 0:
            events, near = frame_contacts(frame, self.radius + w.contact_margin, self.arena, touched)
            onsets = near & ~self.prev_near_contact
            self.prev_near_contact = near
        d_detour = self.detour(frame.pos)
        return reward_from_distances(
            frame.d_rg, events, self.scenario.target_tolerance, w, d_detour, onsets.any(-1),
            proximity_ramp(frame, self.radius, self.arena, w.near_margin) if w.w_near else None,
            sigma if sigma is not None else
            self._sticky_assignment(d_detour) if w.assignment_hysteresis and (w.w_assigned or w.w_own_arrive) else None,
            self.penalty_scale)

    def own_target_paths(self) -> DetourField:
        """The tabulated path lengths of :func:`sim.observations.own_target_paths` for this
        scenario: this reward's own when it measures the same detour, else a field of its own."""
        if self.weights.detour_clearance == OWN_TARGET_CLEARANCE:
            return self.detour
        return DetourField(own_target_paths(self.polygon, self.targets, self.radius), self.arena)

    def _sticky_assignment(self, path: torch.Tensor) -> torch.Tensor:
        """(E, N) assignment kept from the last step unless the optimal one for the (E, N, N)
        distances ``path`` is cheaper in total by more than ``assignment_hysteresis``
        (see :mod:`sim.reward`)."""
        cost = assignment_cost(path, self.weights.assignment_power)
        best = optimal_assignment(cost)
        current = self.assignment.clamp_min(0)
        sigmas = torch.stack((best, current)).unsqueeze(-1)                            # (2, E, N, 1)
        totals = torch.gather(cost.expand(2, *cost.shape), -1, sigmas).sum((-2, -1))   # (2, E)
        fresh = self.assignment[:, 0] < 0
        switch = fresh | (totals[0] < totals[1] - self.weights.assignment_hysteresis)
        self.assignment = torch.where(switch.unsqueeze(-1), best, current)
        return self.assignment
