r"""Deep Dyna-Q (Peng, Li, Li, Gao, Wong, ACL 2018) on the formation task: DQN with a learned
world model that supplies K planned transitions for every real one.

The paper's slowest baseline (Table 1: 40,000 episodes on three robots). Per robot, with
parameter sharing, on the paper's flat observation ``o_i`` (:func:`sim.observations.flat`).

**Action set** (the acceleration discretised, per robot): 9 actions, rest and ``a_max`` along the
8 compass directions ``k * 45 deg``: ``A = {(0, 0)} U {a_max (cos k pi/4, sin k pi/4), k = 0..7}``.

**Q-network** ``Q(o_i) -> R^9``, one network for every robot (2 x 64 ReLU), a target copy
``Q'`` replaced every ``target_interval`` updates; the TD target and loss (Huber)::

    y_i = r_i + gamma (1 - terminated) max_a Q'(o_i', a),      L = huber(Q(o_i, a_i) - y_i)

**World model** ``M(o_1..o_N, a_1..a_N) -> (o_1'..o_N', r_1..r_N)``: one MLP on the team (every
observation and one-hot action in, the change of every observation and every reward out,
2 x 128 ReLU), fitted by mean squared error to the replayed real transitions.

**One update** (one per ``samples_per_update`` real transitions): a model step and a Q step on a
real replay batch, then ``planning_steps`` (K) Q steps on planned batches: the batch's
observations, actions epsilon-greedy from ``Q``, next observations and rewards from ``M``
(never terminal: the task has no terminal state).

**Exploration**: epsilon-greedy, epsilon annealed linearly from ``epsilon_start`` to
``epsilon_end`` over the run's first ``epsilon_anneal_episodes`` finished episodes (the loop's
count, as ``total_episodes``), set after every collection.

**Hyper-parameters** and their source: K = 5 planning steps (the DDQ paper's DDQ(5), its main
setting), epsilon-greedy (0.1 in the paper's dialogue task, here annealed from 1.0 to 0.05 for
a task without a warm start), gamma 0.95, Adam 1e-3, batch 1024, buffer 10^6 and an update every
100 samples (as MADDPG here, so the two off-policy baselines see their data alike), the target
network replaced every 250 updates (DQN's periodic hard update, Mnih et al. 2015).
"""

from __future__ import annotations

import copy
import math
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import torch
from tensordict import TensorDict
from tensordict.nn import TensorDictModule
from torch import nn
from torch.nn import functional as F

from controllers.baselines.offpolicy import BaselineResult, OffPolicyTrainer, RunSettings
from sim.scenario import Scenario
from sim.torchrl_env import GROUP

NUM_ACTIONS = 9


def action_table(accel_limit: float) -> torch.Tensor:
    """(9, 2) the action set [m/s^2] (module docstring): rest, then the 8 compass directions."""
    angles = torch.arange(8, dtype=torch.float64) * math.pi / 4
    ring = accel_limit * torch.stack([torch.cos(angles), torch.sin(angles)], dim=-1)
    return torch.cat([torch.zeros(1, 2, dtype=torch.float64), ring]).to(torch.float32)


@dataclass(frozen=True)
class DDQConfig(RunSettings):
    """Everything a Deep Dyna-Q run depends on (module docstring for the sources); the fields every
    baseline shares are :class:`~controllers.baselines.offpolicy.RunSettings`'.

    Attributes:
        planning_steps: K, planned Q updates per real one.
        target_interval: updates between replacements of the target Q-network.
        lr: Adam rate of the Q-network; model_lr: of the world model.
        hidden: units of the Q-network's 2 hidden layers; model_hidden: of the world model's.
        epsilon_start, epsilon_end, epsilon_anneal_episodes: the exploration schedule.
    """

    total_episodes: int = 40_000
    lr: float = 1e-3
    model_lr: float = 1e-3
    hidden: int = 64
    model_hidden: int = 128
    planning_steps: int = 5
    target_interval: int = 250
    epsilon_start: float = 1.0
    epsilon_end: float = 0.05
    epsilon_anneal_episodes: int = 5_000

    def __post_init__(self) -> None:
        self.check(positive_ints=("total_episodes", "num_envs", "steps_per_collection", "buffer_size",
                                  "batch_size", "samples_per_update", "hidden", "model_hidden",
                                  "target_interval", "epsilon_anneal_episodes", "eval_interval", "eval_episodes"),
                   unit_interval=("gamma", "success_threshold", "epsilon_start"),
                   positive=("lr", "model_lr"))
        if not isinstance(self.planning_steps, int) or self.planning_steps < 0:
            raise self._error("planning_steps", "an integer >= 0 (0: plain DQN)")
        if not 0 <= self.epsilon_end <= self.epsilon_start:
            raise self._error("epsilon_end", f"in [0, epsilon_start ({self.epsilon_start})]")

    def _error(self, name: str, rule: str):
        from controllers.baselines.offpolicy import BaselineConfigError

        return BaselineConfigError(f"{self.algo}.{name} must be {rule}, got {getattr(self, name)!r}")

    @property
    def algo(self) -> str:
        return "ddq"

    @classmethod
    def from_dict(cls, data: dict[str, Any]) -> DDQConfig:
        return cls(**cls.known_fields(data))


