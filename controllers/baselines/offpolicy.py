"""The off-policy training loop of the baselines: collect, store, update, evaluate, checkpoint.

One loop for every baseline (MADDPG, GASIL-MADDPG, Deep Dyna-Q): the algorithm is an *agent*
(:class:`Agent`: what explores, what is evaluated, one update on a replay batch, its state), the
loop gives it the run folder, logs, evaluation and convergence rule of SDPA-MAPPO
(:mod:`controllers.mappo.trainer`)::

    for each collection of steps_per_collection steps of num_envs environments (TorchRL Collector,
                                                   the agent's exploring policy):
        store the transitions (the agent's keys)   in a TensorDictReplayBuffer
        one agent update per samples_per_update transitions added (a replay batch each)
        when due: evaluate the agent's actor (controllers.mappo.evaluate: the convergence rule)
        every CHECKPOINT_EVERY episodes, at the end and on Ctrl-C: checkpoint.pt + replay.pt
"""

from __future__ import annotations

import math
import time
import warnings
from collections.abc import Callable
from dataclasses import asdict, dataclass, fields
from pathlib import Path
from typing import Any, Protocol

import torch
from tensordict import TensorDict
from tqdm import tqdm

from controllers.mappo.checkpoint import CheckpointError, load_checkpoint, save_checkpoint
from controllers.mappo.evaluate import (
    ConvergenceTracker,
    evaluate,
    evaluation_due,
    write_json_atomic,
)
from controllers.mappo.logs import MetricsLog
from sim.files import atomic_path
from sim.interrupts import caused_by_interrupt
from sim.provenance import provenance
from sim.scenario import Scenario, ScenarioError, scenario_from
from sim.torchrl_env import GROUP, FormationTorchRLEnv

TRANSITION = [(GROUP, "observation"), ("next", GROUP, "observation"), ("next", GROUP, "reward"),
              ("next", GROUP, "done"), ("next", GROUP, "terminated")]
"""What every stored transition keeps besides the agent's action keys (no tokens: the baselines
read the flat observation)."""
CHECKPOINT_EVERY = 1000
"""Episodes between checkpoints (and at the end, at convergence and on Ctrl-C): the replay
buffer goes with them, up to 400 MB for 10^6 transitions of three robots."""


class BaselineConfigError(ValueError):
    """A baseline setting that cannot work; the message names the field and the fix."""


class RunDirError(BaselineConfigError, CheckpointError):
    """A run folder that already holds a run, started again without resume (MAPPO's refusal;
    a :class:`CheckpointError` too, so ``formation train`` reports it and exits 2)."""


