r"""ControlStack: one control tick from a fleet state to the commands sent to the robots.

Data path of :meth:`ControlStack.tick` for N robots (N may change from one tick to the next)::

    FleetState (positions, velocities, targets (N, 2) numpy float64; object pose)
      -> observe:  sim.observations tokens (1, N, 2N+1, 4) + mask (1, N, 2N+1), torch float32
                   (or the flat vector (1, N, 4N+2) for an actor with obs_kind == "flat")
      -> policy:   eager nn.Module or TorchScript module ``forward(obs, mask) -> (1, N, 2)``,
                   run under torch.inference_mode; or a plain callable FleetState -> (N, 2)
                   => a_nom (N, 2) [m/s^2]
                   (the tick writes the tokens into a float32 buffer kept per N and, every token
                   being valid, passes ``mask=None`` to a network whose forward accepts it, else
                   an all-true mask kept per N; a TorchScript forward is called directly)
      -> safety:   controllers.safety.SafetyFilter.filter(pos, vel, a_nom)   (optional)
                   => a_safe (N, 2), SafetyStatus
      -> MEC:      controllers.mec.ModelErrorCompensator.step(measured vel, a_safe)   (optional;
                   the compensator keeps the previous command it returned as its model input)
                   => a_cmd = clip_norm(a_safe - d_hat, accel_limit) (N, 2), MecStatus
      -> commands  a_cmd (N, 2) numpy float64, always finite

Non-finite values never pass on. A non-finite fleet state (position or velocity) or a
non-finite policy output replaces the affected stage's output with the maximum-braking command
``clip_norm(c v - v / dt, accel_limit)`` (``v`` non-finite -> 0) and says so in
:attr:`TickResult.policy_status`; a non-finite final command (which no stage should produce) is
replaced the same way with :attr:`TickResult.brake_reason` set. Exceptions raised by a policy
propagate: a bug is not a data error.

Threads: torch's intra-op thread count is the caller's choice. For one fleet (batch of 1) on the
control path call ``torch.set_num_threads(1)`` once before the loop: more threads only add
synchronisation cost for tensors this small.

:func:`run_episode` drives any :class:`sim.fleet.Fleet` with a stack and judges the episode with
:mod:`sim.metrics` (success, final distance, collisions), plus the stack's own counters
(interventions, slack, fallback, braking) and the nominal-model tracking error (see
:func:`nominal_step`).
"""

from __future__ import annotations

import inspect
import json
import math
import time
import warnings
import zipfile
from collections.abc import Callable
from dataclasses import dataclass, field
from enum import StrEnum
from pathlib import Path
from typing import Any

import numpy as np
import torch
from torch import nn

from controllers.mec import MecConfig, MecStatus, ModelErrorCompensator
from controllers.safety import SafetyConfig, SafetyFilter, SafetyStatus, braking_acceleration
from sim.fleet import Fleet, FleetState
from sim.metrics import collision_events, episode_outcome
from sim.observations import LAYOUT_VERSION, TOKEN_DIM, flat, fleet_tokens_np
from sim.scenario import Dynamics, Scenario, clip_norm

PolicyLike = nn.Module | torch.jit.ScriptModule | str | Path | Callable[[FleetState], np.ndarray]


class StackError(ValueError):
    """A stack that cannot be built or a policy that cannot be loaded; the message says the fix."""


class PolicyStatus(StrEnum):
    """What the observe + policy stages produced."""

    OK = "ok"
    INVALID_STATE = "invalid_state"            # the fleet state was not finite: braking
    NON_FINITE_OUTPUT = "non_finite_output"    # the policy returned NaN/inf: braking


