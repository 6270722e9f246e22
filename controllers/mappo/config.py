"""The one configuration of a MAPPO run (saved beside every run and inside every checkpoint)."""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass, field
from typing import Any

from controllers.policy.config import (
    ActorConfig,
    CriticConfig,
    PolicyConfigError,
    dataclass_from_dict,
    is_number,
)

TRAINING_REWARD = {"w_dist": 0.0, "w_assigned": 1.0, "assignment_power": 2.0, "w_arrive": 0.5,
                   "w_own_arrive": 0.5, "w_onset": 2.0, "detour_clearance": 0.03, "contact_margin": 0.01}


def user_fields(fields: dict[str, Any]) -> dict[str, Any]:
    """What a user writes (``formation train --config``, a sweep's grid) -> MAPPOConfig fields:
    an MLP actor gets the MLP critic unless a critic is given, and ``reward_weights`` given
    change the weights of :data:`TRAINING_REWARD` they name and keep the others."""
    out = dict(fields)
    if isinstance(out.get("actor"), dict) and out["actor"].get("variant") == "mlp":
        out.setdefault("critic", {"variant": "mlp"})
    if isinstance(out.get("reward_weights"), dict):
        out["reward_weights"] = {**TRAINING_REWARD, **out["reward_weights"]}
    return out


class TrainConfigError(PolicyConfigError):
    """A training configuration that cannot run; the message names the field and the fix."""


