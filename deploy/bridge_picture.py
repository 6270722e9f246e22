"""What the bridge makes of its robots at a tick: rows, silent and unknown robots, obstacles, the
stall and e-stop rules, and the ``FleetState`` the controller is given.

:class:`BridgePicture` is a base class of :class:`deploy.bridge.Bridge`: its methods read and
write the state the bridge's ``__init__`` sets (its link, registry, clocks, counters and the
states it answered or discarded), and :meth:`deploy.bridge.Bridge.step` calls them each tick.
The command of a row, the command delay, one tick, episodes and lock-step are in
:mod:`deploy.bridge`.

Robots, as the bridge sees them at a tick (``now`` = the bridge's monotonic clock):
    * **row**: liveliness token present and a *usable* state (one not discarded below). Every
      row is in the ``FleetState`` with ``state_age_s`` = ``now - receive time + uplink
      excess``, where the uplink excess is how much longer this state took than the fastest
      transfer seen from that robot (``receive - send_time_ns``, both robot clocks cancel; the
      floor follows clock drift up to 200 ppm). Stale or not, a robot never leaves the
      controller's picture while it is live;
    * **silent**: seen before, but its token is gone (left, crashed, frozen past the link
      lease), or it is live and its latest state was discarded (it rejoined, or the bridge
      stalled, and has sent nothing since). Passed as ``FleetState.silent`` (last position,
      velocity, age, target) so the safety layer keeps it as an obstacle and the controller's
      policy sees it where it must have stopped (:mod:`stack.team_view`); never commanded. A robot
      whose token is gone gets its last state discarded, so after a rejoin it is a row again
      only with a new state (the controller keys its estimates by robot id and resets them); a
      state of a new link (another epoch) that arrives before the rejoining robot's token is
      kept, an obstacle until the token comes and a row from then on;
    * **unknown**: live without a usable state: sent BRAKE (``state_seq`` 0) on each tick;
    * **obstacles**: what a tracker reports on the fleet's sightings key (:mod:`deploy.tracker`),
      passed as ``FleetState.obstacles`` with each sighting's age, so the safety filter keeps
      every robot clear of them; never commanded.

Fleet e-stop (latched, reason 1 = ``ESTOP_STALE_PICTURE``; an operator clears it): raised when
any single live robot has been silent longer than ``estop_after_s`` while the bridge runs,
silence = ``min(state age, time since the bridge could hear it)``, where the bridge can hear a
robot from the moment its token appeared or the bridge resumed from a stall. While it is
engaged every row is sent BRAKE: a latched robot ignores motion commands, and the controller is
told what the robots do.

Controller stall (**the recovery rule**): when two consecutive looks at the fleet lie more than
``estop_after_s`` apart beyond the tick's own wait (``timeout_s + gather_s``) -- the process was
frozen (SIGSTOP), starved, or its controller hung -- the bridge does not act on its old picture:
every state received before the stall is discarded, ``on_stall()`` runs (e.g. reset the
controller's estimators, which saw no motion meanwhile), the command round trips in flight are
forgotten, and each robot becomes a row again with its next state. Meanwhile the robots' own
watchdogs braked them and, past their latch time, latched them (FAULT); once their fresh states
arrive they are re-armed through FAULT -> STOP -> the next command and the fleet drives on.
A stall never raises the e-stop by itself; a robot still silent ``estop_after_s`` after the
resume does. Tested with a 3 s SIGSTOP of the bridge process, 5 runs, one outcome
(``tests/deploy/test_bridge_stall.py``).
"""

from __future__ import annotations

import logging
import math
from collections.abc import Mapping
from dataclasses import dataclass, field

import numpy as np

from deploy.operator_channel import operator_answer
from deploy.transport import ReceivedState
from sim.fleet import FleetState, SilentRobots

log = logging.getLogger("deploy.bridge")   # the bridge's own records, under the bridge's name

ESTOP_STALE_PICTURE = 1  # reason code of an e-stop raised because a robot's state is too old


@dataclass
class View:
    """One tick's robots (module docstring): rows with their ages, silent and unknown robots."""

    rows: list[ReceivedState] = field(default_factory=list)
    ages: list[float] = field(default_factory=list)
    silent: list[tuple[ReceivedState, float]] = field(default_factory=list)
    unknown: list[str] = field(default_factory=list)
    silence: tuple[str, float] | None = None  # the live robot silent longest, and for how long


def state_key(rs: ReceivedState) -> tuple[int, int]:
    """A state's ``(epoch, seq)``: what the bridge records as answered or discarded."""
    return rs.msg.epoch, rs.msg.seq