@dataclass
class TickResult:
    """One control tick for N robots.

    Attributes:
        a_nom: (N, 2) policy command [m/s^2] (braking where the policy failed), finite.
        a_safe: (N, 2) command after the safety filter (``a_nom`` clipped to the actuator limit
            when the filter is off) [m/s^2].
        a_cmd: (N, 2) command to send [m/s^2], finite, norm <= accel_limit.
        policy_status: see :class:`PolicyStatus`.
        safety_status: the filter's :class:`SafetyStatus` (None: filter off).
        mec_status: the compensator's :class:`MecStatus` (None: MEC off).
        safety_reason: the filter's reason text ("" when unchanged or intervened).
        brake_reason: why a stage output was replaced by braking ("" when none was).
        timings_ns: nanoseconds per stage: observe, policy, safety, mec, total.
    """

    a_nom: np.ndarray
    a_safe: np.ndarray
    a_cmd: np.ndarray
    policy_status: PolicyStatus
    safety_status: SafetyStatus | None
    mec_status: MecStatus | None
    safety_reason: str = ""
    brake_reason: str = ""
    timings_ns: dict[str, int] = field(default_factory=dict)

    @property
    def intervened(self) -> bool:
        """The safety filter changed the nominal command (any status but UNCHANGED)."""
        return self.safety_status is not None and self.safety_status is not SafetyStatus.UNCHANGED

    @property
    def infeasible(self) -> bool:
        """The barrier QP was infeasible and the slack QP (or braking) answered."""
        return self.safety_status is SafetyStatus.SLACK or "OSQP" in self.safety_reason

    @property
    def fallback(self) -> bool:
        """Some robot got a braking command from the filter's fallback or post-check."""
        return self.safety_status is SafetyStatus.FALLBACK_BRAKE

    @property
    def braking(self) -> bool:
        """A non-finite value was replaced by braking somewhere in the tick."""
        return self.policy_status is not PolicyStatus.OK or bool(self.brake_reason)

    def events(self) -> dict[str, bool]:
        return {"intervened": self.intervened, "infeasible": self.infeasible,
                "fallback": self.fallback, "braking": self.braking}


@dataclass(frozen=True)
class StackConfig:
    """Which stages run, and their settings.

    Attributes:
        safety: run the safety filter.
        mec: run the model error compensator.
        safety_config: settings of the filter (default: the fused fast path, see
            :mod:`controllers.safety.fused`; ``geometry="fcl"`` gives the same answers slower).
        mec_config: settings of the compensator.
    """

    safety: bool = True
    mec: bool = True
    safety_config: SafetyConfig = field(default_factory=SafetyConfig)
    mec_config: MecConfig = field(default_factory=MecConfig)


def is_torchscript_file(path: str | Path) -> bool:
    """True when ``path`` is a TorchScript archive (a zip holding ``*/constants.pkl``)."""
    try:
        with zipfile.ZipFile(path) as archive:
            return any(name.endswith("/constants.pkl") for name in archive.namelist())
    except (zipfile.BadZipFile, OSError):
        return False


def load_policy(path: str | Path, num_robots: int | None = None) -> nn.Module:
    """A policy module from a TorchScript file or a training checkpoint, in eval mode.

    A TorchScript file written by ``formation export`` carries ``meta.json``
    (:mod:`deploy.export`); its format and observation layout version must be the ones this code
    builds (:data:`sim.observations.LAYOUT_VERSION`), else :class:`StackError` says which differ:
    a policy trained on another token layout would silently read the wrong features. A bare
    ``torch.jit.save`` of an actor has no ``meta.json`` and no layout to check; it is loaded as is.
    """
    path = Path(path)
    if not path.is_file():
        raise StackError(f"policy file {str(path)!r} does not exist; give a TorchScript file or a "
                         "checkpoint.pt written by training")
    if is_torchscript_file(path):
        return _load_torchscript(path)
    from controllers.mappo.checkpoint import CheckpointError, load_actor

    try:
        return load_actor(path, num_robots)
    except CheckpointError as exc:
        raise StackError(str(exc)) from None
    except Exception as exc:  # a file torch cannot read at all: say what was expected
        raise StackError(f"{str(path)!r} is neither a TorchScript file nor a training checkpoint "
                         f"({type(exc).__name__}: {exc})") from None


