"""The policy stage of :class:`stack.pipeline.ControlStack`: what runs the policy, its input, its
output ``a_nom``.

The ``observe`` and ``policy`` steps of the tick's data path (:mod:`stack.pipeline`): a network
(eager or TorchScript; an eager typed actor by the compiled kernel of npz files instead,
:class:`stack.policy_io.ModuleKernel`, unless ``StackConfig.policy_kernel`` is off), an exported
file of any format (:class:`deploy.export.ExportedPolicy`) or a plain callable
``FleetState -> (N, 2)``; tokens written by a compiled kernel into a float32 buffer kept per N.

:class:`PolicyStage` is a base class of ControlStack: ``_init_policy`` sets up its state once
(after ``config``), and the tick calls ``_policy`` and ``_runs``.
"""

from __future__ import annotations

import time
from collections.abc import Callable
from pathlib import Path

import numpy as np
import torch
from torch import nn

from controllers.observation_kernels import fleet_tokens
from deploy.export import ExportedPolicy
from sim.fleet import FleetState
from sim.observations import (
    FleetOwnTargets,
    flat,
    fleet_tokens_np,
    mark_own_targets_np,
    object_token_constants,
)
from sim.scenario import Scenario
from stack.policy_io import ModuleKernel, StackError, _mask_is_optional, load_policy

PolicyLike = nn.Module | torch.jit.ScriptModule | ExportedPolicy | str | Path | Callable[[FleetState], np.ndarray]


class PolicyStage:
    """Runs the policy of a :class:`stack.pipeline.ControlStack` (module docstring)."""

    def _init_policy(self, scenario: Scenario, policy: PolicyLike) -> None:
        """Sort out what runs ``policy`` (a path is loaded) and set up its input: called once,
        by ``ControlStack.__init__``, after ``self.config``."""
        if isinstance(policy, str | Path):
            policy = load_policy(policy)
        self._exported: ExportedPolicy | None = policy if isinstance(policy, ExportedPolicy) else None
        if self._exported is not None:
            self.network, self.callable, self.obs_kind = None, None, "tokens"
        elif isinstance(policy, nn.Module | torch.jit.ScriptModule):
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
        own = self._exported.meta.get("own_target", False) if self._exported is not None else (
            getattr(self.network, "own_target", False) if self.network is not None else False)
        self.own_target = bool(own)     # the policy reads its own target marked (sim.observations)
        self._own_targets = (FleetOwnTargets(scenario.polygon, scenario.robot_radius, scenario.arena,
                                             scenario.targets) if self.own_target else None)
        self._polygon = scenario.polygon
        self._token_constants = (*object_token_constants(np.asarray(self._polygon)),
                                 float(scenario.arena[0] / 2), float(scenario.arena[1] / 2))
        # Per-N buffers of the tick: float32 tokens (numpy and a torch view of the same memory)
        # and the mask to pass (None when the network accepts it: every token is valid).
        self._buffers: dict[int, tuple[np.ndarray, torch.Tensor, torch.Tensor | None]] = {}
        self._forward: Callable[..., torch.Tensor] | None = None
        self._row_masks: dict[int, np.ndarray] = {}
        self._mask_optional = False
        kernel = ModuleKernel.of(self.network) if self.network is not None and self.config.policy_kernel else None
        self._rows = self._exported.runner if self._exported is not None else kernel   # own tokens: unchecked
        if self.network is not None:
            scripted = isinstance(self.network, torch.jit.ScriptModule)
            self._forward = self.network.forward if scripted else self.network
            self._mask_optional = _mask_is_optional(self.network)

    @property
    def policy_runtime(self) -> str:
        """What runs the policy: ``kernel`` (an eager typed actor, :class:`ModuleKernel`), ``file``
        (an exported file), ``torch`` (the module as given) or ``callable``."""
        return ("callable" if self.callable is not None else "file" if self._exported is not None
                else "kernel" if self._rows is not None else "torch")

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
        if self.own_target:
            mark_own_targets_np(out, self._own_targets(state.positions, state.targets))
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
        fleet_tokens(*(np.ascontiguousarray(x) for x in (state.positions, state.velocities, state.targets)),
                     *self._token_constants, array)
        if self.own_target:
            mark_own_targets_np(array, self._own_targets(state.positions, state.targets))
        return tensor, mask

    def _policy(self, state: FleetState, t0: int) -> tuple[np.ndarray, int, int]:
        """``a_nom`` (N, 2) of the policy and the times after observing and after the policy."""
        n = state.num_robots
        if self.callable is not None:
            t_obs = t0
            raw = np.asarray(self.callable(state), dtype=np.float64)
        elif self._rows is not None:    # numpy in, numpy out; rows it flags count as NaN
            if self._exported is not None and n not in self._exported.robot_counts:
                raise StackError(f"{self._exported.path} runs {self._exported.robot_counts_text} "
                                 f"robots, this fleet has {n}; export a typed actor (any team "
                                 "a scenario holds) or one trained for this N")
            self._network_input(state)
            array, mask = self._buffers[n][0], self._row_masks.get(n)
            if mask is None:
                mask = self._row_masks[n] = np.ones(array.shape[:2], dtype=bool)
            t_obs = time.perf_counter_ns()
            accel, valid = self._rows(array, mask)
            valid = np.asarray(valid)
            raw = (accel.astype(np.float64) if np.count_nonzero(valid) == n
                   else np.where(valid[:, None], accel, np.nan).astype(np.float64))
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
        return raw, t_obs, t_pol

    def _runs(self, k: int) -> bool:
        """Whether the policy takes a team of ``k`` robots (silent robots join its view only then)."""
        if self._exported is not None:
            return k in self._exported.robot_counts
        if self.network is not None:        # any N (typed), or its own N (slot, flat MLP)
            num = int(getattr(self.network, "num_robots", 0))
            return (num == -1 and self.obs_kind == "tokens") or num == k
        return False


__all__ = ["PolicyLike", "PolicyStage"]
