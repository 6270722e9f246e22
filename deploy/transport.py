"""The links between one controller and a fleet of robots over Zenoh: :class:`FleetLink`
(controller side, here) and :class:`deploy.robot_link.RobotLink` (robot side), on the keys and the
transport settings of :mod:`deploy.network`.

Threads: Zenoh delivers into bounded :class:`zenoh.handlers.RingChannel` handlers (never a
Python callback, so a Zenoh thread never waits on Python), and one driver thread per channel
blocks in ``recv()``, validates with :class:`deploy.streams.WireDecoder` and updates the link's
tables under one lock. A full ring drops its oldest sample (a robot's command ring holds
``deploy.robot_link.COMMAND_RING`` samples, and a robot counts the commands that never reached
its decoder, from the gaps in the controller's ``seq``: ``RobotLink.missed_commands``; a send
the controller refuses takes no seq). Malformed, foreign or stale
messages are counted in ``link.rejects`` and dropped; the node keeps running.

Latched e-stop: the controller publishes each ESTOP change and also serves the latest ESTOP
message from a queryable on the same key. A robot queries it whenever it sees the
controller's liveliness token appear; the controller declares the queryable before its token,
so a robot that joins after the e-stop was raised still latches it. A robot leaves the latch
only on a newer ESTOP with ENGAGED clear; a restarted controller that never raised one
answers the query with an error reply and clears nothing.

Readiness: each link declares its subscriptions before its liveliness token, so once the
controller sees a robot's token (``alive_robots``) its commands reach that robot, and once a
robot sees ``controller_alive`` its states reach the controller. Peers do not relay for each
other: whoever must reach a robot directly connects to it.

Delivery of states and commands: by default their publishers use congestion control DROP, as
a real-time link should: when the transmit pipeline is stalled the message is lost, never
queued behind older ones, and the next tick's message replaces it. A stalled pipeline needs no
network: a starved CPU is enough (180-tick lock-step runs with four busy loops on two cores
lost an answer on up to 54 ticks). The publishers are not express
(:func:`deploy.network.declare_data_publisher` says why), so a burst of one tick's messages
shares a batch and a scheduling hiccup of a millisecond no longer loses any. A lock-stepped
simulation waits for every answer, so there a lost message stalls the tick until the lock-step
timeout and the robot acts one tick late: links opened with ``lossless=True`` publish with
BLOCK instead (the sender waits for room). The e-stop is always BLOCK.
"""

from __future__ import annotations

import json
import logging
import math
import threading
import time
from collections import deque
from collections.abc import Callable, Sequence
from dataclasses import dataclass

import numpy as np
import zenoh

from deploy.network import FleetKeys, TransportConfig, declare_data_publisher
from deploy.streams import RejectCounter, Stamper, WireDecoder
from deploy.wire import (
    CmdFlags,
    CmdMsg,
    EstopMsg,
    MsgType,
    Reason,
    RobotRegistry,
    StateMsg,
    StateStatus,
    encode,
)

log = logging.getLogger(__name__)

NO_CMD_FLAGS = CmdFlags(0)
NO_STATUS = StateStatus(0)


@dataclass(frozen=True, slots=True)
class ReceivedState:
    robot: str
    msg: StateMsg
    receive_time_ns: int  # receiver's clock


@dataclass(frozen=True, slots=True)
class ReceivedCommand:
    msg: CmdMsg
    receive_time_ns: int  # receiver's clock
    expires_at_ns: int  # receiver's clock: receipt + ttl (and send + ttl on a shared clock)


@dataclass(frozen=True, slots=True)
class LivelinessEvent:
    robot: str
    joined: bool  # True: token appeared; False: token gone (node closed, killed or lease expired)
    time_ns: int  # receiver's clock