@dataclass(frozen=True)
class MAPPOConfig:
    """MAPPO with parameter sharing: one actor and one critic for all robots.

    Counting: every finished parallel episode counts (``num_envs`` environments finishing =
    ``num_envs`` episodes); ``env_steps`` counts environment steps (one per environment).

    Attributes:
        scenario: preset name for :func:`sim.scenario.make_scenario` (``paper-3``, ``transport-N``...)
            or a full scenario as a dict (:meth:`sim.scenario.Scenario.to_dict`).
        actor, critic: the networks (:class:`ActorConfig`, :class:`CriticConfig`).
        reward_weights: overrides of :class:`sim.reward.RewardWeights` fields (e.g.
            ``{"w_object": 2.0}``) for training and evaluation; ``{}`` keeps the plain defaults.
            The default (:data:`TRAINING_REWARD`) is the shaping that learns paper-3: per-robot
            distance to the assigned target instead of the nearest-target cover (which has a
            local optimum with two robots on one target) with the assignment of least squared
            distance (the linear one ties when robots queue, and the leader then blocks the
            follower's target), a larger arrival bonus and one per robot
            on its own target (the team bonus alone left robots stopping short), a one-off cost
            per new contact, a detour path 3 cm off the object and penalties that count a gap
            under 1 cm as contact (a policy trained on exact contact grazes the object).
        team_sizes: train one policy on several team sizes at once (e.g. ``[3, 4, 5]``): the
            training world holds ``num_envs`` environments per size, side by side
            (:mod:`controllers.mappo.rollout`), of the scenario's layout for that many robots
            (:meth:`sim.scenario.Scenario.with_robots`; the scenario itself for its own N), and
            every evaluation runs ``eval_episodes`` per size, its success rate the worst
            size's. Needs networks that run any N (``actor.variant`` typed, ``critic.variant``
            attention). ``[]``: the scenario's own N only.
        distribution: ranges each training episode's layout and actuator are drawn from
            (:class:`sim.distribution.ScenarioDistribution`: object size, offset and shape, the
            formation's direction, start jitter, actuator gain, lag and command delay): a name of
            :data:`sim.distribution.DISTRIBUTIONS` (``"broad"``), a .json/.toml file or a dict,
            stored resolved (a dict). Each group of ``num_envs`` environments (one per team
            size) draws a layout whenever its episodes restart, each environment its actuator.
            Evaluations (and so convergence) stay on the scenario's own layouts.
            None: the scenario as it is.
        num_envs: parallel environments E of the training world (per team size).
        rollout_steps: steps per environment between updates (S); a rollout holds S * E * N
            robot transitions.
        gamma: discount per step (dt = 0.05 s).
        gae_lambda: GAE lambda.
        bootstrap_time_limit: treat the end of an episode (always the 128-step time limit) as a
            truncation and bootstrap its last step from a value estimate; False treats it as
            terminal (then the value depends on the time left, which no robot observes).
        bootstrap_from: that estimate: ``"final"``, V(o_{t+1}) of the state the episode ended
            in (the world reports it before resetting: the textbook target), or ``"last"``,
            V(o_t) of the step's own observation, one step early. paper-3, seeds 0-4 (every one
            converged in both): episodes to convergence 1488, 912, 480, 1440, 1104 (median 1104)
            with "final", 1104, 528, 384, 960, 1200 (median 960) with "last", the default. With
            gamma = 0.99 the two targets differ by one step of a slowly changing value; the
            difference looks like seed noise, but it is not in the right direction, so "last"
            stays.
        clip_coef: PPO ratio clip epsilon (the paper's Equation (1)).
        value_clip: clip of the value update (PPO2), or None for the plain squared error.
        ent_coef: weight of the entropy bonus.
        vf_coef: weight of the value loss.
        lr: Adam learning rate of the actor (1e-3 swings between grazing the object and not).
        critic_lr: Adam learning rate of the critic (None: ``lr``).
        anneal_lr: decay both rates linearly to 0 over ``total_episodes``.
        lr_after_success: multiply both rates by this while the last evaluation's success rate
            is >= ``success_threshold`` (1: off; default 0.2). The deterministic policy of this task is on a
            knife edge (a path 1 cm off the object succeeds in every episode, one on it in none),
            so full-size updates after a success often undo it: smaller steps keep a good
            policy while the stochastic one goes on improving.
        update_epochs: passes over each rollout.
        num_minibatches: minibatches per pass (split over (step, env) pairs, all robots of a
            team stay together because the critic is centralised).
        max_grad_norm: gradient norm clip, per network.
        norm_adv: normalise advantages per minibatch.
        value_norm: learn normalised values with running return statistics.
        target_kl: stop the epochs of an update early above this approximate KL (None: never).
            The critic's epochs stop with the actor's. On paper-3, 0.005 and 0.01 made episodes
            2.3-2.7x cheaper but left 3 of 5 seeds unconverged (docs/learning.md).
        policy_ema: decay of an exponential moving average of the actor's weights, updated
            after every PPO update (``w_avg <- ema * w_avg + (1 - ema) * w``); the averaged actor
            is the policy: it is evaluated, saved as ``policy`` in checkpoints and exported.
            0 turns averaging off (the last weights are the policy). The deterministic policy of
            this task sits close to the object; one update can move its path onto it, so the
            last weights' success jumps between evaluations, and the average does not.
        penalty_curriculum: k of the contact-penalty curriculum: the training world multiplies
            its contact penalties by ``1 + k * a``, with ``a`` a running mean (weight 0.25 per
            finished batch) of the fraction of training episodes that end with every robot on a
            target. Early on robots must explore past each other and the object, and large
            penalties teach them to stay put; once they arrive, a touch that costs little
            return still fails the episode, so the penalty grows with competence. 0: off.
        seed: seeds the networks, the sampling noise and the start jitter.
        total_episodes: training budget in episodes.
        eval_interval: evaluate at least every this many training episodes.
        eval_episodes: deterministic evaluation episodes (fresh random starts) per evaluation.
        success_threshold: convergence threshold of the success rate (see
            :func:`controllers.mappo.evaluate.converged_episode`).
        stop_at_convergence: end the run once the convergence rule is met.
        checkpoint_interval: save ``checkpoint.pt`` every this many iterations (and at the end).
        init_from: checkpoint of an M-robot run to start from (transfer learning), or None.
        init_keep: how much of the ``init_from`` weights to keep ("shrink and perturb", Ash &
            Adams 2020): every actor and critic parameter starts at
            ``init_keep * w_transferred + (1 - init_keep) * w_fresh`` with ``w_fresh`` this
            run's own seeded initialisation. 1 keeps the M-robot networks as they are; smaller
            values keep their direction but restore some of the plasticity and exploration
            (log-std) of a fresh network. Default 0.5, over seeds 0-4 of ``bench/paper_tables.py``:
            paper-3 -> paper-5 converged in 5 of 5 (median 528 episodes), 1 of 5 within 1700
            with every weight kept (1.0; the 3-robot policy sent three robots onto the middle
            target and had stopped exploring); paper-3 -> paper-4 5 of 5 (median 384), 3 of 5
            with 1.0. 0.65 and 0.4 each lost a 3 -> 4 seed; 0.25 was slower on 3 -> 5 seed 1.
        device: torch device.
        torch_threads: ``torch.set_num_threads`` for the run (0 leaves it alone; 1 is fastest
            for these small networks and robust on a busy machine).
        tensorboard: also write the train and eval rows as TensorBoard scalars to
            ``<run_dir>/tensorboard`` (``torch.utils.tensorboard``; needs the tensorboard package).
        progress: show a tqdm progress bar.
    """

    scenario: str | dict = "paper-3"
    actor: ActorConfig = field(default_factory=ActorConfig)
    critic: CriticConfig = field(default_factory=CriticConfig)
    reward_weights: dict = field(default_factory=lambda: dict(TRAINING_REWARD))
    team_sizes: list = field(default_factory=list)
    distribution: str | dict | None = None
    num_envs: int = 16
    rollout_steps: int = 32
    gamma: float = 0.99
    gae_lambda: float = 0.95
    bootstrap_time_limit: bool = True
    bootstrap_from: str = "last"
    clip_coef: float = 0.2
    value_clip: float | None = None
    ent_coef: float = 0.0
    vf_coef: float = 0.5
    lr: float = 3e-4
    critic_lr: float | None = None
    anneal_lr: bool = False
    lr_after_success: float = 0.2
    update_epochs: int = 10
    num_minibatches: int = 4
    max_grad_norm: float = 0.5
    norm_adv: bool = True
    value_norm: bool = True
    target_kl: float | None = None
    policy_ema: float = 0.0
    penalty_curriculum: float = 0.0
    seed: int = 0
    total_episodes: int = 2000
    eval_interval: int = 50
    eval_episodes: int = 100
    success_threshold: float = 0.9
    stop_at_convergence: bool = True
    checkpoint_interval: int = 20
    init_from: str | None = None
    init_keep: float = 0.5
    device: str = "cpu"
    torch_threads: int = 1
    tensorboard: bool = False
    progress: bool = True

    def __post_init__(self) -> None:
        if isinstance(self.actor, dict):
            object.__setattr__(self, "actor", ActorConfig.from_dict(self.actor))
        if isinstance(self.critic, dict):
            object.__setattr__(self, "critic", CriticConfig.from_dict(self.critic))
        if isinstance(self.scenario, str) and self.scenario.endswith((".json", ".toml")):
            object.__setattr__(self, "scenario", self.build_scenario().to_dict())   # the file's content
        if isinstance(self.scenario, dict):   # stored in its JSON form, so resumes compare equal
            object.__setattr__(self, "scenario", _jsonable(self.build_scenario().to_dict()))
        if self.distribution is not None:     # the ranges themselves, not a name or a path
            object.__setattr__(self, "distribution", self.build_distribution().to_dict())
        self.validate()

    def build_scenario(self):
        """The :class:`sim.scenario.Scenario` of this run."""
        from sim.scenario import ScenarioError, ScenarioSourceError, scenario_from

        try:
            return scenario_from(self.scenario)
        except ScenarioSourceError as exc:
            raise TrainConfigError(str(exc)) from None
        except (ScenarioError, TypeError, ValueError) as exc:
            raise TrainConfigError(f"scenario: {exc}") from None

    def build_team_scenarios(self) -> list:
        """The scenario of each team size trained on (:attr:`team_sizes`; the scenario alone
        when empty)."""
        scenario = self.build_scenario()
        return [scenario if n == scenario.num_robots else scenario.with_robots(n)
                for n in (self.team_sizes or [scenario.num_robots])]

    def build_distribution(self):
        """The :class:`sim.distribution.ScenarioDistribution` of this run, or None."""
        from sim.distribution import DistributionError, load_distribution

        if self.distribution is None:
            return None
        if not isinstance(self.distribution, str | dict):
            raise TrainConfigError(f"distribution must be a name, a .json/.toml file or a mapping of "
                                   f"ScenarioDistribution fields, got {self.distribution!r}")
        try:
            return load_distribution(self.distribution)
        except DistributionError as exc:
            raise TrainConfigError(str(exc)) from None

    def build_reward_weights(self):
        """The :class:`sim.reward.RewardWeights` of this run (defaults plus ``reward_weights``)."""
        from sim.reward import RewardWeights

        if not isinstance(self.reward_weights, dict):
            raise TrainConfigError(f"reward_weights must be a mapping of RewardWeights fields, "
                                   f"got {self.reward_weights!r}")
        known = {f.name for f in dataclasses.fields(RewardWeights)}
        unknown = sorted(set(self.reward_weights) - known)
        if unknown:
            raise TrainConfigError(f"unknown reward_weights field(s) {unknown}; known: {sorted(known)}")
        for name, value in self.reward_weights.items():
            if not (is_number(value) and value >= 0):
                raise TrainConfigError(f"reward_weights.{name} must be a number >= 0, got {value!r}")
        return RewardWeights(**{k: float(v) for k, v in self.reward_weights.items()})

    @property
    def scenario_name(self) -> str:
        return self.scenario["name"] if isinstance(self.scenario, dict) else self.scenario

    def validate(self) -> None:
        self.build_scenario()
        self.build_reward_weights()
        if self.bootstrap_from not in ("final", "last"):
            raise TrainConfigError(f"bootstrap_from must be 'final' or 'last', got {self.bootstrap_from!r}")
        for name in ("num_envs", "rollout_steps", "update_epochs", "num_minibatches", "total_episodes",
                     "eval_interval", "eval_episodes", "checkpoint_interval"):
            value = getattr(self, name)
            if not isinstance(value, int) or isinstance(value, bool) or value < 1:
                raise TrainConfigError(f"{name} must be a positive integer, got {value!r}")
        if self.num_minibatches > self.num_envs * self.rollout_steps:
            raise TrainConfigError(f"num_minibatches ({self.num_minibatches}) must be <= num_envs * "
                                   f"rollout_steps ({self.num_envs * self.rollout_steps})")
        for name in ("bootstrap_time_limit", "anneal_lr", "norm_adv", "value_norm", "stop_at_convergence",
                     "tensorboard", "progress"):
            if not isinstance(getattr(self, name), bool):
                raise TrainConfigError(f"{name} must be true or false, got {getattr(self, name)!r}")
        for name, lo, hi in (("gamma", 0.0, 1.0), ("gae_lambda", 0.0, 1.0), ("success_threshold", 0.0, 1.0)):
            value = getattr(self, name)
            if not (is_number(value) and lo <= value <= hi):
                raise TrainConfigError(f"{name} must be in [{lo}, {hi}], got {value!r}")
        for name in ("clip_coef", "lr", "max_grad_norm", "lr_after_success"):
            value = getattr(self, name)
            if not (is_number(value) and value > 0):
                raise TrainConfigError(f"{name} must be a positive number, got {value!r}")
        for name in ("ent_coef", "vf_coef", "penalty_curriculum"):
            value = getattr(self, name)
            if not (is_number(value) and value >= 0):
                raise TrainConfigError(f"{name} must be a number >= 0, got {value!r}")
        for name in ("critic_lr", "value_clip", "target_kl"):
            value = getattr(self, name)
            if value is not None and not (is_number(value) and value > 0):
                raise TrainConfigError(f"{name} must be a positive number or null, got {value!r}")
        if not (is_number(self.policy_ema) and 0.0 <= self.policy_ema < 1.0):
            raise TrainConfigError(f"policy_ema must be in [0, 1) (0 = no averaging; 0.9 averages "
                                   f"~10 updates), got {self.policy_ema!r}")
        if not (is_number(self.init_keep) and 0.0 < self.init_keep <= 1.0):
            raise TrainConfigError(f"init_keep must be in (0, 1] (1 = keep the init_from weights as they "
                                   f"are), got {self.init_keep!r}")
        if not isinstance(self.seed, int) or isinstance(self.seed, bool) or self.seed < 0:
            raise TrainConfigError(f"seed must be an integer >= 0, got {self.seed!r}")
        if not isinstance(self.torch_threads, int) or isinstance(self.torch_threads, bool) or self.torch_threads < 0:
            raise TrainConfigError(f"torch_threads must be an integer >= 0 (0 = leave as is), "
                                   f"got {self.torch_threads!r}")
        self._validate_team_sizes()
        self._validate_distribution()
        if self.actor.obs_kind != self.critic.obs_kind:
            raise TrainConfigError(
                f"actor.variant {self.actor.variant!r} reads {self.actor.obs_kind} observations but "
                f"critic.variant {self.critic.variant!r} reads {self.critic.obs_kind}; use "
                "critic.variant='mlp' with actor.variant='mlp', else critic.variant='attention'")

    def _validate_distribution(self) -> None:
        """Every team size must fit the distribution's layouts (one draw each, seeded)."""
        import numpy as np

        from sim.distribution import DistributionError

        dist = self.build_distribution()
        if dist is None:
            return
        base = self.build_scenario()
        for n in self.team_sizes or [base.num_robots]:
            try:
                dist.layout(base, n, np.random.default_rng(0))
            except DistributionError as exc:
                raise TrainConfigError(f"distribution: {exc}") from None

    def _validate_team_sizes(self) -> None:
        from sim.scenario import MAX_ROBOTS

        sizes = self.team_sizes
        if not isinstance(sizes, list | tuple) or not all(
                isinstance(n, int) and not isinstance(n, bool) and 1 <= n <= MAX_ROBOTS for n in sizes):
            raise TrainConfigError(f"team_sizes must be a list of robot counts in 1..{MAX_ROBOTS} "
                                   f"(e.g. [3, 4, 5]; [] = the scenario's own), got {sizes!r}")
        if len(set(sizes)) != len(sizes):
            raise TrainConfigError(f"team_sizes lists a size twice: {list(sizes)!r}")
        if sizes and (self.actor.variant != "typed" or self.critic.variant != "attention"):
            raise TrainConfigError("team_sizes needs networks that run any team size: actor.variant "
                                   f"{self.actor.variant!r} and critic.variant {self.critic.variant!r} "
                                   "given; use actor.variant 'typed' and critic.variant 'attention'")
        if isinstance(sizes, tuple):
            object.__setattr__(self, "team_sizes", list(sizes))
        if self.distribution is None:         # each size's layout of the scenario's arena and object
            from sim.scenario import ScenarioError

            try:
                self.build_team_scenarios()
            except ScenarioError as exc:
                raise TrainConfigError(f"team_sizes: the layout of a team size does not fit the scenario: "
                                       f"{exc}; give sizes that fit, or a distribution") from None

    # ---------------------------------------------------------------- (de)serialise
    def to_dict(self) -> dict[str, Any]:
        d = {f.name: getattr(self, f.name) for f in dataclasses.fields(self)}
        d["actor"] = self.actor.to_dict()
        d["critic"] = self.critic.to_dict()
        return d

    @classmethod
    def from_dict(cls, data: dict[str, Any]) -> MAPPOConfig:
        try:
            return dataclass_from_dict(cls, data, "config")
        except TrainConfigError:
            raise
        except PolicyConfigError as exc:
            raise TrainConfigError(str(exc)) from None

    def replace(self, **changes: Any) -> MAPPOConfig:
        """A copy with ``changes`` applied (validated)."""
        return dataclasses.replace(self, **changes)

    @property
    def obs_kind(self) -> str:
        return self.actor.obs_kind


def _jsonable(value: Any) -> Any:
    if isinstance(value, dict):
        return {k: _jsonable(v) for k, v in value.items()}
    if isinstance(value, list | tuple):
        return [_jsonable(v) for v in value]
    return value


# Fields that may differ when a run is resumed: they change how long or how visibly it runs,
# never what it computes.
RESUMABLE_CHANGES = ("total_episodes", "progress", "checkpoint_interval", "stop_at_convergence",
                     "torch_threads", "tensorboard")