@dataclass(frozen=True)
class RunSettings:
    """What every baseline config shares: its fields below, its ``algo`` name in ``to_dict``,
    field checks that name ``<algo>.<field>``. Subclasses are frozen dataclasses.

    Attributes:
        scenario: preset name, transport-N, a scenario file (kept as its content) or dict.
        seed: seeds torch, the environments and the evaluations.
        total_episodes: training budget in episodes (every environment's episode counts).
        num_envs: environments collected side by side.
        steps_per_collection: steps of every environment per collection.
        buffer_size: replay capacity [transitions]; batch_size: transitions per update.
        samples_per_update: one update per this many transitions added.
        gamma: discount.
        eval_interval, eval_episodes, success_threshold: the convergence rule's
            (:mod:`controllers.mappo.evaluate`, as SDPA-MAPPO).
        stop_at_convergence: end the run when the rule is met.
        torch_threads: intra-op threads (0: leave torch's default).
    """

    scenario: str | dict = "paper-3"
    seed: int = 0
    total_episodes: int = 25_000
    num_envs: int = 32
    steps_per_collection: int = 25
    buffer_size: int = 1_000_000
    batch_size: int = 1024
    samples_per_update: int = 100
    gamma: float = 0.95
    eval_interval: int = 50
    eval_episodes: int = 100
    success_threshold: float = 0.9
    stop_at_convergence: bool = True
    torch_threads: int = 1

    @property
    def algo(self) -> str:
        raise NotImplementedError

    def check(self, positive_ints: tuple[str, ...], unit_interval: tuple[str, ...],
              positive: tuple[str, ...]) -> None:
        prefix = self.algo
        for f in fields(self):
            value = getattr(self, f.name)
            if f.type in ("int", "float") and (isinstance(value, bool) or not isinstance(value, int | float)
                                               or not math.isfinite(value)):
                raise BaselineConfigError(f"{prefix}.{f.name} must be a finite number, got {value!r}")
            if f.type == "bool" and not isinstance(value, bool):
                raise BaselineConfigError(f"{prefix}.{f.name} must be true or false, got {value!r}")
        for name in positive_ints:
            if not isinstance(getattr(self, name), int) or getattr(self, name) < 1:
                raise BaselineConfigError(f"{prefix}.{name} must be a positive integer, got {getattr(self, name)!r}")
        for name in unit_interval:
            if not 0 < getattr(self, name) <= 1:
                raise BaselineConfigError(f"{prefix}.{name} must be in (0, 1], got {getattr(self, name)!r}")
        for name in positive:
            if getattr(self, name) <= 0:
                raise BaselineConfigError(f"{prefix}.{name} must be > 0, got {getattr(self, name)!r}")
        if self.batch_size > self.buffer_size:
            raise BaselineConfigError(f"{prefix}.batch_size ({self.batch_size}) must not exceed buffer_size "
                                      f"({self.buffer_size})")
        if isinstance(self.scenario, str) and self.scenario.endswith((".json", ".toml")):
            object.__setattr__(self, "scenario", self.build_scenario().to_dict())   # the file's content
        self.build_scenario()

    def build_scenario(self) -> Scenario:
        """The run's scenario."""
        try:
            return scenario_from(self.scenario)
        except (ScenarioError, TypeError, ValueError) as exc:
            raise BaselineConfigError(f"{self.algo}.scenario: {exc}") from None

    @property
    def scenario_name(self) -> str:
        return self.build_scenario().name

    def to_dict(self) -> dict[str, Any]:
        return {"algo": self.algo, **asdict(self)}

    @classmethod
    def known_fields(cls, data: dict[str, Any]) -> dict[str, Any]:
        """``data`` without its ``algo``; unknown fields refused by name."""
        data = {k: v for k, v in data.items() if k != "algo"}
        known = {f.name for f in fields(cls)}
        unknown = sorted(set(data) - known)
        if unknown:
            raise BaselineConfigError(f"unknown {cls.__name__} field(s) {unknown}; known: {sorted(known)}")
        return data


class Agent(Protocol):
    """An off-policy algorithm as the loop drives it.

    Attributes:
        explore: TensorDictModule the collector runs: ``(GROUP, "observation")`` -> the action keys.
        actor: ``nn.Module`` ``(E, N, 4N + 2) -> (E, N, 2)`` with ``obs_kind = "flat"``: the
            deterministic policy that is evaluated.
        action_keys: what the replay buffer keeps of the action (besides :data:`TRANSITION`).
        loss_names: the keys of :meth:`update`'s answer, logged per collection (None until the
            first update).

    ``after_collection(episodes)`` follows each collection with the run's episodes finished so
    far (the loop's count, the unit of ``total_episodes``): exploration schedules run on it.
    """

    explore: Any
    actor: Any
    action_keys: list
    loss_names: tuple[str, ...]

    def record(self, data: TensorDict) -> None: ...
    def update(self, batch: TensorDict) -> dict[str, float]: ...
    def after_collection(self, episodes: int) -> None: ...
    def log_row(self) -> dict[str, Any]: ...
    def state_dict(self) -> dict: ...
    def load_state_dict(self, state: dict) -> None: ...


@dataclass
class BaselineResult:
    episodes: int
    env_steps: int
    wall_time_s: float
    converged_episode: int | None
    final_success_rate: float | None


def team_flags(data: TensorDict, num_robots: int) -> TensorDict:
    """Copy the env's ``("next", "done"/"terminated")`` (..., 1) to every robot,
    ``("next", GROUP, ...)`` (..., N, 1), where per-robot value targets read them."""
    for key in ("done", "terminated"):
        flag = data.get(("next", key))
        data.set(("next", GROUP, key), flag.unsqueeze(-2).expand(*flag.shape[:-1], num_robots, 1).clone())
    return data


