"""Deterministic evaluation of a policy, and the convergence rule used by every report.

Convergence rule (one implementation, used everywhere):
    evaluate at least every ``eval_interval`` (50) training episodes, each time
    ``eval_episodes`` (100) deterministic episodes (mean action) from fresh random starts;
    the run has *converged* at the first evaluation with success rate >= ``threshold`` (0.9)
    whose next evaluation is also >= ``threshold``. The reported number is the training
    episode count at that first evaluation.
"""

from __future__ import annotations

import json
import math
from collections.abc import Sequence
from dataclasses import asdict, dataclass
from pathlib import Path

import torch
from torch import nn

from sim.batched_env import BatchedFormationEnv, reads
from sim.files import atomic_write_text
from sim.reward import RewardWeights
from sim.scenario import Scenario


def write_json_atomic(path: str | Path, data: dict) -> None:
    """Write ``data`` as JSON (no NaN) atomically (:func:`sim.files.atomic_path`)."""
    atomic_write_text(path, json.dumps(data, indent=2, allow_nan=False) + "\n")


@dataclass
class EvalResult:
    """Outcome of ``episodes`` deterministic episodes (means are over episodes).

    success_rate: fraction of episodes with every robot within tolerance at the end and no
        collision; final_distance: mean assigned robot-target distance at the end [m];
    episode_return: undiscounted return (mean over robots); robot/object/wall_collisions:
        collision onsets per episode; collision_rate: fraction of episodes with any collision.
    """

    scenario: str
    num_robots: int
    episodes: int
    seed: int
    success_rate: float
    final_distance: float
    episode_return: float
    robot_collisions: float
    object_collisions: float
    wall_collisions: float
    collision_rate: float

    def to_dict(self) -> dict:
        return asdict(self)

    def save_json(self, path: str | Path) -> None:
        write_json_atomic(path, self.to_dict())


@torch.no_grad()
def evaluate(actor: nn.Module, scenario: Scenario, *, episodes: int = 100, seed: int = 0,
             device: str | torch.device = "cpu", batch_size: int = 1000,
             reward_weights: RewardWeights = RewardWeights()) -> EvalResult:
    """Run ``episodes`` episodes of ``scenario`` with the actor's mean action.

    Episodes run ``batch_size`` at a time in :class:`sim.batched_env.BatchedFormationEnv`
    from fresh jittered starts drawn with ``seed``. Works with eager and TorchScript actors
    that have ``obs_kind`` (``"tokens"`` or ``"flat"``). ``reward_weights`` only changes the
    reported return; success, distance and collisions do not depend on it.
    """
    if not isinstance(episodes, int) or episodes < 1:
        raise ValueError(f"episodes must be a positive integer, got {episodes!r}")
    was_training = actor.training
    actor.eval()
    totals: dict[str, float] = {k: 0.0 for k in ("success", "final_distance", "episode_return",
                                                  "robot_collisions", "object_collisions",
                                                  "wall_collisions", "collided")}
    done_episodes, chunk = 0, 0
    try:
        while done_episodes < episodes:
            e = min(batch_size, episodes - done_episodes)
            env = BatchedFormationEnv(scenario, e, seed=seed + 7919 * chunk, device=device,
                                      reward_weights=reward_weights, **reads(actor))
            obs, mask = env.reset()
            for _ in range(env.episode_steps):
                result = env.step(actor(obs, mask))
                obs, mask = result.obs, result.mask
            f = result.finished
            if len(f) != e:
                raise RuntimeError(f"expected {e} episodes to end after {env.episode_steps} steps, "
                                   f"got {len(f)}")
            collisions = f.robot_collisions + f.object_collisions + f.wall_collisions
            totals["success"] += float(f.success.float().sum())
            totals["final_distance"] += float(f.final_distance.sum())
            totals["episode_return"] += float(f.episode_return.sum())
            totals["robot_collisions"] += float(f.robot_collisions.float().sum())
            totals["object_collisions"] += float(f.object_collisions.float().sum())
            totals["wall_collisions"] += float(f.wall_collisions.float().sum())
            totals["collided"] += float((collisions > 0).float().sum())
            done_episodes += e
            chunk += 1
    finally:
        actor.train(was_training)
    mean = {k: v / episodes for k, v in totals.items()}
    return EvalResult(scenario=scenario.name, num_robots=scenario.num_robots, episodes=episodes,
                      seed=seed, success_rate=mean["success"], final_distance=mean["final_distance"],
                      episode_return=mean["episode_return"], robot_collisions=mean["robot_collisions"],
                      object_collisions=mean["object_collisions"], wall_collisions=mean["wall_collisions"],
                      collision_rate=mean["collided"])


def converged_episode(episodes: Sequence[int], success_rates: Sequence[float],
                      threshold: float = 0.9) -> int | None:
    """The convergence rule (module docstring): ``episodes[k]`` of the first evaluation k with
    ``success_rates[k] >= threshold`` and ``success_rates[k + 1] >= threshold``; else None."""
    if len(episodes) != len(success_rates):
        raise ValueError("episodes and success_rates must have the same length")
    for k in range(len(success_rates) - 1):
        if success_rates[k] >= threshold and success_rates[k + 1] >= threshold:
            return int(episodes[k])
    return None


def evaluation_due(episodes: int, last_eval_episodes: int, interval: int, episodes_per_batch: int) -> bool:
    """Whether to evaluate now so that evaluations are at most ``interval`` episodes apart.

    Episodes finish ``episodes_per_batch`` at a time, so waiting for the next batch is allowed
    only while it would still land within ``interval`` of the last evaluation.
    """
    since = episodes - last_eval_episodes
    return since > 0 and since + episodes_per_batch > interval


@dataclass
class ConvergenceTracker:
    """Evaluation history of one run and its convergence episode (see :func:`converged_episode`)."""

    threshold: float = 0.9
    episodes: list[int] | None = None
    success_rates: list[float] | None = None

    def __post_init__(self) -> None:
        self.episodes = list(self.episodes or [])
        self.success_rates = list(self.success_rates or [])

    def add(self, episodes: int, success_rate: float) -> int | None:
        """Record an evaluation; returns the convergence episode once the rule is met."""
        if not math.isfinite(success_rate):
            raise ValueError(f"success_rate must be finite, got {success_rate!r}")
        self.episodes.append(int(episodes))
        self.success_rates.append(float(success_rate))
        return self.converged_episode

    @property
    def converged_episode(self) -> int | None:
        return converged_episode(self.episodes, self.success_rates, self.threshold)

    def state_dict(self) -> dict:
        return {"threshold": self.threshold, "episodes": list(self.episodes),
                "success_rates": list(self.success_rates)}

    @classmethod
    def from_state_dict(cls, state: dict) -> ConvergenceTracker:
        return cls(float(state["threshold"]), list(state["episodes"]), list(state["success_rates"]))
