"""The formation-change task: arena, transported object, start and target slots, dynamics.

Coordinates are arena metres with the origin at the lower-left corner; the arena is
``[0, width] x [0, height]`` (1 x 1 by default) with walls on all four sides. Robots are
discs of radius ``robot_radius`` (0.04, diameter 0.08). The transported object is a simple
polygon (a rectangle by default) in the middle. ``N`` robots start on the *right transport
positions* (slots to the right of the object, jittered per episode) and must end on the
*left transport positions* (target slots), any robot on any target, within
``target_tolerance`` (0.05) and without a collision.

Dynamics (both worlds), a damped double integrator with semi-implicit Euler, per robot::

    a   = clip_norm(a_cmd, accel_limit)                     [m/s^2]
    v'  = clip_norm(v + dt * (a - damping * v), speed_limit)   [m/s]
    p'  = p + dt * v'                                          [m]

with ``dt`` = 0.05 s and ``episode_steps`` = 128 steps (6.4 s), as in the paper's Table 1.

Every field is validated by :meth:`Scenario.validate`; a bad scenario raises
:class:`ScenarioError` whose message names the field and the fix.
"""

from __future__ import annotations

import dataclasses
import math
import numbers
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

MAX_ROBOTS = 21  # three columns of seven slots fit beside the default object


class ScenarioError(ValueError):
    """A scenario that cannot be run; the message names the field and the fix."""


def _number(value: object, name: str, integer: bool = False) -> float | int:
    """``value`` as the number a field ``name`` holds, or ScenarioError naming the field: a real
    number (not a bool, a string or null); with ``integer`` an integral one, returned as int."""
    if isinstance(value, bool) or not isinstance(value, numbers.Real):
        raise ScenarioError(f"{name} must be {'an integer' if integer else 'a number'}, got {value!r}")
    if integer:
        if not (math.isfinite(value) and int(value) == value):
            raise ScenarioError(f"{name} must be an integer, got {value!r}")
        return int(value)
    return value


class ScenarioSourceError(ScenarioError):
    """A scenario name or file that cannot be resolved; the message begins with the name or file
    ("scenario file 'x.json': ...", "unknown scenario 'x' ..."), so callers need not prefix it."""


