"""Settings of :mod:`deploy.fleet_sim` (its docstring explains them): the robots' watchdog, the
run, and the intruders its tracker reports."""

from __future__ import annotations

import math
from dataclasses import dataclass, field

from deploy.network import TransportConfig
from deploy.wire import check_name
from sim.intruders import Intruder, RobotSightings
from sim.pymunk_world import ModelError
from sim.scenario import Scenario


def robot_names(n: int) -> tuple[str, ...]:
    """Robot ids of a simulated fleet: ``r0 .. r{n-1}`` (row order of the scenario)."""
    return tuple(f"r{i}" for i in range(n))


@dataclass(frozen=True)
class WatchdogConfig:
    """brake_after_ticks: brake on this many ticks in a row without a fresh command (1: on the
    first unanswered tick; see the module docstring); stop_after_s [s]: silence before the
    latch (brake to rest, wait for a re-arm)."""

    brake_after_ticks: int = 1
    stop_after_s: float = 0.5

    def __post_init__(self) -> None:
        if isinstance(self.brake_after_ticks, bool) or not isinstance(self.brake_after_ticks, int) \
                or self.brake_after_ticks < 1:
            raise ValueError(f"brake_after_ticks must be an integer >= 1, got {self.brake_after_ticks!r}")
        if not _finite_positive(self.stop_after_s):      # inf: the latch would never fire
            raise ValueError(f"stop_after_s must be a finite number > 0 seconds, got {self.stop_after_s!r}")


def _finite_positive(value: object) -> bool:
    return (not isinstance(value, bool) and isinstance(value, int | float) and math.isfinite(value)
            and value > 0)


@dataclass
class FleetSimConfig:
    """See the module docstring. ``rate_hz=None`` selects lock-step."""

    fleet: str
    scenario: Scenario
    transport: TransportConfig
    model_error: ModelError = field(default_factory=ModelError)
    seed: int = 0
    rate_hz: float | None = 20.0
    lockstep_timeout_s: float = 0.5
    start_timeout_s: float = 30.0
    max_ticks: int | None = None
    drop_commands: float = 0.0
    watchdog: WatchdogConfig = field(default_factory=WatchdogConfig)
    events: tuple[tuple[int, str, str], ...] = ()
    episodes: int | None = None
    shared_clock: bool | None = None
    playout_ticks: int = 0
    intruders: tuple[Intruder, ...] = ()
    track_robots: RobotSightings | None = None

    def clock_is_shared(self) -> bool:
        """``shared_clock``, or (None) whether every endpoint is on loopback: the controller then
        runs on this host, and its CMDs' send times are on this clock (module docstring)."""
        return self.transport.loopback_only() if self.shared_clock is None else bool(self.shared_clock)

    def __post_init__(self) -> None:
        check_name(self.fleet, "fleet name (--fleet)")
        if self.episodes is not None and (isinstance(self.episodes, bool)
                                          or not isinstance(self.episodes, int) or self.episodes < 1):
            raise ValueError(f"episodes must be a positive integer (or None), got {self.episodes!r}")
        if self.rate_hz is not None and not _finite_positive(self.rate_hz):  # inf: period 0, no watchdog
            raise ValueError(f"rate_hz must be a finite number > 0 (or None for lock-step), got {self.rate_hz!r}")
        for name in ("lockstep_timeout_s", "start_timeout_s"):
            if not _finite_positive(getattr(self, name)):
                raise ValueError(f"{name} must be a finite number > 0 seconds, got {getattr(self, name)!r}")
        if self.max_ticks is not None and (isinstance(self.max_ticks, bool) or not isinstance(self.max_ticks, int)
                                           or self.max_ticks < 0):
            raise ValueError(f"max_ticks must be an integer >= 0 (or None: no limit), got {self.max_ticks!r}")
        if isinstance(self.playout_ticks, bool) or not isinstance(self.playout_ticks, int) or self.playout_ticks < 0:
            raise ValueError(f"playout_ticks must be an integer >= 0, got {self.playout_ticks!r}")
        if not 0.0 <= self.drop_commands < 1.0:
            raise ValueError(f"drop_commands must be in [0, 1), got {self.drop_commands!r}")
        self.intruders = tuple(self.intruders)
        if not all(isinstance(i, Intruder) for i in self.intruders):
            raise TypeError(f"intruders must be sim.intruders.Intruder values, got {self.intruders!r}")
        self.model_error.check_team(self.scenario)
        names = robot_names(self.scenario.num_robots)
        for tick, robot, kind in self.events:
            if robot not in names or kind not in ("leave", "join") or tick < 0:
                raise ValueError(f"event {(tick, robot, kind)!r}: write (tick >= 0, one of "
                                 f"{names}, 'leave' | 'join')")