def _load_torchscript(path: Path) -> torch.jit.ScriptModule:
    """Load a TorchScript policy and check its ``meta.json``, if it has one (see :func:`load_policy`)."""
    from deploy.export import EXPORT_FORMAT, EXPORT_FORMAT_VERSION, META_FILE

    extra = {META_FILE: ""}
    with warnings.catch_warnings():
        warnings.filterwarnings("ignore", category=DeprecationWarning, module="torch.jit")
        module = torch.jit.load(str(path), map_location="cpu", _extra_files=extra)
    if extra[META_FILE]:
        try:
            meta = json.loads(extra[META_FILE])
        except ValueError:
            raise StackError(f"{str(path)!r}: its {META_FILE} is not valid JSON; export the policy "
                             "again with `formation export`") from None
        if not isinstance(meta, dict):
            raise StackError(f"{str(path)!r}: its {META_FILE} is not a JSON object; export it again")
        fmt = (meta.get("format"), meta.get("format_version"))
        if fmt != (EXPORT_FORMAT, EXPORT_FORMAT_VERSION):
            raise StackError(f"{str(path)!r} is a {fmt[0]} v{fmt[1]} file, not {EXPORT_FORMAT} "
                             f"v{EXPORT_FORMAT_VERSION}; export it again with `formation export`")
        if meta.get("layout_version") != LAYOUT_VERSION:
            raise StackError(f"{str(path)!r} was exported for observation layout "
                             f"{meta.get('layout_version')!r} but this code builds layout "
                             f"{LAYOUT_VERSION}; export a policy trained on layout {LAYOUT_VERSION}")
        if meta.get("token_dim", TOKEN_DIM) != TOKEN_DIM:
            raise StackError(f"{str(path)!r} expects {meta.get('token_dim')} features per token but "
                             f"this code builds {TOKEN_DIM}; export a policy trained on this layout")
    return module.eval()


def _mask_is_optional(network: nn.Module) -> bool:
    """True when ``network.forward(obs, mask)`` accepts ``mask=None`` (or takes no mask)."""
    if isinstance(network, torch.jit.ScriptModule):
        args = [a for a in network.forward.schema.arguments if a.name != "self"]
        return len(args) < 2 or isinstance(args[1].type, torch.OptionalType)
    params = list(inspect.signature(network.forward).parameters.values())
    return len(params) < 2 or params[1].default is None


