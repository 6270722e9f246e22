"""The controller process's loop: robot states in, a controller callable, commands out.

``deploy/`` never imports ``stack/``: the controller is a plain callable
``controller(FleetState) -> (N, 2)`` accelerations [m/s^2] for the N robots present.

One tick (:meth:`Bridge.step`):
    1. wait for a fresh state from some robot, then up to ``gather_s`` for every other present
       robot's (a fleet publishes its states as a burst, so one tick answers one burst);
    2. present robots = liveliness token present and newest state younger than
       ``stale_after_s``; live robots with older states are *stale* and left out (counted);
       N changes on the fly as robots join, leave or go stale;
    3. if live robots exist but the newest state of any of them is older than
       ``estop_after_s``, the picture is too old: the fleet e-stop is raised (latched; an
       operator clears it);
    4. ``FleetState`` of the present robots (registry order) -> controller -> commands, each
       with ``ttl_ms`` and the answered ``state_seq``. A controller error, a wrong shape or a
       non-finite value sends BRAKE to every present robot instead (counted); a robot
       reporting FAULT (its watchdog latch) gets a STOP command, which re-arms it.

Episodes (``BridgeConfig.episode_ticks`` = T): a fleet that resets its world every T ticks
without closing its links (:mod:`deploy.fleet_sim` with ``episodes``) publishes state ``seq``
t + 1 at its tick t, so the burst answered belongs to episode ``(max seq - 1) // T``. When that
index changes, ``on_episode(k)`` runs before the controller (e.g. to reset its estimators);
the count is in-band, so it stays right when a burst goes unanswered.
"""

from __future__ import annotations

import logging
import threading
import time
from collections.abc import Callable, Mapping
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from deploy.transport import FleetLink, ReceivedState, TransportConfig
from deploy.wire import CmdFlags, RobotRegistry, StateStatus
from sim.fleet import FleetState

log = logging.getLogger(__name__)

Controller = Callable[[FleetState], np.ndarray]
ESTOP_STALE_PICTURE = 1  # reason code of an e-stop raised because the states are too old


@dataclass(frozen=True)
class BridgeConfig:
    """ttl_ms: command validity; stale_after_s / estop_after_s: state ages [s];
    gather_s: how long a tick waits for the rest of a burst of states [s];
    episode_ticks: ticks per fleet episode (see the module docstring), or None;
    lossless: publish commands with congestion control BLOCK, for a lock-stepped fleet that
    waits for every answer (``fleet-sim --lockstep``); the default DROP is for real time
    (see :mod:`deploy.transport`, Delivery)."""

    ttl_ms: int = 150
    stale_after_s: float = 0.3
    estop_after_s: float = 1.0
    gather_s: float = 0.01
    episode_ticks: int | None = None
    lossless: bool = False

    def __post_init__(self) -> None:
        if self.episode_ticks is not None and (isinstance(self.episode_ticks, bool) or not isinstance(
                self.episode_ticks, int) or self.episode_ticks < 1):
            raise ValueError(f"episode_ticks must be a positive integer or None, got {self.episode_ticks!r}")
        if not self.gather_s >= 0:
            raise ValueError(f"gather_s must be >= 0 seconds, got {self.gather_s!r}")
        if not 1 <= self.ttl_ms <= 65535:
            raise ValueError(f"ttl_ms must be in 1..65535, got {self.ttl_ms!r}")
        if not 0 < self.stale_after_s <= self.estop_after_s:
            raise ValueError("need 0 < stale_after_s <= estop_after_s, got "
                             f"{self.stale_after_s!r}, {self.estop_after_s!r}")


@dataclass
class TickRecord:
    tick: int
    robots: tuple[str, ...]  # present robots, in command row order
    stale: tuple[str, ...]
    commands: np.ndarray  # (N, 2) [m/s^2] sent (zeros where BRAKE/STOP was sent)
    controller_s: float  # time in the controller callable [s]


@dataclass
class BridgeStats:
    ticks: int = 0
    stale_marks: int = 0
    controller_faults: int = 0
    rearms: int = 0
    estops: int = 0
    robot_counts: list[tuple[int, int]] = field(default_factory=list)  # (tick, N) on change


