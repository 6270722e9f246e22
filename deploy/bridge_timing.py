"""How the bridge (:mod:`deploy.bridge`) keeps time: lock-step sim time (:class:`TickClock`), how
much longer a state took than the fastest transfer (:class:`UplinkExcess`, part of its state age)
and command round trips from the wire (:class:`RoundTrips`, the command delay bound and the
commands in flight). The rules they serve are in the docstrings of :mod:`deploy.bridge` and
:mod:`deploy.bridge_picture`.
"""

from __future__ import annotations

import math
import threading
from collections import deque
from collections.abc import Collection

import numpy as np

from deploy.transport import ReceivedState
from deploy.wire import CmdMsg

DRIFT_ALLOWANCE = 2e-4  # [s/s] clock-rate difference between hosts that the uplink floor follows
MIN_ROUND_TRIPS = 8  # round trips needed before command_delay_s is reported


def percentile(values: Collection[float], q: float) -> float:
    """``np.percentile(values, q)`` (linear interpolation between the order statistics around
    ``q / 100 * (n - 1)``) from a partial sort: ~13 against ~60 us for the 256 round trips the
    bridge reads every tick. ``values`` non-empty, ``q`` in [0, 100]."""
    a = np.fromiter(values, np.float64, len(values))
    pos = q / 100.0 * (len(a) - 1)
    lo = math.floor(pos)
    hi = min(lo + 1, len(a) - 1)
    part = np.partition(a, (lo, hi))
    return float(part[lo] + (part[hi] - part[lo]) * (pos - lo))


class TickClock:
    """Sim time of a lock-stepped fleet [ns]: ``period_s`` per :meth:`advance` (one answered
    burst), starting at one period. Thread-safe; called like ``time.monotonic_ns``.

    The fleet steps only once every robot it published is answered, so a new state from a robot
    answered since the clock last advanced means a new tick; new states only from robots not
    answered yet are the late part of the burst just answered (they came after the gather: a
    loaded machine, or a rejoining robot's state racing its token). The bridge answers that part
    at the same sim time (:meth:`rewind`, then :meth:`advance` as the answers go out); counting
    it as a tick put the bridge's time a tick ahead of the fleet's for the rest of the run. A
    robot new to the fleet, or one the last tick went without, sends a state that looks late
    too, when it comes first in the next tick: the bridge waits ``LATE_PART_WAIT_S`` for a new
    state of a robot it answered, which tells the next tick."""

    def __init__(self, period_s: float):
        self.period_ns = round(period_s * 1e9)   # BridgeConfig checked period_s
        self._ticks = 1
        self._lock = threading.Lock()
        self.answered: set[str] = set()   # robots whose new state was answered since the advance

    def late_part(self, fresh: Collection[str]) -> bool:
        """Whether the new states of robots ``fresh`` are the late part of the burst last
        answered: there are some, and none from a robot in :attr:`answered`."""
        return bool(self.answered) and bool(fresh) and self.answered.isdisjoint(fresh)

    def begin(self, fresh: Collection[str]) -> bool:
        """A look at new states of ``fresh``: the late part of the last burst goes back to its
        sim time (True; :meth:`advance` once answered, or if nothing is); a new tick starts
        :attr:`answered` afresh."""
        late = self.late_part(fresh)
        if late:
            self.rewind()
        elif fresh:
            self.answered.clear()
        return late

    def __call__(self) -> int:
        with self._lock:
            return self._ticks * self.period_ns

    def advance(self) -> None:
        with self._lock:
            self._ticks += 1

    def rewind(self) -> None:
        """One period back: for the late part of a burst already answered (class docstring)."""
        with self._lock:
            self._ticks -= 1