class ControlStack:
    """observe -> policy -> safety -> MEC for one fleet (see the module docstring).

    Args:
        scenario: the task (arena, object polygon, dynamics); its robot count is not binding.
        policy: an ``nn.Module`` / TorchScript module with ``forward(obs, mask) -> (E, N, 2)``,
            a TorchScript or checkpoint file path, or a callable ``FleetState -> (N, 2)``.
        config: which stages run (:class:`StackConfig`).
    """

    def __init__(self, scenario: Scenario, policy: PolicyLike, config: StackConfig | None = None):
        self.scenario = scenario
        self.config = config or StackConfig()
        self.dynamics: Dynamics = scenario.dynamics
        if isinstance(policy, str | Path):
            policy = load_policy(policy)
        if isinstance(policy, nn.Module | torch.jit.ScriptModule):
            policy.eval()
            self.network: nn.Module | None = policy
            self.callable: Callable[[FleetState], np.ndarray] | None = None
            self.obs_kind = str(getattr(policy, "obs_kind", "tokens"))
            if self.obs_kind not in ("tokens", "flat"):
                raise StackError(f"policy.obs_kind must be 'tokens' or 'flat', got {self.obs_kind!r}")
        elif callable(policy):
            self.network, self.callable, self.obs_kind = None, policy, "callable"
        else:
            raise StackError(f"policy must be an nn.Module, a TorchScript/checkpoint path or a "
                             f"callable FleetState -> (N, 2); got {type(policy).__name__}")
        self._polygon = scenario.polygon
        self._static_pose_list = [*map(float, scenario.object_center), 0.0]
        # Per-N buffers of the tick: float32 tokens (numpy and a torch view of the same memory)
        # and the mask to pass (None when the network accepts it: every token is valid).
        self._buffers: dict[int, tuple[np.ndarray, torch.Tensor, torch.Tensor | None]] = {}
        self._forward: Callable[..., torch.Tensor] | None = None
        self._mask_optional = False
        if self.network is not None:
            scripted = isinstance(self.network, torch.jit.ScriptModule)
            self._forward = self.network.forward if scripted else self.network
            self._mask_optional = _mask_is_optional(self.network)
        self.safety = SafetyFilter(scenario, self.config.safety_config) if self.config.safety else None
        self.mec = ModelErrorCompensator(self.dynamics, self.config.mec_config) if self.config.mec else None
        self.num_robots: int | None = None

    def reset(self) -> None:
        """Start a new episode: forget the compensator's estimate and any callable's plan."""
        if self.mec is not None:
            self.mec.reset()
        reset = getattr(self.callable, "reset", None)
        if callable(reset):
            reset()
        self.num_robots = None

    # ------------------------------------------------------------------ stages
    def observe(self, state: FleetState) -> tuple[torch.Tensor, torch.Tensor | None]:
        """Policy input of ``state``: tokens (1, N, 2N+1, 4) and mask, or flat (1, N, 4N+2) and None.

        Tokens come from :func:`sim.observations.fleet_tokens_np` (computed in float64, written
        into a float32 array), the numpy twin of the batched torch layout, several times cheaper
        for one fleet. Fresh tensors on every call; the tick itself reuses one buffer per N.
        """
        if self.obs_kind == "flat":
            return self._flat(state), None
        n = state.num_robots
        out = fleet_tokens_np(state.positions, state.velocities, state.targets, self._polygon,
                              self.scenario.arena, np.empty((n, 2 * n + 1, 4), dtype=np.float32))
        return torch.from_numpy(out).unsqueeze(0), torch.ones(1, n, 2 * n + 1, dtype=torch.bool)

    @staticmethod
    def _flat(state: FleetState) -> torch.Tensor:
        stacked = torch.from_numpy(np.stack((state.positions, state.velocities, state.targets)))
        pos, vel, tgt = stacked.to(torch.float32).unsqueeze(1).unbind(0)
        return flat(pos, vel, tgt)

    def _network_input(self, state: FleetState) -> tuple[torch.Tensor, torch.Tensor | None]:
        """The tick's policy input: tokens written into this N's reused float32 buffer (the
        returned tensor shares its memory: valid until the next tick) and the mask to pass."""
        if self.obs_kind == "flat":
            return self._flat(state), None
        n = state.num_robots
        buffers = self._buffers.get(n)
        if buffers is None:
            array = np.zeros((n, 2 * n + 1, 4), dtype=np.float32)
            mask = None if self._mask_optional else torch.ones(1, n, 2 * n + 1, dtype=torch.bool)
            buffers = self._buffers[n] = (array, torch.from_numpy(array).unsqueeze(0), mask)
        array, tensor, mask = buffers
        fleet_tokens_np(state.positions, state.velocities, state.targets, self._polygon,
                        self.scenario.arena, array)
        return tensor, mask

    def brake(self, vel: np.ndarray) -> np.ndarray:
        """(N, 2) maximum-braking command (non-finite velocities -> 0)."""
        return braking_acceleration(vel, self.dynamics)

    # -------------------------------------------------------------------- tick
    def tick(self, state: FleetState) -> TickResult:
        """One control tick for ``state`` (see the module docstring); never returns NaN."""
        t0 = time.perf_counter_ns()
        n = state.num_robots
        if n != self.num_robots:
            self._resize(n)
        pos, vel = state.positions, state.velocities
        policy_status = PolicyStatus.OK
        brake_reason = ""
        t_obs = t_pol = t0
        if not (np.isfinite(pos).all() and np.isfinite(vel).all()):
            a_nom = self.brake(vel)
            policy_status = PolicyStatus.INVALID_STATE
            brake_reason = "non-finite fleet state: policy skipped, braking"
            t_obs = t_pol = time.perf_counter_ns()
        else:
            if self.callable is not None:
                t_obs = t0
                raw = np.asarray(self.callable(state), dtype=np.float64)
            else:
                obs, mask = self._network_input(state)
                t_obs = time.perf_counter_ns()
                with torch.inference_mode():
                    out = self._forward(obs, mask) if mask is not None else self._forward(obs)
                raw = out.numpy()[0].astype(np.float64)
            t_pol = time.perf_counter_ns()
            if raw.shape != (n, 2):
                raise StackError(f"the policy returned shape {raw.shape} for {n} robots; it must "
                                 f"return ({n}, 2) accelerations (or (1, {n}, 2) for a network)")
            if np.isfinite(raw).all():
                a_nom = raw
            else:
                a_nom = self.brake(vel)
                policy_status = PolicyStatus.NON_FINITE_OUTPUT
                brake_reason = "policy output not finite: braking"
        safety_status, safety_reason = None, ""
        if self.safety is not None:
            pose = state.object_pose
            if pose.tolist() == self._static_pose_list:   # the scene's own pose: no re-posing
                pose = None
            result = self.safety.filter(pos, vel, a_nom, pose)
            a_safe, safety_status, safety_reason = result.a_safe, result.status, result.reason
        else:
            a_safe = clip_norm(a_nom, self.dynamics.accel_limit)
        t_safe = time.perf_counter_ns()
        mec_status = None
        if self.mec is not None:
            mec_result = self.mec.step(vel, a_safe)
            a_cmd, mec_status = mec_result.a_cmd, mec_result.status
        else:
            a_cmd = a_safe
        t_mec = time.perf_counter_ns()
        if not np.isfinite(a_cmd).all():   # no stage should get here; the last line of defence
            a_cmd = self.brake(vel)
            brake_reason = (brake_reason + "; " if brake_reason else "") + "final command not finite: braking"
        return TickResult(
            a_nom=a_nom, a_safe=a_safe, a_cmd=a_cmd, policy_status=policy_status,
            safety_status=safety_status, mec_status=mec_status, safety_reason=safety_reason,
            brake_reason=brake_reason,
            timings_ns={"observe": t_obs - t0, "policy": t_pol - t_obs, "safety": t_safe - t_pol,
                        "mec": t_mec - t_safe, "total": t_mec - t0})

    __call__ = tick

    def _resize(self, n: int) -> None:
        """A new robot count: the compensator restarts (its estimate is per robot row); the
        filter builds (once) and caches its QP for N; the policy runs any N it supports."""
        if n < 1:
            raise StackError(f"the fleet state has {n} robots; a tick needs at least one")
        if self.mec is not None:
            self.mec.reset()
        self.num_robots = n


