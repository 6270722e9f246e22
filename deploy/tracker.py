"""Obstacles a tracker sees, over Zenoh: a camera or motion-capture node reports discs the
controller does not command (a person, a foreign robot, a box), and the controller's safety
filter keeps every robot clear of them.

Wire (``docs/wire-format.md``, SIGHTING): one 60-byte message per obstacle per look, on
``formation/<fleet>/tracker/sightings``; the header's ``robot_id`` is the tracker's id of the
obstacle (0..0xFFFE, not a robot), each obstacle its own stream (epoch, seq). The body holds
the centre [m], the radius [m], the fastest the obstacle may move [m/s] and how long before
``send_time_ns`` the picture was taken (``capture_age_ms``). Flag GONE: the tracker no longer
sees the obstacle (it left the arena); the controller forgets it. Flag ROBOT: the disc is one of
the fleet's robots, named by its registry id in the body (a tracker that identifies robots,
e.g. motion capture); the stack then uses it only to bound that robot once it went silent and
came to rest (:mod:`controllers.safety.silent_reach`, Seen at rest), never as an obstacle of the
robot itself.

Controller side (:class:`SightingTable`, in :class:`deploy.transport.FleetLink`): the newest
sighting of each obstacle, until GONE. Its age at a tick is counted as a robot state's is
(:mod:`deploy.bridge_picture`): ``now - receive time + uplink excess + capture_age_ms`` (lock-step: no
uplink term, the bridge runs on sim time). An obstacle the tracker stops reporting without GONE
stays, its disc growing at its top speed with the age of the last sighting: losing sight of a
person does not mean the person left. The tracker's word is needed to forget one.

Who may publish: on a router with access control (:mod:`deploy.security`) only the ``tracker``
certificate (and ``fleet-sim``, which simulates intruders) may put sightings.
"""

from __future__ import annotations

import threading
from collections.abc import Callable, Sequence

import numpy as np
import zenoh

from deploy.bridge_timing import UplinkExcess
from deploy.network import FleetKeys
from deploy.streams import Stamper, WireDecoder
from deploy.transport import FleetLink
from deploy.wire import ROBOT_ALL, MsgType, Reason, RobotRegistry, SightingMsg, encode
from sim.fleet import FleetState, Obstacles, obstacle_name
from sim.intruders import Intruder, IntruderWatch, RobotSightings, in_arena

MAX_CAPTURE_AGE_MS = 0xFFFF


class SightingTable:
    """The newest sighting of every obstacle still in view (module docstring). Thread-safe:
    :meth:`receive` runs on a Zenoh driver thread, :meth:`obstacles` on the controller's."""

    def __init__(self, decoder: WireDecoder, clock_ns: Callable[[], int], uplink: bool = True):
        self.decoder = decoder
        self.clock_ns = clock_ns
        self.uplink = UplinkExcess() if uplink else None
        self._seen: dict[int, tuple[SightingMsg, float]] = {}   # id -> (newest, when it was taken [ns])
        self._lock = threading.Lock()
        self.accepted = 0
        self.gone = 0

    @classmethod
    def listening(cls, link: FleetLink, uplink: bool = True) -> SightingTable:
        """A table fed by ``link``'s sightings subscriber, on its clock, counting its rejections
        in ``link.rejects`` (FROM_FUTURE checked as the link checks its states)."""
        table = cls(WireDecoder(link.registry, link.decoder.clock_ns, counter=link.rejects), link.clock_ns, uplink)
        link.on_sighting = table.receive
        return table

    def receive(self, payload: bytes) -> None:
        """One SIGHTING payload: kept when valid and newer than the last of its obstacle;
        rejections are counted in the decoder's counter (the link's ``rejects``); a robot's
        sighting needs the decoder's registry (UNKNOWN_ROBOT without one)."""
        now = self.clock_ns()
        with self._lock:
            msg = self.decoder.decode(payload, MsgType.SIGHTING)
            if not isinstance(msg, SightingMsg):
                return
            if msg.robot is not None and self.decoder.registry is None:
                self.decoder.reject(Reason.UNKNOWN_ROBOT, f"sighting of robot id {msg.robot} without a registry")
                return
            self.accepted += 1
            if msg.gone:
                self.gone += self._seen.pop(msg.robot_id, None) is not None
                return
            excess = 0.0
            if self.uplink is not None:  # one floor per sender epoch: a tracker's, or an obstacle's own
                excess = self.uplink.excess_ns(f"tracker:{msg.epoch}", msg.epoch, msg.send_time_ns, now)
            self._seen[msg.robot_id] = (msg, now - excess - msg.capture_age_ms * 1e6)

    def obstacles(self, now_ns: int) -> Obstacles | None:
        """What the filter keeps clear at ``now_ns`` (the link's clock); None when nothing is in view."""
        with self._lock:
            seen = sorted(self._seen.items())
        if not seen:
            return None
        msgs = [msg for _, (msg, _) in seen]
        registry = self.decoder.registry
        robots = tuple(None if m.robot is None else registry.name_of(m.robot) for m in msgs)
        return Obstacles(tuple(obstacle_name(i) for i, _ in seen), np.array([m.position for m in msgs]),
                         np.array([m.radius for m in msgs]),
                         np.array([max(0.0, now_ns - taken) / 1e9 for _, (_, taken) in seen]),
                         np.array([m.max_speed for m in msgs]), robots if any(robots) else ())

    def in_view(self) -> tuple[str, ...]:
        with self._lock:
            return tuple(obstacle_name(i) for i in sorted(self._seen))

    def summary(self) -> dict:
        """``accepted`` sightings (GONE included), obstacles ``gone``, those ``in_view`` now."""
        return {"accepted": self.accepted, "gone": self.gone, "in_view": list(self.in_view())}


