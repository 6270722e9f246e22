r"""GASIL (Guo, Oh, Singh, Lee 2018, "Generative Adversarial Self-Imitation Learning") on MADDPG.

The paper's strongest baseline, GASIL-MADDPG: MADDPG (:mod:`controllers.baselines.maddpg`)
whose reward is shaped by a discriminator between the run's own best episodes and what the
current policy does, as GAIL does with an expert's:

* **Good episodes**: the ``good_episodes`` (K) episodes of highest team return (the mean over
  robots of the undiscounted return) seen so far, every step of every robot
  (:class:`GoodEpisodes`).
* **Discriminator** ``D(o_i, a_i) = sigmoid(f(o_i, a_i))``, one network shared by the robots (2 x
  64 ReLU), trained to tell the policy's transitions (label 1, drawn from the replay buffer)
  from the good episodes' (label 0): binary cross-entropy, Adam at ``discriminator_lr``, one step
  per MADDPG update on a batch of each.
* **Shaped reward** of every replayed transition, robot by robot::

      r_i' = r_i + alpha * min(-log D(o_i, a_i), 10)

  (``alpha`` = ``imitation_weight``): large where the pair looks like the good episodes. The
  MADDPG update then runs on ``r'`` unchanged.

Weights (stated as the issue asks): K = 100 episodes (12,800 steps of three robots), alpha =
0.1, discriminator lr 3e-4, the reward bonus capped at 10 (where ``D`` -> 0). The GASIL paper
combines its reward with PPO on MuJoCo with a buffer of the top 1,000-10,000 steps and an
imitation weight of 0.1-1; this is its off-policy form on MADDPG as in the SDPA-MAPPO paper's
reference, with K chosen so the good buffer holds ~1 % of a 10^6 replay.
"""

from __future__ import annotations

import torch
from torch import nn
from torch.nn import functional as F

from sim.torchrl_env import GROUP

BONUS_CAP = 10.0
"""Upper bound of ``-log D`` (module docstring): where D is ~0 the bonus would be unbounded."""


class GoodEpisodes:
    """The K episodes of highest team return, as tensors: observations ``(K, T, N, D)``,
    actions ``(K, T, N, 2)``, returns ``(K,)`` (module docstring)."""

    def __init__(self, capacity: int):
        self.capacity = int(capacity)
        self.obs: torch.Tensor | None = None
        self.action: torch.Tensor | None = None
        self.returns = torch.zeros(0)

    def __len__(self) -> int:
        return len(self.returns)

    def add(self, obs: torch.Tensor, action: torch.Tensor, returns: torch.Tensor) -> None:
        """Offer E finished episodes: ``obs`` (E, T, N, D), ``action`` (E, T, N, 2),
        ``returns`` (E,); keep the best ``capacity`` of those held and these."""
        if self.obs is not None:
            obs, action = torch.cat([self.obs, obs]), torch.cat([self.action, action])
            returns = torch.cat([self.returns, returns])
        keep = torch.argsort(returns, descending=True)[: self.capacity]
        self.obs, self.action, self.returns = obs[keep].clone(), action[keep].clone(), returns[keep].clone()

    def sample(self, size: int, generator: torch.Generator | None = None) -> tuple[torch.Tensor, torch.Tensor]:
        """``size`` robot-steps drawn uniformly: ``(obs (size, D), action (size, 2))``."""
        if self.obs is None:
            raise ValueError("no good episode yet: add finished episodes first")
        obs, action = self.obs.flatten(0, 2), self.action.flatten(0, 2)
        index = torch.randint(len(obs), (size,), generator=generator)
        return obs[index], action[index]

    def state_dict(self) -> dict:
        return {"capacity": self.capacity, "obs": self.obs, "action": self.action, "returns": self.returns}

    def load_state_dict(self, state: dict) -> None:
        self.capacity = int(state["capacity"])
        self.obs, self.action, self.returns = state["obs"], state["action"], state["returns"]


