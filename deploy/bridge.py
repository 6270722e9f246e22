"""The controller process's loop: robot states in, a controller callable, commands out.

``deploy/`` never imports ``stack/``: the controller is a plain callable
``controller(FleetState) -> (N, 2)`` accelerations [m/s^2] for the N rows it is given.

Robots as the bridge sees them at a tick (rows, silent, unknown, obstacles), the fleet e-stop
and the controller stall (**the recovery rule**): :mod:`deploy.bridge_picture`.

Command of a row (:func:`row_flags`): BRAKE (acceleration 0; the robot brakes itself with its
own fresh velocity) when its state is older than ``stale_after_s`` when the command goes out
(the controller's own time counts) or not finite, whatever the controller said; otherwise the controller's row, or BRAKE for every row when the controller
raises, returns a wrong shape or a non-finite value (counted; a :class:`BrakeThisTick` it raises
on purpose is neither counted nor logged with a traceback); ``on_sent(state, braked)`` then
tells the controller which rows got BRAKE or STOP in place of its command. A fresh row whose robot reports
FAULT (its watchdog latch) also gets STOP, which re-arms it (the robot holds at rest until a
command without STOP). A robot that leaves ``rearm_alarm_after`` re-arms in a row unanswered
refuses its commands (:mod:`deploy.rearm_watch`: an alarm is logged): not a row but silent, an
obstacle, its STATEs answered with STOP until one comes without FAULT.

Command delay (:class:`deploy.bridge_timing.RoundTrips`, the rule in its docstring): each
command's round trip on the bridge's clock gives ``FleetState.command_delay_s`` and the
commands still in flight, ``FleetState.commands_pending``.

One tick (:meth:`Bridge.step`): wait for a fresh state from some robot, then up to ``gather_s``
for the rest of the burst: a fresh state of every live robot (in real time: heard within the
last ``QUIET_PERIODS`` fleet periods or live without a usable state yet; a fleet publishes its
states as a burst, so one tick answers one burst; a robot gone quiet is not waited for after
that; the first tick waits, as long, for every registered robot to be live). On a link whose delay jitters a burst comes in pieces, and
a tick that answered one piece would answer its robots twice in one fleet tick, a command the
robot then skips (``bench/jittery_link.py``); check for a stall;
classify; e-stop rule; ``FleetState`` -> controller -> commands, each with ``ttl_ms`` and the
answered ``state_seq``. N changes on the fly as robots join or leave.

Episodes (``BridgeConfig.episode_ticks`` = T): a fleet that resets its world every T ticks
without closing its links (:mod:`deploy.fleet_sim` with ``episodes``) publishes state ``seq``
t + 1 at its tick t, so the burst answered belongs to episode ``(max seq - 1) // T``. When that
index changes, ``on_episode(k)`` runs before the controller (e.g. to reset its estimators);
the count is in-band, so it stays right when a burst goes unanswered.

Lock-step (``BridgeConfig.lockstep``, paired with ``fleet-sim --lockstep``): the simulated
fleet waits for every answer, so wall time says nothing about the fleet's time; the bridge then
runs on :class:`TickClock`, sim time that advances one ``period_s`` per answered burst (ROS's
``use_sim_time``). Ages, silences, round trips and ``FleetState.time`` are counted in fleet
ticks, the uplink takes no time, and a tick waits up to ``LOCKSTEP_GATHER_S`` for the whole
burst. A lock-stepped run is then the same run however loaded the machine is; commands go out
lossless (Zenoh congestion control BLOCK). A burst answered in two parts (:class:`TickClock`)
stays at one sim time.
"""

from __future__ import annotations

import logging
import threading
import time
from collections.abc import Callable, Iterable, Iterator, Mapping
from typing import Any

import numpy as np

