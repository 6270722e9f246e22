r"""MADDPG (Lowe et al., NeurIPS 2017) on the formation task, built from TorchRL's pieces.

The paper's Table 1 compares SDPA-MAPPO with MADDPG-family methods; this is the MADDPG it
replaces, trained on the same world, reward, episode length, evaluation and convergence rule
(:mod:`controllers.mappo.evaluate`) as SDPA-MAPPO, so the episode counts compare.

**Networks** (TorchRL's :class:`~torchrl.modules.MultiAgentMLP`): one actor per robot on the
paper's flat observation ``o_i`` (:func:`sim.observations.flat`, ``(4N + 2,)``), ``a_i = a_max
tanh(mu_i(o_i))``; one centralised critic per robot, ``Q_i(o_1..o_N, a_1..a_N)``. Both 2 hidden
layers of 64 ReLU units (the MADDPG paper's).

**One update** (TorchRL's :class:`~torchrl.objectives.DDPGLoss` with the centralised critic,
TD(0) targets through target networks)::

    y_i      = r_i + gamma (1 - terminated) Q'_i(o', mu'(o'))      (time-limit ends bootstrap)
    L_Q      = mean_i (Q_i(o, a) - y_i)^2                           over a replay batch
    L_mu     = -mean_i Q_i(o, mu(o))                                (every robot's action from
                                                                     its current actor, as
                                                                     TorchRL's loss computes it)
    theta'  <- (1 - tau) theta' + tau theta                         (:class:`SoftUpdate`)

with Adam on each loss and gradient norms clipped to 0.5 (the MADDPG reference code).

**Data**: ``num_envs`` environments of :class:`sim.torchrl_env.FormationTorchRLEnv` collected by
:class:`~torchrl.collectors.Collector`, the actor's action plus Gaussian noise of
standard deviation ``sigma`` (annealed linearly from ``noise_start`` to ``noise_end`` times
``a_max`` over the run's first ``noise_anneal_episodes`` finished episodes, set after every
collection; :class:`~torchrl.modules.AdditiveGaussianModule`,
clipped to the action box), into a :class:`~torchrl.data.TensorDictReplayBuffer`; one update
per ``samples_per_update`` transitions added.

**Hyper-parameters** and their source (MADDPG paper, Appendix; its reference code): Adam, lr
0.01 (both networks), tau 0.01, gamma 0.95, batch 1024 transitions, buffer 10^6, an update every
100 samples added, 2 x 64 ReLU. The exploration noise is ours (the paper's continuous tasks use
Gumbel-softmax on discrete actions); it is the DDPG-style Gaussian, 0.3 -> 0.05 of ``a_max``.

Run directory: as :mod:`controllers.mappo.trainer` (``config.json``, ``run.json``,
``train.jsonl/.csv``, ``eval.jsonl/.csv``, ``checkpoint.pt``, ``result.json``). The checkpoint
keeps the networks, their targets, the optimisers, the noise level, the replay buffer and the
evaluation history: ``resume`` continues the run from there, every environment starting a fresh
episode (a resumed run is not bit-identical to an uninterrupted one).
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import torch
from tensordict import TensorDict
from tensordict.nn import TensorDictModule, TensorDictSequential
from torch import nn

from controllers.baselines.offpolicy import (
    BaselineConfigError,
    BaselineResult,
    OffPolicyTrainer,
    RunSettings,
)
from sim.scenario import Scenario
from sim.torchrl_env import GROUP

MADDPGConfigError = BaselineConfigError


@dataclass(frozen=True)
class MADDPGConfig(RunSettings):
    """Everything a MADDPG run depends on (module docstring for the sources); the fields every
    baseline shares are :class:`~controllers.baselines.offpolicy.RunSettings`'.

    Attributes:
        tau: target network step.
        actor_lr, critic_lr: Adam learning rates.
        hidden, depth: units and hidden layers of every network.
        max_grad_norm: gradient norm clip of each loss.
        noise_start, noise_end: exploration noise std as a fraction of ``accel_limit``.
        noise_anneal_episodes: episodes over which it falls from start to end.
        self_imitation: GASIL-MADDPG (:mod:`controllers.baselines.gasil`): the reward shaped by a
            discriminator between the run's best episodes and the policy's transitions.
        imitation_weight: GASIL's ``alpha``; good_episodes: its K; discriminator_lr: its Adam rate.
    """

    tau: float = 0.01
    actor_lr: float = 0.01
    critic_lr: float = 0.01
    hidden: int = 64
    depth: int = 2
    max_grad_norm: float = 0.5
    noise_start: float = 0.3
    noise_end: float = 0.05
    noise_anneal_episodes: int = 5_000
    self_imitation: bool = False
    imitation_weight: float = 0.1
    good_episodes: int = 100
    discriminator_lr: float = 3e-4

    def __post_init__(self) -> None:
        self.check(positive_ints=("total_episodes", "num_envs", "steps_per_collection", "buffer_size",
                                  "batch_size", "samples_per_update", "hidden", "depth", "noise_anneal_episodes",
                                  "eval_interval", "eval_episodes", "good_episodes"),
                   unit_interval=("gamma", "tau", "success_threshold"),
                   positive=("actor_lr", "critic_lr", "max_grad_norm", "discriminator_lr"))
        if self.imitation_weight < 0:
            raise MADDPGConfigError(f"{self.algo}.imitation_weight must be >= 0, got {self.imitation_weight!r}")
        if not 0 <= self.noise_end <= self.noise_start:
            raise MADDPGConfigError(f"{self.algo}.noise_end ({self.noise_end}) must be in [0, noise_start "
                                    f"({self.noise_start})]: the noise only anneals down")

    @property
    def algo(self) -> str:
        return "gasil-maddpg" if self.self_imitation else "maddpg"

    @classmethod
    def from_dict(cls, data: dict[str, Any]) -> MADDPGConfig:
        if data.get("algo") == "gasil-maddpg":
            data = {"self_imitation": True, **data}
        return cls(**cls.known_fields(data))


class BoundedActor(nn.Module):
    """Per-robot actors: ``(..., N, 4N + 2)`` flat observations -> ``(..., N, 2)`` accelerations
    ``a_max tanh(mu_i(o_i))``; ``obs_kind = "flat"``, so :func:`controllers.mappo.evaluate` and
    the ControlStack run it as they run the MLP-MAPPO actor."""

    obs_kind = "flat"

    def __init__(self, num_robots: int, accel_limit: float, hidden: int, depth: int):
        super().__init__()
        from torchrl.modules import MultiAgentMLP

        self.accel_limit = float(accel_limit)
        self.net = MultiAgentMLP(4 * num_robots + 2, 2, num_robots, centralized=False, share_params=False,
                                 depth=depth, num_cells=hidden, activation_class=nn.ReLU)

    def forward(self, obs: torch.Tensor, mask: torch.Tensor | None = None) -> torch.Tensor:
        return self.accel_limit * torch.tanh(self.net(obs))


class CentralCritic(nn.Module):
    """``Q_i(o_1..o_N, a_1..a_N)`` for every robot i: ``(..., N, 4N + 2)`` and ``(..., N, 2)`` ->
    ``(..., N, 1)``, one network per robot, each reading every robot's observation and action."""

    def __init__(self, num_robots: int, hidden: int, depth: int):
        super().__init__()
        from torchrl.modules import MultiAgentMLP

        self.net = MultiAgentMLP(4 * num_robots + 4, 1, num_robots, centralized=True, share_params=False,
                                 depth=depth, num_cells=hidden, activation_class=nn.ReLU)

    def forward(self, obs: torch.Tensor, action: torch.Tensor) -> torch.Tensor:
        return self.net(torch.cat([obs, action], dim=-1))


