"""FormationTorchRLEnv: the batched training world as a TorchRL ``EnvBase`` (and so for BenchMARL).

``num_envs`` environments of one scenario, one agent group ``"agents"`` of N robots. The keys,
for a batch of E environments (what ``check_env_specs`` holds the env to)::

    ("agents", "tokens")       (E, N, 2N+1, 4) float32  entity tokens (sim.observations)
    ("agents", "mask")         (E, N, 2N+1)    bool     token validity (True: valid)
    ("agents", "observation")  (E, N, 4N+2)    float32  the paper's flat vector (sim.observations.flat)
    ("agents", "action")       (E, N, 2)       float32  accelerations [m/s^2] in [-a_max, a_max]
                                                        (the world clips the norm to a_max)
    ("agents", "reward")       (E, N, 1)       float32  sim.step_reward.StepReward, the reward
                                                        the SDPA-MAPPO trainer learns from
    "done", "truncated"        (E, 1)          bool     the episode's ``episode_steps`` are up
    "terminated"               (E, 1)          bool     never (the task has no terminal state)
    ("agents", "success"), ...                          at the end of an episode, the outcome of
                                                        sim.metrics.episode_outcome (else False/0)

The world itself never resets on its own here: TorchRL's partial reset (``"_reset"``) restarts
the finished environments, so the next observation of a done environment is its true final
one, not already the next episode's. ``reward_weights`` default to the trainer's
(``controllers.mappo.config.TRAINING_REWARD``), so a TorchRL or BenchMARL learner and ours are
judged by the same reward.
"""

from __future__ import annotations

import torch
from tensordict import TensorDict, TensorDictBase
from torchrl.data import Bounded, Categorical, Composite, Unbounded
from torchrl.envs import EnvBase

from sim import observations
from sim.batched_env import BatchedFormationEnv
from sim.metrics import episode_outcome
from sim.reward import RewardWeights
from sim.scenario import Scenario, make_scenario

GROUP = "agents"


def _training_weights() -> RewardWeights:
    from controllers.mappo.config import TRAINING_REWARD

    return RewardWeights(**TRAINING_REWARD)


class FormationTorchRLEnv(EnvBase):
    """TorchRL env over :class:`sim.batched_env.BatchedFormationEnv` (module docstring).

    Args:
        scenario: a :class:`Scenario` or a preset name.
        num_envs: environments E, the env's batch size.
        seed: seeds the start jitter.
        reward_weights: default: the trainer's (module docstring).
        device: torch device of the world and the tensordicts.
    """

    def __init__(self, scenario: Scenario | str = "paper-3", num_envs: int = 32, seed: int = 0,
                 reward_weights: RewardWeights | None = None, device: str | torch.device = "cpu"):
        super().__init__(device=device, batch_size=torch.Size([num_envs]))
        sc = make_scenario(scenario) if isinstance(scenario, str) else scenario
        self.scenario = sc
        self.world = BatchedFormationEnv(sc, num_envs, seed=seed, device=device,
                                         reward_weights=reward_weights or _training_weights())
        self.episode_steps = sc.dynamics.episode_steps
        self.world.episode_steps = 2**62      # the time limit is this env's: TorchRL resets
        e, n = num_envs, sc.num_robots
        tokens = observations.num_tokens(n)
        a = sc.dynamics.accel_limit
        flag = lambda *shape: Categorical(2, shape=torch.Size(shape), dtype=torch.bool, device=device)  # noqa: E731
        group_obs = Composite(
            tokens=Unbounded((e, n, tokens, observations.TOKEN_DIM), dtype=torch.float32, device=device),
            mask=flag(e, n, tokens),
            observation=Unbounded((e, n, 4 * n + 2), dtype=torch.float32, device=device),
            success=flag(e, n, 1), final_distance=Unbounded((e, n, 1), dtype=torch.float32, device=device),
            shape=(e, n))
        self.observation_spec = Composite({GROUP: group_obs}, shape=(e,))
        self.action_spec = Composite({GROUP: Composite(
            action=Bounded(-a, a, (e, n, 2), dtype=torch.float32, device=device), shape=(e, n))}, shape=(e,))
        self.reward_spec = Composite({GROUP: Composite(
            reward=Unbounded((e, n, 1), dtype=torch.float32, device=device), shape=(e, n))}, shape=(e,))
        self.done_spec = Composite(done=flag(e, 1), terminated=flag(e, 1), truncated=flag(e, 1), shape=(e,))
        self._t = torch.zeros(e, dtype=torch.long, device=device)

    # ------------------------------------------------------------------ TorchRL
    def _observation(self, done: torch.Tensor | None = None) -> TensorDict:
        w, (e, n) = self.world, self.batch_size + (self.scenario.num_robots,)
        tokens, mask = w.observe()
        success = torch.zeros(e, n, 1, dtype=torch.bool, device=self.device)
        final = torch.zeros(e, n, 1, dtype=torch.float32, device=self.device)
        if done is not None and done.any():
            out = episode_outcome(w.pos, w.targets, w.collided, self.scenario.target_tolerance)
            success = (out.success & done).view(e, 1, 1).expand(e, n, 1).clone()
            final = torch.where(done, out.final_distance.to(torch.float32), 0.0).view(e, 1, 1).expand(e, n, 1).clone()
        return TensorDict({"tokens": tokens.to(torch.float32), "mask": mask,
                           "observation": observations.flat(w.pos, w.vel, w.targets).to(torch.float32),
                           "success": success, "final_distance": final}, batch_size=(e, n))

    def _reset(self, tensordict: TensorDictBase | None = None, **kwargs) -> TensorDictBase:
        e = self.batch_size[0]
        mask = None if tensordict is None else tensordict.get("_reset", None)
        ids = (torch.arange(e, device=self.device) if mask is None
               else mask.view(e).nonzero().squeeze(-1))
        self.world.reset(env_ids=ids)
        self._t[ids] = 0
        false = torch.zeros(e, 1, dtype=torch.bool, device=self.device)
        return TensorDict({GROUP: self._observation(), "done": false, "terminated": false.clone(),
                           "truncated": false.clone()}, batch_size=(e,))

    def _step(self, tensordict: TensorDictBase) -> TensorDictBase:
        e = self.batch_size[0]
        action = tensordict.get((GROUP, "action"))
        result = self.world.step(action)
        self._t += 1
        done = self._t >= self.episode_steps
        out = TensorDict({GROUP: self._observation(done), "done": done.view(e, 1),
                          "terminated": torch.zeros(e, 1, dtype=torch.bool, device=self.device),
                          "truncated": done.view(e, 1).clone()}, batch_size=(e,))
        out.set((GROUP, "reward"), result.reward.unsqueeze(-1).to(torch.float32))
        return out

    def _set_seed(self, seed: int | None) -> None:
        self.world.seed(seed)
