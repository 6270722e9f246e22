"""Scenario distributions: the ranges a training episode's layout and dynamics are drawn from.

A :class:`ScenarioDistribution` describes, per field, a range ``[lo, hi]`` (or a set of
choices) instead of one value. The training world (:class:`sim.batched_env.BatchedFormationEnv`
with ``distribution=``) draws from it every episode:

* **Layout** (one per group of environments, since they share one object and its reward field;
  the environments of a group start and end their episodes together): the object's width and
  height [m], the offset of its centre from the arena's centre [m], its shape (``"box"``, or
  ``"polygon"``: 5-8 vertices at random angles, at least ``pi / k`` apart, on the ellipse
  inscribed in the width x height box, so always convex), the direction of the formation change
  (:data:`DIRECTIONS`), the start jitter [m] and the spacing of the slots along each column [m]
  (longer columns meet walls and queues that a few robots at the preset spacing never do), and
  the size K of the slot pool that the team's starts and targets are drawn from (``slot_pool``:
  n robots take n of the K start slots and, independently, n of the K target slots of the
  K-robot layout, so three robots meet the outer slots, the walls and the second columns of a
  ten-robot layout without ever training ten).
  Team sizes are the training run's
  ``team_sizes`` (one group each, so every update sees every size).
* **Dynamics** (per environment, at each of its resets): the actuator's gain (one per
  environment, each robot's spread around it by ``gain_spread``), its first-order lag time
  constant [s] and a pure command delay [ticks]: the :class:`sim.model_error.ModelError` knobs
  of the same names, in the batched world (:mod:`sim.actuator`), so the policy meets model error
  before it meets pymunk.

A layout is built as the default right-to-left layout (:func:`sim.scenario.transport_scenario`:
start columns right of the object, targets left) around the object as seen in a frame rotated
so that the formation runs right to left, then turned by the direction's angle about the arena's
centre. A draw whose slots do not fit the arena is drawn again; a distribution that cannot
place ``n`` robots in :data:`ATTEMPTS` draws is refused with the fields to change.

The defaults vary nothing: ``ScenarioDistribution()`` gives the preset layout and a perfect
actuator. :data:`DISTRIBUTIONS` holds named ones (``formation scenarios --show-distribution
NAME`` prints one as a file to edit); a file holds :meth:`ScenarioDistribution.to_dict`.
"""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from sim.scenario import MAX_ROBOTS, Scenario, ScenarioError, transport_scenario

DIRECTIONS = {"right_to_left": 0, "top_to_bottom": 90, "left_to_right": 180, "bottom_to_top": 270}
"""Direction of the formation change -> the angle [deg] the right-to-left layout is turned by,
counter-clockwise: at 90 its start columns (right of the object, +x) come to lie above it (+y)."""
SHAPES = ("box", "polygon")
_LAYOUT_FIELDS = ("object_width", "object_height", "object_offset", "object_shapes", "directions", "start_jitter",
                  "slot_spacing", "slot_pool")
ATTEMPTS = 200
MAX_DELAY_TICKS = 8


class DistributionError(ValueError):
    """A distribution that cannot be sampled; the message names the field and the fix."""


def _pair(name: str, value: Any, lo: float, hi: float, integer: bool = False) -> tuple:
    try:
        a, b = value
        a, b = (int(a), int(b)) if integer else (float(a), float(b))
    except (TypeError, ValueError, OverflowError):          # OverflowError: int(inf)
        raise DistributionError(f"{name} must be a [low, high] pair, got {value!r}") from None
    if integer and (a != value[0] or b != value[1]):
        raise DistributionError(f"{name} must be a pair of integers, got {value!r}")
    if not (math.isfinite(a) and math.isfinite(b) and lo <= a <= b <= hi):
        raise DistributionError(f"{name} must satisfy {lo} <= low <= high <= {hi}, got {list(value)!r}")
    return a, b