class _Link:
    """Session ownership, driver threads, the shared lock and clean close."""

    def __init__(self, transport: TransportConfig | zenoh.Session,
                 clock_ns: Callable[[], int], lossless: bool = False):
        self.lossless = bool(lossless)
        if isinstance(transport, TransportConfig):
            self.session = transport.open()
            self._owns_session = True
        elif isinstance(transport, zenoh.Session):
            self.session = transport
            self._owns_session = False
        else:
            raise TypeError("transport must be a TransportConfig or an open zenoh.Session, "
                            f"got {type(transport).__name__}")
        self.clock_ns = clock_ns
        self.rejects = RejectCounter()
        self.internal_errors = 0  # exceptions in this link's own handlers (logged); should stay 0
        self._cond = threading.Condition()
        self._closed = False
        self._entities: list = []  # undeclared in reverse order on close
        self._threads: list[threading.Thread] = []

    @property
    def data_congestion_control(self) -> zenoh.CongestionControl:
        """Congestion control of the state and command publishers (see ``lossless``)."""
        return zenoh.CongestionControl.BLOCK if self.lossless else zenoh.CongestionControl.DROP

    def _subscribe(self, declared, on_item: Callable, name: str) -> None:
        """Keep a declared subscriber/queryable and start its driver thread."""
        self._entities.append(declared)
        thread = threading.Thread(target=self._drive, args=(declared.handler, on_item),
                                  name=f"{type(self).__name__}-{name}", daemon=True)
        self._threads.append(thread)
        thread.start()

    def _open_or_close(self, capacity: int) -> None:
        """Declare the link's entities (``_open``); on any failure close what is open, then raise."""
        try:
            self._open(capacity)
        except BaseException:
            self.close()
            raise

    def _drive(self, handler, on_item: Callable) -> None:
        while True:
            try:
                item = handler.recv()
            except zenoh.ZError:  # channel closed: entity undeclared or session closed
                return
            try:
                on_item(item)
            except Exception:
                with self._cond:
                    self.internal_errors += 1
                log.exception("%s: error while handling a Zenoh sample", type(self).__name__)

    def _reject(self, reason: Reason) -> None:
        self.rejects.add(reason)

    def wait_for(self, predicate: Callable[[], bool], timeout_s: float) -> bool:
        """Block until ``predicate()`` holds (checked after every update), the timeout passes
        or the link closes; return whether it holds."""
        if math.isnan(timeout_s):                   # would never time out, and spin a core
            raise ValueError(f"{type(self).__name__}.wait_for: timeout_s is NaN; give seconds >= 0")
        deadline = time.monotonic() + timeout_s
        with self._cond:
            while not predicate():
                left = deadline - time.monotonic()
                if left <= 0 or self._closed:
                    return predicate()
                self._cond.wait(min(left, 0.05))
        return True

    @property
    def closed(self) -> bool:
        return self._closed

    def _check_open(self) -> None:
        if self._closed:
            raise RuntimeError(f"{type(self).__name__} is closed; open a new one to send")

    def close(self) -> None:
        """Undeclare everything (liveliness token first), stop the threads, close an owned session.

        Idempotent. Tables stay readable after close.
        """
        with self._cond:
            if self._closed:
                return
            self._closed = True
            self._cond.notify_all()
        for entity in reversed(self._entities):
            try:
                entity.undeclare()
            except zenoh.ZError:  # the session was closed under us: nothing left to undeclare
                pass
        for thread in self._threads:
            thread.join(timeout=2.0)
        if self._owns_session:
            self.session.close()

    def __enter__(self):
        return self

    def __exit__(self, *exc) -> None:
        self.close()


