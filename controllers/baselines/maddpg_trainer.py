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
        bar = tqdm(total=cfg.total_episodes, initial=self.episodes, desc=f"MADDPG {cfg.scenario_name}", unit="ep")
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

    def _updates(self) -> dict[str, float]:
        cfg, out = self.config, {}
        while self.added_since_update >= cfg.samples_per_update and len(self.buffer) >= cfg.batch_size:
            out = maddpg_update(self.parts, self.buffer.sample(), cfg.max_grad_norm)
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
            "algo": "maddpg", "config": self.config.to_dict(), "loss": parts.loss.state_dict(),
            "optimizers": {k: o.state_dict() for k, o in parts.optimizers.items()},
            "noise_sigma": float(parts.noise.sigma), "tracker": self.tracker.state_dict(),
            "counters": {"episodes": self.episodes, "env_steps": self.env_steps, "eval_count": self.eval_count,
                         "last_eval_episodes": self.last_eval_episodes, "wall_time_s": self.wall_time_s,
                         "added_since_update": self.added_since_update},
            "log_rows": {"train": len(self.train_log.read()), "eval": len(self.eval_log.read())},
            "rng": torch.get_rng_state()})
        self.last_checkpoint_episodes = self.episodes

    def _restore(self) -> None:
        data = load_checkpoint(self.run_dir / "checkpoint.pt")
        if data.get("algo") != "maddpg":
            raise CheckpointError(f"{self.run_dir / 'checkpoint.pt'} is not a MADDPG checkpoint; resume it "
                                  "with the command that trained it")
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
        replay = torch.load(self.run_dir / "replay.pt", map_location="cpu", weights_only=True)
        if replay["size"]:
            self.buffer.extend(TensorDict(replay["data"], batch_size=[replay["size"]]))
        self.train_log.truncate(data["log_rows"]["train"])
        self.eval_log.truncate(data["log_rows"]["eval"])

    def _finish(self) -> MADDPGResult:
        result = MADDPGResult(episodes=self.episodes, env_steps=self.env_steps, wall_time_s=self.wall_time_s,
                              converged_episode=self.tracker.converged_episode,
                              final_success_rate=self.tracker.success_rates[-1] if self.tracker.success_rates else None)
        write_json_atomic(self.run_dir / "result.json", {**result.__dict__, "algo": "maddpg",
                                                         "provenance": provenance()})
        return result


__all__ = ["MADDPGTrainer"]
