"""The bridge's alarm for a robot that refuses its commands: re-arms it does not answer.

The bridge re-arms a robot whose STATE reports FAULT (its watchdog latch) with a CMD carrying STOP
(:func:`deploy.bridge.row_flags`); the robot leaves the latch and its next STATE is free of FAULT:
the re-arm is answered within a tick or two. A robot that refuses the bridge's commands never
answers: one forged CMD with a fresh epoch retires the controller's epoch at the robot, so every
genuine CMD after it, STOP included, is STALE there, and the bridge re-armed such a robot 112
times in 6 s without a word (issue #17).

:class:`RearmWatch` counts, per robot, the re-arms sent since its last STATE without FAULT (a
*run*). When a run reaches ``threshold`` (``BridgeConfig.rearm_alarm_after``, 10 by default:
half a second at 20 Hz) the robot is *refusing*: one ERROR line names it, how many re-arms in
how long, its ``last_cmd_seq`` and what to check, repeated at most once per ``interval_s`` while
it refuses (:class:`deploy.reject_log.Throttle`). The bridge then counts it as not under control:
out of the controller's rows, a silent obstacle in ``FleetState.silent``, still sent STOP each
tick; its first STATE without FAULT ends the run (a WARNING says so) and makes it a row again.
"""

from __future__ import annotations

import logging
import time
from collections.abc import Callable
from dataclasses import dataclass

from deploy.reject_log import Throttle
from deploy.wire import FAULT_BIT, StateStatus

log = logging.getLogger(__name__)

REARM_ALARM_AFTER = 10
"""Re-arms in a row without an answer that make a robot *refusing* (module docstring)."""


def check_threshold(threshold: int) -> None:
    """Raise ValueError unless ``threshold`` is an integer >= 1 (a count of re-arms)."""
    if isinstance(threshold, bool) or not isinstance(threshold, int) or threshold < 1:
        raise ValueError(f"rearm_alarm_after must be an integer >= 1 (re-arms), got {threshold!r}")


@dataclass
class _Run:
    count: int       # re-arms sent since the robot's last STATE without FAULT
    start_s: float   # when the first of them went out [s, the watch's clock]
    first_cmd_seq: int   # the last_cmd_seq its STATE named at the first and at the latest
    last_cmd_seq: int
    throttle: Throttle | None = None   # set once the alarm is raised


class RearmWatch:
    """Per robot, the re-arms its STATEs have not answered (module docstring); ``node`` names the
    bridge in log lines, ``clock`` [s] times the runs and the repeats."""

    def __init__(self, node: str, threshold: int = REARM_ALARM_AFTER, interval_s: float = 1.0,
                 clock: Callable[[], float] = time.monotonic):
        check_threshold(threshold)
        self.node, self.threshold, self.interval_s, self.clock = node, threshold, interval_s, clock
        self.alarms = 0                     # runs that reached the threshold
        self.longest: dict[str, int] = {}   # robot -> most re-arms in a row (longest run)
        self._runs: dict[str, _Run] = {}

    def state(self, robot: str, status: StateStatus) -> None:
        """The robot's latest STATE: one without FAULT answers every re-arm sent before it."""
        if int(status) & FAULT_BIT:
            return
        run = self._runs.pop(robot, None)
        if run is not None and run.count >= self.threshold:
            log.warning("%s: robot %s answers its commands again (STATE without FAULT) after %d "
                        "re-arms in %.1f s", self.node, robot, run.count, self.clock() - run.start_s)

    def rearmed(self, robot: str, last_cmd_seq: int) -> None:
        """A re-arm (STOP) just sent to ``robot``, whose STATE named ``last_cmd_seq``."""
        run = self._runs.get(robot)
        if run is None:
            run = self._runs[robot] = _Run(0, self.clock(), last_cmd_seq, last_cmd_seq)
        run.count += 1
        run.last_cmd_seq = last_cmd_seq
        self.longest[robot] = max(self.longest.get(robot, 0), run.count)
        if run.count == self.threshold:
            self.alarms += 1
            run.throttle = Throttle(self.interval_s, self.clock)
            self._alarm(robot, run)

    def refusing(self, robot: str) -> bool:
        """Whether ``robot`` has left ``threshold`` re-arms in a row unanswered."""
        run = self._runs.get(robot)
        return run is not None and run.count >= self.threshold

    def poll(self) -> None:
        """Repeat the alarm of each robot still refusing, at most once per ``interval_s``."""
        for robot, run in self._runs.items():
            if run.throttle is not None and run.throttle.due() is not None:
                self._alarm(robot, run)

    def _alarm(self, robot: str, run: _Run) -> None:
        moved = ("unchanged" if run.last_cmd_seq == run.first_cmd_seq
                 else f"was {run.first_cmd_seq} at the first re-arm")
        log.error("%s: robot %s refuses its commands: re-armed %d times in %.1f s and its STATEs "
                  "still report FAULT (last_cmd_seq %d, %s); it is kept as a silent obstacle, not "
                  "commanded. Check what else publishes on its cmd key (one CMD with a fresh "
                  "epoch from another node makes every genuine one STALE: see the robot's "
                  "rejects and the router's denied puts) and the robot's clock (EXPIRED, "
                  "FROM_FUTURE); restarting the robot's link clears a foreign epoch", self.node,
                  robot, run.count, self.clock() - run.start_s, run.last_cmd_seq, moved)
        run.throttle.done()

    def summary(self) -> dict:
        """``rearm_alarms`` (runs that reached the threshold), ``rearms_in_a_row`` (robot -> its
        longest run, for robots ever re-armed: 1 when each re-arm was answered at once),
        ``refusing`` (robots refusing now) and the threshold, ``rearm_alarm_after``."""
        return {"rearm_alarms": self.alarms, "rearms_in_a_row": dict(sorted(self.longest.items())),
                "refusing": sorted(r for r in self._runs if self.refusing(r)),
                "rearm_alarm_after": self.threshold}


__all__ = ["REARM_ALARM_AFTER", "RearmWatch", "check_threshold"]
