"""Streams of wire messages: epochs and sequence numbers, the receive-side checks that need
context, and the send-side stamps (the format itself is :mod:`deploy.wire`).

``epoch`` is a random non-zero u32 drawn when a sender starts; ``seq`` counts from 1 within an
epoch. A receiver keeps, per stream (message type, robot id), the current epoch and the last
sequence number: an older or repeated sequence is STALE, a new epoch is a sender restart, and a
retired epoch is STALE (so a late packet from before a restart cannot flap the stream back).
:class:`WireDecoder` adds to :func:`deploy.wire.decode` the checks that need context (robot
registry, sequence, clock: ``send_time_ns`` is comparable with the receiver's clock only when
both share it) and counts every rejection in a :class:`RejectCounter`; :class:`Stamper` numbers
what a sender sends.
"""

from __future__ import annotations

import secrets
import threading
import time
from collections import deque
from collections.abc import Callable

from deploy.wire import (
    ROBOT_ALL,
    U32_MAX,
    CmdMsg,
    Message,
    MsgType,
    Reason,
    Rejection,
    RobotRegistry,
    decode,
)


class RejectCounter:
    """Thread-safe count of rejections per :class:`Reason`."""

    def __init__(self) -> None:
        self._counts: dict[Reason, int] = {}
        self._lock = threading.Lock()

    def add(self, reason: Reason) -> None:
        with self._lock:
            self._counts[reason] = self._counts.get(reason, 0) + 1

    def __getitem__(self, reason: Reason) -> int:
        with self._lock:
            return self._counts.get(reason, 0)

    @property
    def total(self) -> int:
        with self._lock:
            return sum(self._counts.values())

    def snapshot(self) -> dict[str, int]:
        """Counts by reason name, e.g. ``{"NON_FINITE": 2}`` (for logs and reports)."""
        with self._lock:
            return {r.name: n for r, n in sorted(self._counts.items())}

    def __repr__(self) -> str:
        return f"RejectCounter({self.snapshot()})"


class SequenceTracker:
    """Per stream: the current (epoch, last seq) and a few retired epochs.

    ``is_fresh`` only looks; ``accept`` records, so a message rejected later for another reason
    does not move the stream forward.
    """

    def __init__(self, retired_epochs: int = 8):
        self._current: dict[tuple[int, int], tuple[int, int]] = {}
        self._retired: dict[tuple[int, int], deque[int]] = {}
        self._retired_len = retired_epochs

    def is_fresh(self, stream: tuple[int, int], epoch: int, seq: int) -> bool:
        current = self._current.get(stream)
        if current is None:
            return True
        cur_epoch, last_seq = current
        if epoch == cur_epoch:
            return seq > last_seq
        return epoch not in self._retired.get(stream, ())

    def accept(self, stream: tuple[int, int], epoch: int, seq: int) -> None:
        current = self._current.get(stream)
        if current is not None and current[0] != epoch:
            self._retired.setdefault(stream, deque(maxlen=self._retired_len)).append(current[0])
        self._current[stream] = (epoch, seq)


