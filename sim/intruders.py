"""Intruders: discs in the arena that the controller does not command (a person crossing, a
foreign robot), for the simulated fleet (``formation fleet-sim --intruder``) and the tracker it
simulates (:mod:`deploy.tracker`).

An intruder walks a straight line at a constant velocity: at tick k of an episode
(``enter_tick <= k < leave_tick``) its centre is ``start + velocity * (k - enter_tick) * dt``.
It is not a pymunk body: it passes through robots and walls, so that what is measured is what
the robots did, not what a push did to them (:class:`IntruderWatch`): how close any robot came
(the gap between the discs, negative when they overlap) and how fast a robot overlapping it
moved towards its centre. A robot that drives into an intruder shows as an overlap with a
speed towards it; one an intruder walks into while braked shows as an overlap at no speed.
"""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from dataclasses import dataclass

import numpy as np

from sim.fleet import FleetState, Obstacles, obstacle_name

DRIVE_IN_SPEED = 0.01
"""[m/s] a robot overlapping an intruder and moving towards its centre faster than this drove into it."""

_FIELDS = {"radius", "x", "y", "vx", "vy", "enter", "leave", "max_speed"}


@dataclass(frozen=True)
class Intruder:
    """radius [m] (> 0); start (x, y) [m]: its centre on ``enter_tick``; velocity [m/s];
    enter_tick / leave_tick: ticks of each episode it is in the arena, ``[enter, leave)``
    (leave None: to the episode's end); max_speed [m/s]: the top speed a tracker reports for it
    (None: the length of ``velocity``; it may not be less)."""

    radius: float
    start: tuple[float, float]
    velocity: tuple[float, float] = (0.0, 0.0)
    enter_tick: int = 0
    leave_tick: int | None = None
    max_speed: float | None = None

    def __post_init__(self) -> None:
        start = tuple(float(v) for v in self.start)
        velocity = tuple(float(v) for v in self.velocity)
        if len(start) != 2 or not all(map(math.isfinite, start)):
            raise ValueError(f"intruder start must be a finite (x, y) [m], got {self.start!r}")
        if len(velocity) != 2 or not all(map(math.isfinite, velocity)):
            raise ValueError(f"intruder velocity must be a finite (vx, vy) [m/s], got {self.velocity!r}")
        object.__setattr__(self, "start", start)
        object.__setattr__(self, "velocity", velocity)
        if not (math.isfinite(self.radius) and self.radius > 0):
            raise ValueError(f"intruder radius must be > 0 m, got {self.radius!r}")
        if isinstance(self.enter_tick, bool) or not isinstance(self.enter_tick, int) or self.enter_tick < 0:
            raise ValueError(f"intruder enter must be a tick >= 0, got {self.enter_tick!r}")
        if self.leave_tick is not None and (not isinstance(self.leave_tick, int) or self.leave_tick <= self.enter_tick):
            raise ValueError(f"intruder leave must be a tick after enter ({self.enter_tick}), got {self.leave_tick!r}")
        if self.max_speed is not None and not (math.isfinite(self.max_speed) and self.max_speed >= self.speed):
            raise ValueError(f"intruder max_speed must be >= its speed {self.speed:.3f} m/s, got {self.max_speed!r}")

    @property
    def speed(self) -> float:
        return math.hypot(*self.velocity)

    @property
    def reported_speed(self) -> float:
        """The top speed a tracker reports [m/s]."""
        return self.speed if self.max_speed is None else float(self.max_speed)

    def present(self, tick: int) -> bool:
        return self.enter_tick <= tick and (self.leave_tick is None or tick < self.leave_tick)

    def centre(self, tick: int, dt: float) -> np.ndarray:
        """(2,) centre at ``tick`` [m] (where it would be, present or not)."""
        return np.asarray(self.start) + np.asarray(self.velocity) * (tick - self.enter_tick) * dt

    @classmethod
    def parse(cls, text: str) -> Intruder:
        """``radius=0.06,x=0.5,y=1.1,vx=0,vy=-0.2,enter=20,leave=120,max_speed=0.3`` (radius, x and
        y required) -> Intruder; ValueError naming the field otherwise."""
        values: dict[str, float] = {}
        for item in (part.strip() for part in text.split(",") if part.strip()):
            key, sep, raw = item.partition("=")
            if not sep or key.strip() not in _FIELDS:
                raise ValueError(f"{item!r} is not FIELD=VALUE with FIELD one of {sorted(_FIELDS)}")
            try:
                values[key.strip()] = float(raw)
            except ValueError:
                raise ValueError(f"{key.strip()}={raw!r} is not a number") from None
        return cls.from_mapping(values)

    @classmethod
    def from_mapping(cls, values: Mapping[str, float]) -> Intruder:
        """The fields of :meth:`parse` as a mapping -> Intruder (ValueError naming the field)."""
        missing = sorted({"radius", "x", "y"} - set(values))
        if missing:
            raise ValueError(f"{', '.join(missing)} missing (e.g. radius=0.06,x=0.5,y=1.1,vy=-0.2)")
        ticks = {}
        for key in ("enter", "leave"):
            if key in values:
                if not float(values[key]).is_integer():
                    raise ValueError(f"{key}={values[key]!r} must be a whole tick")
                ticks[key] = int(values[key])
        return cls(float(values["radius"]), (values["x"], values["y"]),
                   (values.get("vx", 0.0), values.get("vy", 0.0)), ticks.get("enter", 0), ticks.get("leave"),
                   None if "max_speed" not in values else float(values["max_speed"]))