class Discriminator(nn.Module):
    """``f(o_i, a_i)``: the logit of "the current policy's, not a good episode's"; any leading
    shape, last dims ``D`` and ``2`` -> leading shape + ``(1,)``."""

    def __init__(self, obs_dim: int, hidden: int = 64, depth: int = 2):
        super().__init__()
        layers, width = [], obs_dim + 2
        for _ in range(depth):
            layers += [nn.Linear(width, hidden), nn.ReLU()]
            width = hidden
        self.net = nn.Sequential(*layers, nn.Linear(width, 1))

    def forward(self, obs: torch.Tensor, action: torch.Tensor) -> torch.Tensor:
        return self.net(torch.cat([obs, action], dim=-1))


def imitation_bonus(discriminator: Discriminator, obs: torch.Tensor, action: torch.Tensor) -> torch.Tensor:
    """``min(-log D(o, a), BONUS_CAP)`` with ``D = sigmoid(f)``: ``softplus(-f)``, shape of ``f``."""
    with torch.no_grad():
        return F.softplus(-discriminator(obs, action)).clamp(max=BONUS_CAP)


def discriminator_step(discriminator: Discriminator, optimizer: torch.optim.Optimizer,
                       policy: tuple[torch.Tensor, torch.Tensor], good: tuple[torch.Tensor, torch.Tensor]) -> float:
    """One Adam step of binary cross-entropy: the policy's pairs labelled 1, good ones 0."""
    logit_policy, logit_good = discriminator(*policy), discriminator(*good)
    loss = (F.binary_cross_entropy_with_logits(logit_policy, torch.ones_like(logit_policy))
            + F.binary_cross_entropy_with_logits(logit_good, torch.zeros_like(logit_good)))
    optimizer.zero_grad()
    loss.backward()
    optimizer.step()
    return float(loss.detach())


class SelfImitation:
    """GASIL's part of a run: the episodes in progress, the good episodes, the discriminator.
    The environments run in lock step (every episode is ``episode_steps`` long and they all
    start together), so one step index serves them all."""

    def __init__(self, config, num_robots: int):
        self.weight = config.imitation_weight
        self.good = GoodEpisodes(config.good_episodes)
        self.discriminator = Discriminator(4 * num_robots + 2, config.hidden, config.depth)
        self.optimizer = torch.optim.Adam(self.discriminator.parameters(), lr=config.discriminator_lr)
        self._obs: list[torch.Tensor] = []
        self._action: list[torch.Tensor] = []
        self._return: torch.Tensor | None = None

    def record(self, data) -> None:
        """Follow a collection ``(E, K)`` step by step; offer the episodes that end."""
        obs, action = data.get((GROUP, "observation")), data.get((GROUP, "action"))
        reward = data.get(("next", GROUP, "reward"))[..., 0].mean(-1)          # (E, K) team
        done = data.get(("next", "done"))[..., 0]
        for k in range(obs.shape[1]):
            self._obs.append(obs[:, k])
            self._action.append(action[:, k])
            self._return = reward[:, k] if self._return is None else self._return + reward[:, k]
            if done[:, k].any():
                if done[:, k].all():
                    self.good.add(torch.stack(self._obs, 1), torch.stack(self._action, 1), self._return)
                self._obs, self._action, self._return = [], [], None

    def shape(self, batch) -> dict[str, float]:
        """Add ``alpha * min(-log D, cap)`` to the batch's rewards; one discriminator step."""
        if not len(self.good):
            return {}
        obs, action = batch.get((GROUP, "observation")), batch.get((GROUP, "action"))
        bonus = imitation_bonus(self.discriminator, obs, action)                  # (B, N, 1)
        batch.set(("next", GROUP, "reward"), batch.get(("next", GROUP, "reward")) + self.weight * bonus)
        policy = (obs.flatten(0, 1), action.flatten(0, 1))
        loss = discriminator_step(self.discriminator, self.optimizer, policy, self.good.sample(len(policy[0])))
        return {"loss_discriminator": loss, "imitation_bonus": float(bonus.mean())}

    def state_dict(self) -> dict:
        return {"good": self.good.state_dict(), "discriminator": self.discriminator.state_dict(),
                "optimizer": self.optimizer.state_dict()}

    def load_state_dict(self, state: dict) -> None:
        self.good.load_state_dict(state["good"])
        self.discriminator.load_state_dict(state["discriminator"])
        self.optimizer.load_state_dict(state["optimizer"])


__all__ = ["BONUS_CAP", "Discriminator", "GoodEpisodes", "SelfImitation", "discriminator_step", "imitation_bonus"]
