"""The robot side of a fleet's Zenoh link: :class:`RobotLink` publishes a robot's state and
receives its latest command and the latched e-stop (the controller side, the threads, the
delivery rules and the e-stop latch: :mod:`deploy.transport`).
"""

from __future__ import annotations

import math
import threading
import time
from collections import deque
from collections.abc import Callable, Sequence

import zenoh

from deploy.network import FleetKeys, TransportConfig, declare_data_publisher
from deploy.streams import Stamper, WireDecoder
from deploy.transport import NO_STATUS, ReceivedCommand, _Link
from deploy.wire import (
    ACCEPTED_VERSIONS,
    BRAKE_OR_STOP,
    HEADER,
    HEADER_SIZE,
    MAGIC,
    ROBOT_ALL,
    CmdMsg,
    EstopMsg,
    MsgType,
    Reason,
    RobotRegistry,
    StateMsg,
    StateStatus,
    check_name,
    encode,
)

COMMAND_RING = 1024
"""Ring size of a robot's command channel: a burst of this many junk messages still cannot push
out a valid command before the driver thread has decoded it."""


MAX_ANSWER_AGE_S = 0.5
"""[s] default oldest STATE a robot acts on a command for: the filter's default latency bound
(0.15 s state age plus 0.15 s command delay), a 20 Hz tick's wait, and room for a loaded host."""

PUBLISHED_KEPT = 256
"""STATE send times a link remembers (12.8 s at 20 Hz; older answers are refused anyway)."""
RECENT_COMMANDS = 16   # accepted commands kept for a playout buffer (:attr:`RobotLink.recent_commands`)

GAP_WINDOW = 1024
"""Seqs a robot remembers one by one behind and ahead of its newest accepted command (51 s at
20 Hz): a command that arrives within this many seqs of the newest, late or early, is told
apart from a missed one; one further off stays counted as missed (the memory stays bounded)."""


class CommandGaps:
    """Missed commands: commands the controller put on the wire that never reached the decoder.

    The controller numbers the commands it sends a robot 1, 2, ... in one epoch (a refused send
    takes no seq). The counted span of an epoch runs from the first command of it the robot
    accepts to the newest; a seq in that span is missed unless a command with it reached the
    decoder, accepted or rejected: a stale answer, an expired or a malformed-but-numbered
    command is counted once, as a rejection, never also as missed. A command that arrives after
    a newer one (reordered) takes its seq back off the count, within ``GAP_WINDOW``. A new
    epoch (a restarted controller) starts a new span; what an old one counted stays counted.
    Not thread-safe: :class:`RobotLink` calls it under its lock.
    """

    def __init__(self) -> None:
        self.missed = 0
        self._epoch: int | None = None   # epoch of the newest accepted command
        self._high = 0                   # its seq
        self._holes: set[int] = set()    # missed seqs in (high - GAP_WINDOW, high)
        self._hole_order: deque[int] = deque()
        self._ahead: set[int] = set()    # rejected seqs in (high, high + GAP_WINDOW]
        self._early: deque[tuple[int, int]] = deque(maxlen=GAP_WINDOW)  # rejected, other epochs

    def accepted(self, epoch: int, seq: int) -> None:
        """A command the decoder accepted (seq newer than any accepted in its epoch)."""
        if epoch != self._epoch:
            self._epoch, self._high = epoch, seq
            self._holes.clear()
            self._hole_order.clear()
            self._ahead = {s for e, s in self._early if e == epoch and seq < s <= seq + GAP_WINDOW}
            self._early = deque(((e, s) for e, s in self._early if e != epoch), maxlen=GAP_WINDOW)
            return
        if seq <= self._high:
            return
        seen = {s for s in self._ahead if s < seq}
        self.missed += seq - self._high - 1 - len(seen)
        for s in range(max(self._high + 1, seq - GAP_WINDOW + 1), seq):
            if s not in seen:
                self._holes.add(s)
                self._hole_order.append(s)
        self._high = seq
        self._ahead -= seen
        self._ahead.discard(seq)
        while self._hole_order and self._hole_order[0] <= seq - GAP_WINDOW:
            self._holes.discard(self._hole_order.popleft())

    def rejected(self, epoch: int, seq: int) -> None:
        """A numbered command the decoder rejected: it reached the robot, so it is not missed."""
        if epoch != self._epoch:      # may be the start of an epoch accepted later
            self._early.append((epoch, seq))
            return
        if seq > self._high:
            if seq - self._high <= GAP_WINDOW:
                self._ahead.add(seq)
        elif seq in self._holes:
            self._holes.discard(seq)
            self.missed -= 1


