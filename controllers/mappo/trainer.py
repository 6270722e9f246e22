"""MAPPO training loop (CleanRL-style, top to bottom), with parameter sharing across robots.

One iteration::

    rollout   S steps of E environments: a ~ N(actor(o), exp(log_std)^2) per robot,
              V(o) from the centralised critic (de-normalised); with ``team_sizes``, of E
              environments per team size (controllers.mappo.rollout), minibatches of one size
    GAE       advantages and returns per robot (controllers.mappo.losses.compute_gae)
    update    update_epochs x num_minibatches Adam steps over (step, env) pairs, each holding
              the whole team: clipped surrogate - ent_coef * entropy (actor),
              vf_coef * value loss on normalised returns (critic), gradient norm clipping
    evaluate  when due (at least every eval_interval episodes): eval_episodes deterministic
              episodes on fresh starts; the convergence rule of controllers.mappo.evaluate
    schedule  both learning rates x lr_after_success while the last evaluation succeeded
              (x (1 - episodes / total) too with anneal_lr); with policy_ema the averaged
              actor is the one evaluated and saved as the policy

Profile (paper-3, defaults, one torch thread, 2-core machine, 2026-12-01; 12 iterations without
evaluation, ``_update`` timed as ``bench/train_speed.py`` times it for ``update_share``, which
in its 48-episode runs, two evaluations included, reads 81 %): 186 ms per training episode, of which the PPO update is
168 ms (90 %: 10 epochs x 4 minibatches of 128 team samples, ~17 ms per forward + backward of
actor and critic), the rollout and GAE 18 ms, and the evaluation (100 episodes every 50) 7 ms.
The world itself is ~0.1 ms of an episode. So the update's small attention kernels set the cost;
fewer, larger Adam steps (``update_epochs``, ``num_minibatches``) are the lever that changes it.
Kernels tried on one minibatch (2026-12-04, same machine, one thread): in the whole update a step
costs 23.0 ms with SDPA, 36.7 with the attention as explicit matmuls and 27.2 with one query and
the key/value projections absorbed; actor + critic forward and backward alone, alternating in one
process, 17.9 ms with SDPA and 17.3 as elementwise products; ``torch.compile`` (inductor) 20.0
against 17.4 eager, after 40 s of compiling. The step is its matmuls (~6 ms at the 77 GFLOP/s
MKL gives here) and memory-bound passes over (B, T, D) tensors, not kernel-call overhead.
A team-level critic (each environment's 2N+1 entities embedded once, self-attention among them,
robots' values read off their entities) was tried too (2026-12-04, 128 teams of 3, forward and
backward, same process): 8.5 ms against 9.8 for the attention critic, because CPU
flash attention costs ~1.6 ms a backward call at these sizes whatever the row count (the math
backend: 9.3 against 12.3). Not worth a change of what the critic learns from.
The update's arithmetic (``bench/train_speed.py``, 2026-12-07, AMD EPYC): 4.4 GFLOP a training
episode on paper-3 and 10.3 on paper-5, 20-30x MLP-MAPPO's; at the best matrix-product rate of
the machine (93 GFLOP/s, one thread) that alone is 0.048 and 0.111 s an episode, and the update
measured runs at 19-26 % of that rate.

Run directory: ``config.json``, ``run.json`` (git commit, package versions, torch threads, host:
:func:`sim.provenance.provenance`; a resumed run keeps the record before it under
``before_resume``), ``train.jsonl/.csv`` (one row per iteration),
``eval.jsonl/.csv`` (one row per evaluation), ``checkpoint.pt`` (latest), ``result.json`` (at the
end, with the same provenance).
"""

from __future__ import annotations

import copy
import math
import time
from collections.abc import Callable
from dataclasses import asdict, dataclass
from pathlib import Path

import torch
from tqdm import tqdm

from controllers.mappo.checkpoint import (
    CheckpointError,
    actor_from_state,
    checkpoint_config,
    critic_from_state,
    env_state_dict,
    load_checkpoint,
    load_env_state,
    policy_state,
    save_checkpoint,
    shrink_perturb,
)
from controllers.mappo.config import RESUMABLE_CHANGES, MAPPOConfig, TrainConfigError
from controllers.mappo.evaluate import (
    ConvergenceTracker,
    evaluate,
    evaluation_due,
    write_json_atomic,
)
from controllers.mappo.logs import MetricsLog, TensorBoardLog
from controllers.mappo.losses import (
    ValueNormalizer,
    clipped_surrogate_loss,
    compute_gae,
    explained_variance,
    value_loss,
)
from controllers.mappo.rollout import TeamGroup, collect
from controllers.policy import build_actor, build_critic, gaussian_entropy, gaussian_log_prob
from sim.batched_env import BatchedFormationEnv
from sim.files import read_config
from sim.provenance import provenance