class OffPolicyTrainer:
    """The state of one baseline run; :meth:`run` trains until the budget or convergence.

    ``make_agent(scenario, config, action_spec)`` builds the :class:`Agent` (after the seed is set).
    """

    def __init__(self, config, make_agent, run_dir: str | Path, *, resume: bool = False):
        from torchrl.collectors import Collector
        from torchrl.data import LazyTensorStorage, TensorDictReplayBuffer

        self.config = cfg = config
        self.run_dir = Path(run_dir)
        self.run_dir.mkdir(parents=True, exist_ok=True)
        if not resume and (self.run_dir / "checkpoint.pt").exists():      # as MAPPOTrainer
            raise RunDirError(f"run_dir {str(self.run_dir)!r} already holds a run; resume it "
                              "(resume=True) or choose an empty directory")
        if cfg.torch_threads:
            torch.set_num_threads(cfg.torch_threads)
        torch.manual_seed(cfg.seed)
        self.scenario = cfg.build_scenario()
        self.env = FormationTorchRLEnv(self.scenario, num_envs=cfg.num_envs, seed=cfg.seed)
        self.agent: Agent = make_agent(self.scenario, cfg, self.env.action_spec[GROUP, "action"])
        self.stored = TRANSITION + list(self.agent.action_keys)
        self.buffer = TensorDictReplayBuffer(storage=LazyTensorStorage(cfg.buffer_size), batch_size=cfg.batch_size)
        self.collector = Collector(self.env, self.agent.explore, total_frames=-1,
                                   frames_per_batch=cfg.num_envs * cfg.steps_per_collection,
                                   auto_register_policy_transforms=False)
        self.tracker = ConvergenceTracker(cfg.success_threshold)
        self.episodes = self.env_steps = self.eval_count = self.last_eval_episodes = 0
        self.last_checkpoint_episodes = 0
        self.added_since_update = 0
        self.wall_time_s = 0.0
        self.train_log, self.eval_log = MetricsLog(self.run_dir, "train"), MetricsLog(self.run_dir, "eval")
        if resume:
            self._restore()
        else:                  # at most a run stopped before its first checkpoint: it starts over
            self.train_log.truncate(0)
            self.eval_log.truncate(0)
            write_json_atomic(self.run_dir / "config.json", cfg.to_dict())
            write_json_atomic(self.run_dir / "run.json", provenance())

    # ---------------------------------------------------------------- loop
    def run(self, on_iteration: Callable[[dict], None] | None = None) -> BaselineResult:
        """Train until the budget or convergence; ``on_iteration`` (if given) gets each
        collection's log row once it is logged and any checkpoint due is written."""
        cfg = self.config
        bar = tqdm(total=cfg.total_episodes, initial=self.episodes, desc=f"{cfg.algo} {cfg.scenario_name}",
                   unit="ep")
        clock = time.perf_counter()
        try:
            for data in self.collector:
                finished = int(data.get(("next", "done")).sum())
                self._store(data)
                losses = self._updates()
                self.episodes += finished
                self.env_steps += data.numel()
                self.agent.after_collection(self.episodes)
                now = time.perf_counter()              # collection, updates and evaluations
                self.wall_time_s, clock = self.wall_time_s + now - clock, now
                row = self._log(data, finished, losses)
                bar.update(finished)
                if evaluation_due(self.episodes, self.last_eval_episodes, cfg.eval_interval, cfg.num_envs):
                    self._evaluate()
                    bar.set_postfix(eval=self.tracker.success_rates[-1])
                done = self.episodes >= cfg.total_episodes or (
                    cfg.stop_at_convergence and self.tracker.converged_episode is not None)
                if done or self.episodes - self.last_checkpoint_episodes >= CHECKPOINT_EVERY:
                    self._checkpoint()
                if on_iteration is not None:
                    on_iteration(row)
                if done:
                    break
        except BaseException as exc:    # a Ctrl-C may surface as another error (sim.interrupts)
            if caused_by_interrupt(exc):
                self._checkpoint()
            raise
        finally:
            bar.close()
            self.collector.shutdown()
        return self._finish()

    def _store(self, data: TensorDict) -> None:
        flat = team_flags(data, self.scenario.num_robots).reshape(-1).select(*self.stored)
        self.buffer.extend(flat)
        self.added_since_update += flat.numel()
        self.agent.record(data)

    def _updates(self) -> dict[str, float]:
        cfg, out = self.config, {}
        while self.added_since_update >= cfg.samples_per_update and len(self.buffer) >= cfg.batch_size:
            out = self.agent.update(self.buffer.sample())
            self.added_since_update -= cfg.samples_per_update
        return out

    def _log(self, data: TensorDict, finished: int, losses: dict[str, float]) -> dict:
        reward = float(data.get(("next", GROUP, "reward")).mean())
        success = data.get(("next", GROUP, "success"))[..., 0, 0]
        done = data.get(("next", "done"))[..., 0]
        row = {"episodes": self.episodes, "env_steps": self.env_steps, "wall_time_s": round(self.wall_time_s, 3),
               "reward_per_step": reward, "episodes_finished": finished,
               "success_rate": float(success[done].float().mean()) if finished else None}
        row |= {name: losses.get(name) for name in self.agent.loss_names}
        row |= self.agent.log_row() | {"buffer": len(self.buffer)}
        self.train_log.append(row)
        return row

    def _evaluate(self) -> None:
        seed = 1_000_000 * (self.config.seed + 1) + 1_000 * self.eval_count
        result = evaluate(self.agent.actor, self.scenario, episodes=self.config.eval_episodes, seed=seed,
                          reward_weights=self.env.world.reward_weights)     # the reward it trains on
        converged = self.tracker.add(self.episodes, result.success_rate)
        self.eval_count += 1
        self.last_eval_episodes = self.episodes
        measured = {k: getattr(result, k) for k in ("success_rate", "final_distance", "episode_return",
                                                     "robot_collisions", "object_collisions",
                                                     "wall_collisions", "collision_rate")}
        self.eval_log.append({"episodes": self.episodes, "env_steps": self.env_steps,
                              "wall_time_s": round(self.wall_time_s, 3), **measured,
                              "eval_seed": seed, "converged_episode": converged})

    # ---------------------------------------------------------- checkpoints
    def _checkpoint(self) -> None:
        size = len(self.buffer)
        with atomic_path(self.run_dir / "replay.pt") as tmp:
            torch.save({"size": size, "data": self.buffer.storage[:size].to_dict() if size else {},
                        "writer": self.buffer.writer.state_dict()}, tmp)     # the cursor: the oldest slot
        save_checkpoint(self.run_dir / "checkpoint.pt", {
            "algo": self.config.algo, "config": self.config.to_dict(), "agent": self.agent.state_dict(),
            "tracker": self.tracker.state_dict(),
            "counters": {"episodes": self.episodes, "env_steps": self.env_steps, "eval_count": self.eval_count,
                         "last_eval_episodes": self.last_eval_episodes, "wall_time_s": self.wall_time_s,
                         "added_since_update": self.added_since_update},
            "log_rows": {"train": len(self.train_log.read()), "eval": len(self.eval_log.read())},
            "rng": torch.get_rng_state()})
        self.last_checkpoint_episodes = self.episodes

    def _restore(self) -> None:
        data = load_checkpoint(self.run_dir / "checkpoint.pt")
        if data.get("algo") != self.config.algo:
            raise CheckpointError(f"{self.run_dir / 'checkpoint.pt'} is not a {self.config.algo} checkpoint "
                                  f"({data.get('algo')}); resume it with the command that trained it")
        saved = dict(data["config"])
        ours = self.config.to_dict()
        changed = sorted(k for k in ours if k not in ("total_episodes", "stop_at_convergence") and ours[k] != saved.get(k))
        if changed:
            raise CheckpointError(f"--resume with a different configuration ({', '.join(changed)}); only "
                                  "total_episodes and stop_at_convergence may change")
        self.agent.load_state_dict(data["agent"])
        self.tracker = ConvergenceTracker.from_state_dict(data["tracker"])
        for name, value in data["counters"].items():
            setattr(self, name, value)
        self.last_checkpoint_episodes = self.episodes
        torch.set_rng_state(data["rng"])
        replay = torch.load(self.run_dir / "replay.pt", map_location="cpu", weights_only=True)
        if replay["size"]:
            self.buffer.extend(TensorDict(replay["data"], batch_size=[replay["size"]]))
        if "writer" in replay:          # the next transitions replace the oldest, as they would have
            self.buffer.writer.load_state_dict(replay["writer"])
        elif replay["size"] >= self.config.buffer_size:
            warnings.warn(f"{self.run_dir / 'replay.pt'} predates the saved write cursor: the full replay "
                          "buffer's age order is unknown, so the next transitions replace slots from 0 on, "
                          "not necessarily the oldest", stacklevel=2)
        self.train_log.truncate(data["log_rows"]["train"])
        self.eval_log.truncate(data["log_rows"]["eval"])

    def _finish(self) -> BaselineResult:
        result = BaselineResult(episodes=self.episodes, env_steps=self.env_steps, wall_time_s=self.wall_time_s,
                                converged_episode=self.tracker.converged_episode,
                                final_success_rate=self.tracker.success_rates[-1] if self.tracker.success_rates
                                else None)
        write_json_atomic(self.run_dir / "result.json", {**asdict(result), "algo": self.config.algo,
                                                         "provenance": provenance()})
        return result


__all__ = ["CHECKPOINT_EVERY", "TRANSITION", "Agent", "BaselineConfigError", "BaselineResult",
           "OffPolicyTrainer", "RunDirError", "RunSettings", "team_flags"]