class SightingPublisher:
    """Tracker side: publish what the tracker sees on an open Zenoh ``session``.

    ``publish(i, ...)`` reports obstacle ``i`` (0..0xFFFE) now; ``gone(i)`` tells the controller
    it left. Each obstacle is its own stream, numbered by its own :class:`deploy.streams.Stamper`
    (one epoch per publisher). Sightings go out with congestion control DROP, as states do: the
    next look replaces a lost one (``lossless``: BLOCK, for a lock-stepped simulation).
    """

    def __init__(self, session: zenoh.Session, fleet: str, clock_ns: Callable[[], int] | None = None,
                 lossless: bool = False):
        self.keys = FleetKeys(fleet)
        first = Stamper() if clock_ns is None else Stamper(clock_ns)
        self._first = first
        self._stampers: dict[int, Stamper] = {}
        self._publisher = session.declare_publisher(
            self.keys.sightings,
            congestion_control=zenoh.CongestionControl.BLOCK if lossless else zenoh.CongestionControl.DROP,
            priority=zenoh.Priority.INTERACTIVE_HIGH)

    def _stamp(self, obstacle_id: int) -> tuple[int, int, int]:
        if isinstance(obstacle_id, bool) or not isinstance(obstacle_id, int) or not 0 <= obstacle_id < ROBOT_ALL:
            raise ValueError(f"obstacle_id must be an int in [0, {ROBOT_ALL - 1}], got {obstacle_id!r}")
        if obstacle_id not in self._stampers:
            self._stampers[obstacle_id] = Stamper(self._first.clock_ns, self._first.epoch)
        return self._stampers[obstacle_id].next()

    def publish(self, obstacle_id: int, position: Sequence[float], radius: float, max_speed: float,
                capture_age_s: float = 0.0, robot: int | None = None) -> SightingMsg:
        """Report obstacle ``obstacle_id``: a disc of ``radius`` [m] at ``position`` [m], seen
        ``capture_age_s`` [s] ago, moving at most ``max_speed`` [m/s]; ``robot``: the registry id
        of the fleet robot it is (None: none). Raises ValueError (nothing is sent) on a bad
        field, naming it."""
        if not 0.0 <= capture_age_s <= MAX_CAPTURE_AGE_MS / 1e3:
            raise ValueError(f"capture_age_s must be in [0, {MAX_CAPTURE_AGE_MS / 1e3}] s, got {capture_age_s!r}")
        epoch, seq, now = self._stamp(obstacle_id)
        msg = SightingMsg(obstacle_id, epoch, seq, now, tuple(position), float(radius), float(max_speed),
                          int(np.ceil(capture_age_s * 1e3)), robot=robot)
        self._publisher.put(encode(msg))
        return msg

    def gone(self, obstacle_id: int) -> SightingMsg:
        """Tell the controller obstacle ``obstacle_id`` left (the tracker no longer sees it)."""
        epoch, seq, now = self._stamp(obstacle_id)
        msg = SightingMsg(obstacle_id, epoch, seq, now, (0.0, 0.0), 1.0, 0.0, 0, gone=True)
        self._publisher.put(encode(msg))
        return msg

    def close(self) -> None:
        self._publisher.undeclare()


class SimulatedTracker:
    """The tracker of a simulated fleet (:mod:`deploy.fleet_sim`): it sees each
    :class:`sim.intruders.Intruder` exactly, publishes it as obstacle ``i`` (its index) while it
    is in the arena and GONE on the tick it leaves, and watches what the robots did near it
    (:class:`sim.intruders.IntruderWatch`). With ``robots`` (and the fleet's ``registry``) it
    identifies the fleet's robots too, as :class:`sim.intruders.RobotSightings` says, each as
    obstacle ``len(intruders) + k`` with flag ROBOT."""

    def __init__(self, publisher: SightingPublisher, intruders: Sequence[Intruder], robot_radius: float,
                 dt: float, robots: RobotSightings | None = None, registry: RobotRegistry | None = None):
        if robots is not None and registry is None:
            raise ValueError("a tracker that identifies robots needs the fleet's registry")
        self.publisher = publisher
        self.intruders = tuple(intruders)
        self.dt = dt
        self.robot_radius = robot_radius
        self.robots, self.registry = robots, registry
        self._rng = np.random.default_rng(None if robots is None else robots.seed)
        self.watch = IntruderWatch(self.intruders, robot_radius, dt)
        self._in_view: set[int] = set()

    def reset(self) -> None:
        """A new episode: every intruder goes back to its start."""
        for i in sorted(self._in_view):
            self.publisher.gone(i)
        self._in_view.clear()
        self.watch.reset()

    def look(self, tick: int, robots: FleetState | None = None) -> None:
        """Publish what is in the arena at ``tick`` of the episode (before the robots' states of
        that tick, so a lock-stepped controller has it when it answers them); ``robots``: their
        true state, when the tracker identifies them."""
        here = in_arena(self.intruders, tick, self.dt)
        for i, intruder, centre in here:
            self.publisher.publish(i, centre, intruder.radius, intruder.reported_speed)
        if self.robots is not None and robots is not None:
            centres, radius, speeds = self.robots.report(self._rng, robots.positions, robots.velocities,
                                                         self.robot_radius)
            for k, name in enumerate(robots.robot_ids):
                self.publisher.publish(len(self.intruders) + k, centres[k], radius, float(speeds[k]),
                                       robot=self.registry.id_of(name))
        now = {i for i, _, _ in here}
        for i in sorted(self._in_view - now):
            self.publisher.gone(i)
        self._in_view = now


__all__ = ["SightingPublisher", "SightingTable", "SimulatedTracker"]
