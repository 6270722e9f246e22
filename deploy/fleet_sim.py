"""A simulated fleet over Zenoh: :class:`sim.pymunk_world.PymunkWorld` as N robots.

One process, one Zenoh session, one :class:`deploy.robot_link.RobotLink` per robot (robot
``r<i>`` is row i of the scenario). Each tick every online robot publishes its measured
state (position [m], velocity [m/s]); the world then advances one ``dt`` with, per robot,
the acceleration chosen by its own watchdog (below).

Pacing:
    * real time: one tick every ``1 / rate_hz`` seconds of wall time;
    * lock-step (tests): after publishing the states of tick k, wait until every online robot
      holds a command answering its state of tick k (``state_seq``), has seen the
      controller's liveliness token (a link opened this tick learns of it on another Zenoh
      thread; a command taken before would be ignored) and has its answer to the query for the
      latched e-stop (before it, the robot brakes), or ``lockstep_timeout_s``; then
      advance. Deterministic when the controller is. States are published lossless
      (:mod:`deploy.transport`, Delivery), so a starved CPU delays a tick but loses none, and
      carry the STATE flag LOCKSTEP, so a bridge sends its commands lossless too; run the
      controller lock-stepped as well (``bridge --lockstep``: sim time).

Episodes (``episodes=K``): the world is reset with seed ``seed + k`` at the start of episode
k and runs the scenario's ``episode_steps`` ticks T; the run ends after K episodes. Global
tick t belongs to episode ``t // T``; every robot link stays open, so robot state ``seq``
(1, 2, ... per link) is ``t + 1`` while no robot leaves, and a controller can tell episode
boundaries from it (``(seq - 1) // T``, see :class:`deploy.bridge.BridgeConfig`). Each finished
episode is judged on the true state (success, final distance, assignment, collision onsets)
and keeps its true positions (T+1, N, 2) [m], contacts (T, N, 3) (robot, object, wall) and,
in lock-step, the round trip of each tick [ms]: first state published -> every command in.

Playout (``playout_ticks = D``, 0: off): a robot acts on its newest command that answers its
STATE of D ticks ago or older (``state_seq``; a command answering no state, ``state_seq`` 0,
at once), so a command that came early waits in its buffer
(:attr:`deploy.robot_link.RobotLink.recent_commands`) and one that came late acts on arrival.
A delay that jitters up to D ticks then acts as a steady D, which the controller measures
(``last_cmd_seq``) and predicts through; the commands' ``ttl`` must cover the D ticks. Without
it a robot acts on its newest command, and commands that arrive a tick early or late are
skipped or held (``bench/jittery_link.py``).

Watchdog (per robot; ages in ticks of this process, converted with the tick period:
``1 / rate_hz`` in real time, ``dt`` = sim time in lock-step). A command is *fresh* for tick k
when it arrived during tick k (after the state of tick k was published; with playout, when it
fell due); decided per tick, in
priority order::

    e-stop latched (ESTOP)                      -> brake               status ESTOPPED
    watchdog latch set                          -> brake, hold at rest status WATCHDOG_BRAKING|FAULT
    no command accepted yet                     -> brake (not armed)   status WATCHDOG_BRAKING
    last command older than stop_after_s        -> set the latch       (armed robots only)
    brake_after_ticks ticks in a row without a
      fresh command, or the command past its
      ttl (real time only)                      -> brake               status WATCHDOG_BRAKING
    command flag BRAKE, or STOP held            -> brake
    otherwise                                   -> the commanded acceleration

``brake`` is :meth:`sim.scenario.Dynamics.brake`, the one braking law of the project
(``clip_norm(c v - v / dt, accel_limit)``: at rest after one tick in the nominal model when the
actuator allows, never reversing). With ``brake_after_ticks = 1`` (the default) a robot brakes on
the first tick whose state goes unanswered, so a controller killed or frozen while the fleet
runs at the 0.4 m/s speed limit leaves it at rest 8 braking ticks later: every published speed
is 0 within 9 ticks (0.45 s) of the last command, measured 0.445 s from outside
(``tests/deploy/test_watchdog_stop_time.py``; 0.55 s with the former 2 ticks of grace).
The status published with a state says what the robot does if that state goes unanswered.
Re-arming the latch: the controller sees FAULT in the robot's state and sends a command with
the STOP flag; the robot leaves the latch into STOP (held at rest) and moves again on the
next command without STOP. While latched, other commands are ignored and counted. So are
commands the robot would take (at its tick) while it sees no controller liveliness token
(``ctrl/alive``): a robot obeys the node that holds it, not any node that can publish on its
key. The token is judged when a command is taken, not when it arrived: token and commands reach
the robot on separate Zenoh threads, and a lock-stepped fleet waits for both before its tick.
So a command that came shortly before a controller's token can act, for one tick at most (the
controller answers the next state), once the latched e-stop has been fetched; mutual TLS with
access control on a router is what keeps other nodes off the command keys.

Trace (``summary()["trace"]``, one entry per tick k, the true state at tick k; a real-time run
without ``max_ticks`` keeps the newest ``TRACE_TICKS``): ``modes`` (each
robot's watchdog branch when it published its state), ``applied`` (the branch whose acceleration
it applied), ``speeds`` [m/s], ``positions`` (N, 2) [m] and ``contacts`` (N, 3) (robot, object,
wall; from the previous tick's motion).

Clock: on one host (``shared_clock``; by default when every endpoint is on loopback) a robot
refuses a CMD sent more than 100 ms ahead of its clock (FROM_FUTURE) and, in real time, one older
than its ttl (EXPIRED), as ``docs/wire-format.md`` asks; lock-step runs on sim time, where a
command's wall-clock age says nothing, so only FROM_FUTURE applies there. In real time a robot
also refuses a CMD answering a STATE it sent more than ``MAX_ANSWER_AGE_S`` (0.5 s) ago by its
own clock (STALE_ANSWER, :class:`deploy.robot_link.RobotLink`): on any link, shared clock or not.

Intruders (``intruders``, :class:`sim.intruders.Intruder`): discs that walk straight lines
through the arena, restarted every episode. The fleet's simulated tracker
(:class:`deploy.tracker.SimulatedTracker`) publishes each one as a SIGHTING on the fleet's
sightings key before the robots' states of every tick, and GONE when it leaves; each episode's
record (and the summary, for the last one) says how close the robots came and whether one drove
into an intruder (``intruders``: ``min_gap_mm``, ``drive_in_ticks``, ``max_drive_in_speed``).
With ``track_robots`` (:class:`sim.intruders.RobotSightings`) the tracker identifies the robots
too, online or not, every tick (flag ROBOT, :mod:`deploy.tracker`).

Test knobs: ``drop_commands`` (probability that a newly arrived command is discarded, as if
lost) and ``events`` (``(tick, robot, "leave" | "join")``: the robot's link closes or opens;
a robot whose first event is a join starts offline; an offline robot brakes and is not
published).
"""

