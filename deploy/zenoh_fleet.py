"""A fleet over Zenoh behind the :class:`sim.fleet.Fleet` interface: the same three calls as the
simulated worlds, so :func:`stack.pipeline.run_episode` (and ``formation eval --world zenoh``)
drives a real fleet, or ``formation fleet-sim``, with the same metrics::

    fleet = ZenohFleet(scenario, "lab", TransportConfig(connect=("tcp/127.0.0.1:7447",)))
    state = fleet.reset()
    fleet.send_accelerations(controller(state)); state = fleet.step()

Underneath runs a :class:`deploy.bridge.Bridge` in a thread, with every rule of the bridge (BRAKE
for stale or non-finite rows, silent robots as obstacles, the fleet e-stop): its controller
hands each picture to :meth:`step` and waits for the answer of :meth:`send_accelerations`
(``answer_timeout_s``; then the bridge brakes every robot that tick, as for a failed controller,
and the late answer is dropped, not taken for the next picture's). :meth:`braked_in_place` says
which rows of a picture got BRAKE in place of the answer.

Episodes are the fleet's own: a fleet that resets its world every ``episode_steps`` ticks
(``fleet-sim --episodes``) starts episode k at state ``seq`` k T + 1. :meth:`reset` waits for the
first state of the next episode, answering the ticks in between with BRAKE (the first call takes
the first state it gets); the seed is the fleet's (``fleet-sim --seed S`` plays S, S + 1, ...), so
``seed`` is only recorded. The robots must stay the same N for the whole episode: a fleet whose
robots join and leave is a job for ``formation bridge``.

The fleet's robots must be the scenario's (``r0 .. r{N-1}``): the fleet's liveliness tokens name
the robots it runs, and a fleet that runs robots the scenario lacks, or lacks some of them, is
refused with :class:`FleetMismatch` at the first state (not driven as a part of itself, its
other robots left unanswered).

Between episodes (and after a late answer) the bridge brakes every robot: the controller raises
:class:`deploy.bridge.BrakeThisTick` (no fault, no traceback).
"""

from __future__ import annotations

import dataclasses
import queue
import threading
import time
from collections import deque

import numpy as np

from deploy.bridge import BrakeThisTick, Bridge, BridgeConfig
from deploy.fleet_sim import robot_names
from deploy.network import TransportConfig
from deploy.wire import RobotRegistry
from sim.fleet import FleetState, check_accelerations
from sim.scenario import Scenario


class FleetTimeout(RuntimeError):
    """The fleet sent no state in time; the message says what to check."""


class FleetMismatch(ValueError):
    """The fleet runs other robots than the scenario's: ``scenario_robots`` and
    ``fleet_robots`` (those whose liveliness tokens are up), each sorted."""

    def __init__(self, fleet: str, scenario_robots: tuple[str, ...], fleet_robots: tuple[str, ...]):
        self.fleet, self.scenario_robots, self.fleet_robots = fleet, scenario_robots, fleet_robots
        super().__init__(f"the scenario has robots {robot_span(scenario_robots)}, but fleet {fleet!r} "
                         f"runs {robot_span(fleet_robots) or 'none'}: give the scenario the fleet runs")


def robot_span(names: tuple[str, ...] | list[str]) -> str:
    """``r0..r4`` for consecutive ``r0 .. r4``; the names, comma-separated, otherwise."""
    if len(names) > 2 and list(names) == [f"r{i}" for i in range(len(names))]:
        return f"r0..r{len(names) - 1}"
    return ", ".join(names)


