"""What the latency prediction of the safety filter assumes of the link
(:mod:`controllers.safety.latency`, where the maths is)."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from controllers.checks import check_numbers


class LatencyConfigError(ValueError):
    """A latency setting that cannot work; the message names the field and the fix."""


@dataclass(frozen=True)
class LatencyConfig:
    """What the filter assumes of the link (:mod:`controllers.safety.latency`). The defaults
    cover 150 ms.

    Attributes:
        enabled: predict and tighten (False: the filter judges the measured state as it is).
        command_delay_s: bound ``L`` on the time from sending a command to it acting (transport
            plus actuation, jitter included) [s]; a measured bound, if larger, wins.
        stale_after_s: a state older than this makes its robot a fixed obstacle [s].
        accel_uncertainty: ``delta_a``, bound on achieved minus asked acceleration [m/s^2].
        position_noise: ``sigma_p``, bound on the position measurement error [m].
        velocity_noise: ``sigma_v``, bound on the velocity measurement error [m/s].
        watchdog_s: a robot that hears no command brakes on its own after this long [s].
        spread_weight: ``w``, weight of the command spread in the tightening
            (:mod:`controllers.safety.latency`, Tightening).
        jitter_spread_weight: the weight for a robot whose observed delay changed lately or whose
            pending count is unknown (the larger of the two weights applies).
        jitter_brake_measured: a robot whose observed delay changed lately is braked from its
            measured velocity, not the predicted one (:mod:`controllers.safety.latency`, Braking).
        measured_velocity_sigmas: how many standard deviations of each robot's measured velocity
            noise (the caller's ``velocity_noise``, the compensator's) count as approach speed,
            besides ``velocity_noise`` (0 on an exact link, where nothing is measured).
        cover_merge: a silent robot at rest is bounded by discs round groups of its branches'
            rest points, each group within this of its centre [m]
            (:meth:`~controllers.safety.silent_reach.SilentPaths.cover`).
        cover_discs: at most this many discs per silent robot (1: the one disc of its branches).
        cover_late: a robot whose state is a tick or more late, not yet stale, is grown to hold
            it too where it would be had it stopped acting on commands at its last state
            (:mod:`controllers.safety.late_cover`).
    """

    enabled: bool = True
    command_delay_s: float = 0.15
    stale_after_s: float = 0.15
    accel_uncertainty: float = 0.05
    position_noise: float = 0.0
    velocity_noise: float = 0.0
    watchdog_s: float = 0.1
    spread_weight: float = 0.25
    jitter_spread_weight: float = 0.5
    jitter_brake_measured: bool = True
    measured_velocity_sigmas: float = 2.0
    cover_merge: float = 0.01
    cover_discs: int = 6
    cover_late: bool = True

    def delay_bound(self, measured_s: float | None) -> float:
        """``L`` [s]: ``command_delay_s``, or the measured bound where that is larger."""
        return max(self.command_delay_s, measured_s or 0.0)

    def __post_init__(self) -> None:
        check_numbers(self, ("command_delay_s", "stale_after_s", "accel_uncertainty", "position_noise",
                             "velocity_noise", "watchdog_s", "spread_weight", "jitter_spread_weight",
                             "measured_velocity_sigmas"),
                      "latency", LatencyConfigError)
        check_numbers(self, ("cover_merge",), "latency", LatencyConfigError, positive=True)
        if isinstance(self.cover_discs, bool) or not isinstance(self.cover_discs, int | np.integer) \
                or self.cover_discs < 1:
            raise LatencyConfigError(f"latency.cover_discs must be a whole number >= 1, got {self.cover_discs!r}")
        for name in ("jitter_brake_measured", "cover_late"):
            if not isinstance(getattr(self, name), bool | np.bool_):
                raise LatencyConfigError(f"latency.{name} must be true or false, got {getattr(self, name)!r}")
        if self.stale_after_s <= 0:
            raise LatencyConfigError(f"latency.stale_after_s must be > 0 seconds, got {self.stale_after_s!r}")


__all__ = ["LatencyConfig", "LatencyConfigError"]