from __future__ import annotations

import json
import threading
import time
from collections import deque
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import zenoh

from deploy.fleet_sim_config import FleetSimConfig, WatchdogConfig, robot_names
from deploy.reject_log import RejectLog
from deploy.robot_link import MAX_ANSWER_AGE_S, RobotLink
from deploy.tracker import SightingPublisher, SimulatedTracker
from deploy.wire import CmdFlags, RobotRegistry, StateStatus
from sim.files import atomic_write_text
from sim.pymunk_world import PymunkWorld

TRACE_TICKS = 12_000
"""Ticks of trace a real-time run without ``max_ticks`` keeps (10 minutes at 20 Hz)."""


@dataclass
class _Robot:
    name: str
    link: RobotLink | None = None
    seen: tuple[int, int] = (0, 0)  # (epoch, seq) of the newest command looked at
    accel: np.ndarray = field(default_factory=lambda: np.zeros(2))
    flags: CmdFlags = CmdFlags(0)
    cmd_tick: int | None = None
    expires_ns: int = 0
    stop_held: bool = False
    latched: bool = False
    estopped: bool = False
    estop_unknown: bool = False   # the controller's latched e-stop not fetched yet: brake
    mode: str = "idle"
    accepted_seq: int = 0  # seq of the command in force (0: none yet)
    state_seq: int = 0     # seq of the newest STATE its link published (0: none yet)