class Bridge:
    """Controller side of a fleet. ``targets`` maps each robot to its target slot (2,) [m];
    ``object_pose`` is (3,) [m, m, rad]; ``on_episode(k)`` see the module docstring."""

    def __init__(self, fleet: str, registry: RobotRegistry,
                 transport: TransportConfig, controller: Controller, *,
                 targets: Mapping[str, np.ndarray], object_pose: np.ndarray,
                 config: BridgeConfig = BridgeConfig(),
                 on_episode: Callable[[int], Any] | None = None):
        missing = [r for r in registry.names if r not in targets]
        if missing:
            raise ValueError(f"targets are missing for robots {missing}; give one (x, y) per robot")
        self.registry = registry
        self.controller = controller
        self.targets = {r: np.asarray(targets[r], dtype=np.float64) for r in registry.names}
        self.object_pose = np.asarray(object_pose, dtype=np.float64)
        self.config = config
        self.link = FleetLink(fleet, registry, transport, lossless=config.lossless)
        self.stats = BridgeStats()
        self._answered: dict[str, int] = {}  # robot -> state seq last answered
        self._stop = threading.Event()
        self._start = time.monotonic()
        self.on_episode = on_episode
        self.episode: int | None = None  # fleet episode of the last burst answered

    # ------------------------------------------------------------------ helpers
    def _fresh(self, states: Mapping[str, ReceivedState], robot: str) -> bool:
        s = states.get(robot)
        return s is not None and s.msg.seq != self._answered.get(robot)

    def _wait_burst(self, timeout_s: float) -> bool:
        link = self.link
        if not link.wait_for(lambda: any(self._fresh(link.latest_states(), r)
                                         for r in link.alive_robots), timeout_s):
            return False
        link.wait_for(lambda: all(self._fresh(link.latest_states(), r)
                                  for r in link.alive_robots), self.config.gather_s)
        return True

    def stop(self) -> None:
        self._stop.set()

    # ------------------------------------------------------------------ one tick
    def step(self, timeout_s: float = 0.1) -> TickRecord | None:
        """Answer one burst of states (None if none came within ``timeout_s``)."""
        got = self._wait_burst(timeout_s)
        now = self.link.clock_ns()
        states = self.link.latest_states()
        alive = [r for r in self.registry.names if r in self.link.alive_robots and r in states]
        ages = {r: (now - states[r].receive_time_ns) / 1e9 for r in alive}
        if alive and min(ages.values()) > self.config.estop_after_s \
                and not self.link.estop_engaged:
            log.error("newest robot state is %.3f s old: raising the fleet e-stop",
                      min(ages.values()))
            self.link.raise_estop(ESTOP_STALE_PICTURE)
            self.stats.estops += 1
        if not got:
            return None
        present = tuple(r for r in alive if ages[r] <= self.config.stale_after_s)
        stale = tuple(r for r in alive if ages[r] > self.config.stale_after_s)
        self.stats.stale_marks += len(stale)
        if not self.stats.robot_counts or self.stats.robot_counts[-1][1] != len(present):
            self.stats.robot_counts.append((self.stats.ticks, len(present)))
        commands = np.zeros((len(present), 2))
        controller_s = 0.0
        if present:
            rows = [states[r].msg for r in present]
            if self.config.episode_ticks is not None:
                episode = (max(m.seq for m in rows) - 1) // self.config.episode_ticks
                if episode != self.episode:
                    self.episode = episode
                    if self.on_episode is not None:
                        self.on_episode(episode)
            fleet_state = FleetState(
                time=time.monotonic() - self._start, step=self.stats.ticks,
                positions=np.array([m.position for m in rows]),
                velocities=np.array([m.velocity for m in rows]),
                targets=np.array([self.targets[r] for r in present]),
                object_pose=self.object_pose.copy(), robot_ids=present)
            t0 = time.perf_counter()
            flags = CmdFlags(0)
            try:
                out = np.asarray(self.controller(fleet_state), dtype=np.float64)
                if out.shape != (len(present), 2) or not np.all(np.isfinite(out)):
                    raise ValueError(f"controller returned shape {out.shape} or non-finite values "
                                     f"for {len(present)} robots")
                commands = out
            except Exception:
                log.exception("controller failed: braking every robot this tick")
                self.stats.controller_faults += 1
                flags = CmdFlags.BRAKE
            controller_s = time.perf_counter() - t0
            for i, robot in enumerate(present):
                msg = rows[i]
                robot_flags = flags
                if msg.status & StateStatus.FAULT:
                    robot_flags |= CmdFlags.STOP
                    self.stats.rearms += 1
                self.link.send_command(robot, commands[i], self.config.ttl_ms, robot_flags,
                                       state_seq=msg.seq)
                self._answered[robot] = msg.seq
        self.stats.ticks += 1
        return TickRecord(self.stats.ticks - 1, present, stale, commands, controller_s)

    def run(self, max_ticks: int | None = None,
            on_tick: Callable[[TickRecord], Any] | None = None) -> BridgeStats:
        """Tick until :meth:`stop` (e.g. from a signal handler) or ``max_ticks`` answered."""
        while not self._stop.is_set() and (max_ticks is None or self.stats.ticks < max_ticks):
            record = self.step()
            if record is not None and on_tick is not None:
                on_tick(record)
        return self.stats

    def summary(self) -> dict[str, Any]:
        s = self.stats
        return {"ticks": s.ticks, "stale_marks": s.stale_marks,
                "controller_faults": s.controller_faults, "rearms": s.rearms, "estops": s.estops,
                "robot_counts": s.robot_counts, "rejects": self.link.rejects.snapshot(),
                "estop_engaged": self.link.estop_engaged, "lossless": self.link.lossless}

    def close(self) -> None:
        self.link.close()

    def __enter__(self) -> Bridge:
        return self

    def __exit__(self, *exc) -> None:
        self.close()


__all__ = ["Bridge", "BridgeConfig", "BridgeStats", "Controller", "TickRecord"]