class WireDecoder:
    """Full receive-side validation: :func:`decode` plus registry, sequence and clock checks.

    Args:
        registry: known robots; ids not in it are UNKNOWN_ROBOT (a SIGHTING's header id is the
            tracker's obstacle id: only the robot it names, flag ROBOT, is checked). None skips
            the check.
        clock_ns: the receiver's clock, only if it is the same clock as the senders'
            (``time.monotonic_ns`` on one host): enables EXPIRED (CMD older than ttl_ms) and
            FROM_FUTURE (any message sent more than ``max_future_ms`` ahead of now).
        counter: where rejections are counted (a new one if None).
        check_expiry: with ``clock_ns``, also judge EXPIRED (False: FROM_FUTURE only, for a
            receiver on sim time, where a command's wall-clock age says nothing).
    """

    def __init__(self, registry: RobotRegistry | None = None,
                 clock_ns: Callable[[], int] | None = None, max_future_ms: float = 100.0,
                 counter: RejectCounter | None = None, check_expiry: bool = True):
        self.registry = registry
        self.clock_ns = clock_ns
        self.check_expiry = check_expiry
        self.max_future_ns = int(max_future_ms * 1e6)
        self.rejects = counter if counter is not None else RejectCounter()
        self.sequences = SequenceTracker()

    def reject(self, reason: Reason, detail: str) -> Rejection:
        self.rejects.add(reason)
        return Rejection(reason, detail)

    def decode(self, data: bytes | bytearray | memoryview, expect: MsgType | None = None,
               robot_id: int | None = None,
               check: Callable[[Message], tuple[Reason, str] | None] | None = None) -> Message | Rejection:
        """Validate one message; ``robot_id`` is the id the key names (ROBOT_MISMATCH if not).

        ``check``: the receiver's own last check (e.g. a robot's STALE_ANSWER), run after every
        other one; a ``(reason, detail)`` it returns rejects the message. Only accepted messages
        advance the per-(type, robot id) sequence; rejections are counted.
        """
        msg = decode(data, expect)
        if isinstance(msg, Rejection):
            self.rejects.add(msg.reason)
            return msg
        if (self.registry is not None and msg.robot_id != ROBOT_ALL and msg.TYPE is not MsgType.SIGHTING
                and self.registry.name_of(msg.robot_id) is None):   # a sighting's id names an obstacle
            return self.reject(Reason.UNKNOWN_ROBOT, f"robot id {msg.robot_id} is not registered")
        if (self.registry is not None and msg.TYPE is MsgType.SIGHTING and msg.robot is not None
                and self.registry.name_of(msg.robot) is None):
            return self.reject(Reason.UNKNOWN_ROBOT, f"sighting of robot id {msg.robot}, which is not registered")
        if robot_id is not None and msg.robot_id != robot_id:
            return self.reject(Reason.ROBOT_MISMATCH,
                               f"robot id {msg.robot_id} on the key of robot id {robot_id}")
        if self.clock_ns is not None:
            now = self.clock_ns()
            if msg.send_time_ns > now + self.max_future_ns:
                return self.reject(Reason.FROM_FUTURE, f"sent {(msg.send_time_ns - now) / 1e6:.3f}"
                                   " ms in the future: sender and receiver clocks differ")
            if (self.check_expiry and isinstance(msg, CmdMsg)
                    and now - msg.send_time_ns > msg.ttl_ms * 1_000_000):
                return self.reject(Reason.EXPIRED, f"command is {(now - msg.send_time_ns) / 1e6:.3f}"
                                   f" ms old, ttl {msg.ttl_ms} ms")
        stream = (int(msg.TYPE), msg.robot_id)
        if not self.sequences.is_fresh(stream, msg.epoch, msg.seq):
            return self.reject(Reason.STALE, f"{msg.TYPE.name} epoch {msg.epoch} seq {msg.seq} is "
                               "not newer than the last accepted")
        refused = check(msg) if check is not None else None
        if refused is not None:
            return self.reject(*refused)
        self.sequences.accept(stream, msg.epoch, msg.seq)
        return msg


def new_epoch() -> int:
    """A random non-zero u32 identifying one run of a sender."""
    return secrets.randbelow(U32_MAX) + 1


class Stamper:
    """Sender side of one stream: (epoch, seq, send_time_ns) for each new message.

    seq counts 1, 2, ...; at 2**32 - 1 a new epoch starts at seq 1 (receivers treat it as a
    restart). Thread-safe.
    """

    def __init__(self, clock_ns: Callable[[], int] = time.monotonic_ns, epoch: int | None = None):
        self.clock_ns = clock_ns
        self.epoch = new_epoch() if epoch is None else epoch
        if not 1 <= self.epoch <= U32_MAX:
            raise ValueError(f"epoch={self.epoch} must be in [1, 2**32 - 1]")
        self.seq = 0
        self._lock = threading.Lock()

    def next(self) -> tuple[int, int, int]:
        with self._lock:
            if self.seq >= U32_MAX:
                old = self.epoch
                while self.epoch == old:
                    self.epoch = new_epoch()
                self.seq = 0
            self.seq += 1
            return self.epoch, self.seq, self.clock_ns()
