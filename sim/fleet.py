"""The small fleet interface that every world implements: read state, send accelerations, step.

The batched world (:class:`BatchedFleet`, one environment), the pymunk world
(:class:`sim.pymunk_world.PymunkWorld`) and, later, a real fleet over Zenoh all present the same
three calls, in the manner of the Robotarium's ``get_poses`` / ``set_velocities`` / ``step``::

    state = fleet.reset(seed=0)
    while not done:
        fleet.send_accelerations(controller(state))   # (N, 2) m/s^2
        state = fleet.step()                          # advances dt, returns the new state

Arrays at this edge are numpy float64.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Protocol, runtime_checkable

import numpy as np
import torch

from sim.scenario import Scenario


@dataclass
class FleetState:
    """A snapshot of the fleet.

    Attributes:
        time: seconds since reset [s].
        step: control ticks since reset.
        positions: (N, 2) robot centres [m] (as measured: may carry noise).
        velocities: (N, 2) robot velocities [m/s] (as measured).
        targets: (N, 2) target slots [m].
        object_pose: (3,) object centroid x, y [m] and heading [rad].
        robot_ids: N robot names, in row order.
    """

    time: float
    step: int
    positions: np.ndarray
    velocities: np.ndarray
    targets: np.ndarray
    object_pose: np.ndarray
    robot_ids: tuple[str, ...] = field(default_factory=tuple)

    def __post_init__(self) -> None:
        n = len(self.positions)
        if not self.robot_ids:
            self.robot_ids = tuple(f"r{i}" for i in range(n))
        for name in ("positions", "velocities", "targets"):
            arr = np.asarray(getattr(self, name), dtype=np.float64)
            if arr.shape != (n, 2):
                raise ValueError(f"FleetState.{name} must have shape ({n}, 2), got {arr.shape}")
            setattr(self, name, arr)
        if len(self.robot_ids) != n:
            raise ValueError(f"FleetState.robot_ids has {len(self.robot_ids)} names for {n} robots")

    @property
    def num_robots(self) -> int:
        return len(self.positions)


@runtime_checkable
class Fleet(Protocol):
    """What a controller needs from a fleet, simulated or real."""

    scenario: Scenario

    @property
    def dt(self) -> float: ...

    def reset(self, seed: int | None = None) -> FleetState: ...

    def read_state(self) -> FleetState: ...

    def send_accelerations(self, accelerations: np.ndarray) -> None: ...

    def step(self) -> FleetState: ...


def check_accelerations(accelerations: np.ndarray, n: int) -> np.ndarray:
    """Validate an (N, 2) command at a fleet's edge: shape and finiteness, with a clear error."""
    a = np.asarray(accelerations, dtype=np.float64)
    if a.shape != (n, 2):
        raise ValueError(f"accelerations must have shape (num_robots, 2) = ({n}, 2), got {a.shape}")
    if not np.all(np.isfinite(a)):
        raise ValueError("accelerations contain NaN or inf; refusing to send them to robots")
    return a


class BatchedFleet:
    """The batched training world with one environment, behind the :class:`Fleet` interface.

    No automatic reset: the episode runs until the caller stops; collisions and the outcome are
    judged with :mod:`sim.metrics` by whoever drives it.
    """

    def __init__(self, scenario: Scenario):
        from sim.batched_env import BatchedFormationEnv

        self.scenario = scenario
        self.env = BatchedFormationEnv(scenario, 1, dtype=torch.float64)
        self.env.episode_steps = 2**62  # the driver decides when the episode ends
        self._command = np.zeros((scenario.num_robots, 2))
        self._step = 0

    @property
    def dt(self) -> float:
        return self.scenario.dynamics.dt

    def reset(self, seed: int | None = None) -> FleetState:
        self.env.reset(seed=seed)
        self._command[:] = 0
        self._step = 0
        return self.read_state()

    def read_state(self) -> FleetState:
        s = self.scenario
        c = s.object_center
        return FleetState(time=self._step * self.dt, step=self._step,
                          positions=self.env.pos[0].numpy().copy(),
                          velocities=self.env.vel[0].numpy().copy(), targets=s.targets.copy(),
                          object_pose=np.array([c[0], c[1], 0.0]))

    def send_accelerations(self, accelerations: np.ndarray) -> None:
        self._command = check_accelerations(accelerations, self.scenario.num_robots)

    def step(self) -> FleetState:
        self.env.step(torch.from_numpy(self._command).unsqueeze(0))
        self._step += 1
        return self.read_state()