def in_arena(intruders: Sequence[Intruder], tick: int, dt: float) -> list[tuple[int, Intruder, np.ndarray]]:
    """``(index, intruder, centre (2,) [m])`` of each intruder in the arena at ``tick``: what a
    tracker that sees them exactly reports (:class:`IntruderFleet`, deploy.tracker.SimulatedTracker)."""
    return [(i, x, x.centre(tick, dt)) for i, x in enumerate(intruders) if x.present(tick)]


class IntruderWatch:
    """What the robots did near the intruders over one episode (module docstring)."""

    def __init__(self, intruders: Sequence[Intruder], robot_radius: float, dt: float):
        self.intruders = tuple(intruders)
        self.robot_radius = robot_radius
        self.dt = dt
        self.reset()

    def reset(self) -> None:
        self.min_gap = math.inf
        self.drive_in_ticks = 0
        self.max_drive_in_speed = 0.0

    def observe(self, tick: int, positions: np.ndarray, velocities: np.ndarray) -> None:
        """The robots' true (N, 2) positions [m] and velocities [m/s] at ``tick``."""
        for intruder in self.intruders:
            if not intruder.present(tick):
                continue
            offset = intruder.centre(tick, self.dt) - positions
            dist = np.linalg.norm(offset, axis=1)
            gap = dist - intruder.radius - self.robot_radius
            self.min_gap = min(self.min_gap, float(gap.min()))
            touching = np.flatnonzero(gap < 0)
            if touching.size:
                towards = np.einsum("ij,ij->i", velocities[touching], offset[touching]) / np.maximum(dist[touching], 1e-12)
                fastest = float(towards.max())
                self.max_drive_in_speed = max(self.max_drive_in_speed, fastest)
                self.drive_in_ticks += fastest > DRIVE_IN_SPEED

    def summary(self) -> dict[str, float | int | None]:
        """``min_gap_mm`` (None: no intruder was in the arena), ``drive_in_ticks`` (ticks in which
        some robot overlapping an intruder moved towards it faster than DRIVE_IN_SPEED) and the
        fastest such speed [m/s]."""
        return {"min_gap_mm": None if math.isinf(self.min_gap) else round(1e3 * self.min_gap, 3),
                "drive_in_ticks": self.drive_in_ticks,
                "max_drive_in_speed": round(self.max_drive_in_speed, 4)}


@dataclass(frozen=True)
class RobotSightings:
    """How a tracker that identifies the fleet's robots (motion capture) reports each of them:
    its centre drawn uniformly within ``position_error`` [m] of the true one, as a disc of the
    robot's radius plus ``position_error`` (so it holds the robot), with a top speed of its true
    speed plus ``speed_margin`` [m/s]; ``seed`` draws the errors."""

    position_error: float = 0.005
    speed_margin: float = 0.02
    seed: int = 0

    def __post_init__(self) -> None:
        for name in ("position_error", "speed_margin"):
            value = getattr(self, name)
            if isinstance(value, bool) or not isinstance(value, int | float) or not math.isfinite(value) or value < 0:
                raise ValueError(f"RobotSightings.{name} must be a finite number >= 0, got {value!r}")

    def report(self, rng: np.random.Generator, positions: np.ndarray, velocities: np.ndarray,
               robot_radius: float) -> tuple[np.ndarray, float, np.ndarray]:
        """What the tracker reports of N robots at their true (N, 2) ``positions`` [m] and
        ``velocities`` [m/s]: ``(centres (N, 2) [m], radius [m], top speeds (N,) [m/s])``."""
        n = len(positions)
        angle, dist = rng.uniform(0.0, 2.0 * np.pi, n), self.position_error * np.sqrt(rng.uniform(size=n))
        centres = positions + dist[:, None] * np.stack([np.cos(angle), np.sin(angle)], axis=1)
        return centres, robot_radius + self.position_error, np.hypot(*velocities.T) + self.speed_margin