# ------------------------------------------------------------------- episodes
def nominal_step(pos: np.ndarray, vel: np.ndarray, acc: np.ndarray,
                 dynamics: Dynamics) -> tuple[np.ndarray, np.ndarray]:
    """One tick of the nominal model (:class:`sim.scenario.Dynamics`, no error, no contact).

    ``a = clip_norm(acc, accel_limit)``, ``v' = clip_norm(v + dt (a - c v), speed_limit)``,
    ``p' = p + dt v'``; (N, 2) arrays in m, m/s, m/s^2 -> (p', v').
    """
    return dynamics.step_np(pos, vel, acc)


@dataclass
class EpisodeMetrics:
    """One episode of a stack on a fleet.

    Attributes:
        success: every robot within tolerance of its assigned target at the end, no collision.
        final_distance: mean assigned robot-target distance at the end [m].
        collided: any collision onset during the episode.
        robot_collisions, object_collisions, wall_collisions: collision onsets per kind.
        steps: ticks run.
        interventions, infeasible, fallbacks, braking: ticks with that event (see TickResult).
        tracking_error: mean one-tick position error [m] of the fleet against the nominal model
            driven by ``a_safe`` from the measured state (:func:`nominal_step`); what the MEC
            drives towards 0.
        p50_tick_ms, p99_tick_ms: tick latency percentiles [ms].
    """

    success: bool
    final_distance: float
    collided: bool
    robot_collisions: int
    object_collisions: int
    wall_collisions: int
    steps: int
    interventions: int
    infeasible: int
    fallbacks: int
    braking: int
    tracking_error: float
    p50_tick_ms: float
    p99_tick_ms: float

    def to_dict(self) -> dict[str, Any]:
        return dict(self.__dict__)


