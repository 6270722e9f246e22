"""The bridge's settings, its per-row command rule and what it counts (:mod:`deploy.bridge`
has the loop and the rules in full, with :mod:`deploy.bridge_picture`)."""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np

from deploy.bridge_timing import MIN_ROUND_TRIPS
from deploy.rearm_watch import REARM_ALARM_AFTER, check_threshold
from deploy.wire import FAULT_BIT, CmdFlags, StateStatus


@dataclass(frozen=True)
class BridgeConfig:
    """ttl_ms: command validity [ms]; stale_after_s: state age [s] past which a row gets BRAKE;
    estop_after_s: silence [s] of one live robot that raises the fleet e-stop, and the gap that
    counts as a stall of the bridge itself; gather_s: how long a tick waits for the rest of a
    burst of states [s] (half a 20 Hz period: over 20 +- 10 ms of jitter each way 0.01 split
    bursts, module docstring); episode_ticks: ticks per fleet episode (module docstring), or None;
    lossless: publish commands with congestion control BLOCK, for a fleet that waits for every
    answer; the default DROP is for real time (:mod:`deploy.transport`, Delivery); lockstep:
    the fleet is lock-stepped (``fleet-sim --lockstep``): sim time of ``period_s`` per tick
    (module docstring) and lossless; delay_percentile, delay_window: the command delay
    bound is this percentile of the last delay_window round trips; shared_clock: the robots
    stamp their STATEs on this host's monotonic clock, so one sent more than 100 ms ahead of it
    is refused (FROM_FUTURE); None: when every endpoint of the transport is on loopback;
    rearm_alarm_after: re-arms in a row a robot leaves unanswered (its STATEs still FAULT) before
    it counts as refusing its commands (:mod:`deploy.rearm_watch`)."""

    ttl_ms: int = 150
    stale_after_s: float = 0.15
    estop_after_s: float = 1.0
    gather_s: float = 0.025
    episode_ticks: int | None = None
    lossless: bool = False
    lockstep: bool = False
    period_s: float = 0.05
    delay_percentile: float = 99.0
    delay_window: int = 256
    shared_clock: bool | None = None
    rearm_alarm_after: int = REARM_ALARM_AFTER

    def __post_init__(self) -> None:
        check_threshold(self.rearm_alarm_after)
        if self.episode_ticks is not None and (isinstance(self.episode_ticks, bool) or not isinstance(
                self.episode_ticks, int) or self.episode_ticks < 1):
            raise ValueError(f"episode_ticks must be a positive integer or None, got {self.episode_ticks!r}")
        if not (math.isfinite(self.period_s) and self.period_s > 0):
            raise ValueError(f"period_s must be a positive number of seconds, got {self.period_s!r}")
        if not self.gather_s >= 0:
            raise ValueError(f"gather_s must be >= 0 seconds, got {self.gather_s!r}")
        if isinstance(self.ttl_ms, bool) or not isinstance(self.ttl_ms, int) \
                or not 1 <= self.ttl_ms <= 65535:
            raise ValueError(f"ttl_ms must be an integer in 1..65535, got {self.ttl_ms!r}")
        if not (math.isfinite(self.estop_after_s) and 0 < self.stale_after_s <= self.estop_after_s):
            raise ValueError("need 0 < stale_after_s <= estop_after_s (finite seconds), got "
                             f"stale_after_s={self.stale_after_s!r}, estop_after_s={self.estop_after_s!r}")
        if not 50.0 <= self.delay_percentile <= 100.0:
            raise ValueError(f"delay_percentile must be in [50, 100], got {self.delay_percentile!r}")
        if isinstance(self.delay_window, bool) or not isinstance(self.delay_window, int) \
                or self.delay_window < MIN_ROUND_TRIPS:
            raise ValueError(f"delay_window must be an integer >= {MIN_ROUND_TRIPS}, "
                             f"got {self.delay_window!r}")


def row_flags(controller_flags: CmdFlags, age_s: float, finite: bool, status: StateStatus,
              stale_after_s: float) -> CmdFlags:
    """CMD flags for one row (module docstring): BRAKE for a stale or non-finite state whatever
    the controller said; else the controller's flags, plus STOP to re-arm a robot in FAULT."""
    if not finite or not age_s <= stale_after_s:
        return CmdFlags.BRAKE
    if int(status) & FAULT_BIT:
        return controller_flags | CmdFlags.STOP
    return controller_flags


@dataclass
class TickRecord:
    tick: int
    robots: tuple[str, ...]  # rows, in command row order
    stale: tuple[str, ...]  # rows sent BRAKE because their state was older than stale_after_s
    commands: np.ndarray  # (N, 2) [m/s^2] sent (zeros where BRAKE/STOP was sent)
    controller_s: float  # time in the controller callable [s]
    silent: tuple[str, ...] = ()  # FleetState.silent robots
    ages: np.ndarray | None = None  # (N,) state ages of the rows [s]
    flags: tuple[CmdFlags, ...] = ()  # CMD flags sent per row


@dataclass
class BridgeStats:
    ticks: int = 0
    stale_marks: int = 0  # stale rows, summed over ticks
    controller_faults: int = 0
    rearms: int = 0
    estops: int = 0
    robot_counts: list[tuple[int, int]] = field(default_factory=list)  # (tick, N) on change
    silent_marks: int = 0  # silent robots, summed over ticks
    silent_counts: list[tuple[int, int]] = field(default_factory=list)  # (tick, M) on change
    nonfinite_brakes: int = 0
    unknown_brakes: int = 0
    stalls: int = 0
    longest_stall_s: float = 0.0
    estop_robot: str | None = None  # the robot whose silence raised the e-stop
    estop_silence_s: float | None = None
    heap_frozen: int = 0  # objects moved out of the collector's reach when the loop started
    late_parts: int = 0  # lock-step: bursts answered in two parts (TickClock), the late ones