CHECKPOINT_NAME = "checkpoint.pt"


@dataclass
class TrainResult:
    """Summary of a run (also written to ``result.json``)."""

    run_dir: str
    converged_episode: int | None
    episodes: int
    iterations: int
    env_steps: int
    wall_time_s: float
    last_eval: dict | None
    checkpoint: str

    def to_dict(self) -> dict:
        return asdict(self)


def train(config: MAPPOConfig, run_dir: str | Path, *, resume: bool = False,
          on_iteration: Callable[[dict], None] | None = None) -> TrainResult:
    """Train (or, with ``resume``, continue the run in ``run_dir``) and return the summary;
    ``on_iteration`` (if given) gets each iteration's log row once it is logged and any checkpoint
    due is written (a sweep reports there, which is where its scheduler can stop the run)."""
    return MAPPOTrainer(config, run_dir, resume=resume).run(on_iteration)


class MAPPOTrainer:
    """The state of one run; :meth:`run` trains until the budget or convergence."""

    def __init__(self, config: MAPPOConfig, run_dir: str | Path, *, resume: bool = False):
        self.config = cfg = config
        self.run_dir = Path(run_dir)
        self.run_dir.mkdir(parents=True, exist_ok=True)
        if cfg.torch_threads:
            torch.set_num_threads(cfg.torch_threads)
        self.device = torch.device(cfg.device)
        self.scenario = cfg.build_scenario()
        self.num_robots = self.scenario.num_robots
        self.accel_limit = self.scenario.dynamics.accel_limit

        torch.manual_seed(cfg.seed)
        self.actor = build_actor(cfg.actor, self.num_robots, self.accel_limit).to(self.device)
        self.critic = build_critic(cfg.critic, self.num_robots).to(self.device)
        self.value_norm = ValueNormalizer(cfg.value_norm).to(self.device)
        self.transferred_from: str | None = None
        if cfg.init_from and not resume:
            self._transfer(cfg.init_from)
        self.policy = copy.deepcopy(self.actor).requires_grad_(False) if cfg.policy_ema else self.actor
        # the fused kernel: one call per step instead of one per tensor (7x faster for these nets)
        fused = self.device.type in ("cpu", "cuda")
        self.actor_optimizer = torch.optim.Adam(self.actor.parameters(), lr=cfg.lr, eps=1e-5, fused=fused)
        self.critic_optimizer = torch.optim.Adam(self.critic.parameters(), lr=cfg.critic_lr or cfg.lr, eps=1e-5,
                                                 fused=fused)
        self.sampler = torch.Generator(device=self.device).manual_seed(cfg.seed + 1)

        self.reward_weights = cfg.build_reward_weights()
        self.scenarios = cfg.build_team_scenarios()        # one per team size trained on
        distribution = cfg.build_distribution()
        self.groups = [TeamGroup.start(BatchedFormationEnv(sc, cfg.num_envs, seed=cfg.seed + 7919 * k,
                                                           device=self.device, obs=cfg.obs_kind,
                                                           reward_weights=self.reward_weights,
                                                           distribution=distribution,
                                                           own_target=cfg.actor.own_target))
                       for k, sc in enumerate(self.scenarios)]
        self.arrival_rate = 0.0     # running fraction of training episodes ending on target
        self.iteration = self.episodes = self.env_steps = self.eval_count = self.last_eval_episodes = 0
        self.wall_time_s = 0.0
        self.tracker = ConvergenceTracker(cfg.success_threshold)
        self.last_eval: dict | None = None
        self.train_log = MetricsLog(self.run_dir, "train")
        self.eval_log = MetricsLog(self.run_dir, "eval")
        self.scalars = TensorBoardLog(self.run_dir) if cfg.tensorboard else None
        if resume:
            self._resume()
        elif (self.run_dir / CHECKPOINT_NAME).exists():
            raise TrainConfigError(f"run_dir {str(self.run_dir)!r} already holds a run; resume it "
                                   "(resume=True) or choose an empty directory")
        elif self.train_log.read() or self.eval_log.read():   # stopped before its first checkpoint:
            self.train_log.truncate(0)                        # nothing to resume, so it starts over
            self.eval_log.truncate(0)
        write_json_atomic(self.run_dir / "config.json", cfg.to_dict())
        self.provenance = provenance()
        if resume and (self.run_dir / "run.json").exists():   # the run so far came from elsewhere, maybe
            self.provenance["before_resume"] = read_config(self.run_dir / "run.json", "run.json")
        write_json_atomic(self.run_dir / "run.json", self.provenance)

    # ------------------------------------------------------------------ main loop
    def run(self, on_iteration: Callable[[dict], None] | None = None) -> TrainResult:
        cfg = self.config
        bar = tqdm(total=cfg.total_episodes, initial=self.episodes, unit="ep", disable=not cfg.progress,
                   dynamic_ncols=True, desc=f"MAPPO {cfg.scenario_name}"
                   + (f" N={','.join(map(str, cfg.team_sizes))}" if cfg.team_sizes else ""))
        shown = {"ret": "-", "succ": "-"}      # training return and success of the last finished batch
        try:
            if self.eval_count == 0:
                self._evaluate()
            while self.episodes < cfg.total_episodes and not self._stop():
                before = self.episodes
                row = self._iteration()
                bar.update(self.episodes - before)
                if evaluation_due(self.episodes, self.last_eval_episodes, cfg.eval_interval,
                                  cfg.num_envs * len(self.groups)):
                    self._evaluate()
                if self.iteration % cfg.checkpoint_interval == 0:
                    self.save()
                if row["episodes_finished"]:
                    shown = {"ret": _fmt(row["return_mean"]), "succ": _fmt(row["success_rate"])}
                bar.set_postfix(**shown, eval=_fmt(self.last_eval["success_rate"] if self.last_eval else None),
                                refresh=False)
                if on_iteration is not None:
                    on_iteration(row)
        finally:
            bar.close()
            if self.scalars is not None:
                self.scalars.close()
        self.save()
        result = TrainResult(run_dir=str(self.run_dir), converged_episode=self.tracker.converged_episode,
                             episodes=self.episodes, iterations=self.iteration, env_steps=self.env_steps,
                             wall_time_s=round(self.wall_time_s, 3), last_eval=self.last_eval,
                             checkpoint=str(self.run_dir / CHECKPOINT_NAME))
        write_json_atomic(self.run_dir / "result.json",
                          {**result.to_dict(), "transferred_from": self.transferred_from,
                           "evaluations": self.tracker.state_dict(), "provenance": self.provenance})
        return result

    def _stop(self) -> bool:
        return self.config.stop_at_convergence and self.tracker.converged_episode is not None

    def _iteration(self) -> dict:
        cfg = self.config
        start = time.perf_counter()
        scale = max(0.0, 1.0 - self.episodes / cfg.total_episodes) if cfg.anneal_lr else 1.0
        if self.last_eval is not None and self.last_eval["success_rate"] >= cfg.success_threshold:
            scale *= cfg.lr_after_success
        for opt, lr in ((self.actor_optimizer, cfg.lr), (self.critic_optimizer, cfg.critic_lr or cfg.lr)):
            opt.param_groups[0]["lr"] = scale * lr

        rollouts = [collect(g, self.actor, self.critic, self.value_norm, cfg.rollout_steps, self.sampler,
                            cfg.bootstrap_from == "final") for g in self.groups]
        # Episodes end only by the time limit, which the observation does not show: bootstrap
        # the final step from V of its own observation ("last") or of the state it ended in ("final")
        gae = [compute_gae(r.rewards, r.values, r.dones, r.next_values, cfg.gamma, cfg.gae_lambda,
                           truncation_values=r.final_values if cfg.bootstrap_time_limit else None)
               for r in rollouts]
        self.value_norm.update(torch.cat([returns.reshape(-1) for _, returns in gae]))
        stats = self._update([r.flat(adv, self.value_norm.normalize(ret), self.value_norm.normalize(r.values))
                              for r, (adv, ret) in zip(rollouts, gae, strict=True)])
        if self.policy is not self.actor:
            self._average_policy()

        finished = [f for r in rollouts for f in r.finished]
        self.iteration += 1
        self.env_steps += cfg.rollout_steps * cfg.num_envs * len(self.groups)
        episodes_now = sum(len(f) for f in finished)
        if episodes_now:
            arrived = float(torch.cat([f.arrived for f in finished]).float().mean())
            self._set_arrival_rate(self.arrival_rate + 0.25 * (arrived - self.arrival_rate))
        self.episodes += episodes_now
        self.wall_time_s += time.perf_counter() - start
        values = torch.cat([r.values.reshape(-1) for r in rollouts])
        returns = torch.cat([ret.reshape(-1) for _, ret in gae])
        row = {"iteration": self.iteration, "episodes": self.episodes, "env_steps": self.env_steps,
               "wall_time_s": round(self.wall_time_s, 3), "episodes_finished": episodes_now,
               **_episode_summary(finished),
               "reward_mean": float(torch.cat([r.rewards.reshape(-1) for r in rollouts]).mean()),
               "explained_variance": explained_variance(values, returns),
               "action_std": float(self.actor.log_std.detach().exp().mean()),
               "lr": self.actor_optimizer.param_groups[0]["lr"], "penalty_scale": self.groups[0].env.penalty_scale,
               **stats}
        self.train_log.append(row)
        if self.scalars is not None:
            self.scalars.add("train", row)
        return row

    def _minibatches(self, batches: list[dict]) -> list[tuple[dict, torch.Tensor]]:
        """One epoch's minibatches: each group's (step, env) samples split ``num_minibatches``
        ways in a fresh random order (teams stay whole); several groups take turns at random."""
        out = []
        for batch in batches:
            b = batch["obs"].shape[0]
            order = torch.randperm(b, generator=self.sampler, device=self.device)
            out += [(batch, idx) for idx in order.split(math.ceil(b / self.config.num_minibatches))]
        if len(batches) > 1:
            out = [out[k] for k in torch.randperm(len(out), generator=self.sampler).tolist()]
        return out

    def _update(self, batches: list[dict]) -> dict:
        """PPO epochs over the rollouts of every group (:meth:`_minibatches`)."""
        cfg = self.config
        sums = {"policy_loss": 0.0, "value_loss": 0.0, "entropy": 0.0, "approx_kl": 0.0, "clipfrac": 0.0}
        steps = 0
        for _ in range(cfg.update_epochs):
            kl_epoch = []
            for flat, idx in self._minibatches(batches):
                mb_mask = None if flat["mask"] is None else flat["mask"][idx]
                mean = self.actor(flat["obs"][idx], mb_mask)
                new_log_prob = gaussian_log_prob(flat["actions"][idx], mean, self.actor.log_std)
                log_ratio = new_log_prob - flat["old_log_probs"][idx]
                adv = flat["advantages"][idx]
                if cfg.norm_adv and adv.numel() > 1:
                    adv = (adv - adv.mean()) / (adv.std() + 1e-8)
                pg_loss = clipped_surrogate_loss(new_log_prob, flat["old_log_probs"][idx], adv, cfg.clip_coef)
                entropy = gaussian_entropy(self.actor.log_std)
                v_loss = value_loss(self.critic(flat["obs"][idx], mb_mask), flat["old_values"][idx],
                                    flat["returns"][idx], cfg.value_clip)
                self.actor_optimizer.zero_grad(set_to_none=True)
                self.critic_optimizer.zero_grad(set_to_none=True)
                (pg_loss - cfg.ent_coef * entropy + cfg.vf_coef * v_loss).backward()
                torch.nn.utils.clip_grad_norm_(self.actor.parameters(), cfg.max_grad_norm)
                torch.nn.utils.clip_grad_norm_(self.critic.parameters(), cfg.max_grad_norm)
                self.actor_optimizer.step()
                self.critic_optimizer.step()
                with torch.no_grad():
                    ratio = log_ratio.exp()
                    approx_kl = float(((ratio - 1) - log_ratio).mean())
                    sums["clipfrac"] += float(((ratio - 1).abs() > cfg.clip_coef).float().mean())
                kl_epoch.append(approx_kl)
                sums["policy_loss"] += float(pg_loss.detach())
                sums["value_loss"] += float(v_loss.detach())
                sums["entropy"] += float(entropy.detach())
                sums["approx_kl"] += approx_kl
                steps += 1
            if cfg.target_kl is not None and sum(kl_epoch) / len(kl_epoch) > cfg.target_kl:
                break
        return {k: v / steps for k, v in sums.items()}

    def _set_arrival_rate(self, rate: float) -> None:
        """Record the running arrival rate and set the contact-penalty curriculum from it."""
        self.arrival_rate = rate
        for group in self.groups:
            group.env.penalty_scale = 1.0 + self.config.penalty_curriculum * rate

    @torch.no_grad()
    def _average_policy(self) -> None:
        """``policy <- ema * policy + (1 - ema) * actor``, parameters and buffers."""
        weight = 1.0 - self.config.policy_ema
        for avg, new in zip(self.policy.state_dict().values(), self.actor.state_dict().values(), strict=True):
            if avg.is_floating_point():
                avg.lerp_(new, weight)
            else:
                avg.copy_(new)

    # ------------------------------------------------------------ evaluation
    def eval_seed(self, index: int) -> int:
        """Seed of evaluation ``index``: fresh starts each time, reproducible per run."""
        return 1_000_000 * (self.config.seed + 1) + 1_000 * index

    def _evaluate(self) -> None:
        """``eval_episodes`` deterministic episodes per team size; with several sizes the run's
        success rate is the worst size's (every size must meet the convergence rule), the other
        numbers are means over sizes, and each size's success rate is kept (``success_rate_n<N>``)."""
        cfg = self.config
        start = time.perf_counter()
        seed = self.eval_seed(self.eval_count)
        results = [evaluate(self.policy, sc, episodes=cfg.eval_episodes, seed=seed, device=self.device,
                            reward_weights=self.reward_weights) for sc in self.scenarios]
        success = min(r.success_rate for r in results)
        converged = self.tracker.add(self.episodes, success)
        self.eval_count += 1
        self.last_eval_episodes = self.episodes
        self.wall_time_s += time.perf_counter() - start

        def mean(name: str) -> float:
            return sum(getattr(r, name) for r in results) / len(results)

        self.last_eval = {"iteration": self.iteration, "episodes": self.episodes, "env_steps": self.env_steps,
                          "wall_time_s": round(self.wall_time_s, 3), "success_rate": success,
                          "final_distance": mean("final_distance"), "episode_return": mean("episode_return"),
                          "robot_collisions": mean("robot_collisions"),
                          "object_collisions": mean("object_collisions"),
                          "wall_collisions": mean("wall_collisions"), "collision_rate": mean("collision_rate"),
                          "eval_seed": seed, "converged_episode": converged}
        if len(results) > 1:
            self.last_eval.update({f"success_rate_n{sc.num_robots}": r.success_rate
                                   for sc, r in zip(self.scenarios, results, strict=True)})
        self.eval_log.append(self.last_eval)
        if self.scalars is not None:
            self.scalars.add("eval", self.last_eval)

    # ------------------------------------------------------------ checkpoints
    def save(self, path: str | Path | None = None) -> Path:
        path = Path(path) if path is not None else self.run_dir / CHECKPOINT_NAME
        save_checkpoint(path, {
            "num_robots": self.num_robots, "scenario": self.config.scenario_name, "accel_limit": self.accel_limit,
            "config": self.config.to_dict(),
            "actor": self.actor.state_dict(), "policy": self.policy.state_dict(), "critic": self.critic.state_dict(),
            "value_norm": self.value_norm.state_dict(),
            "actor_optimizer": self.actor_optimizer.state_dict(),
            "critic_optimizer": self.critic_optimizer.state_dict(),
            "counters": {"iteration": self.iteration, "episodes": self.episodes, "env_steps": self.env_steps,
                         "eval_count": self.eval_count, "last_eval_episodes": self.last_eval_episodes,
                         "wall_time_s": self.wall_time_s, "arrival_rate": self.arrival_rate},
            "convergence": self.tracker.state_dict(), "last_eval": self.last_eval,
            "transferred_from": self.transferred_from,
            "rng": {"sampler": self.sampler.get_state()}, "env_state": _env_states(self.groups),
        })
        return path

    def _resume(self) -> None:
        if not (self.run_dir / CHECKPOINT_NAME).exists():
            raise TrainConfigError(f"cannot resume {str(self.run_dir)!r}: it holds no checkpoint yet (one is "
                                   f"written every checkpoint_interval = {self.config.checkpoint_interval} "
                                   "iterations); start it again without resume, in the same directory")
        data = load_checkpoint(self.run_dir / CHECKPOINT_NAME)
        saved = checkpoint_config(data)
        mine, theirs = self.config.to_dict(), saved.to_dict()
        ignored = set(RESUMABLE_CHANGES) - ({"total_episodes"} if self.config.anneal_lr else set())
        for key in mine:
            if key not in ignored and mine[key] != theirs[key]:
                raise TrainConfigError(f"cannot resume: config field {key!r} is {mine[key]!r} here but "
                                       f"{theirs[key]!r} in the checkpoint; use the run's config.json "
                                       f"(only {sorted(ignored)} may change)")
        self.actor.load_state_dict(data["actor"])
        if self.policy is not self.actor:
            self.policy.load_state_dict(data.get("policy", data["actor"]))
        self.critic.load_state_dict(data["critic"])
        self.value_norm.load_state_dict(data["value_norm"])
        self.actor_optimizer.load_state_dict(data["actor_optimizer"])
        self.critic_optimizer.load_state_dict(data["critic_optimizer"])
        c = data["counters"]
        self.iteration, self.episodes, self.env_steps = c["iteration"], c["episodes"], c["env_steps"]
        self.eval_count, self.last_eval_episodes = c["eval_count"], c["last_eval_episodes"]
        self.wall_time_s = c["wall_time_s"]
        self._set_arrival_rate(float(c.get("arrival_rate", 0.0)))
        self.tracker = ConvergenceTracker.from_state_dict(data["convergence"])
        self.last_eval = data["last_eval"]
        self.transferred_from = data["transferred_from"]
        self.sampler.set_state(data["rng"]["sampler"])
        # one state per team group (the config check above made the groups the checkpoint's)
        states = data["env_state"] if isinstance(data["env_state"], list) else [data["env_state"]]
        for group, state in zip(self.groups, states, strict=True):
            load_env_state(group.env, state)
            group.obs, group.mask = group.env.observe()
        self.train_log.truncate(self.iteration)
        self.eval_log.truncate(self.eval_count)

    def _transfer(self, path: str) -> None:
        """Start from the actor, critic and value statistics of an M-robot checkpoint."""
        data = load_checkpoint(path)
        source = checkpoint_config(data)
        mine, theirs = self.config.actor.to_dict(), source.actor.to_dict()
        # every setting the source network computes with (init_log_std only starts a fresh one;
        # token_layers may grow, below): the actor is rebuilt from the source's settings
        for key in ("variant", "embed_dim", "num_heads", "embed_hidden", "hidden_sizes", "input_scale",
                    "velocity_damping", "frame", "own_target"):
            if mine[key] != theirs[key]:
                raise CheckpointError(f"init_from: actor.{key} is {theirs[key]!r} in {path!r} but {mine[key]!r} "
                                      "here; use the source run's actor settings")
        if self.config.critic.to_dict() != source.critic.to_dict():
            raise CheckpointError(f"init_from: the critic settings of {path!r} differ from this run's; "
                                  "use the source run's critic settings")
        if mine["token_layers"] < theirs["token_layers"]:
            raise CheckpointError(f"init_from: {path!r} has actor.token_layers={theirs['token_layers']}; this run "
                                  f"needs at least as many (it adds identity blocks, it cannot drop trained ones)")
        m = int(data["num_robots"])
        fresh_actor, fresh_critic = self.actor, self.critic
        self.actor = actor_from_state(source.actor, policy_state(data), m, self.num_robots,
                                      accel_limit=self.accel_limit, seed=self.config.seed).to(self.device)
        if mine["token_layers"] > theirs["token_layers"]:     # new blocks start as the identity
            state = {**fresh_actor.state_dict(), **self.actor.state_dict()}
            self.actor = copy.deepcopy(fresh_actor)
            self.actor.load_state_dict(state)
        self.critic = critic_from_state(source.critic, data["critic"], m, self.num_robots).to(self.device)
        shrink_perturb(self.actor, fresh_actor, self.config.init_keep)
        shrink_perturb(self.critic, fresh_critic, self.config.init_keep)
        if source.value_norm == self.config.value_norm:
            self.value_norm.load_state_dict(data["value_norm"])
        self.transferred_from = str(path)


def _env_states(groups: list[TeamGroup]) -> dict | list[dict]:
    """The checkpoint's environment state: one dict (one team size, as before) or one per group."""
    states = [env_state_dict(g.env) for g in groups]
    return states[0] if len(states) == 1 else states


def _episode_summary(finished: list) -> dict:
    """Means over the episodes that ended in an iteration (None when none ended)."""
    keys = ("return_mean", "success_rate", "final_distance", "collision_rate")
    if not finished:
        return dict.fromkeys(keys)
    ret = torch.cat([f.episode_return for f in finished])
    success = torch.cat([f.success for f in finished]).float()
    dist = torch.cat([f.final_distance for f in finished])
    coll = torch.cat([(f.robot_collisions + f.object_collisions + f.wall_collisions) > 0 for f in finished])
    return dict(zip(keys, (float(ret.mean()), float(success.mean()), float(dist.mean()),
                           float(coll.float().mean())), strict=True))


def _fmt(x: float | None) -> str:
    return "-" if x is None else f"{x:.3g}"