class FleetSim:
    """Run with :meth:`run`; stop from another thread (or a signal handler) with :meth:`stop`.

    ``on_episode(record)``, if given, is called with each finished episode's record (episodes
    mode), e.g. to report progress.
    """

    def __init__(self, config: FleetSimConfig,
                 on_episode: Callable[[dict[str, Any]], Any] | None = None):
        self.config = config
        sc = config.scenario
        self.world = PymunkWorld(sc, config.model_error, seed=config.seed)
        self.names = robot_names(sc.num_robots)
        self.registry = RobotRegistry(self.names)
        self.period_s = 1.0 / config.rate_hz if config.rate_hz else sc.dynamics.dt
        self.robots = [_Robot(name) for name in self.names]
        self._rng = np.random.default_rng(config.seed + 1)
        self._stop = threading.Event()
        self.tick = 0
        self.dropped = 0
        self._in_force: deque[np.ndarray] = deque(maxlen=64)  # accepted seqs per tick, newest last
        self._acted = np.zeros(len(self.robots), dtype=np.int64)
        self.ignored_while_latched = 0
        self.ignored_without_controller = 0
        self.lockstep_timeouts = 0
        # a run without a tick or episode limit may go on for days (lock-step too): keep the newest
        endless = config.max_ticks is None and config.episodes is None          # TRACE_TICKS ticks
        self.trace: deque[dict[str, Any]] = deque(maxlen=TRACE_TICKS if endless else None)
        self.on_episode = on_episode
        self.episode_ticks = sc.dynamics.episode_steps
        self.episodes: list[dict[str, Any]] = []
        self._episode: dict[str, list] | None = None
        self._timeouts_before = 0
        self.closed_link_rejects: dict[str, int] = {}
        self.closed_link_missed = 0
        self._reject_log = RejectLog(f"fleet-sim {config.fleet}", self.rejects)
        self.session: zenoh.Session | None = None
        self.tracker: SimulatedTracker | None = None

    def stop(self) -> None:
        self._stop.set()

    @property
    def lossless(self) -> bool:
        """Lock-step links publish states with BLOCK (see the module docstring, Pacing)."""
        return self.config.rate_hz is None

    # ------------------------------------------------------------------ links
    def _open_link(self, robot: _Robot) -> None:
        robot.link = RobotLink(self.config.fleet, robot.name, self.registry, self.session,
                               shared_clock=self.config.clock_is_shared(), expiry=not self.lossless,
                               lossless=self.lossless,
                               max_answer_age_s=None if self.lossless else MAX_ANSWER_AGE_S)
        robot.seen = (0, 0)
        robot.state_seq = 0

    def _close_link(self, robot: _Robot) -> None:
        if robot.link is not None:
            for reason, count in robot.link.rejects.snapshot().items():
                self.closed_link_rejects[reason] = self.closed_link_rejects.get(reason, 0) + count
            self.closed_link_missed += robot.link.missed_commands
            robot.link.close()
            robot.link = None

    def missed_commands(self) -> int:
        """Commands the controller sent that never reached a robot's decoder (gaps in its seq;
        :class:`deploy.robot_link.CommandGaps`), open and closed links."""
        return self.closed_link_missed + sum(r.link.missed_commands for r in self.robots if r.link is not None)

    def rejects(self) -> dict[str, int]:
        """Rejected messages by reason over every robot link, open and closed."""
        total = dict(self.closed_link_rejects)
        for robot in self.robots:
            if robot.link is not None:
                for reason, count in robot.link.rejects.snapshot().items():
                    total[reason] = total.get(reason, 0) + count
        return total

    # ------------------------------------------------------------------ watchdog
    def _take_command(self, robot: _Robot, tick_seq: int) -> None:
        """Take the robot's newest command (with a playout buffer, its newest due one: module
        docstring, Playout); ``tick_seq`` is the seq of its STATE of this tick."""
        link = robot.link
        if link is None:
            return
        # until the controller has answered the query for its latched e-stop, the robot cannot
        # know whether one is engaged: where it would move, it brakes (:meth:`_choose`)
        robot.estopped = link.estopped
        robot.estop_unknown = link.controller_alive and not link.estop_synced
        if self.config.playout_ticks:
            received = self._due_command(link.recent_commands, robot.seen, tick_seq - self.config.playout_ticks)
        else:
            received = link.latest_command
        if received is None or (received.msg.epoch, received.msg.seq) == robot.seen:
            return
        robot.seen = (received.msg.epoch, received.msg.seq)
        if not link.controller_alive:      # only the node holding the controller token commands
            self.ignored_without_controller += 1
            return
        if self.config.drop_commands and self._rng.random() < self.config.drop_commands:
            self.dropped += 1
            return
        flags = received.msg.flags
        if robot.latched:
            if not flags & CmdFlags.STOP:
                self.ignored_while_latched += 1
                return
            robot.latched = False
        robot.accel = np.asarray(received.msg.acceleration, dtype=np.float64)
        robot.accepted_seq = received.msg.seq
        robot.flags = flags
        robot.stop_held = bool(flags & CmdFlags.STOP)
        robot.cmd_tick = self.tick
        robot.expires_ns = received.expires_at_ns

    @staticmethod
    def _due_command(recent, seen: tuple[int, int], due_seq: int):
        """The newest of ``recent`` (oldest first) that arrived after the one ``seen`` and is
        due: it answers a STATE of seq ``due_seq`` or older, or none (``state_seq`` 0)."""
        keys = [(r.msg.epoch, r.msg.seq) for r in recent]
        start = keys.index(seen) + 1 if seen in keys else 0
        due = [r for r in recent[start:] if r.msg.state_seq <= due_seq]
        return due[-1] if due else None

    def _choose(self, robot: _Robot, velocity: np.ndarray, now_ns: int,
                deciding: bool = True) -> tuple[np.ndarray, StateStatus]:
        """The acceleration this robot applies this tick and its status bits.

        ``deciding``: the commands of this tick are in (the acceleration is applied); False
        when publishing the state, before its answer can have arrived (the status then says
        what the robot does if this state goes unanswered)."""
        brake = self.config.scenario.dynamics.brake(velocity[None])[0]
        wd = self.config.watchdog
        if robot.estopped:
            robot.mode = "estop"
            return brake, StateStatus.ESTOPPED
        if robot.cmd_tick is None:
            robot.mode = "idle"
            return brake, StateStatus.WATCHDOG_BRAKING
        age_s = (self.tick - robot.cmd_tick) * self.period_s
        if not robot.latched and age_s >= wd.stop_after_s:
            robot.latched = True
        if robot.latched:
            robot.mode = "latched"
            return brake, StateStatus.WATCHDOG_BRAKING | StateStatus.FAULT
        unanswered = self.tick - robot.cmd_tick - (0 if deciding else 1)
        expired = self.config.rate_hz is not None and now_ns >= robot.expires_ns
        if unanswered >= wd.brake_after_ticks or expired:
            robot.mode = "watchdog"
            return brake, StateStatus.WATCHDOG_BRAKING
        if robot.estop_unknown:           # would move, but cannot know yet whether it may
            robot.mode = "estop_unknown"
            return brake, StateStatus(0)
        if robot.stop_held or robot.flags & CmdFlags.BRAKE:
            robot.mode = "stop"
            return brake, StateStatus(0)
        robot.mode = "run"
        return robot.accel, StateStatus(0)

    # ------------------------------------------------------------------ episodes
    def _start_episode(self):
        """Reset the world for episode ``len(self.episodes)``; return its measured state."""
        state = self.world.reset(seed=self.config.seed + len(self.episodes))
        if self.tracker is not None:
            self.tracker.reset()
        self._episode = {"positions": [self.world.true_state().positions.round(6).tolist()],
                         "contacts": [], "round_trip_ms": [], "timeout_ticks": []}
        return state

    def _record_tick(self, round_trip_ms: float | None) -> None:
        ep = self._episode
        c = self.world.contacts
        ep["positions"].append(self.world.true_state().positions.round(6).tolist())
        ep["contacts"].append(np.stack((c.robot, c.object, c.wall), -1).astype(int).tolist())
        if round_trip_ms is not None:
            ep["round_trip_ms"].append(round(round_trip_ms, 4))
        elif self.config.rate_hz is None:
            ep["timeout_ticks"].append(len(ep["contacts"]) - 1)

    def _finish_episode(self) -> None:
        outcome = self.world.outcome()
        counts = self.world.collision_counts
        ep, self._episode = self._episode, None
        rtt = np.asarray(ep["round_trip_ms"]) if ep["round_trip_ms"] else None
        record = {"episode": len(self.episodes), "seed": self.config.seed + len(self.episodes),
                  "ticks": len(ep["contacts"]), "success": bool(outcome.success.item()),
                  "final_distance": float(outcome.final_distance.item()),
                  "assignment": outcome.assignment[0].tolist(),
                  "collisions": {"robot": counts.robot, "object": counts.object, "wall": counts.wall},
                  "lockstep_timeouts": self.lockstep_timeouts - self._timeouts_before,
                  "timeout_ticks": ep["timeout_ticks"],
                  "round_trip_ms": None if rtt is None else {
                      "p50": float(np.percentile(rtt, 50)), "p99": float(np.percentile(rtt, 99)),
                      "max": float(rtt.max())},
                  "positions": ep["positions"], "contacts": ep["contacts"]}
        if self.tracker is not None:
            record["intruders"] = self.tracker.watch.summary()
        self.episodes.append(record)
        if self.on_episode is not None:
            self.on_episode(record)

    # ------------------------------------------------------------------ loop
    def _apply_events(self) -> None:
        for tick, name, kind in self.config.events:
            if tick == self.tick:
                robot = self.robots[self.names.index(name)]
                if kind == "leave":
                    self._close_link(robot)
                elif robot.link is None:
                    self._open_link(robot)

    def _trace_entry(self, modes: list[str]) -> dict[str, Any]:
        """This tick's trace entry (the true state; see the module docstring, Trace)."""
        true = self.world.true_state()
        c = self.world.contacts
        entry = {"tick": self.tick, "t": round(true.time, 6), "modes": modes,
                 "speeds": np.linalg.norm(true.velocities, axis=1).round(6).tolist(),
                 "positions": true.positions.round(6).tolist(),
                 "contacts": np.stack((c.robot, c.object, c.wall), -1).astype(int).tolist()}
        self.trace.append(entry)
        return entry

    def _wait_lockstep(self, answered: dict[str, int]) -> bool:
        """Wait for every answer (see the module docstring); False on a timeout."""
        deadline = time.monotonic() + self.config.lockstep_timeout_s
        for robot in self.robots:
            link, seq = robot.link, answered.get(robot.name)
            if link is None or seq is None:
                continue
            ok = link.wait_for(lambda lk=link, s=seq: lk.latest_command is not None
                               and lk.latest_command.msg.state_seq >= s and lk.controller_alive
                               and lk.estop_synced,
                               max(0.0, deadline - time.monotonic()))
            if not ok:
                self.lockstep_timeouts += 1
                return False
        return True

    def run(self) -> dict[str, Any]:
        """Run until :meth:`stop` or ``max_ticks``; return :meth:`summary`."""
        cfg = self.config
        self.session = cfg.transport.open()
        try:
            if cfg.intruders or cfg.track_robots is not None:
                self.tracker = SimulatedTracker(SightingPublisher(self.session, cfg.fleet, lossless=self.lossless),
                                                cfg.intruders, cfg.scenario.robot_radius, cfg.scenario.dynamics.dt,
                                                cfg.track_robots, self.registry)
            first_event = {}
            for _, name, kind in sorted(cfg.events, key=lambda event: event[0]):   # as _apply_events:
                first_event.setdefault(name, kind)                                 # a tick's in config order
            for robot in self.robots:
                if first_event.get(robot.name) != "join":
                    self._open_link(robot)
            online = [r.link for r in self.robots if r.link is not None]
            if online:
                online[0].wait_for(lambda: online[0].controller_alive or self._stop.is_set(),
                                   cfg.start_timeout_s)
            state = self.world.read_state()
            next_time = time.monotonic()
            while not self._stop.is_set() and (cfg.max_ticks is None or self.tick < cfg.max_ticks):
                if cfg.episodes is not None and self._episode is None:
                    if len(self.episodes) >= cfg.episodes:
                        break
                    state = self._start_episode()
                    self._timeouts_before = self.lockstep_timeouts
                self._apply_events()
                if self.tracker is not None:
                    self.tracker.look(self._episode_tick(), self.world.true_state())
                now_ns = time.monotonic_ns()
                published_ns = None
                accels = np.zeros((len(self.robots), 2))
                answered: dict[str, int] = {}
                modes = []
                for i, robot in enumerate(self.robots):
                    self._take_command(robot, robot.state_seq + 1)
                    accels[i], status = self._choose(robot, state.velocities[i], now_ns,
                                                     deciding=False)
                    modes.append(robot.mode if robot.link is not None else "offline")
                    if robot.link is not None:
                        published_ns = published_ns or time.perf_counter_ns()
                        if self.lossless:   # the wire says so: the controller then sends lossless
                            status |= StateStatus.LOCKSTEP
                        msg = robot.link.publish_state(state.positions[i], state.velocities[i], status,
                                                       last_cmd_seq=int(self._acted[i]))
                        answered[robot.name] = robot.state_seq = msg.seq
                entry = self._trace_entry(modes)
                round_trip_ms = None
                if cfg.rate_hz is None:
                    if self._wait_lockstep(answered) and published_ns is not None:
                        round_trip_ms = (time.perf_counter_ns() - published_ns) / 1e6
                    for i, robot in enumerate(self.robots):  # take the answers of this tick
                        self._take_command(robot, robot.state_seq)
                        accels[i], _ = self._choose(robot, state.velocities[i], now_ns)
                else:
                    next_time += self.period_s
                    time.sleep(max(0.0, next_time - time.monotonic()))
                    for i, robot in enumerate(self.robots):
                        self._take_command(robot, robot.state_seq)
                        accels[i], _ = self._choose(robot, state.velocities[i], time.monotonic_ns())
                entry["applied"] = [r.mode if r.link is not None else "offline" for r in self.robots]
                self.world.send_accelerations(accels)
                self._in_force.append(np.array([r.accepted_seq for r in self.robots], dtype=np.int64))
                state = self.world.step()
                self._acted = self._acted_seqs(state)
                self.tick += 1
                if self.tracker is not None:
                    true = self.world.true_state()
                    self.tracker.watch.observe(self._episode_tick(moved=True), true.positions, true.velocities)
                self._reject_log.poll()
                if self._episode is not None:
                    self._record_tick(round_trip_ms)
                    if len(self._episode["contacts"]) >= self.episode_ticks:
                        self._finish_episode()
        finally:
            for robot in self.robots:
                self._close_link(robot)
            self.session.close()
        return self.summary()

    def _episode_tick(self, moved: bool = False) -> int:
        """Tick of the current episode (of the run, without episodes) the world is at; ``moved``:
        the world stepped and the tick is not recorded yet."""
        if self._episode is None:
            return self.tick
        return len(self._episode["contacts"]) + moved

    def _acted_seqs(self, state) -> np.ndarray:
        """(N,) seq of the command each robot acted on in the motion ``state`` measures: the
        one in force ``commands_pending`` world ticks ago (the world's own delay), the STATE's
        ``last_cmd_seq``."""
        back = np.minimum(state.pending(), len(self._in_force) - 1).clip(min=0)
        return np.array([self._in_force[-1 - b][i] for i, b in enumerate(back)], dtype=np.int64)

    def summary(self) -> dict[str, Any]:
        outcome = self.world.outcome()
        counts = self.world.collision_counts
        true = self.world.true_state()
        return {"ticks": self.tick, "success": bool(outcome.success.item()),
                "final_distance": float(outcome.final_distance.item()),
                "collisions": {"robot": counts.robot, "object": counts.object, "wall": counts.wall},
                "positions": true.positions.tolist(),
                "speeds": np.linalg.norm(true.velocities, axis=1).tolist(),
                "dropped_commands": self.dropped, "missed_commands": self.missed_commands(),
                "intruders": None if self.tracker is None else self.tracker.watch.summary(),
                "ignored_while_latched": self.ignored_while_latched,
                "ignored_without_controller": self.ignored_without_controller,
                "lockstep_timeouts": self.lockstep_timeouts, "rejects": self.rejects(),
                "lossless": self.lossless, "shared_clock": self.config.clock_is_shared(),
                "episodes": self.episodes, "trace": list(self.trace)}


def write_json(path: str | Path, document: dict[str, Any]) -> None:
    """Atomic JSON write (:func:`sim.files.atomic_path`)."""
    atomic_write_text(path, json.dumps(document))


__all__ = ["FleetSim", "FleetSimConfig", "WatchdogConfig", "robot_names", "write_json"]
