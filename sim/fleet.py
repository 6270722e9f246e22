"""The small fleet interface that every world implements: read state, send accelerations, step.

The batched world (:class:`BatchedFleet`, one environment), the pymunk world
(:class:`sim.pymunk_world.PymunkWorld`) and a fleet over Zenoh (:class:`deploy.zenoh_fleet.ZenohFleet`)
all present the same three calls, in the manner of the Robotarium's ``get_poses`` /
``set_velocities`` / ``step``::

    state = fleet.reset(seed=0)
    while not done:
        fleet.send_accelerations(controller(state))   # (N, 2) m/s^2
        state = fleet.step()                          # advances dt, returns the new state

Arrays at this edge are numpy float64.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, field
from typing import Protocol, runtime_checkable

import numpy as np
import torch

from sim.scenario import Scenario


@dataclass
class SilentRobots:
    """Robots the controller no longer commands but that still stand somewhere: gone from the
    link (left, crashed) or silent for too long. The safety filter keeps each one as an
    obstacle, a disc grown by where it can have gone since its last state.

    Attributes:
        ids: M robot names.
        positions: (M, 2) last known centres [m].
        velocities: (M, 2) last known velocities [m/s].
        age_s: (M,) seconds since each of those states was measured [s], >= 0.
        targets: (M, 2) their target slots [m], or None (unknown). Known, the policy and docking
            see the silent robots as teammates that stand where they must have stopped (as a
            stale row is seen); unknown, only the safety filter sees them.
        commands_pending: (M,) int, control ticks since the command each robot had acted on when
            its last state was measured (every command sent to it since, and every tick since it
            was last sent one: the controller's own record of those ticks holds what it may
            still act on), -1 where unknown; or None (all unknown). Known, the filter bounds it
            by exactly those commands instead of every count the link's delay allows
            (:mod:`controllers.safety.silent_reach`).
    """

    ids: tuple[str, ...]
    positions: np.ndarray
    velocities: np.ndarray
    age_s: np.ndarray
    targets: np.ndarray | None = None
    commands_pending: np.ndarray | None = None

    def __post_init__(self) -> None:
        m = len(self.ids)
        for name in ("positions", "velocities", "targets"):
            if name == "targets" and self.targets is None:      # unknown
                continue
            arr = np.asarray(getattr(self, name), dtype=np.float64).reshape(-1, 2)
            if arr.shape != (m, 2):
                raise ValueError(f"SilentRobots.{name} must have shape ({m}, 2), got {arr.shape}")
            setattr(self, name, arr)
        if self.targets is not None and not np.isfinite(self.targets).all():
            raise ValueError(f"SilentRobots.targets must be finite (x, y) slots [m] or None, got {self.targets!r}")
        age = np.asarray(self.age_s, dtype=np.float64).reshape(-1)
        if age.shape != (m,) or not (age >= 0).all():
            raise ValueError(f"SilentRobots.age_s must be {m} ages >= 0 seconds, got {self.age_s!r}")
        self.age_s = age
        if self.commands_pending is not None:
            pending = np.asarray(self.commands_pending).reshape(-1)
            if pending.shape != (m,) or not np.issubdtype(pending.dtype, np.integer) or not (pending >= -1).all():
                raise ValueError(f"SilentRobots.commands_pending must be {m} integers >= 0 (-1: unknown) "
                                 f"or None, got {self.commands_pending!r}")
            self.commands_pending = pending.astype(np.int64)

    def pending(self) -> np.ndarray:
        """(M,) ``commands_pending``, -1 where unknown."""
        if self.commands_pending is None:
            return np.full(len(self.ids), -1, dtype=np.int64)
        return self.commands_pending

    @classmethod
    def empty(cls) -> SilentRobots:
        return cls((), np.zeros((0, 2)), np.zeros((0, 2)), np.zeros(0))

    def __len__(self) -> int:
        return len(self.ids)


def obstacle_name(obstacle_id: int) -> str:
    """The name of a tracker's obstacle ``obstacle_id`` in :class:`Obstacles` and in logs: ``#3``."""
    return f"#{obstacle_id}"