@dataclass
class MADDPGParts:
    """The TorchRL modules of one run (:func:`build_maddpg`)."""

    actor: BoundedActor
    critic: CentralCritic
    policy: TensorDictModule
    explore: TensorDictSequential
    noise: Any
    loss: Any
    target_update: Any
    optimizers: dict[str, torch.optim.Optimizer]


def build_maddpg(scenario: Scenario, config: MADDPGConfig, action_spec) -> MADDPGParts:
    """Actor, critic, exploration, loss, target updater and optimisers (module docstring)."""
    from torchrl.modules import AdditiveGaussianModule
    from torchrl.objectives import DDPGLoss, SoftUpdate, ValueEstimators

    n, a_max = scenario.num_robots, scenario.dynamics.accel_limit
    actor = BoundedActor(n, a_max, config.hidden, config.depth)
    critic = CentralCritic(n, config.hidden, config.depth)
    policy = TensorDictModule(actor, in_keys=[(GROUP, "observation")], out_keys=[(GROUP, "action")])
    value = TensorDictModule(critic, in_keys=[(GROUP, "observation"), (GROUP, "action")],
                             out_keys=[(GROUP, "state_action_value")])
    noise = AdditiveGaussianModule(spec=action_spec, sigma_init=config.noise_start * a_max,
                                   sigma_end=config.noise_end * a_max,
                                   annealing_num_steps=config.noise_anneal_episodes,   # set by episode:
                                   action_key=(GROUP, "action"))                       # noise_sigma()
    explore = TensorDictSequential(policy, noise)
    loss = DDPGLoss(actor_network=policy, value_network=value, delay_value=True, delay_actor=True,
                    loss_function="l2")
    loss.set_keys(state_action_value=(GROUP, "state_action_value"), reward=(GROUP, "reward"),
                  done=(GROUP, "done"), terminated=(GROUP, "terminated"))
    loss.make_value_estimator(ValueEstimators.TD0, gamma=config.gamma)
    target_update = SoftUpdate(loss, tau=config.tau)
    optimizers = {
        "loss_actor": torch.optim.Adam(loss.actor_network_params.flatten_keys().values(), lr=config.actor_lr),
        "loss_value": torch.optim.Adam(loss.value_network_params.flatten_keys().values(), lr=config.critic_lr),
    }
    return MADDPGParts(actor, critic, policy, explore, noise, loss, target_update, optimizers)