from deploy.bridge_picture import ESTOP_STALE_PICTURE, BridgePicture, View, state_key
from deploy.bridge_timing import RoundTrips, TickClock, UplinkExcess
from deploy.bridge_types import BridgeConfig, BridgeStats, TickRecord, row_flags
from deploy.network import TransportConfig
from deploy.operator_channel import ESTOP_OPERATOR
from deploy.rearm_watch import RearmWatch
from deploy.reject_log import RejectLog
from deploy.tracker import SightingTable
from deploy.transport import FleetLink, ReceivedState
from deploy.wire import (
    BRAKE_OR_STOP,
    LOCKSTEP_BIT,
    STOP_BIT,
    CmdFlags,
    RobotRegistry,
)
from sim.fleet import FleetState

log = logging.getLogger(__name__)

Controller = Callable[[FleetState], np.ndarray]


class BrakeThisTick(Exception):
    """Raised by a controller that wants every robot braked this tick on purpose (e.g.
    :class:`deploy.zenoh_fleet.ZenohFleet` between episodes): the bridge brakes them as for a
    failed controller, but logs one line without a traceback and counts no fault."""


NO_FLAGS = CmdFlags(0)
LOCKSTEP_GATHER_S = 0.2  # [s] wall time a lock-stepped tick waits for the rest of a burst
LATE_PART_WAIT_S = 0.02  # [s] ... and what looks like a burst's late part waits for the next tick


QUIET_PERIODS = 1.5   # a live robot unheard for this many fleet periods is not waited for (gather)