def numbered_command(payload: bytes, robot_id: int) -> tuple[int, int] | None:
    """(epoch, seq) from the header of a CMD to ``robot_id``, whatever else about it is wrong;
    None for anything without such a header (junk, another type or robot, epoch or seq 0)."""
    if len(payload) < HEADER_SIZE:
        return None
    magic, version, msg_type, rid, _flags, epoch, seq, _sent = HEADER.unpack_from(payload)
    if (magic != MAGIC or version not in ACCEPTED_VERSIONS or msg_type != MsgType.CMD
            or rid != robot_id or epoch == 0 or seq == 0):
        return None
    return epoch, seq


class RobotLink(_Link):
    """Robot side: publish state, receive the latest command, latch the e-stop.

    Several RobotLinks may share one session (a simulated fleet in one process).

    Args:
        fleet, robot: fleet and robot names; ``robot`` must be in ``registry``.
        transport: a TransportConfig (the link owns the session) or an open session.
        clock_ns: the robot's monotonic clock [ns].
        shared_clock: the controller shares ``clock_ns`` (same host): reject EXPIRED and
            FROM_FUTURE commands at receipt and count expiry from the send time too.
        expiry: with ``shared_clock``, judge EXPIRED (False: FROM_FUTURE only, for a robot on
            sim time, as a lock-stepped simulation is).
        estop_query_timeout_s: how long one query for the latched e-stop waits for replies.
        lossless: publish states with congestion control BLOCK instead of DROP (module
            docstring, Delivery): for a lock-stepped simulation, where every state is awaited.
        max_answer_age_s: refuse (STALE_ANSWER) a CMD whose ``state_seq`` names a STATE this link
            published longer ago than this, by the robot's own clock, or none it published in
            this epoch; a CMD with ``state_seq`` 0 answers no state and is judged by its ttl
            only, and BRAKE or STOP always pass (they act on the robot's own state). None: off (a robot on sim time, as a lock-stepped simulation is). It needs no
            shared clock: on a link that queues commands (a congested router) it is what stops
            a robot acting on a command computed from where it was a second ago.
    """

    def __init__(self, fleet: str, robot: str, registry: RobotRegistry,
                 transport: TransportConfig | zenoh.Session, *,
                 clock_ns: Callable[[], int] = time.monotonic_ns, shared_clock: bool = False,
                 expiry: bool = True, queue_capacity: int = 16, estop_query_timeout_s: float = 1.0,
                 lossless: bool = False, max_answer_age_s: float | None = MAX_ANSWER_AGE_S):
        self.keys = FleetKeys(fleet)
        self.robot = check_name(robot)
        robot_id = registry.id_of(robot)
        if robot_id is None:
            raise ValueError(f"robot {robot!r} is not in the registry {registry.names}")
        self.robot_id = robot_id
        self.registry = registry
        super().__init__(transport, clock_ns, lossless)
        self.shared_clock = shared_clock and expiry   # expiry counted from the send time too
        self.decoder = WireDecoder(registry, clock_ns if shared_clock else None,
                                   counter=self.rejects, check_expiry=expiry)
        self.estop_query_timeout_s = estop_query_timeout_s
        if max_answer_age_s is not None and not (math.isfinite(max_answer_age_s) and max_answer_age_s > 0):
            raise ValueError(f"max_answer_age_s must be a positive number of seconds or None, "
                             f"got {max_answer_age_s!r}")
        self._max_answer_ns = None if max_answer_age_s is None else int(max_answer_age_s * 1e9)
        self._published: dict[int, int] = {}      # seq -> send time of this epoch's recent STATEs
        self._stamper = Stamper(clock_ns)
        self._command: ReceivedCommand | None = None
        self._recent: deque[ReceivedCommand] = deque(maxlen=RECENT_COMMANDS)
        self._gaps = CommandGaps()   # :attr:`missed_commands`
        self._estopped = False
        self._estop_reason = 0
        self._estop_bytes: bytes | None = None
        self._estop_synced = False
        self._controller_alive = False
        self._cancel_queries = zenoh.CancellationToken()
        self._open_or_close(queue_capacity)

    def _open(self, capacity: int) -> None:
        s = self.session
        # a burst of junk must not push a valid command out of the ring before the driver
        # thread decodes it (16 lost 19 % of the valid ones behind 50 junk messages each)
        self._subscribe(s.declare_subscriber(self.keys.cmd(self.robot),
                                             zenoh.handlers.RingChannel(COMMAND_RING)),
                        self._on_cmd, "cmd")
        self._subscribe(s.declare_subscriber(self.keys.estop,
                                             zenoh.handlers.RingChannel(capacity)),
                        lambda sample: self._on_estop(sample.payload.to_bytes()), "estop")
        self._subscribe(s.liveliness().declare_subscriber(
            self.keys.ctrl_alive, zenoh.handlers.RingChannel(capacity), history=True),
            self._on_ctrl_liveliness, "ctrl-alive")
        self._state_publisher = declare_data_publisher(s, self.keys.state(self.robot),
                                                       self.data_congestion_control)
        self._entities.append(self._state_publisher)
        self._entities.append(s.liveliness().declare_token(self.keys.robot_alive(self.robot)))

    # -- inbound (driver threads) ---------------------------------------------------------
    def _on_cmd(self, sample: zenoh.Sample) -> None:
        now = self.clock_ns()
        payload = sample.payload.to_bytes()
        with self._cond:
            msg = self.decoder.decode(payload, MsgType.CMD, self.robot_id,
                                      check=lambda m: self._stale_answer(m, now))
            if not isinstance(msg, CmdMsg):
                numbered = numbered_command(payload, self.robot_id)
                if numbered is not None:
                    self._gaps.rejected(*numbered)
            else:
                self._gaps.accepted(msg.epoch, msg.seq)
                expires = now + msg.ttl_ms * 1_000_000
                if self.shared_clock:
                    expires = min(expires, msg.send_time_ns + msg.ttl_ms * 1_000_000)
                self._command = ReceivedCommand(msg, now, expires)
                self._recent.append(self._command)
                self._cond.notify_all()

    def _stale_answer(self, msg: CmdMsg, now: int) -> tuple[Reason, str] | None:
        """STALE_ANSWER if the CMD names a STATE older than ``max_answer_age_s``, or one not sent
        in this epoch; BRAKE and STOP always pass (they use the robot's own state, never the
        controller's). Judged before the CMD may move the command stream on."""
        if self._max_answer_ns is None or msg.state_seq == 0 or int(msg.flags) & BRAKE_OR_STOP:
            return None
        sent = self._published.get(msg.state_seq)
        if sent is None:
            return Reason.STALE_ANSWER, f"answers state seq {msg.state_seq}, not one of this epoch"
        if now - sent > self._max_answer_ns:
            return Reason.STALE_ANSWER, f"answers a state sent {(now - sent) / 1e6:.0f} ms ago"
        return None

    def _on_estop(self, payload: bytes) -> None:
        with self._cond:
            if payload == self._estop_bytes:  # the latched message again (query after publish)
                return
            msg = self.decoder.decode(payload, MsgType.ESTOP, ROBOT_ALL)
            if isinstance(msg, EstopMsg):
                self._estop_bytes = payload
                self._estopped = msg.engaged
                self._estop_reason = msg.reason_code
                self._cond.notify_all()

    def _on_ctrl_liveliness(self, sample: zenoh.Sample) -> None:
        joined = sample.kind == zenoh.SampleKind.PUT
        with self._cond:
            self._controller_alive = joined
            if not joined:
                self._estop_synced = False
            self._cond.notify_all()
        if joined and not self._closed:
            thread = threading.Thread(target=self._query_estop, daemon=True,
                                      name=f"RobotLink-{self.robot}-estop-get")
            self._threads.append(thread)
            thread.start()

    def _query_estop(self) -> None:
        """Fetch the latched e-stop from the controller's queryable, retried until it answers.

        A robot that never syncs could miss a latched e-stop, so it keeps asking while the
        controller is alive (a busy machine can leave the first queries unanswered)."""
        while True:
            with self._cond:
                if self._closed or not self._controller_alive:
                    return
            try:
                replies = self.session.get(self.keys.estop, zenoh.handlers.RingChannel(8),
                                           timeout=self.estop_query_timeout_s,
                                           cancellation_token=self._cancel_queries)
                answered = False
                while True:
                    try:
                        reply = replies.recv()
                    except zenoh.ZError:  # all replies in (or timed out, or session closed)
                        break
                    answered = True
                    if reply.ok is not None:
                        self._on_estop(reply.ok.payload.to_bytes())
            except zenoh.ZError:  # session closed while querying
                return
            if answered:
                with self._cond:
                    self._estop_synced = True
                    self._cond.notify_all()
                return
            if self._closed:
                return

    def close(self) -> None:
        self._cancel_queries.cancel()
        super().close()

    # -- tables ---------------------------------------------------------------------------
    @property
    def missed_commands(self) -> int:
        """Commands the controller put on the wire that never reached this robot's decoder
        (lost, or pushed out of a full ring), counted from the first command the robot
        accepted in each epoch; rejected commands are counted in ``rejects`` only
        (:class:`CommandGaps`)."""
        with self._cond:
            return self._gaps.missed

    @property
    def latest_command(self) -> ReceivedCommand | None:
        """The newest accepted command, expired or not."""
        with self._cond:
            return self._command

    @property
    def recent_commands(self) -> tuple[ReceivedCommand, ...]:
        """The last ``RECENT_COMMANDS`` accepted commands, oldest first (in the order they
        arrived), expired or not: what a robot with a playout buffer chooses from."""
        with self._cond:
            return tuple(self._recent)

    def command(self, now_ns: int | None = None) -> ReceivedCommand | None:
        """The newest accepted command if it has not expired at ``now_ns`` (default: now)."""
        now = self.clock_ns() if now_ns is None else now_ns
        with self._cond:
            cmd = self._command
        return cmd if cmd is not None and now < cmd.expires_at_ns else None

    @property
    def estopped(self) -> bool:
        """Latched e-stop: True from an ENGAGED ESTOP until a newer one with ENGAGED clear."""
        with self._cond:
            return self._estopped

    @property
    def estop_reason(self) -> int:
        with self._cond:
            return self._estop_reason

    @property
    def estop_synced(self) -> bool:
        """The controller answered a query for the latched e-stop since it last appeared."""
        with self._cond:
            return self._estop_synced

    @property
    def controller_alive(self) -> bool:
        with self._cond:
            return self._controller_alive

    # -- outbound -------------------------------------------------------------------------
    def publish_state(self, position: Sequence[float], velocity: Sequence[float],
                      status: StateStatus = NO_STATUS, last_cmd_seq: int | None = None) -> StateMsg:
        """Publish position (x, y) [m] and velocity (x, y) [m/s].

        ESTOPPED and CONTROLLER_LOST are added to ``status`` from the link's own view.
        ``last_cmd_seq``: the seq of the command the robot acted on in the motion this state
        measures (the controller predicts through the ones after it); None: the latest
        accepted command's, for a robot that acts on a command in the tick it accepts it.
        Raises ValueError on NaN/inf, and then takes no seq: the controller reads a robot's
        seqs as its ticks (a lock-stepped episode is ``(seq - 1) // T``).
        """
        self._check_open()
        encode(StateMsg(self.robot_id, 1, 1, 0, tuple(position), tuple(velocity), status,
                        last_cmd_seq or 0))   # checks only
        with self._cond:
            if self._estopped:
                status |= StateStatus.ESTOPPED
            if not self._controller_alive:
                status |= StateStatus.CONTROLLER_LOST
            if last_cmd_seq is None:
                last_cmd_seq = self._command.msg.seq if self._command else 0
        epoch, seq, now = self._stamper.next()
        msg = StateMsg(self.robot_id, epoch, seq, now, tuple(position), tuple(velocity), status,
                       last_cmd_seq)
        with self._cond:
            if seq == 1:                              # a new epoch: its seqs start over
                self._published.clear()
            self._published[seq] = now
            if len(self._published) > PUBLISHED_KEPT:
                del self._published[next(iter(self._published))]
        self._state_publisher.put(encode(msg))
        return msg


__all__ = ["COMMAND_RING", "GAP_WINDOW", "MAX_ANSWER_AGE_S", "RECENT_COMMANDS", "CommandGaps",
           "RobotLink", "numbered_command"]
