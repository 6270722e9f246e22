"""The training world of MAPPO: one group of batched environments per team size, and rollouts.

A run trains on one team size (the scenario's N) or on several (``MAPPOConfig.team_sizes``):
one :class:`TeamGroup` per size N, each a :class:`sim.batched_env.BatchedFormationEnv` of
``num_envs`` environments of N robots, side by side. The actor and the critic read entity
tokens and run any N, so the groups share both networks without padding: a rollout is
collected per group, and the update draws its minibatches from one group at a time (a
minibatch holds whole teams of one size). Shapes below: S steps, E environments, N robots of
the group, T = 2N + 1 tokens of F features.
"""

from __future__ import annotations

from dataclasses import dataclass

import torch

from controllers.policy import gaussian_log_prob
from sim.batched_env import BatchedFormationEnv


@dataclass
class TeamGroup:
    """The environments of one team size and the observation they stand at."""

    env: BatchedFormationEnv
    obs: torch.Tensor                  # (E, N, T, F) tokens, or (E, N, 4N+2) flat vectors
    mask: torch.Tensor | None          # (E, N, T) bool, None for flat observations

    @classmethod
    def start(cls, env: BatchedFormationEnv) -> TeamGroup:
        return cls(env, *env.reset())

    @property
    def num_robots(self) -> int:
        return self.env.num_robots


@dataclass
class Rollout:
    """S steps of one group (tensors (S, E, ...), per robot where it says N)."""

    obs: torch.Tensor
    mask: torch.Tensor | None
    actions: torch.Tensor              # (S, E, N, 2) sampled accelerations [m/s^2]
    log_probs: torch.Tensor            # (S, E, N)
    values: torch.Tensor               # (S, E, N) de-normalised V(o_t)
    rewards: torch.Tensor              # (S, E, N)
    dones: torch.Tensor                # (S, E) bool: the episode ended at step t
    final_values: torch.Tensor         # (S, E, N) V of the state an episode ended in ("final")
    next_values: torch.Tensor          # (E, N) V(o_S)
    finished: list                     # EpisodeStats of the episodes that ended

    def flat(self, advantages: torch.Tensor, returns_n: torch.Tensor, values_n: torch.Tensor) -> dict:
        """The update's samples: (S * E, ...) tensors, one team per sample, and its mask."""
        return {"obs": self.obs.flatten(0, 1), "mask": None if self.mask is None else self.mask.flatten(0, 1),
                "actions": self.actions.flatten(0, 1), "old_log_probs": self.log_probs.flatten(0, 1),
                "advantages": advantages.flatten(0, 1), "returns": returns_n.flatten(0, 1),
                "old_values": values_n.flatten(0, 1)}


@torch.no_grad()
def collect(group: TeamGroup, actor, critic, value_norm, steps: int, sampler: torch.Generator,
            bootstrap_final: bool) -> Rollout:
    """Run ``steps`` steps of ``group`` with ``a ~ N(actor(o), exp(log_std)^2)`` per robot and
    V(o) from the centralised critic; ``group`` is left at the next observation."""
    obs0, e, n = group.obs, group.env.num_envs, group.num_robots
    obs_buf = obs0.new_empty((steps, *obs0.shape))
    mask_buf = None if group.mask is None else group.mask.new_empty((steps, *group.mask.shape))
    actions = obs0.new_empty((steps, e, n, 2))
    log_probs, values, rewards = (obs0.new_empty((steps, e, n)) for _ in range(3))
    dones = torch.zeros(steps, e, dtype=torch.bool, device=obs0.device)
    final_values = torch.zeros_like(values) if bootstrap_final else values
    finished = []
    log_std = actor.log_std
    for t in range(steps):
        obs_buf[t] = group.obs
        if mask_buf is not None:
            mask_buf[t] = group.mask
        mean = actor(group.obs, group.mask)
        noise = torch.randn(mean.shape, generator=sampler, device=mean.device, dtype=mean.dtype)
        action = mean + noise * log_std.exp()
        actions[t] = action
        log_probs[t] = gaussian_log_prob(action, mean, log_std)
        values[t] = value_norm.denormalize(critic(group.obs, group.mask))
        step = group.env.step(action)
        rewards[t], dones[t] = step.reward, step.done
        group.obs, group.mask = step.obs, step.mask
        if len(step.finished):
            finished.append(step.finished)
            if step.final_obs is not None and bootstrap_final:
                final_values[t] = value_norm.denormalize(critic(step.final_obs, step.final_mask))
    next_values = value_norm.denormalize(critic(group.obs, group.mask))
    return Rollout(obs_buf, mask_buf, actions, log_probs, values, rewards, dones, final_values,
                   next_values, finished)


__all__ = ["Rollout", "TeamGroup", "collect"]