@dataclass(frozen=True)
class ScenarioDistribution:
    """Ranges of a training episode's layout and dynamics (see the module docstring).

    Attributes:
        object_width: ``[lo, hi]`` extent of the object along x [m] (in the arena frame).
        object_height: ``[lo, hi]`` extent along y [m].
        object_offset: ``[max |dx|, max |dy|]`` of the object's centre from the arena's [m].
        object_shapes: choices among :data:`SHAPES`, drawn with equal probability.
        directions: choices among :data:`DIRECTIONS`, drawn with equal probability.
        start_jitter: ``[lo, hi]`` of the layout's start jitter [m] (per axis, per episode).
        slot_spacing: ``[lo, hi]`` of the distance between neighbouring slots of a column [m]
            (the preset's 0.125; at least 0.09). Start slots need two radii plus 2 sqrt(2) times the
            start jitter (0.122 m at the default 1.5 cm), so closer draws are drawn again: the
            range in effect starts there.
        slot_pool: ``[lo, hi]`` integers: the layout is built for K ~ U{max(n, lo)..max(n, hi)}
            robots and the team's n starts and n targets are drawn from its K slots without
            replacement, each set on its own; ``[0, 0]`` (the default): K = n, every slot used.
        gain: ``[lo, hi]`` of an environment's actuator gain (achieved / commanded).
        gain_spread: each robot's gain is the environment's plus U(-spread, spread).
        lag_tau: ``[lo, hi]`` of the actuator lag time constant [s] (0: none).
        delay_ticks: ``[lo, hi]`` of the pure command delay [ticks], integers in 0..8.
    """

    object_width: tuple[float, float] = (0.2, 0.2)
    object_height: tuple[float, float] = (0.3, 0.3)
    object_offset: tuple[float, float] = (0.0, 0.0)
    object_shapes: tuple[str, ...] = ("box",)
    directions: tuple[str, ...] = ("right_to_left",)
    start_jitter: tuple[float, float] = (0.015, 0.015)
    slot_spacing: tuple[float, float] = (0.125, 0.125)
    slot_pool: tuple[int, int] = (0, 0)
    gain: tuple[float, float] = (1.0, 1.0)
    gain_spread: float = 0.0
    lag_tau: tuple[float, float] = (0.0, 0.0)
    delay_ticks: tuple[int, int] = (0, 0)

    def __post_init__(self) -> None:
        for name, lo, hi in (("object_width", 0.02, 0.9), ("object_height", 0.02, 0.9),
                             ("object_offset", 0.0, 0.45), ("start_jitter", 0.0, 0.05),
                             ("slot_spacing", 0.09, 0.45),
                             ("gain", 0.05, 2.0), ("lag_tau", 0.0, 1.0)):
            value = getattr(self, name)
            if name == "object_offset":      # two maxima, not a range
                if not (isinstance(value, list | tuple) and len(value) == 2):
                    raise DistributionError(f"object_offset must be [max |dx|, max |dy|] in metres, got {value!r}")
                for v in value:
                    _pair("object_offset", (0.0, v), lo, hi)
                object.__setattr__(self, name, (float(value[0]), float(value[1])))
                continue
            object.__setattr__(self, name, _pair(name, value, lo, hi))
        object.__setattr__(self, "delay_ticks", _pair("delay_ticks", self.delay_ticks, 0, MAX_DELAY_TICKS, True))
        object.__setattr__(self, "slot_pool", _pair("slot_pool", self.slot_pool, 0, MAX_ROBOTS, True))
        for name, allowed in (("object_shapes", SHAPES), ("directions", tuple(DIRECTIONS))):
            value = getattr(self, name)
            if isinstance(value, str) or not isinstance(value, list | tuple) or not value:
                raise DistributionError(f"{name} must be a non-empty list of choices among {list(allowed)}, "
                                        f"got {value!r}")
            bad = [v for v in value if v not in allowed]
            if bad:
                raise DistributionError(f"{name}: unknown choice(s) {bad}; choose among {list(allowed)}")
            object.__setattr__(self, name, tuple(value))
        if not (isinstance(self.gain_spread, int | float) and 0 <= self.gain_spread < self.gain[0]):
            raise DistributionError(f"gain_spread must be >= 0 and below the lowest gain {self.gain[0]} "
                                    f"(every robot's gain stays positive), got {self.gain_spread!r}")
        object.__setattr__(self, "gain_spread", float(self.gain_spread))

    # ------------------------------------------------------------ properties
    @property
    def varies_layout(self) -> bool:
        """Whether a draw can differ from the preset layout: a range, or a single value other
        than the default's, in any layout field (False: the training world keeps its scenario)."""
        return any(getattr(self, f.name) != f.default for f in dataclasses.fields(self) if f.name in _LAYOUT_FIELDS)

    @property
    def varies_dynamics(self) -> bool:
        """Whether any draw departs from a perfect actuator (gain 1, no lag, no delay)."""
        return self.gain != (1.0, 1.0) or self.gain_spread > 0 or self.lag_tau != (0.0, 0.0) or self.delay_ticks != (0, 0)

    # --------------------------------------------------------------- layouts
    def layout(self, base: Scenario, n: int, rng: np.random.Generator) -> Scenario:
        """A layout of ``n`` robots drawn with ``rng``; arena, radius, tolerance and dynamics are
        ``base``'s. Raises DistributionError when no draw fits the arena."""
        last = ""
        for _ in range(ATTEMPTS):
            try:
                return self._draw(base, n, rng)
            except ScenarioError as exc:
                last = str(exc)
        raise DistributionError(
            f"no layout of {n} robots drawn from this distribution fits the {base.arena[0]:g} x "
            f"{base.arena[1]:g} arena in {ATTEMPTS} draws (last: {last}); narrow object_width / "
            "object_height / object_offset / slot_spacing / slot_pool, or train fewer robots")

    def _draw(self, base: Scenario, n: int, rng: np.random.Generator) -> Scenario:
        w, h = rng.uniform(*self.object_width), rng.uniform(*self.object_height)
        centre = np.asarray(base.arena) / 2
        offset = rng.uniform(-1.0, 1.0, 2) * np.asarray(self.object_offset)
        shape = self.object_shapes[rng.integers(len(self.object_shapes))]
        direction = self.directions[rng.integers(len(self.directions))]
        jitter = float(rng.uniform(*self.start_jitter))
        lo, hi = self.slot_spacing     # drawn only when it varies: older distributions' draws stay the same
        spacing = float(rng.uniform(lo, hi)) if lo < hi else lo
        vertices = object_polygon(shape, centre + offset, (w, h), rng)
        angle = DIRECTIONS[direction]
        pool = n if self.slot_pool == (0, 0) else int(rng.integers(max(n, self.slot_pool[0]),
                                                                   max(n, self.slot_pool[1]) + 1))
        canonical = transport_scenario(pool, object_vertices=turn_points(vertices, -angle, centre),
                                       start_jitter=jitter, spacing=spacing, dynamics=base.dynamics,
                                       arena=base.arena, robot_radius=base.robot_radius,
                                       target_tolerance=base.target_tolerance)
        starts, targets = np.asarray(canonical.starts), np.asarray(canonical.targets)
        if pool > n:
            starts = starts[np.sort(rng.choice(pool, n, replace=False))]
            targets = targets[np.sort(rng.choice(pool, n, replace=False))]
        return Scenario(
            name=f"{direction}-{shape}-{n}", num_robots=n,
            start_slots=turn_points(starts, angle, centre), target_slots=turn_points(targets, angle, centre),
            object_vertices=vertices, arena=base.arena, robot_radius=base.robot_radius,
            target_tolerance=base.target_tolerance, start_jitter=jitter, dynamics=base.dynamics)

    # -------------------------------------------------------------- dynamics
    def actuator_draw(self, count: int, n: int, dt: float, rng: np.random.Generator):
        """``count`` environments' actuators: gains (count, n), lag factors ``alpha = 1 -
        exp(-dt / tau)`` (count,) (1: no lag) and delays (count,) ints [ticks]."""
        gain = rng.uniform(*self.gain, size=(count, 1)) + rng.uniform(-self.gain_spread, self.gain_spread,
                                                                       size=(count, n))
        tau = rng.uniform(*self.lag_tau, size=count)
        alpha = np.where(tau > 0, -np.expm1(-dt / np.maximum(tau, 1e-12)), 1.0)
        delay = rng.integers(self.delay_ticks[0], self.delay_ticks[1] + 1, size=count)
        return gain, alpha, delay

    # -------------------------------------------------------- (de)serialise
    def to_dict(self) -> dict:
        return {k: list(v) if isinstance(v, tuple) else v for k, v in dataclasses.asdict(self).items()}

    @classmethod
    def from_dict(cls, data: dict) -> ScenarioDistribution:
        if not isinstance(data, dict):
            raise DistributionError(f"a distribution must be a mapping of fields, got {type(data).__name__}")
        known = {f.name for f in dataclasses.fields(cls)}
        unknown = sorted(set(data) - known)
        if unknown:
            raise DistributionError(f"unknown distribution field(s) {unknown}; known fields: {sorted(known)}")
        return cls(**data)


