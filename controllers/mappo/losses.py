"""The arithmetic of MAPPO: GAE, the clipped surrogate, the value loss, value normalisation.

Shapes: ``S`` rollout steps, ``E`` environments, ``N`` robots. Rewards, values, advantages and
returns are (S, E, N); ``dones`` are (S, E) because a whole team finishes together.
"""

from __future__ import annotations

import torch


def compute_gae(rewards: torch.Tensor, values: torch.Tensor, dones: torch.Tensor,
                next_values: torch.Tensor, gamma: float, gae_lambda: float,
                truncation_values: torch.Tensor | None = None):
    """Generalised advantage estimation (Schulman et al. 2016).

    Args:
        rewards: (S, E, N) reward of step t.
        values: (S, E, N) value estimates V(o_t) of the observations the actions were taken in.
        dones: (S, E) bool, True where step t *ended* the episode (the environment was reset,
            so o_{t+1} starts a new episode and must not be bootstrapped from).
        next_values: (E, N) V(o_S), the observation after the last step.
        gamma, gae_lambda: discount and GAE lambda.
        truncation_values: (S, E, N) or None. None: an ended episode is terminal (nothing
            after it). Given: episodes end by a *time limit* (truncation), and the discounted
            future after step t is bootstrapped from ``truncation_values[t]`` (an estimate of
            the value of the final state, which the auto-resetting world no longer shows).

    Returns:
        advantages (S, E, N) and returns = advantages + values (S, E, N), where, with
        ``B_t = V(o_{t+1})`` if not done_t, else ``truncation_values[t]`` (or 0 if None)::

            delta_t = r_t + gamma * B_t - V(o_t)
            A_t     = delta_t + gamma * lambda * (1 - done_t) * A_{t+1},     A_S = 0
    """
    if rewards.shape != values.shape or rewards.dim() != 3:
        raise ValueError(f"rewards and values must both be (steps, envs, robots), got "
                         f"{tuple(rewards.shape)} and {tuple(values.shape)}")
    if dones.shape != rewards.shape[:2]:
        raise ValueError(f"dones must be (steps, envs) = {tuple(rewards.shape[:2])}, got {tuple(dones.shape)}")
    if next_values.shape != rewards.shape[1:]:
        raise ValueError(f"next_values must be (envs, robots) = {tuple(rewards.shape[1:])}, "
                         f"got {tuple(next_values.shape)}")
    if truncation_values is not None and truncation_values.shape != rewards.shape:
        raise ValueError(f"truncation_values must be (steps, envs, robots) = {tuple(rewards.shape)}, "
                         f"got {tuple(truncation_values.shape)}")
    done = dones.bool().unsqueeze(-1)                                      # (S, E, 1)
    not_done = (~done).to(rewards.dtype)
    advantages = torch.zeros_like(rewards)
    last = torch.zeros_like(next_values)
    for t in reversed(range(rewards.shape[0])):
        following = next_values if t == rewards.shape[0] - 1 else values[t + 1]
        if truncation_values is None:
            following = not_done[t] * following
        else:
            following = torch.where(done[t], truncation_values[t], following)
        delta = rewards[t] + gamma * following - values[t]
        last = delta + gamma * gae_lambda * not_done[t] * last
        advantages[t] = last
    return advantages, advantages + values


def clipped_surrogate_loss(new_log_prob: torch.Tensor, old_log_prob: torch.Tensor,
                           advantages: torch.Tensor, clip_coef: float) -> torch.Tensor:
    """PPO's clipped objective (the paper's Equation (1)) as a loss to minimise::

        r = exp(log pi_new(a|o) - log pi_old(a|o))
        L = -mean( min(r A, clip(r, 1 - clip_coef, 1 + clip_coef) A) )
    """
    ratio = torch.exp(new_log_prob - old_log_prob)
    unclipped = ratio * advantages
    clipped = torch.clamp(ratio, 1.0 - clip_coef, 1.0 + clip_coef) * advantages
    return -torch.min(unclipped, clipped).mean()


def value_loss(new_values: torch.Tensor, old_values: torch.Tensor, targets: torch.Tensor,
               clip_coef: float | None) -> torch.Tensor:
    """``1/2 mean((V - target)^2)``; with ``clip_coef`` the PPO2 clipped form::

        V_clip = V_old + clip(V - V_old, -c, c)
        L = 1/2 mean(max((V - target)^2, (V_clip - target)^2))
    """
    err = (new_values - targets) ** 2
    if clip_coef is None:
        return 0.5 * err.mean()
    clipped = old_values + torch.clamp(new_values - old_values, -clip_coef, clip_coef)
    return 0.5 * torch.max(err, (clipped - targets) ** 2).mean()


def explained_variance(predicted: torch.Tensor, targets: torch.Tensor) -> float:
    """``1 - Var(target - predicted) / Var(target)`` (1 = perfect, 0 = no better than the mean)."""
    var = targets.var()
    if var.item() == 0:
        return float("nan")
    return float(1.0 - (targets - predicted).var() / var)


class ValueNormalizer(torch.nn.Module):
    """Running mean and variance of the value targets (returns), in float64.

    The critic learns ``(G - mean) / std``; values are turned back with ``V * std + mean``
    before GAE. Batches are merged with the parallel-variance formula (Chan et al.)::

        delta = mean_b - mean,  n' = n + n_b
        mean' = mean + delta * n_b / n'
        var'  = (var * n + var_b * n_b + delta^2 * n * n_b / n') / n'

    With ``enabled=False`` both maps are the identity.
    """

    def __init__(self, enabled: bool = True, epsilon: float = 1e-5):
        super().__init__()
        self.enabled = enabled
        self.epsilon = epsilon
        self.register_buffer("mean", torch.zeros((), dtype=torch.float64))
        self.register_buffer("var", torch.ones((), dtype=torch.float64))
        self.register_buffer("count", torch.zeros((), dtype=torch.float64))

    @torch.no_grad()
    def update(self, x: torch.Tensor) -> None:
        if not self.enabled or x.numel() == 0:
            return
        x = x.detach().double().reshape(-1)
        batch_mean, batch_var, n_b = x.mean(), x.var(unbiased=False), float(x.numel())
        if self.count.item() == 0:
            self.mean.copy_(batch_mean)
            self.var.copy_(batch_var)
            self.count.fill_(n_b)
            return
        n = self.count
        total = n + n_b
        delta = batch_mean - self.mean
        self.mean.add_(delta * n_b / total)
        self.var.copy_((self.var * n + batch_var * n_b + delta * delta * n * n_b / total) / total)
        self.count.copy_(total)

    @property
    def std(self) -> torch.Tensor:
        return torch.sqrt(self.var + self.epsilon)

    def normalize(self, x: torch.Tensor) -> torch.Tensor:
        if not self.enabled:
            return x
        return ((x.double() - self.mean) / self.std).to(x.dtype)

    def denormalize(self, x: torch.Tensor) -> torch.Tensor:
        if not self.enabled:
            return x
        return (x.double() * self.std + self.mean).to(x.dtype)