class FleetLink(_Link):
    """Controller side: latest state per robot, robot liveliness, commands, latched e-stop.

    Args:
        fleet: fleet name (one key chunk).
        registry: the robots (string ids <-> wire ids); states of others are UNKNOWN_ROBOT.
        transport: a TransportConfig (the link opens and owns the session) or an open session.
        clock_ns: the controller's monotonic clock [ns].
        shared_clock: the robots stamp ``send_time_ns`` on ``sender_clock_ns`` of this host
            (same host): also reject FROM_FUTURE sends. See :meth:`TransportConfig.loopback_only`.
        sender_clock_ns: the robots' clock read here (their monotonic clock; not ``clock_ns``,
            which may be a lock-step bridge's sim time).
        queue_capacity: ring size of each inbound channel (oldest dropped when full).
        lossless: publish commands with congestion control BLOCK instead of DROP (module
            docstring, Delivery): for a lock-stepped fleet, where every command is awaited.
    """

    def __init__(self, fleet: str, registry: RobotRegistry,
                 transport: TransportConfig | zenoh.Session, *,
                 clock_ns: Callable[[], int] = time.monotonic_ns, shared_clock: bool = False,
                 sender_clock_ns: Callable[[], int] = time.monotonic_ns,
                 queue_capacity: int = 256, lossless: bool = False):
        self.keys = FleetKeys(fleet)
        self.registry = registry
        super().__init__(transport, clock_ns, lossless)
        self.shared_clock = shared_clock
        self.decoder = WireDecoder(registry, sender_clock_ns if shared_clock else None,
                                   counter=self.rejects)
        self._states: dict[str, ReceivedState] = {}
        self._alive: set[str] = set()
        self._events: deque[LivelinessEvent] = deque(maxlen=4096)
        first = Stamper(clock_ns)
        self._cmd_stampers = {r: Stamper(clock_ns, first.epoch) for r in registry.names}
        self._estop_stamper = first
        self._estop_bytes: bytes | None = None
        self._estop_engaged = False
        self._estop_order = threading.Lock()
        self.on_operator: Callable[[str], dict] | None = None
        self.on_sighting: Callable[[bytes], None] | None = None
        self._open_or_close(queue_capacity)

    def _open(self, capacity: int) -> None:
        s = self.session
        self._subscribe(s.declare_subscriber(self.keys.all_states,
                                             zenoh.handlers.RingChannel(capacity)),
                        self._on_state, "states")
        self._subscribe(s.liveliness().declare_subscriber(
            self.keys.all_robot_alive, zenoh.handlers.RingChannel(capacity), history=True),
            self._on_liveliness, "alive")
        self._subscribe(s.declare_subscriber(self.keys.sightings, zenoh.handlers.RingChannel(capacity)),
                        self._on_sighting, "sightings")
        self._subscribe(s.declare_queryable(self.keys.operator, zenoh.handlers.RingChannel(8)),
                        self._on_operator_query, "operator")
        self._subscribe(s.declare_queryable(self.keys.estop, zenoh.handlers.RingChannel(64)),
                        self._on_estop_query, "estop-query")
        self._cmd_publishers = {robot: self._cmd_publisher(robot) for robot in self.registry.names}
        self._entities.extend(self._cmd_publishers.values())
        self._estop_publisher = s.declare_publisher(
            self.keys.estop, congestion_control=zenoh.CongestionControl.BLOCK,
            priority=zenoh.Priority.REAL_TIME, express=True)
        self._entities.append(self._estop_publisher)
        self._entities.append(s.liveliness().declare_token(self.keys.ctrl_alive))

    # -- inbound (driver threads) ---------------------------------------------------------
    def _on_state(self, sample: zenoh.Sample) -> None:
        now = self.clock_ns()
        robot = self.keys.robot_in(str(sample.key_expr), "state")
        if robot is None:
            return self._reject(Reason.BAD_KEY)
        robot_id = self.registry.id_of(robot)
        if robot_id is None:
            return self._reject(Reason.UNKNOWN_ROBOT)
        payload = sample.payload.to_bytes()
        with self._cond:
            msg = self.decoder.decode(payload, MsgType.STATE, robot_id)
            if isinstance(msg, StateMsg):
                self._states[robot] = ReceivedState(robot, msg, now)
                self._cond.notify_all()

    def _on_sighting(self, sample: zenoh.Sample) -> None:
        """A tracker's SIGHTING, handed to ``on_sighting`` (set by the controller,
        :class:`deploy.tracker.SightingTable`; none: not listened to)."""
        handler = self.on_sighting
        if handler is not None:
            handler(sample.payload.to_bytes())

    def _on_liveliness(self, sample: zenoh.Sample) -> None:
        robot = self.keys.robot_in(str(sample.key_expr), "alive")
        if robot is None:
            return self._reject(Reason.BAD_KEY)
        if robot not in self.registry:
            return self._reject(Reason.UNKNOWN_ROBOT)
        joined = sample.kind == zenoh.SampleKind.PUT
        with self._cond:
            (self._alive.add if joined else self._alive.discard)(robot)
            self._events.append(LivelinessEvent(robot, joined, self.clock_ns()))
            self._cond.notify_all()

    def _on_operator_query(self, query: zenoh.Query) -> None:
        """An operator's request (the query's payload: ``engage``, ``release`` or ``status``),
        answered with the JSON of ``on_operator(request)`` (set by the controller; none: refused)."""
        try:
            request = query.payload.to_bytes().decode("utf-8", "replace").strip() if query.payload else "status"
            handler = self.on_operator
            answer = ({"ok": False, "reason": "this controller takes no operator requests"}
                      if handler is None else handler(request))
            query.reply(self.keys.operator, json.dumps(answer).encode())
        finally:
            query.drop()

    def _on_estop_query(self, query: zenoh.Query) -> None:
        with self._cond:
            latest = self._estop_bytes
        try:
            if latest is None:
                query.reply_err(b"no e-stop has been published by this controller")
            else:
                query.reply(self.keys.estop, latest)
        finally:
            query.drop()

    # -- tables ---------------------------------------------------------------------------
    def latest_states(self) -> dict[str, ReceivedState]:
        """Newest accepted state per robot (robots never heard from are absent)."""
        with self._cond:
            return dict(self._states)

    def state_of(self, robot: str) -> ReceivedState | None:
        with self._cond:
            return self._states.get(robot)

    @property
    def alive_robots(self) -> frozenset[str]:
        """Registered robots whose liveliness token is present now."""
        with self._cond:
            return frozenset(self._alive)

    def pop_events(self) -> list[LivelinessEvent]:
        """Robot join/leave events since the last call, oldest first."""
        with self._cond:
            events = list(self._events)
            self._events.clear()
            return events

    # -- outbound -------------------------------------------------------------------------
    def send_command(self, robot: str, acceleration: Sequence[float], ttl_ms: int,
                     flags: CmdFlags = NO_CMD_FLAGS, state_seq: int = 0) -> CmdMsg:
        """Publish one command: acceleration (x, y) [m/s^2], valid ttl_ms [ms].

        Raises ValueError (nothing is sent, and no seq is taken) for an unknown robot or an
        invalid field (NaN...): the robot counts a gap in the seqs as a missed command.
        """
        self._check_open()
        robot_id = self.registry.id_of(robot)
        if robot_id is None:
            raise ValueError(f"robot {robot!r} is not in the registry {self.registry.names}")
        encode(CmdMsg(robot_id, 1, 1, 0, tuple(acceleration), ttl_ms, flags, state_seq))  # checks only
        epoch, seq, now = self._cmd_stampers[robot].next()
        msg = CmdMsg(robot_id, epoch, seq, now, tuple(acceleration), ttl_ms, flags, state_seq)
        self._cmd_publishers[robot].put(encode(msg))
        return msg

    def send_accelerations(self, robots: Sequence[str], accelerations: np.ndarray, ttl_ms: int,
                           flags: CmdFlags = NO_CMD_FLAGS) -> list[CmdMsg]:
        """Publish one command per row of ``accelerations`` (N, 2) [m/s^2] to ``robots`` (N).

        All rows are validated before any is sent. ``state_seq`` echoes each robot's latest
        accepted state seq (0 if none).
        """
        acc = np.asarray(accelerations, dtype=np.float64)
        if acc.shape != (len(robots), 2):
            raise ValueError(f"accelerations must have shape (num_robots, 2) = "
                             f"({len(robots)}, 2), got {acc.shape}")
        if not np.all(np.isfinite(acc)):
            raise ValueError("accelerations contain NaN or inf; refusing to send them to robots")
        unknown = [r for r in robots if r not in self.registry]
        if unknown:
            raise ValueError(f"robots {unknown} are not in the registry {self.registry.names}")
        states = self.latest_states()
        return [self.send_command(r, acc[i], ttl_ms, flags,
                                  states[r].msg.seq if r in states else 0)
                for i, r in enumerate(robots)]

    def _cmd_publisher(self, robot: str) -> zenoh.Publisher:
        return declare_data_publisher(self.session, self.keys.cmd(robot), self.data_congestion_control)

    def make_lossless(self) -> None:
        """Publish commands with BLOCK from now on (a lock-stepped fleet awaits every answer):
        the command publishers are declared again. Call it from the thread that sends commands."""
        if self.lossless:
            return
        self.lossless = True
        for robot, old in list(self._cmd_publishers.items()):
            new = self._cmd_publisher(robot)
            self._cmd_publishers[robot] = new
            self._entities.append(new)
            self._entities.remove(old)
            old.undeclare()

    @property
    def estop_engaged(self) -> bool:
        with self._cond:
            return self._estop_engaged

    def raise_estop(self, reason_code: int = 0) -> EstopMsg:
        """Latch the fleet-wide e-stop (published now and served to late joiners)."""
        return self._publish_estop(True, reason_code)

    def clear_estop(self) -> EstopMsg:
        """Release the e-stop: robots leave their latch on this newer message."""
        return self._publish_estop(False, 0)

    def _publish_estop(self, engaged: bool, reason_code: int) -> EstopMsg:
        """Latch and publish one ESTOP. The put (BLOCK) may wait on the network: it runs under
        its own lock, which keeps seq order on the wire, not under the lock every driver thread
        needs (the latched bytes, which the queryable serves, are updated under that one first)."""
        self._check_open()
        with self._estop_order:
            epoch, seq, now = self._estop_stamper.next()
            msg = EstopMsg(epoch, seq, now, engaged, reason_code)
            data = encode(msg)
            with self._cond:
                self._estop_bytes = data
                self._estop_engaged = engaged
            self._estop_publisher.put(data)
        return msg


__all__ = ["FleetLink", "LivelinessEvent", "NO_STATUS", "ReceivedCommand", "ReceivedState"]