def object_polygon(shape: str, centre: np.ndarray, size: tuple[float, float],
                   rng: np.random.Generator) -> tuple[tuple[float, float], ...]:
    """Counter-clockwise vertices of a ``shape`` object of bounding ``size`` (w, h) at ``centre``.

    ``"polygon"``: k ~ U{5..8} vertices at angles ``phi + cumsum(2 pi (1/(2k) + g_j / 2))``
    with g ~ Dirichlet(1, ..., 1) (gaps of at least ``pi / k``) on the inscribed ellipse."""
    w, h = size
    if shape == "box":
        angles = np.array([-3, -1, 1, 3]) * np.pi / 4
        pts = np.stack((np.sign(np.cos(angles)) * w / 2, np.sign(np.sin(angles)) * h / 2), 1)
    else:
        k = int(rng.integers(5, 9))
        gaps = 2 * np.pi * (0.5 / k + 0.5 * rng.dirichlet(np.ones(k)))
        angles = rng.uniform(0, 2 * np.pi) + np.concatenate(([0.0], np.cumsum(gaps[:-1])))
        pts = np.stack((np.cos(angles) * w / 2, np.sin(angles) * h / 2), 1)
    return tuple(map(tuple, (pts + centre).round(6)))


def turn_points(points, degrees: float, centre: np.ndarray) -> tuple[tuple[float, float], ...]:
    """``points`` (K, 2) turned counter-clockwise by ``degrees`` (a multiple of 90) about
    ``centre``, exactly (no rounding error: the rotation matrix has entries 0 and +-1)."""
    c, s = {0: (1, 0), 90: (0, 1), 180: (-1, 0), 270: (0, -1)}[int(degrees) % 360]
    p = np.asarray(points, dtype=float) - centre
    turned = np.stack((c * p[:, 0] - s * p[:, 1], s * p[:, 0] + c * p[:, 1]), 1) + centre
    return tuple(map(tuple, turned))