class UplinkExcess:
    """Per robot, how much longer a state took than the fastest transfer seen [ns].

    ``receive - send_time_ns`` is the uplink delay plus the (unknown, constant) offset between
    the robot's clock and ours; its running minimum, allowed to creep up by DRIFT_ALLOWANCE for
    clocks that run at different rates, estimates the offset plus the fastest transfer. A new
    epoch (the robot restarted, maybe its clock too) starts over. At most ``MAX_SENDERS`` floors
    are kept (the least recently heard go first): a tracker keys its floors by epoch, and epochs
    come and go over a long run."""

    MAX_SENDERS = 1024

    def __init__(self) -> None:
        self._floor: dict[str, tuple[int, float, int]] = {}  # robot -> (epoch, floor, when)

    def excess_ns(self, sender: str, epoch: int, send_time_ns: int, receive_time_ns: int) -> float:
        """How much longer this message of ``sender`` (a robot, or a tracker) took than its fastest."""
        offset = receive_time_ns - send_time_ns
        prev = self._floor.get(sender)
        if prev is None or prev[0] != epoch:
            floor = float(offset)
        else:
            floor = min(prev[1] + DRIFT_ALLOWANCE * max(0, receive_time_ns - prev[2]), offset)
        self._floor.pop(sender, None)                 # re-inserted last: the dict's order is recency
        self._floor[sender] = (epoch, floor, receive_time_ns)
        if len(self._floor) > self.MAX_SENDERS:
            del self._floor[next(iter(self._floor))]
        return offset - floor


class RoundTrips:
    """Command round trips on the bridge's clock: CMD sent -> first STATE whose ``last_cmd_seq``
    names it [ns]; :meth:`bound_s` is the configured percentile of the recent ones.

    Every command's send time is kept; a STATE whose ``last_cmd_seq`` names one for
    the first time closes a round trip on the bridge's clock (command out, robot accepted and acted,
    state back). The ``delay_percentile`` of the last ``delay_window`` round trips (at least 8;
    :class:`~deploy.bridge_types.BridgeConfig`) is ``FleetState.command_delay_s``: a conservative
    bound on transport + actuation (it includes the robot's wait for its next tick and the
    uplink). The bridge's ``summary()`` reports it. The same send times
    count each row's commands still in flight (sent after its ``last_cmd_seq``):
    ``FleetState.commands_pending``, so the safety filter predicts through exactly those. A silent
    robot's count (``SilentRobots.commands_pending``) adds the ticks since it was last sent one: the
    controller records a braking row for it on each of them, so its count names the same commands."""

    KEEP = 64  # send times kept per robot

    def __init__(self, window: int, percentile: float):
        self.percentile = percentile
        self.samples: deque[int] = deque(maxlen=window)
        self._sent: dict[str, dict[int, int]] = {}
        self._matched: dict[str, int] = {}
        self._bound: float | None = None

    def sent(self, robot: str, msg: CmdMsg) -> None:
        sent = self._sent.setdefault(robot, {})
        sent[msg.seq] = msg.send_time_ns
        if len(sent) > self.KEEP:
            del sent[next(iter(sent))]

    def observe(self, rs: ReceivedState) -> None:
        seq = rs.msg.last_cmd_seq
        if not seq or self._matched.get(rs.robot) == seq:
            return
        self._matched[rs.robot] = seq
        sent = self._sent.get(rs.robot, {}).get(seq)
        if sent is not None and rs.receive_time_ns >= sent:
            self.samples.append(rs.receive_time_ns - sent)
            self._bound = None

    def pending(self, robot: str, last_cmd_seq: int) -> int:
        """Commands sent to ``robot`` after the one its state says it acted on (the
        ``FleetState.commands_pending`` of its row); -1 when that one is not among the kept
        send times (none yet, forgotten after a stall, or older than ``KEEP`` commands)."""
        sent = self._sent.get(robot)
        if not last_cmd_seq or not sent or last_cmd_seq not in sent:
            return -1
        count = 0
        for seq in reversed(sent):
            if seq <= last_cmd_seq:
                return count
            count += 1
        return count

    def forget_sent(self) -> None:
        """Commands sent before a stall cannot time a round trip: drop their send times."""
        self._sent.clear()

    def bound_s(self) -> float | None:
        if len(self.samples) < MIN_ROUND_TRIPS:
            return None
        if self._bound is None:
            self._bound = percentile(self.samples, self.percentile) / 1e9
        return self._bound

    def summary(self) -> dict[str, float] | None:
        if not self.samples:
            return None
        ms = np.asarray(self.samples, dtype=np.float64) / 1e6
        return {"count": len(ms), "p50": float(np.percentile(ms, 50)),
                "p99": float(np.percentile(ms, 99)), "max": float(ms.max())}


__all__ = ["DRIFT_ALLOWANCE", "MIN_ROUND_TRIPS", "RoundTrips", "TickClock", "UplinkExcess", "percentile"]