class Bridge(BridgePicture):
    """Controller side of a fleet. ``targets`` maps each robot to its target slot (2,) [m];
    ``object_pose`` is (3,) [m, m, rad]; ``on_episode(k)``: see the module docstring;
    ``on_stall()``: :mod:`deploy.bridge_picture`."""

    def __init__(self, fleet: str, registry: RobotRegistry,
                 transport: TransportConfig, controller: Controller, *,
                 targets: Mapping[str, np.ndarray], object_pose: np.ndarray,
                 config: BridgeConfig | None = None,
                 on_episode: Callable[[int], Any] | None = None,
                 on_stall: Callable[[], Any] | None = None,
                 on_sent: Callable[[FleetState, np.ndarray], Any] | None = None):
        missing = [r for r in registry.names if r not in targets]
        if missing:
            raise ValueError(f"targets are missing for robots {missing}; give one (x, y) per robot")
        self.registry = registry
        self._registered = frozenset(registry.names)
        self.controller = controller
        self.targets = {r: np.asarray(targets[r], dtype=np.float64) for r in registry.names}
        self.object_pose = np.asarray(object_pose, dtype=np.float64)
        config = self.config = config or BridgeConfig()
        self.clock = TickClock(config.period_s) if config.lockstep else None
        shared = config.shared_clock
        if shared is None:
            shared = isinstance(transport, TransportConfig) and transport.loopback_only()
        self.link = FleetLink(fleet, registry, transport, clock_ns=time.monotonic_ns if self.clock is None else self.clock,
                              lossless=config.lossless or config.lockstep, shared_clock=bool(shared))
        self.sightings = SightingTable.listening(self.link, uplink=self.clock is None)
        self.stats = BridgeStats()
        self.uplink = UplinkExcess()
        self.round_trips = RoundTrips(config.delay_window, config.delay_percentile)
        self._reject_log = RejectLog(f"bridge {fleet}", self.link.rejects.snapshot)
        self.rearm = RearmWatch(f"bridge {fleet}", config.rearm_alarm_after)
        self._silence: tuple[str, float] | None = None   # the longest-silent live robot, last tick
        self.link.on_operator = self.operator_request
        self._answered: dict[str, tuple[int, int]] = {}  # robot -> (epoch, seq) last answered
        self._discard: dict[str, tuple[int, int]] = {}  # robot -> (epoch, seq) not to act on
        self._heard_since: dict[str, int] = {}  # live robot -> when the bridge noticed it [ns]
        self._sent_tick: dict[str, int] = {}  # robot -> the tick it was last sent a row's command
        self._resume_ns = 0  # end of the last stall [ns]
        self._last_look_ns: int | None = None
        self._stop = threading.Event()
        self._start_ns = self.link.clock_ns()
        self.on_episode = on_episode
        self.on_stall = on_stall
        self.on_sent = on_sent
        self.episode: int | None = None  # fleet episode of the last burst answered

    # ------------------------------------------------------------------ helpers
    def _unanswered(self, states: Mapping[str, ReceivedState], robot: str) -> bool:
        s = states.get(robot)
        return s is not None and state_key(s) != self._answered.get(robot) \
            and state_key(s) != self._discard.get(robot)

    def _wait_burst(self, timeout_s: float) -> bool:
        """Wait for a new state of some live robot, then up to ``gather_s`` for every live one
        (in real time: heard within ``QUIET_PERIODS`` fleet periods or without a usable state);
        before the first answered tick, for every registered robot to be live with a state (the
        first burst of a fleet reaches the bridge over some milliseconds, and its robots would
        otherwise join one tick at a time). The predicates run on every arriving state, under
        the link's lock: each reads the table once (it used to copy it once per robot: 146
        copies a tick at 50 robots, now 15)."""
        link = self.link

        def unanswered(robots: frozenset[str]) -> Iterator[bool]:
            states = link.latest_states()
            return (self._unanswered(states, r) for r in robots)

        def gathered() -> bool:
            alive = link.alive_robots
            if self.stats.ticks == 0 and not alive >= self._registered:
                return False
            states = link.latest_states()
            if self.stats.ticks == 0 or self.clock is not None:    # lock-step: every live robot answers
                awaited = alive - self.clock.answered if self._late_part(states, alive) else alive
                return all(self._unanswered(states, r) for r in awaited)
            recent = link.clock_ns() - int(QUIET_PERIODS * self.config.period_s * 1e9)

            def awaited(robot: str) -> bool:     # heard lately, or live without a usable state yet (a rejoin)
                rs = states.get(robot)
                return (robot not in self._heard_since or rs is None or state_key(rs) == self._discard.get(robot)
                        or rs.receive_time_ns >= recent)

            return all(self._unanswered(states, r) for r in alive if awaited(r))

        if not link.wait_for(lambda: any(unanswered(link.alive_robots)), timeout_s):
            return False
        if self._late_part(link.latest_states(), link.alive_robots):   # or the next tick's first state,
            link.wait_for(lambda: not self._late_part(link.latest_states(), link.alive_robots),  # from a
                          LATE_PART_WAIT_S)                                                      # robot new to it
        gather_s = LOCKSTEP_GATHER_S if self.clock is not None else self.config.gather_s
        link.wait_for(gathered, gather_s)
        return True

    def _fresh(self, states: Mapping[str, ReceivedState], alive: Iterable[str]) -> list[str]:
        """The robots of ``alive`` with a state not answered yet."""
        return [r for r in alive if self._unanswered(states, r)]

    def _late_part(self, states: Mapping[str, ReceivedState], alive: Iterable[str]) -> bool:
        """Lock-step: whether the new states are a burst's late part (TickClock's docstring)."""
        return self.clock is not None and self.clock.late_part(self._fresh(states, alive))

    def _mark_answered(self, rs: ReceivedState) -> None:
        """Record the answer to ``rs``; a new state answered joins the lock-step tick's part."""
        if self.clock is not None and state_key(rs) != self._answered.get(rs.robot):
            self.clock.answered.add(rs.robot)
        self._answered[rs.robot] = state_key(rs)

    def stop(self) -> None:
        self._stop.set()

    def _run_controller(self, state: FleetState) -> tuple[CmdFlags, np.ndarray, float]:
        n = state.num_robots
        t0 = time.perf_counter()
        try:
            out = np.asarray(self.controller(state), dtype=np.float64)
            if out.shape != (n, 2) or not np.all(np.isfinite(out)):
                raise ValueError(f"controller returned shape {out.shape} or non-finite values "
                                 f"for {n} robots")
            return NO_FLAGS, out, time.perf_counter() - t0
        except BrakeThisTick as brake:
            log.info("controller: braking every robot this tick (%s)", brake)
            return CmdFlags.BRAKE, np.zeros((n, 2)), time.perf_counter() - t0
        except Exception:
            log.exception("controller failed: braking every robot this tick")
            self.stats.controller_faults += 1
            return CmdFlags.BRAKE, np.zeros((n, 2)), time.perf_counter() - t0

    def _report_overrides(self, state: FleetState, sent_flags: list[CmdFlags], controller_flags: CmdFlags) -> None:
        """``on_sent(state, braked)``: the rows sent BRAKE or STOP in place of the controller's
        command (all of them when it failed), so a controller that keeps what it sent (the
        stack's command history) stays in step. A failing callback is logged, never raised."""
        if self.on_sent is None:
            return
        braked = np.array([bool(int(f) & BRAKE_OR_STOP) for f in sent_flags], dtype=bool)
        if not braked.any() and not int(controller_flags):
            return
        try:
            self.on_sent(state, braked)
        except Exception:
            log.exception("on_sent failed")

    def _count(self, view: View) -> None:
        s = self.stats
        for counts, value in ((s.robot_counts, len(view.rows)), (s.silent_counts, len(view.silent))):
            if (not counts and value) or (counts and counts[-1][1] != value):
                counts.append((s.ticks, value))
        s.silent_marks += len(view.silent)

    def _new_episode(self, view: View) -> None:
        if self.config.episode_ticks is None:
            return
        episode = (max(rs.msg.seq for rs in view.rows) - 1) // self.config.episode_ticks
        if episode != self.episode:
            self.episode = episode
            if self.on_episode is not None:
                self.on_episode(episode)

    def _rearm(self, rs: ReceivedState) -> None:
        self.stats.rearms += 1
        self.rearm.rearmed(rs.robot, rs.msg.last_cmd_seq)

    def _rearm_refusing(self, view: View, states: Mapping[str, ReceivedState]) -> None:
        """Answer each new STATE of a robot that refuses its commands with STOP, its re-arm."""
        for robot in view.unknown:
            if self.rearm.refusing(robot) and self._unanswered(states, robot):
                rs = states[robot]
                self.link.send_command(robot, (0.0, 0.0), self.config.ttl_ms, CmdFlags.STOP,
                                       state_seq=rs.msg.seq)
                self._mark_answered(rs)
                self._rearm(rs)

    # ------------------------------------------------------------------ one tick
    def step(self, timeout_s: float = 0.1) -> TickRecord | None:
        """Answer one burst of states (None if no row has a new one within ``timeout_s``)."""
        self._wait_burst(timeout_s)
        states = self.link.latest_states()
        late = self.clock is not None and self.clock.begin(self._fresh(states, self.link.alive_robots))
        now = self.link.clock_ns()
        if not self.link.lossless and any(int(rs.msg.status) & LOCKSTEP_BIT for rs in states.values()):
            log.warning("the fleet is lock-stepped (STATE flag LOCKSTEP): sending commands lossless")
            self.link.make_lossless()
        self._check_stall(now, states, timeout_s)
        view = self._classify(now, states)
        self._check_estop(view)
        self._rearm_refusing(view, states)
        self.rearm.poll()
        if not any(self._unanswered(states, rs.robot) for rs in view.rows):
            if late:
                self.clock.advance()
            return None
        self.stats.late_parts += late
        self._count(view)
        for robot in view.unknown:
            if not self.rearm.refusing(robot):
                self.link.send_command(robot, (0.0, 0.0), self.config.ttl_ms, CmdFlags.BRAKE)
                self.stats.unknown_brakes += 1
        self._new_episode(view)
        for rs in view.rows:
            self.round_trips.observe(rs)
        state = self._fleet_state(view, now)
        controller_flags, commands, controller_s = self._run_controller(state)
        if self.link.estop_engaged:                 # latched robots ignore motion: say what they do
            controller_flags |= CmdFlags.BRAKE
        late_s = (self.link.clock_ns() - now) / 1e9  # the picture aged while the controller ran
        if self.clock is not None:
            self.clock.advance()  # before the answers go out: the next burst is one tick later
        finite = np.isfinite(state.positions).all(1) & np.isfinite(state.velocities).all(1)
        sent_flags = []
        for i, rs in enumerate(view.rows):
            flags = row_flags(controller_flags, view.ages[i] + late_s, bool(finite[i]),
                              rs.msg.status, self.config.stale_after_s)
            self.stats.nonfinite_brakes += not finite[i]
            bits = int(flags)
            if bits & STOP_BIT:
                self._rearm(rs)
            if bits & BRAKE_OR_STOP:
                commands[i] = 0.0
            msg = self.link.send_command(rs.robot, (float(commands[i, 0]), float(commands[i, 1])),
                                         self.config.ttl_ms, flags, state_seq=rs.msg.seq)
            self.round_trips.sent(rs.robot, msg)
            self._sent_tick[rs.robot] = self.stats.ticks
            self._mark_answered(rs)
            sent_flags.append(flags)
        self._report_overrides(state, sent_flags, controller_flags)
        stale = tuple(rs.robot for rs, age in zip(view.rows, view.ages, strict=True)
                      if not age + late_s <= self.config.stale_after_s)
        self.stats.stale_marks += len(stale)
        self.stats.ticks += 1
        return TickRecord(self.stats.ticks - 1, state.robot_ids, stale, commands, controller_s,
                          tuple(rs.robot for rs, _ in view.silent), state.state_age_s,
                          tuple(sent_flags))

    def run(self, max_ticks: int | None = None,
            on_tick: Callable[[TickRecord], Any] | None = None) -> BridgeStats:
        """Tick until :meth:`stop` (e.g. from a signal handler) or ``max_ticks`` answered."""
        while not self._stop.is_set() and (max_ticks is None or self.stats.ticks < max_ticks):
            record = self.step()
            self._reject_log.poll()
            if record is not None and on_tick is not None:
                on_tick(record)
        return self.stats

    def summary(self) -> dict[str, Any]:
        s = self.stats
        return {"ticks": s.ticks, "stale_marks": s.stale_marks,
                "controller_faults": s.controller_faults, "rearms": s.rearms, "estops": s.estops,
                "robot_counts": s.robot_counts, "rejects": self.link.rejects.snapshot(),
                "estop_engaged": self.link.estop_engaged, "lossless": self.link.lossless,
                "lockstep": self.config.lockstep, "shared_clock": self.link.shared_clock,
                "silent_marks": s.silent_marks, "silent_counts": s.silent_counts,
                "nonfinite_brakes": s.nonfinite_brakes, "unknown_brakes": s.unknown_brakes,
                "stalls": s.stalls, "longest_stall_s": s.longest_stall_s, "heap_frozen": s.heap_frozen,
                "late_parts": s.late_parts,
                "estop_robot": s.estop_robot, "estop_silence_s": s.estop_silence_s,
                "command_delay_s": self.round_trips.bound_s(),
                "round_trip_ms": self.round_trips.summary(), **self.rearm.summary(),
                "sightings": self.sightings.summary()}

    def close(self) -> None:
        self.link.close()

    def __enter__(self) -> Bridge:
        return self

    def __exit__(self, *exc) -> None:
        self.close()


__all__ = ["ESTOP_OPERATOR", "ESTOP_STALE_PICTURE", "Bridge", "BridgeConfig", "BridgeStats",
           "Controller", "RoundTrips", "TickClock", "TickRecord", "UplinkExcess", "row_flags"]