def run_episode(fleet: Fleet, stack: ControlStack, seed: int | None, steps: int | None = None,
                *, start: Callable[[Fleet], FleetState] | None = None) -> EpisodeMetrics:
    """Reset ``fleet`` with ``seed`` and run ``steps`` ticks (default: the scenario's episode).

    Collisions: a fleet with ``collision_counts`` and ``outcome()`` (the pymunk world) judges
    itself on its true state; any other fleet is judged here with :mod:`sim.metrics` on the
    state it reports. ``start(fleet)``, if given, runs after the reset (e.g. to place robots)
    and returns the first state.
    """
    scenario = fleet.scenario
    steps = scenario.dynamics.episode_steps if steps is None else steps
    if not isinstance(steps, int) or steps < 1:
        raise ValueError(f"steps must be a positive integer, got {steps!r}")
    state = fleet.reset(seed=seed)
    if start is not None:
        state = start(fleet)
    stack.reset()
    self_judging = hasattr(fleet, "collision_counts") and hasattr(fleet, "outcome")
    polygon = torch.as_tensor(scenario.polygon, dtype=torch.float64)
    prev_contact = np.zeros((state.num_robots, 3), dtype=bool)
    counts = np.zeros(3, dtype=np.int64)
    counters = dict.fromkeys(("interventions", "infeasible", "fallbacks", "braking"), 0)
    tracking, latency = [], []
    for _ in range(steps):
        tick = stack.tick(state)
        latency.append(tick.timings_ns["total"])
        counters["interventions"] += tick.intervened
        counters["infeasible"] += tick.infeasible
        counters["fallbacks"] += tick.fallback
        counters["braking"] += tick.braking
        predicted, _ = nominal_step(state.positions, state.velocities, tick.a_safe, scenario.dynamics)
        fleet.send_accelerations(tick.a_cmd)
        state = fleet.step()
        tracking.append(float(np.linalg.norm(state.positions - predicted, axis=1).mean()))
        if not self_judging:
            ev = collision_events(torch.from_numpy(state.positions)[None], polygon,
                                  scenario.robot_radius, scenario.arena)
            contact = torch.stack((ev.robot[0], ev.object[0], ev.wall[0]), -1).numpy()
            counts += (contact & ~prev_contact).sum(0)
            prev_contact = contact
    if self_judging:
        c = fleet.collision_counts
        counts = np.array([c.robot, c.object, c.wall])
        outcome = fleet.outcome()
    else:
        outcome = episode_outcome(torch.from_numpy(state.positions)[None],
                                  torch.from_numpy(state.targets)[None],
                                  torch.tensor([bool(counts.sum() > 0)]), scenario.target_tolerance)
    lat = np.asarray(latency) / 1e6
    return EpisodeMetrics(
        success=bool(outcome.success[0]), final_distance=float(outcome.final_distance[0]),
        collided=bool(counts.sum() > 0), robot_collisions=int(counts[0]),
        object_collisions=int(counts[1]), wall_collisions=int(counts[2]), steps=steps,
        tracking_error=float(np.mean(tracking)) if tracking else math.nan,
        p50_tick_ms=float(np.percentile(lat, 50)), p99_tick_ms=float(np.percentile(lat, 99)),
        **counters)