_LAYOUTS = dict(object_width=(0.1, 0.4), object_height=(0.1, 0.4), object_offset=(0.05, 0.05),
                object_shapes=SHAPES, directions=tuple(DIRECTIONS), start_jitter=(0.0, 0.02))
_ACTUATORS = dict(gain=(0.6, 1.2), gain_spread=0.1, lag_tau=(0.0, 0.1), delay_ticks=(0, 3))
DISTRIBUTIONS: dict[str, ScenarioDistribution] = {
    "none": ScenarioDistribution(),
    "actuators": ScenarioDistribution(**_ACTUATORS),
    "layouts": ScenarioDistribution(**_LAYOUTS),
    "broad": ScenarioDistribution(**_LAYOUTS, **_ACTUATORS),
}
"""Named distributions: ``none`` (the preset layout, a perfect actuator); ``actuators`` (the
preset layout; gain 0.6-1.2 with a 0.1 per-robot spread, up to 100 ms of lag and 150 ms (3
ticks) of delay: the link the safety layer is built for); ``layouts`` (a perfect actuator;
objects of 0.1-0.4 m a side, where two columns of 7 robots still fit beside one in the 1 x 1
arena, either shape, every direction, 0-2 cm of start jitter); ``broad`` (both)."""


def load_distribution(source: str | Path | dict) -> ScenarioDistribution:
    """A distribution by name (:data:`DISTRIBUTIONS`), from a mapping, inline JSON or a
    JSON/TOML file; every error starts with ``distribution`` and names the field (and file)."""
    if isinstance(source, str) and source in DISTRIBUTIONS:
        return DISTRIBUTIONS[source]
    where = "distribution"
    if not isinstance(source, dict):
        from sim.files import ConfigFileError, is_file, read_config

        if not is_file(source) and not str(source).strip().startswith("{"):
            raise DistributionError(f"distribution {str(source)!r} is neither a name ({', '.join(DISTRIBUTIONS)}) "
                                    "nor a .json/.toml file nor inline JSON")
        where = f"distribution {str(source)!r}" if is_file(source) else "distribution"
        try:
            source = read_config(source, where)
        except ConfigFileError as exc:
            raise DistributionError(str(exc)) from None
    try:
        return ScenarioDistribution.from_dict(source)
    except DistributionError as exc:
        raise DistributionError(f"{where}: {exc}") from None


__all__ = ["DIRECTIONS", "DISTRIBUTIONS", "DistributionError", "SHAPES", "ScenarioDistribution", "turn_points",
           "load_distribution", "object_polygon"]