def noise_sigma(noise, episodes: int) -> float:
    """The exploration std after ``episodes`` finished episodes: linear from ``sigma_init`` to
    ``sigma_end`` over ``noise.annealing_num_steps`` (= ``noise_anneal_episodes``) episodes."""
    progress = min(1.0, episodes / noise.annealing_num_steps)
    start, end = float(noise.sigma_init), float(noise.sigma_end)
    return start + progress * (end - start)


def maddpg_update(parts: MADDPGParts, batch: TensorDict, max_grad_norm: float) -> dict[str, float]:
    """One critic and one actor step on a replay ``batch`` (module docstring), then the targets."""
    losses = parts.loss(batch)
    out = {}
    for name, optimizer in parts.optimizers.items():
        optimizer.zero_grad()
        losses[name].backward()
        params = [p for group in optimizer.param_groups for p in group["params"]]
        torch.nn.utils.clip_grad_norm_(params, max_grad_norm)
        optimizer.step()
        out[name] = float(losses[name].detach())
    parts.target_update.step()
    return out


class MADDPGAgent:
    """MADDPG (or GASIL-MADDPG) as the off-policy loop drives it (:class:`~controllers.baselines.offpolicy.Agent`)."""

    action_keys = [(GROUP, "action")]

    def __init__(self, scenario: Scenario, config: MADDPGConfig, action_spec):
        from controllers.baselines.gasil import SelfImitation

        self.config = config
        self.parts = build_maddpg(scenario, config, action_spec)
        self.explore, self.actor = self.parts.explore, self.parts.actor
        self.gasil = SelfImitation(config, scenario.num_robots) if config.self_imitation else None
        self.loss_names = ("loss_actor", "loss_value") + (
            ("loss_discriminator", "imitation_bonus") if self.gasil is not None else ())

    def record(self, data: TensorDict) -> None:
        if self.gasil is not None:
            self.gasil.record(data)

    def update(self, batch: TensorDict) -> dict[str, float]:
        shaped = self.gasil.shape(batch) if self.gasil is not None else {}
        return maddpg_update(self.parts, batch, self.config.max_grad_norm) | shaped

    def after_collection(self, episodes: int) -> None:
        """The noise for the run's ``episodes`` finished so far (:func:`noise_sigma`)."""
        self.parts.noise.sigma.fill_(noise_sigma(self.parts.noise, episodes))

    def log_row(self) -> dict[str, Any]:
        row = {"noise_sigma": float(self.parts.noise.sigma)}
        if self.gasil is not None:
            row["good_episodes"] = len(self.gasil.good)
        return row

    def state_dict(self) -> dict:
        parts = self.parts
        return {"loss": parts.loss.state_dict(), "noise_sigma": float(parts.noise.sigma),
                "optimizers": {k: o.state_dict() for k, o in parts.optimizers.items()},
                "gasil": self.gasil.state_dict() if self.gasil is not None else None}

    def load_state_dict(self, state: dict) -> None:
        self.parts.loss.load_state_dict(state["loss"])
        for name, optimizer_state in state["optimizers"].items():
            self.parts.optimizers[name].load_state_dict(optimizer_state)
        self.parts.noise.sigma.fill_(state["noise_sigma"])
        if self.gasil is not None:
            self.gasil.load_state_dict(state["gasil"])


def train_maddpg(config: MADDPGConfig, run_dir: str | Path, *, resume: bool = False,
                 on_iteration: Callable[[dict], None] | None = None) -> BaselineResult:
    """Train MADDPG or GASIL-MADDPG (or continue the run in ``run_dir``); returns the summary."""
    return OffPolicyTrainer(config, MADDPGAgent, run_dir, resume=resume).run(on_iteration)


__all__ = ["BoundedActor", "CentralCritic", "MADDPGAgent", "MADDPGConfig", "MADDPGConfigError", "MADDPGParts",
           "build_maddpg", "maddpg_update", "noise_sigma", "train_maddpg"]
