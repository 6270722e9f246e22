"""Model error in the batched world: per-environment actuator gain, first-order lag and pure delay.

The same law as :class:`sim.model_error.ModelError` (its ``gain``, ``gain_spread``, ``lag_tau``
and ``delay_ticks``), per environment e and robot i, at step k of an episode::

    u_k    = c_{k - d_e}             the command clipped in norm, sent d_e steps earlier (0 before the first)
    a_act += alpha_e (g_ei u_k - a_act),   alpha_e = 1 - exp(-dt / tau_e)   (1: no lag)
    a_k    = a_act                   the acceleration the dynamics integrate [m/s^2]

``a_act`` starts at 0 and the delay line empty at every reset of the environment. The knobs are
drawn per environment from a :class:`sim.distribution.ScenarioDistribution` at each reset.
Tensors: commands (E, N, 2); the delay line (L = max delay + 1, E, N, 2), written at slot
``k mod L`` every step and read at ``(k - d_e) mod L``.
"""

from __future__ import annotations

import numpy as np
import torch


class BatchedActuators:
    """The actuators of ``num_envs`` environments of ``num_robots`` robots (module docstring)."""

    def __init__(self, num_envs: int, num_robots: int, max_delay: int, *, dtype: torch.dtype,
                 device: torch.device):
        kw = dict(dtype=dtype, device=device)
        self.length = int(max_delay) + 1
        self.gain = torch.ones(num_envs, num_robots, 1, **kw)
        self.alpha = torch.ones(num_envs, 1, 1, **kw)
        self.delay = torch.zeros(num_envs, dtype=torch.long, device=device)
        self.line = torch.zeros(self.length, num_envs, num_robots, 2, **kw)
        self.act = torch.zeros(num_envs, num_robots, 2, **kw)
        self.step_index = 0
        self._envs = torch.arange(num_envs, device=device)

    def reset(self, ids: torch.Tensor, gain: np.ndarray, alpha: np.ndarray, delay: np.ndarray) -> None:
        """New knobs for environments ``ids`` (K,): gains (K, N), lag factors (K,), delays (K,)."""
        if int(np.max(delay, initial=0)) >= self.length:
            raise ValueError(f"delay {int(np.max(delay))} ticks exceeds the delay line ({self.length - 1})")
        kw = dict(dtype=self.gain.dtype, device=self.gain.device)
        self.gain[ids] = torch.as_tensor(gain, **kw).unsqueeze(-1)
        self.alpha[ids] = torch.as_tensor(alpha, **kw).view(-1, 1, 1)
        self.delay[ids] = torch.as_tensor(delay, dtype=torch.long, device=self.gain.device)
        self.line[:, ids] = 0
        self.act[ids] = 0

    def __call__(self, command: torch.Tensor) -> torch.Tensor:
        """(E, N, 2) clipped commands of this step -> (E, N, 2) achieved accelerations."""
        self.line[self.step_index % self.length] = command
        read = (self.step_index - self.delay) % self.length
        self.step_index += 1
        u = self.line[read, self._envs]
        self.act = self.act + self.alpha * (self.gain * u - self.act)
        return self.act

    def state_dict(self) -> dict:
        return {"gain": self.gain.clone(), "alpha": self.alpha.clone(), "delay": self.delay.clone(),
                "line": self.line.clone(), "act": self.act.clone(), "step_index": self.step_index}

    def load_state_dict(self, state: dict) -> None:
        for name in ("gain", "alpha", "delay", "line", "act"):
            saved, current = state[name], getattr(self, name)
            if saved.shape != current.shape:
                raise ValueError(f"saved actuator {name} has shape {tuple(saved.shape)}, this world's "
                                 f"is {tuple(current.shape)}")
            current.copy_(saved)
        self.step_index = int(state["step_index"])
