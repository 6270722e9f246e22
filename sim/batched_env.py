"""BatchedFormationEnv: the training world, many episodes of one scenario stepped at once in torch.

State is ``(num_envs, num_robots, 2)`` positions and velocities. ``step`` has no Python loop over
environments or robots: the dynamics of :class:`sim.scenario.Dynamics`, the walls (an inelastic
stop: the disc is put back inside and its velocity into the wall removed, and the touch counts as a
wall collision), collision detection, reward and the automatic reset of finished environments are
all tensor operations. The object is solid, as in the pymunk world: a disc that would overlap it
is put back on its boundary (centre at distance r along the outward normal) and stopped (the
wheels of a robot pushed against the load lose their grip: no sliding along it), and the
touch counts as an object collision. Robots pass through each
other (no contact forces between robots): every overlap counts as a collision, is penalised,
and makes the episode a failure. Contacts count along each step's straight path, not only at
its ends (:func:`sim.metrics.swept_contacts`): two robots crossing within one step touch, and a
robot cutting round a corner of the object within one step touches it and stops.

Episodes last ``dynamics.episode_steps`` steps. When an environment finishes, its outcome
(:class:`EpisodeStats`) is returned in ``StepResult.finished`` and it restarts from jittered
start slots in the same call, so the returned observation is the first one of the new episode.
"""

from __future__ import annotations

import secrets
from dataclasses import dataclass

import numpy as np
import torch

from sim import observations
from sim.actuator import BatchedActuators
from sim.distribution import MAX_DELAY_TICKS, ScenarioDistribution
from sim.geometry import Frame, Polygon
from sim.metrics import episode_outcome, swept_contacts
from sim.reward import RewardWeights
from sim.scenario import Scenario
from sim.step_reward import StepReward, frame_contacts


@dataclass
class EpisodeStats:
    """Outcomes of the environments that finished in one step; every field is (F,) for F finished."""

    env_ids: torch.Tensor          # long
    success: torch.Tensor          # bool
    final_distance: torch.Tensor   # mean assigned distance [m]
    episode_return: torch.Tensor   # undiscounted return, mean over robots
    robot_collisions: torch.Tensor  # collision onsets (robot, step) summed over the episode
    object_collisions: torch.Tensor
    wall_collisions: torch.Tensor
    length: torch.Tensor           # steps
    arrived: torch.Tensor          # bool: every robot within tolerance at the end (collisions aside)

    def __len__(self) -> int:
        return int(self.env_ids.numel())


@dataclass
class StepResult:
    """What one call to ``step`` returns.

    obs: (E, N, 2N+1, 4) entity tokens (or (E, N, 4N+2) flat vectors with ``obs="flat"``).
    mask: (E, N, 2N+1) bool token validity (None for flat observations).
    reward: (E, N) reward of this step.
    done: (E,) bool, the episode ended with this step (the env has already been reset).
    finished: outcomes of the finished environments (empty when none finished).
    final_obs, final_mask: when some environment finished, the observation of the state this
        step ended in, before the reset (rows of the ``done`` environments are the ones that
        differ from ``obs``): what a time-limit bootstrap needs; None otherwise.
    """

    obs: torch.Tensor
    mask: torch.Tensor | None
    reward: torch.Tensor
    done: torch.Tensor
    finished: EpisodeStats
    final_obs: torch.Tensor | None = None
    final_mask: torch.Tensor | None = None


