"""FormationParallelEnv: the pymunk world as a PettingZoo ``ParallelEnv``.

Agents are ``"robot_0" .. "robot_{N-1}"`` (row order of the world). Per agent:

* observation: that robot's entity tokens of :func:`sim.observations.tokens`, computed from the
  *measured* state (what a robot sees, noise included) and flattened row by row to a float32
  vector of ``(2N + 1) * TOKEN_DIM`` features (token ``t``, feature ``f`` at ``t * 4 + f``);
  ``Box(-inf, inf)``.
* action: the commanded acceleration ``Box(-accel_limit, accel_limit, (2,))`` [m/s^2]; the
  world then clips its norm to ``accel_limit`` (a box corner has norm ``sqrt(2) * accel_limit``).
* reward: :class:`sim.step_reward.StepReward`, the object the batched training world rewards
  with (detour distances, contact onsets, the contact margin, the sticky assignment), on the
  *true* state, with pymunk's own contacts (a robot pushed by another, stopped by the object or
  a wall) joined to the geometric ones: equal weights, equal rewards on equal states (tested).
  ``reward_weights=RewardWeights(**controllers.mappo.config.TRAINING_REWARD)`` gives the trainer's.
* termination: never. Truncation: every agent at ``dynamics.episode_steps`` steps, after which
  ``agents`` is empty until ``reset``.
* info: ``collision_robot``, ``collision_object``, ``collision_wall`` (this robot, this tick) and
  ``collided`` (any collision of any robot this episode); at the last step also ``success`` and
  ``final_distance`` [m] from :func:`sim.metrics.episode_outcome`.
"""

from __future__ import annotations

from typing import Any

import numpy as np
import torch
from gymnasium import spaces
from pettingzoo import ParallelEnv

from sim import observations
from sim.fleet import FleetState
from sim.geometry import Frame, Polygon
from sim.pymunk_world import ModelError, PymunkWorld
from sim.reward import RewardWeights
from sim.scenario import Scenario, make_scenario
from sim.step_reward import StepReward, frame_contacts


def agent_name(i: int) -> str:
    return f"robot_{i}"