class ZenohFleet:
    """A :class:`sim.fleet.Fleet` over Zenoh (module docstring). Close it, or use it as a
    context manager."""

    def __init__(self, scenario: Scenario, fleet: str, transport: TransportConfig,
                 config: BridgeConfig | None = None, state_timeout_s: float = 30.0,
                 answer_timeout_s: float = 5.0):
        self.scenario = scenario
        self.state_timeout_s, self.answer_timeout_s = state_timeout_s, answer_timeout_s
        names = robot_names(scenario.num_robots)
        config = dataclasses.replace(config or BridgeConfig(period_s=scenario.dynamics.dt),
                                     episode_ticks=scenario.dynamics.episode_steps)
        c = scenario.object_center
        self._states: queue.Queue[tuple[FleetState, int | None]] = queue.Queue(maxsize=1)
        # each answer names the state it answers: one that comes after its deadline is dropped
        self._answers: queue.Queue[tuple[FleetState | None, np.ndarray | None]] = queue.Queue(maxsize=1)
        self._braked: deque[tuple[FleetState, np.ndarray]] = deque(maxlen=16)   # the bridge's on_sent
        self._state: FleetState | None = None      # the newest state, waiting for its answer
        self._state_episode: int | None = None     # the fleet episode it belongs to
        self._episode: int | None = None           # the episode being run
        self.bridge = Bridge(fleet, RobotRegistry(names), transport, self._controller,
                             targets=dict(zip(names, scenario.targets, strict=True)),
                             object_pose=np.array([c[0], c[1], 0.0]), config=config,
                             on_sent=self._on_sent)
        self._names = names
        self._fleet_robots: set[str] = set()       # robots whose liveliness tokens are up
        self._robots_lock = threading.Lock()
        self._checked = False                      # the fleet's robots checked at the first state
        try:
            link = self.bridge.link
            self._alive_subscriber = link.session.liveliness().declare_subscriber(
                link.keys.all_robot_alive, self._on_alive, history=True)
        except BaseException:
            self.bridge.close()
            raise
        self._thread = threading.Thread(target=self.bridge.run, name="ZenohFleet-bridge", daemon=True)
        self._thread.start()

    @property
    def dt(self) -> float:
        return self.scenario.dynamics.dt

    # ------------------------------------------------------------ bridge thread
    def _on_alive(self, sample) -> None:
        """A robot's liveliness token came up or went down (any name, the scenario's or not)."""
        robot = self.bridge.link.keys.robot_in(str(sample.key_expr), "alive")
        if robot is not None:
            import zenoh

            with self._robots_lock:
                (self._fleet_robots.add if sample.kind == zenoh.SampleKind.PUT else self._fleet_robots.discard)(robot)

    def fleet_robots(self) -> tuple[str, ...]:
        """The robots the fleet runs (liveliness tokens up), in name order (``r2`` before ``r10``)."""
        with self._robots_lock:
            robots = list(self._fleet_robots)
        return tuple(sorted(robots, key=lambda r: (len(r), r)))

    def _controller(self, state: FleetState) -> np.ndarray:
        self._states.put((state, self.bridge.episode), timeout=self.answer_timeout_s)
        deadline = time.monotonic() + self.answer_timeout_s
        while True:     # queue.Empty at the deadline: the bridge brakes every robot this tick
            answered, answer = self._answers.get(timeout=max(deadline - time.monotonic(), 0.0))
            if answered is None or answered is state:    # None: closing
                break
        if answer is None:
            raise BrakeThisTick("between episodes")
        return answer

    def _on_sent(self, state: FleetState, braked: np.ndarray) -> None:
        self._braked.append((state, braked.copy()))

    def braked_in_place(self, state: FleetState) -> np.ndarray | None:
        """(N,) bool: the rows of ``state`` (one this fleet handed out, after the next
        :meth:`step`) that the bridge sent BRAKE in place of the answer (its age, or an answer
        later than ``answer_timeout_s``: then every row), or None when it sent the answer as it
        was. :func:`stack.episodes.run_episode` passes it to the stack
        (:meth:`stack.pipeline.ControlStack.sent_braking`)."""
        for braked_state, braked in list(self._braked):
            if braked_state is state:
                return braked
        return None

    # ------------------------------------------------------------ Fleet
    def _next_state(self) -> FleetState:
        try:
            state, episode = self._states.get(timeout=self.state_timeout_s)
        except queue.Empty:
            raise FleetTimeout(f"no state from fleet {self.bridge.link.keys.fleet!r} within "
                               f"{self.state_timeout_s} s: is the fleet running, on the same "
                               "endpoints, with these robot names?") from None
        self._check_robots(first=not self._checked)
        if state.num_robots != self.scenario.num_robots:
            raise FleetTimeout(f"the fleet reports {state.num_robots} robots ({state.robot_ids}), the "
                               f"scenario has {self.scenario.num_robots}: robots joined or left")
        self._state, self._state_episode = state, episode
        return state

    def _check_robots(self, first: bool, settle_s: float = 1.0) -> None:
        """FleetMismatch when the fleet runs a robot the scenario lacks, or (``first``: at the
        first state) lacks one of the scenario's. The bridge answers a first state once every
        scenario robot it hears of is live, so the tokens of the rest of the fleet are due too:
        they get ``settle_s`` to arrive. Later, a robot that leaves is the FleetTimeout of
        :meth:`_next_state`."""
        names = set(self._names)
        deadline = time.monotonic() + (settle_s if first else 0.0)
        robots = self.fleet_robots()
        while set(robots) != names and time.monotonic() < deadline:
            time.sleep(0.02)
            robots = self.fleet_robots()
        if set(robots) - names or (first and set(robots) != names):
            raise FleetMismatch(self.bridge.link.keys.fleet, tuple(self._names), robots)
        self._checked = True

    def reset(self, seed: int | None = None) -> FleetState:
        """The first state of the fleet's next episode (module docstring; ``seed`` is the fleet's)."""
        if self._state is not None:
            if self._state_episode != self._episode:    # the last step already began the next one
                self._episode = self._state_episode
                return self._state
            self._answer(self._state, None)             # its answer: brake
        while True:
            state = self._next_state()
            if self._episode is None or self._state_episode != self._episode:
                self._episode = self._state_episode
                return state
            self._answer(state, None)

    def read_state(self) -> FleetState:
        if self._state is None:
            raise RuntimeError("ZenohFleet.read_state before reset: call reset() first")
        return self._state

    def send_accelerations(self, accelerations: np.ndarray) -> None:
        if self._state is None:
            raise RuntimeError("ZenohFleet.send_accelerations before reset: call reset() first")
        self._answer(self._state, check_accelerations(accelerations, self.scenario.num_robots).copy())

    def _answer(self, state: FleetState | None, answer: np.ndarray | None) -> None:
        """Queue the answer to ``state``; one still queued is for an older picture, which the
        bridge gave up on (it would block this call if the fleet went quiet): dropped."""
        while True:
            try:
                self._answers.put_nowait((state, answer))
                return
            except queue.Full:
                try:
                    self._answers.get_nowait()
                except queue.Empty:
                    pass

    def step(self) -> FleetState:
        """The fleet's next state (the one that answers the accelerations just sent)."""
        return self._next_state()

    def close(self) -> None:
        self.bridge.stop()
        try:
            self._alive_subscriber.undeclare()
        except Exception:    # the session may be closing already
            pass
        while not self._answers.full():             # release a controller call that waits
            self._answers.put((None, None))
        self._thread.join(timeout=5.0)
        self.bridge.close()

    def __enter__(self) -> ZenohFleet:
        return self

    def __exit__(self, *exc) -> None:
        self.close()