@dataclass(frozen=True)
class Dynamics:
    """Damped double integrator shared by the batched and the pymunk worlds.

    Attributes:
        dt: control period [s].
        episode_steps: steps per episode (128 in the paper).
        accel_limit: bound on the norm of the commanded acceleration [m/s^2].
        speed_limit: bound on the norm of the velocity [m/s].
        damping: linear damping coefficient c in ``dv/dt = a - c v`` [1/s].
    """

    dt: float = 0.05
    episode_steps: int = 128
    accel_limit: float = 1.0
    speed_limit: float = 0.4
    damping: float = 0.5

    def __post_init__(self) -> None:
        for f in dataclasses.fields(self):
            value = _number(getattr(self, f.name), f"dynamics.{f.name}", integer=f.name == "episode_steps")
            object.__setattr__(self, f.name, value)

    def step_np(self, pos: np.ndarray, vel: np.ndarray,
                acc: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """One tick of the nominal model (module docstring) on (N, 2) numpy arrays -> (p', v')."""
        a = clip_norm(acc, self.accel_limit)
        v = clip_norm(vel + self.dt * (a - self.damping * vel), self.speed_limit)
        return pos + self.dt * v, v

    def brake(self, vel: np.ndarray) -> np.ndarray:
        """The one braking law of every robot, simulated or real, and of the safety filter.

        ``a = clip_norm(c v - v / dt, accel_limit)`` for (N, 2) velocities [m/s] -> (N, 2)
        [m/s^2]: the command under which the nominal model stops in one tick
        (``v' = v + dt (a - c v) = 0``), clipped along ``-v`` when that needs more than the
        actuator gives. It never reverses a robot (``-v / dt`` alone would overshoot to
        ``-c dt v``). Non-finite velocities give 0. From the speed limit 0.4 m/s at
        ``accel_limit`` 1 and ``c`` 0.5 a robot is at rest after 8 ticks (0.4 s).
        """
        v = np.where(np.isfinite(vel), vel, 0.0)
        return clip_norm(self.damping * v - v / self.dt, self.accel_limit)

    def validate(self) -> None:
        for name in ("dt", "accel_limit", "speed_limit"):
            value = getattr(self, name)
            if not (math.isfinite(value) and value > 0):
                raise ScenarioError(f"dynamics.{name} must be a positive finite number, got {value!r}")
        if not (math.isfinite(self.damping) and self.damping >= 0):
            raise ScenarioError(f"dynamics.damping must be >= 0, got {self.damping!r}")
        if self.damping * self.dt >= 1:
            raise ScenarioError(
                f"dynamics.damping * dynamics.dt = {self.damping * self.dt} must be < 1 "
                "(the explicit damping step would reverse the velocity); lower damping or dt"
            )
        if self.episode_steps < 1:
            raise ScenarioError(f"dynamics.episode_steps must be a positive integer, got {self.episode_steps!r}")


def clip_norm(x: np.ndarray, limit: float) -> np.ndarray:
    """Scale each (..., 2) row down to norm <= limit, keeping its direction."""
    norm = np.hypot(x[..., 0], x[..., 1])[..., None]
    return x * (limit / np.maximum(norm, limit))


def rectangle(center: tuple[float, float], size: tuple[float, float]) -> tuple[tuple[float, float], ...]:
    """Counter-clockwise vertices of an axis-aligned rectangle ``size = (width, height)``."""
    cx, cy = center
    hw, hh = size[0] / 2, size[1] / 2
    return ((cx - hw, cy - hh), (cx + hw, cy - hh), (cx + hw, cy + hh), (cx - hw, cy + hh))


def column_slots(n: int, x: float, y_center: float, spacing: float, side: int,
                 per_column: int = 7, column_spacing: float = 0.125) -> tuple[tuple[float, float], ...]:
    """``n`` slots in columns beside the object, filled from the object outwards.

    ``side`` is +1 for the right of the object (columns go to larger x) and -1 for the left.
    Each column holds up to ``per_column`` slots spaced ``spacing`` apart, centred on ``y_center``.
    """
    slots = []
    for col in range(math.ceil(n / per_column)):
        k = min(per_column, n - col * per_column)
        xs = x + side * col * column_spacing
        for j in range(k):
            slots.append((xs, y_center + (j - (k - 1) / 2) * spacing))
    return tuple(slots)


@dataclass(frozen=True)
class Scenario:
    """One formation-change task (see the module docstring for conventions).

    Attributes:
        name: preset name, shown in reports.
        num_robots: N, the number of robots, start slots and target slots.
        start_slots: N (x, y) right transport positions [m].
        target_slots: N (x, y) left transport positions [m].
        object_vertices: the object's polygon, counter-clockwise (x, y) vertices [m].
        arena: (width, height) of the arena [m].
        robot_radius: disc radius [m] (0.04: diameter 0.08 as in the paper).
        target_tolerance: a robot is on a target within this distance [m] (0.05).
        start_jitter: each start slot is moved by U(-j, j) per axis per episode [m].
        dynamics: see :class:`Dynamics`.
    """

    name: str
    num_robots: int
    start_slots: tuple[tuple[float, float], ...]
    target_slots: tuple[tuple[float, float], ...]
    object_vertices: tuple[tuple[float, float], ...] = rectangle((0.5, 0.5), (0.2, 0.3))
    arena: tuple[float, float] = (1.0, 1.0)
    robot_radius: float = 0.04
    target_tolerance: float = 0.05
    start_jitter: float = 0.015
    dynamics: Dynamics = field(default_factory=Dynamics)

    def __post_init__(self) -> None:
        object.__setattr__(self, "num_robots", _number(self.num_robots, "num_robots", integer=True))
        for name in ("robot_radius", "target_tolerance", "start_jitter"):
            _number(getattr(self, name), name)
        arena = self.arena
        if isinstance(arena, str) or not hasattr(arena, "__len__") or len(arena) != 2:
            raise ScenarioError(f"arena must be a (width, height) pair [m], got {arena!r}")
        object.__setattr__(self, "arena", tuple(_number(c, "arena") for c in arena))
        # Accept lists (e.g. from JSON) but store tuples so the scenario stays hashable.
        for name in ("start_slots", "target_slots", "object_vertices"):
            value = getattr(self, name)
            try:
                object.__setattr__(self, name, tuple(tuple(float(c) for c in p) for p in value))
            except (TypeError, ValueError) as exc:
                raise ScenarioError(f"{name} must be a list of (x, y) pairs: {exc}") from None
        object.__setattr__(self, "arena", tuple(float(c) for c in self.arena))
        if isinstance(self.dynamics, dict):
            object.__setattr__(self, "dynamics", Dynamics(**self.dynamics))
        if not isinstance(self.dynamics, Dynamics):
            raise ScenarioError(f"dynamics must be a mapping of Dynamics fields, got {self.dynamics!r}")
        self.validate()

    # ------------------------------------------------------------------ arrays
    @property
    def starts(self) -> np.ndarray:
        """(N, 2) start slots [m]."""
        return np.asarray(self.start_slots, dtype=np.float64).reshape(-1, 2)

    @property
    def targets(self) -> np.ndarray:
        """(N, 2) target slots [m]."""
        return np.asarray(self.target_slots, dtype=np.float64).reshape(-1, 2)

    @property
    def polygon(self) -> np.ndarray:
        """(M, 2) object vertices, counter-clockwise [m]."""
        return np.asarray(self.object_vertices, dtype=np.float64).reshape(-1, 2)

    @property
    def object_center(self) -> np.ndarray:
        """(2,) centroid of the object polygon [m]."""
        return polygon_centroid(self.polygon)

    # -------------------------------------------------------------- validation
    def validate(self) -> None:
        """Raise :class:`ScenarioError` naming the field and the fix."""
        from sim.geometry import point_polygon_signed_distance_np

        n = self.num_robots
        if not isinstance(n, int | np.integer) or not 1 <= n <= MAX_ROBOTS:
            raise ScenarioError(f"num_robots must be an integer in 1..{MAX_ROBOTS}, got {n!r}")
        for name in ("start_slots", "target_slots"):
            count = len(getattr(self, name))
            if count != n:
                raise ScenarioError(
                    f"{name} has {count} slots but num_robots is {n}: give exactly one slot per robot"
                )
        for name in ("start_slots", "target_slots", "object_vertices"):
            if any(len(p) != 2 for p in getattr(self, name)):
                raise ScenarioError(f"{name}: every point must be an (x, y) pair")
            if not np.all(np.isfinite(np.asarray(getattr(self, name), dtype=float))):
                raise ScenarioError(f"{name} contains a non-finite coordinate")
        w, h = self.arena
        if not (len(self.arena) == 2 and w > 0 and h > 0 and math.isfinite(w) and math.isfinite(h)):
            raise ScenarioError(f"arena must be (width, height) > 0, got {self.arena!r}")
        r = self.robot_radius
        if not (math.isfinite(r) and 0 < r < min(w, h) / 2):
            raise ScenarioError(f"robot_radius must be in (0, {min(w, h) / 2}), got {r!r}")
        if not (math.isfinite(self.target_tolerance) and self.target_tolerance > 0):
            raise ScenarioError(f"target_tolerance must be > 0, got {self.target_tolerance!r}")
        if not (math.isfinite(self.start_jitter) and self.start_jitter >= 0):
            raise ScenarioError(f"start_jitter must be >= 0, got {self.start_jitter!r}")
        poly = self.polygon
        if len(poly) < 3:
            raise ScenarioError("object_vertices needs at least 3 vertices")
        edge = np.linalg.norm(np.roll(poly, -1, axis=0) - poly, axis=1)
        for i in np.flatnonzero(edge < 1e-9):
            raise ScenarioError(
                f"object_vertices[{i}] and object_vertices[{(i + 1) % len(poly)}] are the same point: "
                "list each vertex once (the polygon closes itself; do not repeat the first vertex)")
        if polygon_signed_area(poly) <= 0:
            raise ScenarioError(
                "object_vertices must be listed counter-clockwise with a non-zero area; reverse the list"
            )
        if np.any(poly < 0) or np.any(poly[:, 0] > w) or np.any(poly[:, 1] > h):
            raise ScenarioError("object_vertices: the object must lie inside the arena")
        self.dynamics.validate()
        j = self.start_jitter
        for name, pts, slack in (("start_slots", self.starts, j), ("target_slots", self.targets, 0.0)):
            reach = r + slack
            for i, (x, y) in enumerate(pts):
                if x - reach < 0 or x + reach > w or y - reach < 0 or y + reach > h:
                    raise ScenarioError(
                        f"{name}[{i}] = ({x:.3f}, {y:.3f}) is outside the arena for a robot of radius {r}"
                        + (f" with start jitter {j}" if slack else "")
                        + "; move it inward"
                    )
            sd = point_polygon_signed_distance_np(pts, poly)
            clear = r + math.sqrt(2) * slack         # the jitter is per axis: up to sqrt(2) j away
            for i in np.flatnonzero(sd < clear):
                raise ScenarioError(
                    f"{name}[{i}] = ({pts[i, 0]:.3f}, {pts[i, 1]:.3f}) is inside or touching the object "
                    f"(clearance {sd[i]:.3f} m < {clear:.3f} m"
                    + (f", a radius plus sqrt(2) x start jitter {j}" if slack else "")
                    + "); move it away from the object"
                )
            d = np.linalg.norm(pts[:, None] - pts[None], axis=-1) + np.eye(n) * 1e9
            i, k = np.unravel_index(np.argmin(d), d.shape)
            min_gap = 2 * r + 2 * math.sqrt(2) * slack
            if n > 1 and d[i, k] < min_gap:
                raise ScenarioError(
                    f"{name}[{i}] and {name}[{k}] overlap: centres {d[i, k]:.3f} m apart, need >= "
                    f"{min_gap:.3f} m (two radii" + (" plus jitter" if slack else "") + "); spread the slots"
                )

    # ------------------------------------------------------------- (de)serialise
    def to_dict(self) -> dict:
        return dataclasses.asdict(self)

    @classmethod
    def from_dict(cls, data: dict) -> Scenario:
        known = {f.name for f in dataclasses.fields(cls)}
        unknown = set(data) - known
        if unknown:
            raise ScenarioError(f"unknown scenario field(s) {sorted(unknown)}; known fields: {sorted(known)}")
        data = dict(data)
        if isinstance(data.get("dynamics"), dict):
            dyn_known = {f.name for f in dataclasses.fields(Dynamics)}
            bad = set(data["dynamics"]) - dyn_known
            if bad:
                raise ScenarioError(f"unknown dynamics field(s) {sorted(bad)}; known: {sorted(dyn_known)}")
            data["dynamics"] = Dynamics(**data["dynamics"])
        return cls(**data)

    def with_robots(self, n: int) -> Scenario:
        """The default layout of this arena and object for ``n`` robots, with this scenario's
        robots (radius), tolerance, jitter and dynamics."""
        return transport_scenario(n, object_vertices=self.object_vertices, dynamics=self.dynamics,
                                  start_jitter=self.start_jitter, arena=self.arena,
                                  robot_radius=self.robot_radius, target_tolerance=self.target_tolerance)


def polygon_signed_area(poly: np.ndarray) -> float:
    x, y = poly[:, 0], poly[:, 1]
    return 0.5 * float(np.sum(x * np.roll(y, -1) - np.roll(x, -1) * y))


def polygon_centroid(poly: np.ndarray) -> np.ndarray:
    x, y = poly[:, 0], poly[:, 1]
    cross = x * np.roll(y, -1) - np.roll(x, -1) * y
    area = 0.5 * cross.sum()
    cx = np.sum((x + np.roll(x, -1)) * cross) / (6 * area)
    cy = np.sum((y + np.roll(y, -1)) * cross) / (6 * area)
    return np.array([cx, cy])


def transport_scenario(n: int, *, object_vertices=None, dynamics: Dynamics | None = None,
                       start_jitter: float = 0.015, spacing: float = 0.125, name: str | None = None,
                       arena: tuple[float, float] = (1.0, 1.0), robot_radius: float = 0.04,
                       target_tolerance: float = 0.05) -> Scenario:
    """The default layout for ``n`` robots: slots in columns right (start) and left (target) of the object.

    The object's bounding box sets the columns: starts at ``right edge + 0.07``, targets at
    ``left edge - 0.07`` (robot radius 0.04, jitter 0.015, 0.015 clearance), one column per 7 robots.
    ``arena``, ``robot_radius`` and ``target_tolerance`` are the scenario's fields (a larger
    radius or jitter than the slots allow is refused by :meth:`Scenario.validate`).
    """
    if not isinstance(n, int | np.integer) or not 1 <= n <= MAX_ROBOTS:
        raise ScenarioError(f"num_robots must be an integer in 1..{MAX_ROBOTS}, got {n!r}")
    verts = object_vertices if object_vertices is not None else rectangle((0.5, 0.5), (0.2, 0.3))
    poly = np.asarray(verts, dtype=float)
    xmin, xmax = poly[:, 0].min(), poly[:, 0].max()
    yc = 0.5 * (poly[:, 1].min() + poly[:, 1].max())
    return Scenario(
        name=name or f"transport-{n}",
        num_robots=int(n),
        start_slots=column_slots(n, xmax + 0.07, yc, spacing, side=+1),
        target_slots=column_slots(n, xmin - 0.07, yc, spacing, side=-1),
        object_vertices=tuple(map(tuple, poly)),
        arena=tuple(arena),
        robot_radius=robot_radius,
        target_tolerance=target_tolerance,
        start_jitter=start_jitter,
        dynamics=dynamics or Dynamics(),
    )


PRESETS: dict[str, str] = {
    "paper-3": "the paper's three robots: right to left of a 0.2 x 0.3 box",
    "paper-4": "the paper's four robots",
    "paper-5": "the paper's five robots",
    "line-1": "one robot (smallest case, for smoke tests)",
    "crowd-16": "sixteen robots in three columns",
}


def load_scenario_file(path: str | Path) -> Scenario:
    """A scenario from a .json or .toml file holding :meth:`Scenario.to_dict` (what
    ``formation scenarios --show NAME`` prints); errors name the file and the field."""
    from sim.files import ConfigFileError, read_config

    try:
        data = read_config(path, f"scenario file {str(path)!r}")
    except ConfigFileError as exc:
        raise ScenarioSourceError(str(exc)) from None
    try:
        return Scenario.from_dict(data)
    except TypeError as exc:        # a required field missing: the dataclass names it
        raise ScenarioSourceError(f"scenario file {str(path)!r}: {exc}; start from "
                            "`formation scenarios --show paper-3`") from None
    except ScenarioError as exc:
        raise ScenarioSourceError(f"scenario file {str(path)!r}: {exc}") from None


def scenario_from(value: str | dict) -> Scenario:
    """A run config's ``scenario`` field: a preset name, transport-N, a scenario file, or a
    scenario dict (a file's content, as a run's config.json keeps it). ScenarioError or
    TypeError (a missing field) name what is wrong; ValueError for any other kind of value."""
    if isinstance(value, dict):
        return Scenario.from_dict(dict(value))
    if isinstance(value, str):
        return make_scenario(value)
    raise ValueError(f"scenario must be a preset name, a scenario file or a scenario dict, got {value!r}")


def make_scenario(name: str) -> Scenario:
    """Build a preset by name (see :data:`PRESETS`), ``transport-N`` for any N, or the scenario of
    a .json/.toml file (:func:`load_scenario_file`)."""
    from sim.files import is_file

    if name.endswith((".json", ".toml")) or is_file(name):
        return load_scenario_file(name)
    if name.startswith("paper-") and name[6:].isdigit() and name in PRESETS:
        return transport_scenario(int(name[6:]), name=name)
    if name == "line-1":
        return transport_scenario(1, name=name)
    if name == "crowd-16":
        return transport_scenario(16, name=name)
    if name.startswith("transport-") and name[10:].isdigit():
        if not 1 <= int(name[10:]) <= MAX_ROBOTS:
            raise ScenarioSourceError(f"scenario {name!r}: transport-N takes N = 1..{MAX_ROBOTS} robots")
        return transport_scenario(int(name[10:]))
    raise ScenarioSourceError(f"unknown scenario {name!r}; choose one of {sorted(PRESETS)}, transport-N "
                        f"(N = 1..{MAX_ROBOTS}) or a .json/.toml scenario file")