class BatchedFormationEnv:
    """``num_envs`` copies of ``scenario`` stepped together (see the module docstring).

    Args:
        scenario: the task.
        num_envs: number of parallel environments E.
        seed: seeds the start jitter; the same seed and actions repeat a run exactly.
        device: torch device.
        obs: ``"tokens"`` (entity tokens, any N) or ``"flat"`` (the paper's fixed-size vector).
        reward_weights: see :mod:`sim.reward`.
        distribution: ranges to draw each episode's layout and actuator from
            (:mod:`sim.distribution`); None: ``scenario`` as it is, a perfect actuator. The layout
            (object, slots, direction, jitter) is one for all ``num_envs`` environments and is
            drawn again whenever all of them restart together (their episodes run in step, so
            at every episode's end unless some were reset alone); the actuator is drawn per
            environment at each of its resets (:mod:`sim.actuator`). ``scenario`` gives the
            arena, radius, tolerance, dynamics and N.
        own_target: mark each robot's own target in its tokens
            (:func:`sim.observations.mark_own_targets`, for an actor with
            ``ActorConfig.own_target``) and reward the assigned terms by that same assignment.
    """

    def __init__(self, scenario: Scenario, num_envs: int, *, seed: int | None = None,
                 device: str | torch.device = "cpu", obs: str = "tokens",
                 reward_weights: RewardWeights = RewardWeights(), dtype: torch.dtype = torch.float32,
                 distribution: ScenarioDistribution | None = None, own_target: bool = False):
        if not isinstance(num_envs, int) or num_envs < 1:
            raise ValueError(f"num_envs must be a positive integer, got {num_envs!r}")
        if obs not in ("tokens", "flat"):
            raise ValueError(f"obs must be 'tokens' or 'flat', got {obs!r}")
        self.base_scenario = scenario
        self.distribution = distribution
        self.num_envs = num_envs
        self.num_robots = scenario.num_robots
        self.device = torch.device(device)
        self.dtype = dtype
        self.obs_kind = obs
        self.own_target = bool(own_target)
        self._sigma: tuple[Frame, torch.Tensor] | None = None
        if self.own_target and obs != "tokens":
            raise ValueError("own_target marks entity tokens; it needs obs='tokens'")
        self.reward_weights = reward_weights
        dyn = scenario.dynamics
        self.dt, self.episode_steps = dyn.dt, dyn.episode_steps
        self.arena = scenario.arena
        self.radius = scenario.robot_radius
        kw = dict(dtype=dtype, device=self.device)
        self.rewarder: StepReward | None = None
        self.generator = torch.Generator(device=self.device)
        self.seed(seed)
        self._set_layout(scenario)             # with a distribution, every reset of all draws one
        self.actuators = None
        if distribution is not None and distribution.varies_dynamics:
            self.actuators = BatchedActuators(num_envs, self.num_robots, MAX_DELAY_TICKS, dtype=dtype,
                                              device=self.device)
        e, n = num_envs, self.num_robots
        self.pos = torch.zeros(e, n, 2, **kw)
        self.vel = torch.zeros(e, n, 2, **kw)
        self.t = torch.zeros(e, dtype=torch.long, device=self.device)
        self.collided = torch.zeros(e, dtype=torch.bool, device=self.device)
        self.ret = torch.zeros(e, **kw)
        self.counts = torch.zeros(e, 3, dtype=torch.long, device=self.device)
        self.prev_contact = torch.zeros(e, n, 3, dtype=torch.bool, device=self.device)
        self._t_max = 0   # host-side upper bound of self.t, so most steps skip the done check
        self._not_done = torch.zeros(e, dtype=torch.bool, device=self.device)
        none = torch.zeros(0, dtype=torch.long, device=self.device)
        self._none_finished = EpisodeStats(none, none.bool(), none.to(dtype), none.to(dtype),
                                           none, none, none, none, none.bool())
        self._lo = torch.tensor([self.radius, self.radius], **kw)
        self._hi = torch.tensor([self.arena[0] - self.radius, self.arena[1] - self.radius], **kw)

    def _set_layout(self, scenario: Scenario) -> None:
        """Object, slots and the reward's field of ``scenario`` (same N); the reward's remembered
        state is cleared (every environment restarts) and its curriculum scale kept."""
        kw = dict(dtype=self.dtype, device=self.device)
        self.scenario = scenario
        self.polygon = Polygon(torch.as_tensor(scenario.polygon, **kw))
        self.centroid = observations._centroid(self.polygon.vertices)
        self._frame: Frame | None = None
        self.start_slots = torch.as_tensor(scenario.starts, **kw)
        self.targets = torch.as_tensor(scenario.targets, **kw).expand(self.num_envs, -1, -1)
        scale = self.rewarder.penalty_scale if self.rewarder is not None else 1.0
        self.rewarder = StepReward(scenario, self.num_envs, self.reward_weights, self.polygon, self.device)
        self.rewarder.penalty_scale = scale
        if self.own_target:
            self._own_paths = self.rewarder.own_target_paths()

    # the reward's remembered state and the curriculum's scale live in self.rewarder
    prev_near_contact = property(lambda self: self.rewarder.prev_near_contact)
    assignment = property(lambda self: self.rewarder.assignment)

    @property
    def penalty_scale(self) -> float:
        return self.rewarder.penalty_scale

    @penalty_scale.setter
    def penalty_scale(self, value: float) -> None:
        self.rewarder.penalty_scale = value

    # ----------------------------------------------------------------- set-up
    def seed(self, seed: int | None) -> None:
        """Seed the start jitter and (with a distribution) the layout and actuator draws."""
        seed = int(seed) if seed is not None else secrets.randbits(63)   # torch.seed() would reseed torch's global RNG
        self.generator.manual_seed(seed)
        self._layout_rng = np.random.default_rng([seed, 1])
        self._actuator_rng = np.random.default_rng([seed, 2])

    def reset(self, seed: int | None = None, env_ids: torch.Tensor | None = None):
        """Restart all (or ``env_ids``) environments; returns ``(obs, mask)`` of all environments."""
        if seed is not None:
            self.seed(seed)
        ids = torch.arange(self.num_envs, device=self.device) if env_ids is None else env_ids
        self._reset_ids(ids)
        return self.observe()

    def _reset_ids(self, ids: torch.Tensor) -> None:
        k = ids.numel()
        if self.distribution is not None and self.distribution.varies_layout and k == self.num_envs:
            self._set_layout(self.distribution.layout(self.base_scenario, self.num_robots, self._layout_rng))
        if self.actuators is not None:
            self.actuators.reset(ids, *self.distribution.actuator_draw(k, self.num_robots, self.dt,
                                                                       self._actuator_rng))
        jitter = self.scenario.start_jitter
        noise = (torch.rand(k, self.num_robots, 2, generator=self.generator, device=self.device,
                            dtype=self.dtype) * 2 - 1) * jitter
        self._frame = None
        self.pos[ids] = self.start_slots + noise
        self.vel[ids] = 0
        self.t[ids] = 0
        self.collided[ids] = False
        self.ret[ids] = 0
        self.counts[ids] = 0
        self.prev_contact[ids] = False
        self.rewarder.reset(ids)
        self._t_max = int(self.t.max())

    # ------------------------------------------------------------ observation
    def observe(self) -> tuple[torch.Tensor, torch.Tensor | None]:
        """Observations of the current state: tokens and mask, or ``(flat, None)``."""
        if self.obs_kind == "flat":
            return observations.flat(self.pos, self.vel, self.targets), None
        frame = self._frame if self._frame is not None else Frame(self.pos, self.vel, self.targets, self.polygon)
        toks, mask = observations.frame_tokens(frame, self.arena, self.centroid)
        if self.own_target:
            sigma = self._sigma if self._sigma is not None and self._sigma[0] is frame else None
            toks = observations.mark_own_targets(toks, sigma[1] if sigma is not None else self._own_sigma(frame))
        return toks, mask

    def _own_sigma(self, frame: Frame) -> torch.Tensor:
        """(E, N) the assignment the own-target marks and the reward's assigned terms follow."""
        return observations.own_assignment(self._own_paths(frame.pos))

    def state(self) -> dict[str, torch.Tensor]:
        """Copies of the raw state: ``pos``, ``vel``, ``targets`` (E, N, 2) and ``t`` (E,)."""
        return {"pos": self.pos.clone(), "vel": self.vel.clone(), "targets": self.targets.clone(),
                "t": self.t.clone()}

    def set_state(self, pos: torch.Tensor, vel: torch.Tensor) -> None:
        """Overwrite positions and velocities, (E, N, 2) each (for tests and scripted starts)."""
        for name, x in (("pos", pos), ("vel", vel)):
            if tuple(x.shape) != (self.num_envs, self.num_robots, 2):
                raise ValueError(f"{name} must have shape {(self.num_envs, self.num_robots, 2)}, "
                                 f"got {tuple(x.shape)}")
        self.pos.copy_(pos)
        self.vel.copy_(vel)
        self._frame = None

    # ------------------------------------------------------------------- step
    @torch.no_grad()
    def step(self, actions: torch.Tensor) -> StepResult:
        """Advance every environment by one ``dt`` with (E, N, 2) commanded accelerations [m/s^2]."""
        shape = (self.num_envs, self.num_robots, 2)
        if tuple(actions.shape) != shape:
            raise ValueError(f"actions must have shape (num_envs, num_robots, 2) = {shape}, "
                             f"got {tuple(actions.shape)}")
        a = actions.to(self.pos)
        if not torch.isfinite(a).all():
            raise ValueError("actions contain NaN or inf; the policy output must be finite")
        dyn = self.scenario.dynamics
        a = _clip_norm(a, dyn.accel_limit)
        if self.actuators is not None:
            a = self.actuators(a)
        vel = _clip_norm(self.vel + self.dt * (a - dyn.damping * self.vel), dyn.speed_limit)
        pos = self.pos + self.dt * vel
        pos, vel, hit_object = self._stop_at_object(pos, vel)
        inside = pos.clamp(self._lo, self._hi)
        hit_wall_axis = inside != pos
        vel = torch.where(hit_wall_axis, torch.zeros_like(vel), vel)
        passed_robot, passed_corner = swept_contacts(self.pos, inside, self.radius, self.polygon.vertices)
        vel = torch.where(passed_corner.unsqueeze(-1), torch.zeros_like(vel), vel)   # a graze stops too
        self.pos, self.vel = inside, vel

        frame = Frame(self.pos, self.vel, self.targets, self.polygon)
        touched = (hit_wall_axis.any(-1), hit_object | passed_corner, passed_robot)
        events, contact = frame_contacts(frame, self.radius, self.arena, touched)
        new_contact = contact & ~self.prev_contact                               # (E,N,3)
        self.prev_contact = contact
        self.counts += new_contact.sum(1)
        self.collided |= contact.any(-1).any(-1)
        sigma = self._own_sigma(frame) if self.own_target else None
        self._sigma = (frame, sigma) if sigma is not None else None
        reward = self.rewarder(frame, touched, events, new_contact, sigma)   # sim.step_reward
        self.ret += reward.mean(-1)
        self.t += 1
        self._t_max += 1
        final_obs = final_mask = None
        if self._t_max >= self.episode_steps:   # some env may be done: look (one host sync)
            done = self.t >= self.episode_steps
            self._frame = frame
            final_obs, final_mask = self.observe()
            finished = self._finish(done)
            self._t_max = int(self.t.max())
        else:
            done, finished = self._not_done, self._none_finished
        self._frame = frame if len(finished) == 0 else None
        obs, mask = self.observe()
        if len(finished) == 0:
            final_obs = final_mask = None
        return StepResult(obs=obs, mask=mask, reward=reward, done=done, finished=finished,
                          final_obs=final_obs, final_mask=final_mask)

    def _stop_at_object(self, pos: torch.Tensor, vel: torch.Tensor):
        """Stop at the object: centres closer than r to it go back to distance r along the
        outward normal n, with zero velocity. Returns ``(pos, vel, hit)``, ``hit`` (E, N) bool.

        Stopping (rather than removing only the velocity into the object) keeps a touch from
        being a free guide rail around the object: a learner that grazes it loses time."""
        px, py = pos[..., 0], pos[..., 1]
        sd, sx, sy = self.polygon.signed_distance_xy(px, py)
        hit = sd < self.radius
        if not bool(hit.any()):
            return pos, vel, hit
        dx, dy = px - sx, py - sy
        norm = (dx * dx + dy * dy).sqrt().clamp_min(1e-12)
        sign = torch.where(sd < 0, -1.0, 1.0).to(pos)          # inside: the normal points from p to s
        nx, ny = sign * dx / norm, sign * dy / norm
        pushed = torch.stack((sx + self.radius * nx, sy + self.radius * ny), -1)
        h = hit.unsqueeze(-1)
        return torch.where(h, pushed, pos), torch.where(h, torch.zeros_like(vel), vel), hit

    def _finish(self, done: torch.Tensor) -> EpisodeStats:
        ids = done.nonzero().squeeze(-1)
        if ids.numel() == 0:
            return self._none_finished
        out = episode_outcome(self.pos[ids], self.targets[ids], self.collided[ids],
                              self.scenario.target_tolerance)
        stats = EpisodeStats(
            env_ids=ids, success=out.success, final_distance=out.final_distance,
            episode_return=self.ret[ids].clone(), robot_collisions=self.counts[ids, 0].clone(),
            object_collisions=self.counts[ids, 1].clone(), wall_collisions=self.counts[ids, 2].clone(),
            length=self.t[ids].clone(), arrived=out.max_distance <= self.scenario.target_tolerance)
        self._reset_ids(ids)
        return stats


def reads(actor) -> dict:
    """The observation keywords of :class:`BatchedFormationEnv` that give ``actor`` what it reads:
    its ``obs_kind`` (tokens unless it says otherwise) and the own-target marks it was trained on."""
    return {"obs": getattr(actor, "obs_kind", "tokens"), "own_target": bool(getattr(actor, "own_target", False))}


def _clip_norm(x: torch.Tensor, limit: float) -> torch.Tensor:
    """Scale each (..., 2) vector down to norm <= limit (direction kept)."""
    norm = (x * x).sum(-1, keepdim=True).sqrt()
    return x * (limit / norm.clamp_min(limit))