class BridgePicture:
    """The bridge's picture of its robots at a tick (module docstring); a base of
    :class:`deploy.bridge.Bridge`, whose ``__init__`` sets the state these methods use."""

    def _age_s(self, rs: ReceivedState, now: int) -> float:
        uplink_ns = 0 if self.clock is not None else self.uplink.excess_ns(rs.robot, rs.msg.epoch, rs.msg.send_time_ns,
                                                                            rs.receive_time_ns)
        return max(0.0, now - rs.receive_time_ns + uplink_ns) / 1e9

    def _check_stall(self, now: int, states: Mapping[str, ReceivedState], timeout_s: float) -> None:
        """The recovery rule (module docstring): a gap between two looks beyond the tick's own
        wait and ``estop_after_s`` discards every state received so far."""
        last, self._last_look_ns = self._last_look_ns, now
        if last is None:
            return
        gap_s = (now - last) / 1e9 - timeout_s - self.config.gather_s
        if gap_s <= self.config.estop_after_s:
            return
        log.warning("the bridge stalled for %.2f s: discarding every state received before, "
                    "waiting for fresh ones (latched robots are re-armed)", gap_s)
        self.stats.stalls += 1
        self.stats.longest_stall_s = max(self.stats.longest_stall_s, gap_s)
        self._resume_ns = now
        self._discard.update((r, state_key(rs)) for r, rs in states.items())
        self.round_trips.forget_sent()
        self._sent_tick.clear()
        if self.on_stall is not None:
            self.on_stall()

    def _classify(self, now: int, states: Mapping[str, ReceivedState]) -> View:
        """Rows, silent and unknown robots, and the longest silence of a live one."""
        view = View()
        self._forget_departed(states)
        alive = self.link.alive_robots
        for robot in self.registry.names:
            rs = states.get(robot)
            if robot not in alive:
                was_alive = self._heard_since.pop(robot, None) is not None
                if rs is not None:
                    if was_alive or not self._new_link(robot, rs):
                        self._discard[robot] = state_key(rs)
                    view.silent.append((rs, self._age_s(rs, now)))
                continue
            since = max(self._heard_since.setdefault(robot, now), self._resume_ns)
            age = self._age_s(rs, now) if rs is not None else math.inf
            silence = min(age, (now - since) / 1e9)
            if view.silence is None or silence > view.silence[1]:
                view.silence = (robot, silence)
            usable = rs is not None and state_key(rs) != self._discard.get(robot)
            if usable:
                self._discard.pop(robot, None)
                self.rearm.state(robot, rs.msg.status)
            if usable and not self.rearm.refusing(robot):
                view.rows.append(rs)
                view.ages.append(age)
            else:
                view.unknown.append(robot)
                if rs is not None:
                    view.silent.append((rs, age))
        return view

    def _forget_departed(self, states: Mapping[str, ReceivedState]) -> None:
        """A robot whose token went since the last look, even if it is back (a restart between
        two ticks): its state received before it left is discarded, and it is heard anew."""
        for event in self.link.pop_events():
            if event.joined:
                continue
            self._heard_since.pop(event.robot, None)
            rs = states.get(event.robot)
            if rs is not None and rs.receive_time_ns <= event.time_ns:
                self._discard[event.robot] = state_key(rs)

    def _new_link(self, robot: str, rs: ReceivedState) -> bool:
        """Whether ``rs``, from a robot without a liveliness token, opens a new link: another epoch
        than the state discarded when it went. A rejoining robot's first STATE can reach the bridge
        before its token does (they travel apart); kept, it is answered as soon as the token comes
        (discarded, the robot waited a tick for its next one, and a lock-stepped fleet stalled
        for its whole timeout). A late STATE of the old link (same epoch) is discarded."""
        gone = self._discard.get(robot)
        return gone is None or rs.msg.epoch != gone[0]

    def _check_estop(self, view: View) -> None:
        self._silence = view.silence
        if view.silence is None or view.silence[1] <= self.config.estop_after_s \
                or self.link.estop_engaged:
            return
        robot, silence = view.silence
        log.error("robot %s has been silent for %.3f s: raising the fleet e-stop", robot, silence)
        self.link.raise_estop(ESTOP_STALE_PICTURE)
        self.stats.estops += 1
        self.stats.estop_robot, self.stats.estop_silence_s = robot, float(silence)

    def operator_request(self, request: str) -> dict:
        """An operator's e-stop request (``formation estop``), answered on a Zenoh thread by
        :func:`deploy.operator_channel.operator_answer` with the silence seen last tick."""
        if request == "engage":
            self.stats.estops += 1
        return operator_answer(request, self.link, self._silence, self.config.estop_after_s)

    def _fleet_state(self, view: View, now: int) -> FleetState:
        rows = [rs.msg for rs in view.rows]
        silent = None
        if view.silent:
            silent = SilentRobots(tuple(rs.robot for rs, _ in view.silent),
                                  np.array([rs.msg.position for rs, _ in view.silent]),
                                  np.array([rs.msg.velocity for rs, _ in view.silent]),
                                  np.array([age for _, age in view.silent]),
                                  np.array([self.targets[rs.robot] for rs, _ in view.silent]),
                                  np.array([self._silent_pending(rs) for rs, _ in view.silent], dtype=np.int64))
        return FleetState(
            time=(self.link.clock_ns() - self._start_ns) / 1e9, step=self.stats.ticks,
            positions=np.array([m.position for m in rows]),
            velocities=np.array([m.velocity for m in rows]),
            targets=np.array([self.targets[rs.robot] for rs in view.rows]),
            object_pose=self.object_pose.copy(), robot_ids=tuple(rs.robot for rs in view.rows),
            state_age_s=np.array(view.ages), silent=silent,
            command_delay_s=self.round_trips.bound_s(),
            commands_pending=np.array([self.round_trips.pending(rs.robot, rs.msg.last_cmd_seq)
                                       for rs in view.rows], dtype=np.int64).reshape(-1),
            obstacles=self.sightings.obstacles(now))

    def _silent_pending(self, rs: ReceivedState) -> int:
        """A silent robot's ``SilentRobots.commands_pending`` (:mod:`deploy.bridge`, Command delay):
        the commands sent after the one its last state names, plus the ticks since the last of
        them; -1 when those are not known."""
        pending = self.round_trips.pending(rs.robot, rs.msg.last_cmd_seq)
        last = self._sent_tick.get(rs.robot)
        if pending < 0 or last is None:
            return -1
        return pending + self.stats.ticks - last - 1


__all__ = ["ESTOP_STALE_PICTURE", "BridgePicture", "View", "state_key"]