def _mlp(inputs: int, hidden: int, outputs: int) -> nn.Sequential:
    return nn.Sequential(nn.Linear(inputs, hidden), nn.ReLU(), nn.Linear(hidden, hidden), nn.ReLU(),
                         nn.Linear(hidden, outputs))


class GreedyActor(nn.Module):
    """The evaluated policy: every robot's greedy action, ``(..., N, 4N + 2) -> (..., N, 2)``."""

    obs_kind = "flat"

    def __init__(self, q_net: nn.Module, table: torch.Tensor):
        super().__init__()
        self.q_net = q_net
        self.register_buffer("table", table)

    def forward(self, obs: torch.Tensor, mask: torch.Tensor | None = None) -> torch.Tensor:
        return self.table[self.q_net(obs).argmax(-1)]


class EpsilonGreedy(nn.Module):
    """The exploring policy: ``(..., N, D)`` -> (action index ``(..., N)``, acceleration ``(..., N, 2)``)."""

    def __init__(self, q_net: nn.Module, table: torch.Tensor, epsilon: float):
        super().__init__()
        self.q_net = q_net
        self.register_buffer("table", table)
        self.epsilon = float(epsilon)

    @torch.no_grad()
    def forward(self, obs: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        index = choose(self.q_net, obs, self.epsilon)
        return index, self.table[index]


def choose(q_net: nn.Module, obs: torch.Tensor, epsilon: float) -> torch.Tensor:
    """Epsilon-greedy action indices ``obs.shape[:-1]`` (long)."""
    greedy = q_net(obs).argmax(-1)
    explore = torch.rand(greedy.shape) < epsilon
    return torch.where(explore, torch.randint(NUM_ACTIONS, greedy.shape), greedy)


class WorldModel(nn.Module):
    """``M``: team observations ``(B, N, D)`` and action indices ``(B, N)`` -> next observations
    ``(B, N, D)`` and rewards ``(B, N, 1)`` (module docstring)."""

    def __init__(self, num_robots: int, obs_dim: int, hidden: int):
        super().__init__()
        self.n, self.d = num_robots, obs_dim
        self.net = _mlp(num_robots * (obs_dim + NUM_ACTIONS), hidden, num_robots * (obs_dim + 1))

    def forward(self, obs: torch.Tensor, index: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        b = obs.shape[0]
        x = torch.cat([obs, F.one_hot(index, NUM_ACTIONS).to(obs.dtype)], dim=-1).reshape(b, -1)
        out = self.net(x).reshape(b, self.n, self.d + 1)
        return obs + out[..., : self.d], out[..., self.d:]


class DDQAgent:
    """Deep Dyna-Q as the off-policy loop drives it (:class:`~controllers.baselines.offpolicy.Agent`)."""

    action_keys = [(GROUP, "action_index")]
    loss_names = ("loss_q", "loss_model", "loss_q_planned")

    def __init__(self, scenario: Scenario, config: DDQConfig, action_spec=None):
        n = scenario.num_robots
        self.config = config
        table = action_table(scenario.dynamics.accel_limit)
        self.q_net = _mlp(4 * n + 2, config.hidden, NUM_ACTIONS)
        self.target = copy.deepcopy(self.q_net).requires_grad_(False)
        self.model = WorldModel(n, 4 * n + 2, config.model_hidden)
        self.q_optimizer = torch.optim.Adam(self.q_net.parameters(), lr=config.lr)
        self.model_optimizer = torch.optim.Adam(self.model.parameters(), lr=config.model_lr)
        self.greedy = EpsilonGreedy(self.q_net, table, config.epsilon_start)
        self.explore = TensorDictModule(self.greedy, in_keys=[(GROUP, "observation")],
                                        out_keys=[(GROUP, "action_index"), (GROUP, "action")])
        self.actor = GreedyActor(self.q_net, table)
        self.updates = 0
        self.collections = 0

    # ------------------------------------------------------------------ Agent
    def record(self, data: TensorDict) -> None:
        """Nothing to follow between collections."""

    def update(self, batch: TensorDict) -> dict[str, float]:
        """A model step and a Q step on the real ``batch``, then K planned Q steps."""
        obs, index = batch.get((GROUP, "observation")), batch.get((GROUP, "action_index"))
        next_obs, reward = batch.get(("next", GROUP, "observation")), batch.get(("next", GROUP, "reward"))
        terminated = batch.get(("next", GROUP, "terminated")).to(reward.dtype)
        predicted_obs, predicted_reward = self.model(obs, index)
        loss_model = F.mse_loss(predicted_obs, next_obs) + F.mse_loss(predicted_reward, reward)
        self.model_optimizer.zero_grad()
        loss_model.backward()
        self.model_optimizer.step()
        loss_q = self.q_step(obs, index, reward, next_obs, terminated)
        planned = []
        for _ in range(self.config.planning_steps):
            with torch.no_grad():
                plan_index = choose(self.q_net, obs, self.greedy.epsilon)
                plan_next, plan_reward = self.model(obs, plan_index)
            planned.append(self.q_step(obs, plan_index, plan_reward, plan_next, torch.zeros_like(plan_reward)))
        return {"loss_q": loss_q, "loss_model": float(loss_model.detach()),
                "loss_q_planned": sum(planned) / len(planned) if planned else None}

    def q_step(self, obs, index, reward, next_obs, terminated) -> float:
        """One Adam step of the Huber TD loss (module docstring); the target copied when due."""
        with torch.no_grad():
            target = reward + self.config.gamma * (1 - terminated) * self.target(next_obs).max(-1, keepdim=True).values
        value = self.q_net(obs).gather(-1, index.unsqueeze(-1))
        loss = F.smooth_l1_loss(value, target)
        self.q_optimizer.zero_grad()
        loss.backward()
        self.q_optimizer.step()
        self.updates += 1
        if self.updates % self.config.target_interval == 0:
            self.target.load_state_dict(self.q_net.state_dict())
        return float(loss.detach())

    def after_collection(self, episodes: int) -> None:
        """Epsilon for the run's ``episodes`` finished so far (the schedule: module docstring)."""
        cfg = self.config
        self.collections += 1
        progress = min(1.0, episodes / cfg.epsilon_anneal_episodes)
        self.greedy.epsilon = cfg.epsilon_start + progress * (cfg.epsilon_end - cfg.epsilon_start)

    def log_row(self) -> dict[str, Any]:
        return {"epsilon": self.greedy.epsilon}

    def state_dict(self) -> dict:
        return {"q": self.q_net.state_dict(), "target": self.target.state_dict(), "model": self.model.state_dict(),
                "q_optimizer": self.q_optimizer.state_dict(), "model_optimizer": self.model_optimizer.state_dict(),
                "updates": self.updates, "collections": self.collections, "epsilon": self.greedy.epsilon}

    def load_state_dict(self, state: dict) -> None:
        self.q_net.load_state_dict(state["q"])
        self.target.load_state_dict(state["target"])
        self.model.load_state_dict(state["model"])
        self.q_optimizer.load_state_dict(state["q_optimizer"])
        self.model_optimizer.load_state_dict(state["model_optimizer"])
        self.updates, self.collections = int(state["updates"]), int(state["collections"])
        self.greedy.epsilon = float(state["epsilon"])


def train_ddq(config: DDQConfig, run_dir: str | Path, *, resume: bool = False,
              on_iteration: Callable[[dict], None] | None = None) -> BaselineResult:
    """Train Deep Dyna-Q (or continue the run in ``run_dir``); returns the summary."""
    return OffPolicyTrainer(config, DDQAgent, run_dir, resume=resume).run(on_iteration)


__all__ = ["NUM_ACTIONS", "DDQAgent", "DDQConfig", "EpsilonGreedy", "GreedyActor", "WorldModel", "action_table",
           "choose", "train_ddq"]