@dataclass
class Obstacles:
    """Things in the arena the controller does not command, seen by something else (a tracker
    or camera over the arena): a person, a foreign robot, a box, or a robot of the fleet that
    stopped reporting. The safety filter keeps each one as a fixed disc grown by how far it may
    have moved (:meth:`controllers.safety.prediction.Prediction.with_obstacles`).

    Attributes:
        ids: K names.
        positions: (K, 2) centres when seen [m].
        radii: (K,) radii [m], > 0.
        age_s: (K,) seconds since each was seen [s], >= 0.
        speed: (K,) the fastest each may move [m/s], >= 0 (0: it stands still, e.g. a box).
        robots: K names of the fleet's robots each one is, None where it is none of them (a
            tracker that identifies robots, e.g. motion capture); ``()``: none is. A robot's own
            sighting never holds it: the filter takes it in place of a silent robot's own bound
            once that robot is at rest (:mod:`controllers.safety.silent_reach`, Seen at rest)
            and ignores it else.
    """

    ids: tuple[str, ...]
    positions: np.ndarray
    radii: np.ndarray
    age_s: np.ndarray
    speed: np.ndarray
    robots: tuple[str | None, ...] = ()

    def __post_init__(self) -> None:
        k = len(self.ids)
        pos = np.asarray(self.positions, dtype=np.float64).reshape(-1, 2)
        if pos.shape != (k, 2) or not np.isfinite(pos).all():
            raise ValueError(f"Obstacles.positions must be {k} finite (x, y) centres [m], got {self.positions!r}")
        self.positions = pos
        for name, low, strict in (("radii", 0.0, True), ("age_s", 0.0, False), ("speed", 0.0, False)):
            arr = np.asarray(getattr(self, name), dtype=np.float64).reshape(-1)
            ok = arr.shape == (k,) and np.isfinite(arr).all() and ((arr > low) if strict else (arr >= low)).all()
            if not ok:
                raise ValueError(f"Obstacles.{name} must be {k} finite values {'>' if strict else '>='} {low}, "
                                 f"got {getattr(self, name)!r}")
            setattr(self, name, arr)
        self.robots = tuple(self.robots)
        if self.robots and len(self.robots) != k:
            raise ValueError(f"Obstacles.robots must name {k} robots (None: not a robot) or be (), "
                             f"got {self.robots!r}")

    def __len__(self) -> int:
        return len(self.ids)

    def split(self, robot_ids: Sequence[str]) -> tuple[dict[str, int], Obstacles | None]:
        """``(row of each sighted robot of robot_ids, by name -> index here; the rest)``: the
        obstacles that are none of ``robot_ids`` (None if no obstacle is left). A robot sighted
        more than once (a tracker that gave it a new track before ending the old one) is named
        by its freshest sighting, and none of its sightings is left as an obstacle."""
        names = set(robot_ids)
        seen: dict[str, int] = {}
        for k, name in enumerate(self.robots):
            if name is not None and name in names and (name not in seen or self.age_s[k] < self.age_s[seen[name]]):
                seen[name] = k
        if not seen:
            return {}, self
        keep = np.array([r is None or r not in seen for r in self.robots])
        if not keep.any():
            return seen, None
        robots = tuple(r for r, kept in zip(self.robots, keep, strict=True) if kept)
        return seen, Obstacles(tuple(i for i, kept in zip(self.ids, keep, strict=True) if kept),
                               self.positions[keep], self.radii[keep], self.age_s[keep], self.speed[keep], robots)


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
        state_age_s: (N,) seconds since each row was measured, when the controller reads it
            (a link's transport time, a dropped update, a silent robot); None: all fresh (0).
        silent: robots not commanded any more that stay obstacles (see :class:`SilentRobots`);
            None: none.
        command_delay_s: measured bound on the time from now until a command sent now acts
            (transport + actuation) [s], e.g. from a link's round trips; None: not measured.
            The safety filter covers the larger of this and its configured bound.
        commands_pending: (N,) int, commands sent to each robot after the newest one it had
            acted on when its row was measured (the last CMD seq sent minus the STATE's
            ``last_cmd_seq``), -1 where unknown; None: unknown for all. The safety filter then
            predicts each robot through exactly those commands, not through as many as its
            latency bound allows (which counts commands that already acted twice).
        obstacles: what a tracker sees that the controller does not command (see
            :class:`Obstacles`); None: nothing.
    """

    time: float
    step: int
    positions: np.ndarray
    velocities: np.ndarray
    targets: np.ndarray
    object_pose: np.ndarray
    robot_ids: tuple[str, ...] = field(default_factory=tuple)
    state_age_s: np.ndarray | None = None
    silent: SilentRobots | None = None
    command_delay_s: float | None = None
    commands_pending: np.ndarray | None = None
    obstacles: Obstacles | None = None

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
        if self.state_age_s is not None:
            age = np.asarray(self.state_age_s, dtype=np.float64).reshape(-1)
            if age.shape != (n,) or not (age >= 0).all():
                raise ValueError(f"FleetState.state_age_s must be {n} ages >= 0 seconds (or None), "
                                 f"got {self.state_age_s!r}")
            self.state_age_s = age
        if self.command_delay_s is not None and not (np.isfinite(self.command_delay_s)
                                                     and self.command_delay_s >= 0):
            raise ValueError(f"FleetState.command_delay_s must be >= 0 seconds or None, "
                             f"got {self.command_delay_s!r}")

        if self.commands_pending is not None:
            pending = np.asarray(self.commands_pending).reshape(-1)
            if pending.shape != (n,) or not np.issubdtype(pending.dtype, np.integer) or (pending < -1).any():
                raise ValueError(f"FleetState.commands_pending must be {n} integers >= 0 (-1: unknown) "
                                 f"or None, got {self.commands_pending!r}")
            self.commands_pending = pending.astype(np.int64)

    def replaced(self, **fields) -> FleetState:
        """A shallow copy with ``fields`` replaced, not validated again: the caller keeps every
        shape (a control tick's stand-ins and estimates)."""
        new = object.__new__(type(self))
        new.__dict__.update(self.__dict__, **fields)
        return new

    def ages(self) -> np.ndarray:
        """(N,) state ages [s] (zeros when ``state_age_s`` is None)."""
        return np.zeros(self.num_robots) if self.state_age_s is None else self.state_age_s

    def pending(self) -> np.ndarray:
        """(N,) commands in flight per robot, -1 where unknown (all -1 when ``commands_pending`` is None)."""
        return np.full(self.num_robots, -1, dtype=np.int64) if self.commands_pending is None \
            else self.commands_pending

    @property
    def num_robots(self) -> int:
        return len(self.positions)


@runtime_checkable
class Fleet(Protocol):
    """What a controller needs from a fleet, simulated or real.

    A fleet whose link may send BRAKE in place of a command (the Zenoh fleet's bridge) also has
    ``braked_in_place(state) -> (N,) bool | None``: the rows of ``state`` that got BRAKE instead
    of the answer, known once :meth:`step` has returned the next state.
    """

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

    No automatic reset: the episode runs until the caller stops. It judges itself, as the
    batched world does in training (:attr:`collision_counts`, :meth:`outcome`, :attr:`contacts`):
    a robot the world stops at a wall or the object rests exactly touching it, which a test of
    positions alone (:func:`sim.metrics.collision_events`, ``< r - 1e-6``) would not see.
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

    @property
    def collision_counts(self):
        """Collision onsets since reset, the world's own count (:class:`sim.pymunk_world.CollisionCounts`)."""
        from sim.pymunk_world import CollisionCounts

        robot, obj, wall = (int(c) for c in self.env.counts[0])
        return CollisionCounts(robot=robot, object=obj, wall=wall)

    @property
    def contacts(self):
        """This instant's contacts (:class:`sim.pymunk_world.Contacts`), as the world counted them."""
        from sim.pymunk_world import Contacts

        robot, obj, wall = self.env.prev_contact[0].numpy().T.copy()
        return Contacts(robot=robot, object=obj, wall=wall)

    def outcome(self):
        """:func:`sim.metrics.episode_outcome` of the current positions (batch of 1)."""
        from sim.metrics import episode_outcome

        return episode_outcome(self.env.pos[:1], self.env.targets[:1], self.env.collided[:1],
                               self.scenario.target_tolerance)