class IntruderFleet:
    """A :class:`sim.fleet.Fleet` (``world``, e.g. a :class:`sim.pymunk_world.PymunkWorld`) with
    intruders, seen by a tracker: every state it returns carries the intruders in the arena as
    ``FleetState.obstacles``, where they were ``sighting_delay_ticks`` ticks before (with that
    age), at their reported top speed; with ``robots``, the fleet's own robots too, as that
    tracker reports them (:class:`RobotSightings`, identified by ``Obstacles.robots``).
    :attr:`watch` holds the episode's :class:`IntruderWatch` (reset with the world). Anything
    else is the world's."""

    def __init__(self, world, intruders: Sequence[Intruder], sighting_delay_ticks: int = 0,
                 robots: RobotSightings | None = None):
        if isinstance(sighting_delay_ticks, bool) or not isinstance(sighting_delay_ticks, int) \
                or sighting_delay_ticks < 0:
            raise ValueError(f"sighting_delay_ticks must be an integer >= 0, got {sighting_delay_ticks!r}")
        self.world = world
        self.intruders = tuple(intruders)
        self.delay = sighting_delay_ticks
        self.robots = robots
        self.watch = IntruderWatch(self.intruders, world.scenario.robot_radius, world.dt)
        self.tick = 0
        self._true: list[FleetState] = []        # the last delay + 1 true states, oldest first
        self._rng = np.random.default_rng(None if robots is None else robots.seed)

    def __getattr__(self, name: str):
        return getattr(self.world, name)

    def reset(self, seed: int | None = None) -> FleetState:
        self.tick = 0
        self.watch.reset()
        state = self.world.reset(seed)
        self._true = [self.world.true_state()]
        if self.robots is not None:
            self._rng = np.random.default_rng([self.robots.seed, 0 if seed is None else seed])
        return self._seen(state)

    def read_state(self) -> FleetState:
        if self.tick == 0:              # placed after the reset (a bench's random start)
            self._true = [self.world.true_state()]
        return self._seen(self.world.read_state())

    def send_accelerations(self, accelerations: np.ndarray) -> None:
        self.world.send_accelerations(accelerations)

    def step(self) -> FleetState:
        state = self.world.step()
        self.tick += 1
        true = self.world.true_state()
        self.watch.observe(self.tick, true.positions, true.velocities)
        self._true = (self._true + [true])[-(self.delay + 1):]
        return self._seen(state)

    def _seen(self, state: FleetState) -> FleetState:
        seen = max(self.tick - self.delay, 0)
        age = (self.tick - seen) * self.world.dt
        here = in_arena(self.intruders, seen, self.world.dt)
        ids = [obstacle_name(i) for i, _, _ in here]
        centres = [c for _, _, c in here]
        radii = [x.radius for _, x, _ in here]
        speeds = [x.reported_speed for _, x, _ in here]
        robots: list[str | None] = [None] * len(here)
        if self.robots is not None:
            true = self._true[0]
            seen_at, radius, speed = self.robots.report(self._rng, true.positions, true.velocities,
                                                        self.world.scenario.robot_radius)
            ids += [f"#{name}" for name in true.robot_ids]
            centres += list(seen_at)
            radii += [radius] * len(seen_at)
            speeds += list(speed)
            robots += list(true.robot_ids)
        if not ids:
            return state
        obstacles = Obstacles(tuple(ids), np.array(centres), radii, [age] * len(ids), speeds,
                              tuple(robots) if self.robots is not None else ())
        return state.replaced(obstacles=obstacles)


def scattered_boxes(rng: np.random.Generator, starts: np.ndarray, arena: tuple[float, float],
                    robot_radius: float, count: int) -> Obstacles:
    """``count`` standing boxes of radius 1-3 cm, as a tracker reports them (a cluttered arena):
    centres anywhere 3 cm inside the arena and ``robot_radius + 5 cm`` clear of every start
    slot (``starts`` (N, 2)) [m]."""
    w, h = arena
    centres: list[np.ndarray] = []
    while len(centres) < count:
        c = rng.uniform([0.03, 0.03], [w - 0.03, h - 0.03])
        if np.linalg.norm(starts - c, axis=1).min() > robot_radius + 0.05:
            centres.append(c)
    return Obstacles(tuple(f"box{k}" for k in range(count)), np.array(centres).reshape(-1, 2),
                     rng.uniform(0.01, 0.03, count), np.zeros(count), np.zeros(count))


__all__ = ["DRIVE_IN_SPEED", "Intruder", "IntruderFleet", "IntruderWatch", "RobotSightings", "in_arena",
           "scattered_boxes"]
