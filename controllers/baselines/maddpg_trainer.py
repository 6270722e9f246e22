"""The MADDPG training loop: collect, store, update, evaluate, checkpoint (one screen).

The algorithm and its sources are in :mod:`controllers.baselines.maddpg`; this module runs it
with the run folder, logs, evaluation and convergence rule of SDPA-MAPPO
(:mod:`controllers.mappo.trainer`).
"""

from __future__ import annotations

import time
from pathlib import Path

import torch
from tensordict import TensorDict
from tqdm import tqdm

from controllers.baselines.gasil import (
    Discriminator,
    GoodEpisodes,
    discriminator_step,
    imitation_bonus,
)
from controllers.baselines.maddpg import (
    MADDPGConfig,
    MADDPGResult,
    build_maddpg,
    maddpg_update,
    team_flags,
)
from controllers.mappo.checkpoint import CheckpointError, load_checkpoint, save_checkpoint
from controllers.mappo.evaluate import (
    ConvergenceTracker,
    evaluate,
    evaluation_due,
    write_json_atomic,
)
from controllers.mappo.logs import MetricsLog
from sim.files import atomic_path
from sim.provenance import provenance
from sim.torchrl_env import GROUP, FormationTorchRLEnv

STORED = [(GROUP, "observation"), (GROUP, "action"), ("next", GROUP, "observation"),
          ("next", GROUP, "reward"), ("next", GROUP, "done"), ("next", GROUP, "terminated")]
"""What a transition keeps in the replay buffer (the tokens are not read by MADDPG)."""
CHECKPOINT_EVERY = 1000
"""Episodes between checkpoints (and at the end, at convergence and on Ctrl-C): the replay
buffer goes with them, up to 400 MB for 10^6 transitions of three robots."""