class FormationParallelEnv(ParallelEnv):
    """PettingZoo parallel env over :class:`sim.pymunk_world.PymunkWorld` (see the module docstring).

    Args:
        scenario: a :class:`Scenario` or a preset name for :func:`sim.scenario.make_scenario`.
        model_error: the robots' model error (default ``ModelError()``: none).
        reward_weights: see :mod:`sim.reward`.
        own_target: mark each robot's own target in its tokens (an actor with
            ``ActorConfig.own_target``; :func:`sim.observations.mark_own_targets`), assigned on
            the measured state, and reward the assigned terms by that assignment, as the
            batched world does.
        render_mode: only ``None`` (no rendering).
        **world_options: passed to :class:`PymunkWorld` (``substeps``, ``contact_friction``, ...).
    """

    metadata = {"name": "formation_v0", "render_modes": [], "is_parallelizable": True}

    def __init__(self, scenario: Scenario | str = "paper-3", model_error: ModelError | None = None, *,
                 reward_weights: RewardWeights = RewardWeights(), own_target: bool = False,
                 render_mode: str | None = None, **world_options: Any):
        if render_mode is not None:
            raise ValueError(f"render_mode must be None (this env does not render), got {render_mode!r}")
        self.render_mode = None
        sc = make_scenario(scenario) if isinstance(scenario, str) else scenario
        self.world = PymunkWorld(sc, model_error or ModelError(), **world_options)
        self.scenario = sc
        self.reward_weights = reward_weights
        n = sc.num_robots
        self.possible_agents = [agent_name(i) for i in range(n)]
        self.agents: list[str] = []
        obs_dim = observations.num_tokens(n) * observations.TOKEN_DIM
        limit = np.float32(sc.dynamics.accel_limit)
        self.observation_spaces = {a: spaces.Box(-np.inf, np.inf, (obs_dim,), np.float32)
                                   for a in self.possible_agents}
        self.action_spaces = {a: spaces.Box(-limit, limit, (2,), np.float32) for a in self.possible_agents}
        self._polygon = Polygon(torch.as_tensor(sc.polygon, dtype=torch.float64))
        self._targets = torch.as_tensor(sc.targets).unsqueeze(0)
        self.rewarder = StepReward(sc, 1, reward_weights, self._polygon)
        self._own_paths = self.rewarder.own_target_paths() if own_target else None
        self._prev_contact = torch.zeros(1, n, 3, dtype=torch.bool)

    def observation_space(self, agent: str) -> spaces.Box:
        return self.observation_spaces[agent]

    def action_space(self, agent: str) -> spaces.Box:
        return self.action_spaces[agent]

    # ---------------------------------------------------------------- episode
    def reset(self, seed: int | None = None, options: dict | None = None):
        """Start an episode; ``seed`` seeds the world (start jitter, gains, noise). ``options`` unused."""
        state = self.world.reset(seed=seed)
        self.rewarder.reset()
        self._prev_contact.zero_()
        self.agents = list(self.possible_agents)
        infos = self._infos(last=False)
        return self._observations(state, self._own_sigma(state)), infos

    def step(self, actions: dict[str, np.ndarray]):
        """Apply one (2,) acceleration per live agent [m/s^2] and advance one control tick."""
        if not self.agents:
            raise RuntimeError("the episode is over (every agent was truncated): call reset() first")
        unknown = set(actions) - set(self.agents)
        missing = set(self.agents) - set(actions)
        if unknown or missing:
            raise ValueError(f"actions must hold exactly the live agents {self.agents}; "
                             f"missing {sorted(missing)}, unknown {sorted(unknown)}")
        command = np.zeros((self.scenario.num_robots, 2))
        for i, agent in enumerate(self.possible_agents):
            a = np.asarray(actions[agent], dtype=np.float64)
            if a.shape != (2,):
                raise ValueError(f"action of {agent} must have shape (2,) [m/s^2], got {a.shape}")
            command[i] = a
        self.world.send_accelerations(command)
        state = self.world.step()

        sigma = self._own_sigma(state)
        reward = self._reward(sigma)
        last = state.step >= self.scenario.dynamics.episode_steps
        obs = self._observations(state, sigma)
        rewards = {a: float(reward[i]) for i, a in enumerate(self.possible_agents)}
        terminations = dict.fromkeys(self.possible_agents, False)
        truncations = dict.fromkeys(self.possible_agents, last)
        infos = self._infos(last)
        if last:
            self.agents = []
        return obs, rewards, terminations, truncations, infos

    def render(self) -> None:
        """No rendering."""
        return None

    def close(self) -> None:
        pass

    # ---------------------------------------------------------------- helpers
    def _own_sigma(self, state: FleetState) -> torch.Tensor | None:
        """(1, N) own-target assignment of the measured ``state``, or None without ``own_target``."""
        if self._own_paths is None:
            return None
        return observations.own_assignment(self._own_paths(torch.from_numpy(state.positions)[None]))

    def _reward(self, sigma: torch.Tensor | None) -> torch.Tensor:
        """(N,) reward of the step just taken, on the true state (module docstring); ``sigma``
        the assignment of the assigned terms (None: the reward's own)."""
        true, c = self.world.true_state(), self.world.contacts
        frame = Frame(torch.from_numpy(true.positions).unsqueeze(0), torch.from_numpy(true.velocities).unsqueeze(0),
                      self._targets, self._polygon)
        touched = (torch.from_numpy(c.wall).unsqueeze(0), torch.from_numpy(c.object).unsqueeze(0))
        events, contact = frame_contacts(frame, self.scenario.robot_radius, self.scenario.arena, touched)
        events.robot = events.robot | torch.from_numpy(c.robot).unsqueeze(0)
        contact[..., 0] = events.robot
        onsets, self._prev_contact = contact & ~self._prev_contact, contact
        return self.rewarder(frame, touched, events, onsets, sigma)[0]

    def _observations(self, s: FleetState, sigma: torch.Tensor | None) -> dict[str, np.ndarray]:
        """Each agent's flat tokens of the measured state ``s`` (the one the step returned)."""
        toks, _ = observations.tokens(torch.from_numpy(s.positions).unsqueeze(0),
                                      torch.from_numpy(s.velocities).unsqueeze(0), self._targets,
                                      self._polygon, self.scenario.arena)
        if sigma is not None:
            toks = observations.mark_own_targets(toks, sigma)
        flat = toks[0].reshape(self.scenario.num_robots, -1).numpy().astype(np.float32)
        return {a: flat[i] for i, a in enumerate(self.possible_agents)}

    def _infos(self, last: bool) -> dict[str, dict[str, Any]]:
        c = self.world.contacts
        collided = self.world.collision_counts.any
        infos = {a: {"collision_robot": bool(c.robot[i]), "collision_object": bool(c.object[i]),
                     "collision_wall": bool(c.wall[i]), "collided": collided}
                 for i, a in enumerate(self.possible_agents)}
        if last:
            out = self.world.outcome()
            for info in infos.values():
                info["success"] = bool(out.success[0])
                info["final_distance"] = float(out.final_distance[0])
        return infos