class MADDPGTrainer:
    """The state of one MADDPG run; :meth:`run` trains until the budget or convergence."""

    def __init__(self, config: MADDPGConfig, run_dir: str | Path, *, resume: bool = False):
        from torchrl.collectors import Collector
        from torchrl.data import LazyTensorStorage, TensorDictReplayBuffer

        self.config = cfg = config
        self.run_dir = Path(run_dir)
        self.run_dir.mkdir(parents=True, exist_ok=True)
        if cfg.torch_threads:
            torch.set_num_threads(cfg.torch_threads)
        torch.manual_seed(cfg.seed)
        self.scenario = cfg.build_scenario()
        self.env = FormationTorchRLEnv(self.scenario, num_envs=cfg.num_envs, seed=cfg.seed)
        self.parts = build_maddpg(self.scenario, cfg, self.env.action_spec[GROUP, "action"])
        self.buffer = TensorDictReplayBuffer(storage=LazyTensorStorage(cfg.buffer_size), batch_size=cfg.batch_size)
        self.collector = Collector(self.env, self.parts.explore, total_frames=-1,
                                           frames_per_batch=cfg.num_envs * cfg.steps_per_collection,
                                           auto_register_policy_transforms=False)
        self.gasil = _Gasil(cfg, self.scenario.num_robots) if cfg.self_imitation else None
        self.tracker = ConvergenceTracker(cfg.success_threshold)
        self.episodes = self.env_steps = self.eval_count = self.last_eval_episodes = 0
        self.last_checkpoint_episodes = 0
        self.added_since_update = 0
        self.wall_time_s = 0.0
        self.train_log, self.eval_log = MetricsLog(self.run_dir, "train"), MetricsLog(self.run_dir, "eval")
        if resume:
            self._restore()
        else:
            self.train_log.truncate(0)
            self.eval_log.truncate(0)
            write_json_atomic(self.run_dir / "config.json", cfg.to_dict())
            write_json_atomic(self.run_dir / "run.json", provenance())

    # ---------------------------------------------------------------- loop
    def run(self) -> MADDPGResult:
        cfg = self.config
        bar = tqdm(total=cfg.total_episodes, initial=self.episodes, desc=f"{cfg.algo} {cfg.scenario_name}",
                   unit="ep")
        try:
            for data in self.collector:
                start = time.perf_counter()
                finished = int(data.get(("next", "done")).sum())
                self._store(data)
                losses = self._updates()
                self.episodes += finished
                self.env_steps += data.numel()
                self.parts.noise.step()
                self.wall_time_s += time.perf_counter() - start
                self._log(data, finished, losses)
                bar.update(finished)
                if evaluation_due(self.episodes, self.last_eval_episodes, cfg.eval_interval, cfg.num_envs):
                    self._evaluate()
                    bar.set_postfix(eval=self.tracker.success_rates[-1])
                done = self.episodes >= cfg.total_episodes or (
                    cfg.stop_at_convergence and self.tracker.converged_episode is not None)
                if done or self.episodes - self.last_checkpoint_episodes >= CHECKPOINT_EVERY:
                    self._checkpoint()
                if done:
                    break
        except KeyboardInterrupt:
            self._checkpoint()
            raise
        finally:
            bar.close()
            self.collector.shutdown()
        return self._finish()

    def _store(self, data: TensorDict) -> None:
        flat = team_flags(data, self.scenario.num_robots).reshape(-1).select(*STORED)
        self.buffer.extend(flat)
        self.added_since_update += flat.numel()
        if self.gasil is not None:
            self.gasil.record(data)

    def _updates(self) -> dict[str, float]:
        cfg, out = self.config, {}
        while self.added_since_update >= cfg.samples_per_update and len(self.buffer) >= cfg.batch_size:
            batch = self.buffer.sample()
            shaped = self.gasil.shape(batch) if self.gasil is not None else {}
            out = {**maddpg_update(self.parts, batch, cfg.max_grad_norm), **shaped}
            self.added_since_update -= cfg.samples_per_update
        return out

    def _log(self, data: TensorDict, finished: int, losses: dict[str, float]) -> None:
        reward = float(data.get(("next", GROUP, "reward")).mean())
        success = data.get(("next", GROUP, "success"))[..., 0, 0]
        done = data.get(("next", "done"))[..., 0]
        self.train_log.append({
            "episodes": self.episodes, "env_steps": self.env_steps, "wall_time_s": round(self.wall_time_s, 3),
            "reward_per_step": reward, "episodes_finished": finished,
            "success_rate": float(success[done].float().mean()) if finished else None,
            "loss_actor": losses.get("loss_actor"), "loss_value": losses.get("loss_value"),
            "loss_discriminator": losses.get("loss_discriminator"), "imitation_bonus": losses.get("imitation_bonus"),
            "good_episodes": len(self.gasil.good) if self.gasil is not None else None,
            "noise_sigma": float(self.parts.noise.sigma), "buffer": len(self.buffer)})

    def _evaluate(self) -> None:
        start = time.perf_counter()
        seed = 1_000_000 * (self.config.seed + 1) + 1_000 * self.eval_count
        result = evaluate(self.parts.actor, self.scenario, episodes=self.config.eval_episodes, seed=seed)
        converged = self.tracker.add(self.episodes, result.success_rate)
        self.eval_count += 1
        self.last_eval_episodes = self.episodes
        self.wall_time_s += time.perf_counter() - start
        measured = {k: getattr(result, k) for k in ("success_rate", "final_distance", "episode_return",
                                                     "robot_collisions", "object_collisions",
                                                     "wall_collisions", "collision_rate")}
        self.eval_log.append({"episodes": self.episodes, "env_steps": self.env_steps,
                              "wall_time_s": round(self.wall_time_s, 3), **measured,
                              "eval_seed": seed, "converged_episode": converged})

    # ---------------------------------------------------------- checkpoints
    def _checkpoint(self) -> None:
        parts = self.parts
        size = len(self.buffer)
        with atomic_path(self.run_dir / "replay.pt") as tmp:
            torch.save({"size": size, "data": self.buffer.storage[:size].to_dict() if size else {}}, tmp)
        save_checkpoint(self.run_dir / "checkpoint.pt", {
            "algo": self.config.algo, "config": self.config.to_dict(), "loss": parts.loss.state_dict(),
            "optimizers": {k: o.state_dict() for k, o in parts.optimizers.items()},
            "noise_sigma": float(parts.noise.sigma), "tracker": self.tracker.state_dict(),
            "counters": {"episodes": self.episodes, "env_steps": self.env_steps, "eval_count": self.eval_count,
                         "last_eval_episodes": self.last_eval_episodes, "wall_time_s": self.wall_time_s,
                         "added_since_update": self.added_since_update},
            "log_rows": {"train": len(self.train_log.read()), "eval": len(self.eval_log.read())},
            "gasil": self.gasil.state_dict() if self.gasil is not None else None,
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
        self.parts.loss.load_state_dict(data["loss"])
        for name, state in data["optimizers"].items():
            self.parts.optimizers[name].load_state_dict(state)
        self.parts.noise.sigma.fill_(data["noise_sigma"])
        self.tracker = ConvergenceTracker.from_state_dict(data["tracker"])
        for name, value in data["counters"].items():
            setattr(self, name, value)
        self.last_checkpoint_episodes = self.episodes
        torch.set_rng_state(data["rng"])
        if self.gasil is not None:
            self.gasil.load_state_dict(data["gasil"])
        replay = torch.load(self.run_dir / "replay.pt", map_location="cpu", weights_only=True)
        if replay["size"]:
            self.buffer.extend(TensorDict(replay["data"], batch_size=[replay["size"]]))
        self.train_log.truncate(data["log_rows"]["train"])
        self.eval_log.truncate(data["log_rows"]["eval"])

    def _finish(self) -> MADDPGResult:
        result = MADDPGResult(episodes=self.episodes, env_steps=self.env_steps, wall_time_s=self.wall_time_s,
                              converged_episode=self.tracker.converged_episode,
                              final_success_rate=self.tracker.success_rates[-1] if self.tracker.success_rates else None)
        write_json_atomic(self.run_dir / "result.json", {**result.__dict__, "algo": self.config.algo,
                                                         "provenance": provenance()})
        return result


class _Gasil:
    """GASIL's part of a run (:mod:`controllers.baselines.gasil`): the episodes in progress, the
    good episodes, the discriminator; the environments run in lock step (every episode is
    ``episode_steps`` long and they all start together), so one step index serves them all."""

    def __init__(self, config: MADDPGConfig, num_robots: int):
        self.weight = config.imitation_weight
        self.good = GoodEpisodes(config.good_episodes)
        self.discriminator = Discriminator(4 * num_robots + 2, config.hidden, config.depth)
        self.optimizer = torch.optim.Adam(self.discriminator.parameters(), lr=config.discriminator_lr)
        self._obs: list[torch.Tensor] = []
        self._action: list[torch.Tensor] = []
        self._return: torch.Tensor | None = None

    def record(self, data: TensorDict) -> None:
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

    def shape(self, batch: TensorDict) -> dict[str, float]:
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


__all__ = ["MADDPGTrainer"]
