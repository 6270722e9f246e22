r"""Docking: a terminal mode that takes a robot the last centimetres onto its target.

A learned policy is judged on success within the 5 cm target tolerance, and stops where it is
good enough: the policies here end 3-4 cm off their targets, where a robot cannot take hold of
the object. Docking replaces a robot's command, close to a free target, by a PD law onto it;
the result goes through the safety filter like any command (the filter may still slow or stop
a docking robot: docking never bypasses it).

**Which target.** The targets are matched to the robots one to one by least total distance
(:func:`scipy.optimize.linear_sum_assignment`, the assignment success is judged by,
:func:`sim.metrics.episode_outcome`). Robot ``i`` matched to target ``t_i`` docks when

* it is within ``capture_radius`` of ``t_i`` (``release_radius`` once docking: hysteresis),
* the target is free: no other robot's centre within ``2 r + free_margin`` of ``t_i``, and
* to start docking, it has slowed below ``capture_speed``: the matching of one moment is not
  where the policy is taking a robot that passes a target on its way to another. Without that
  gate, robots passing at speed were captured, held on a target the matching later gave to
  another robot, and released: with the safety filter on, the whole team came within 5 cm of
  its targets 61 ticks after the start (mean of 15 paper-3/4/5 episodes, a 3-5 robot policy,
  pymunk) where the same stack without docking took 53; with the gate at 0.2 m/s, 48 (at 0.1
  m/s, 49, and 73 -> 65 under gain 0.7, lag and friction), final distances 0.00-0.24 mm as
  before. At 0.1 m/s robots that oscillate near their targets under 150 ms of command delay
  were never captured (the policy succeeded in 25 of 30 episodes with the stack, 30 of 30
  without the gate); at 0.2 m/s, 30 of 30 there and under the jittering and gain-0.7 links.

**How near: two tiers.** A robot is captured within ``capture_radius`` (6 cm, just beyond the
5 cm tolerance) once slower than ``capture_speed``, or within ``stall_radius`` (12 cm, three
robot radii: a robot's diameter of displacement plus the tolerance) once it has all but stopped
(``stall_speed``, 0.1 m/s). The first tier brings home the robots a policy leaves a few
centimetres off. The second is for a crowd: a team larger than any the policy trained on packs
its column, and a robot held off its free slot by its neighbours stops short while the policy,
out of its depth, pushes it sideways into the next robot. Traced on transport-8 (an own-target
generalist trained on 3-5 robots, through the default stack in pymunk, gain 0.85 and one tick
of delay): the robot bound for the slot behind the column ended 9.4 cm from it, the three
robots beside it 2-6 cm from theirs. One 12 cm tier for every robot below 0.2 m/s brought those
teams home too, but it took over robots still on their way, by the matching of the moment: the
demo's unmarked generalist on 6 robots under the demo's model error succeeded in 0.60 of 20
episodes (6 cm: 0.70; two tiers: 1.00, 3.9 mm). Measured with ``bench/generalization.py``
(2026-12-05, 10 pymunk episodes a cell with gain 0.85 +- 0.15, 30 ms lag and one tick of delay;
``docs/results/docking_two_tier_2026-12-05.json``, one tier of 12 and of 6 cm in
``docking_radius_2026-12-05.json``): with two tiers four of five own-target generalists bring 8
robots home in every episode (6 cm: none), 9 robots in 0.60-1.00 and 10 in 0.60-1.00; on 3-7
robots no cell of the seven policies moves by more than one episode of ten from 6 cm; no contact
in any episode. A target reached by docking counts for success whichever robot the matching
sent there.

**Law** (per docking robot, m/s^2; ``p``, ``v`` its position and velocity)::

    a = clip_norm(kp (t_i - p) - kd v, accel_limit)

With the nominal damped double integrator (damping ``c``) the closed loop is
``x'' + (kd + c) x' + kp x = 0``: natural frequency ``sqrt(kp)`` and damping ratio
``(kd + c) / (2 sqrt(kp))``; the defaults (6, 4, c = 0.5) give 2.4 rad/s and 0.92: no overshoot
to speak of (measured on the nominal model from 5 cm: 3e-8 m), within 1 mm 2.15 s after capture. A gain or friction error
is the MEC's to compensate (the law asks for the nominal response).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.optimize import linear_sum_assignment

from controllers import docking_kernels
from controllers.checks import check_numbers
from controllers.jit import f64, require_shapes


class DockingConfigError(ValueError):
    """A docking setting that cannot work; the message names the field and the fix."""


@dataclass(frozen=True)
class DockingConfig:
    """Settings of the docking mode (module docstring).

    Attributes:
        enabled: dock (False: the policy's command stands).
        capture_radius: a robot this close to its free matched target, slower than
            ``capture_speed``, starts docking [m].
        release_radius: a docking robot farther than this from it stops docking [m].
        free_margin: a target is taken when another robot's centre is within ``2 r`` plus this [m].
        kp: position gain [1/s^2].
        kd: velocity gain [1/s].
        capture_speed: a robot starts docking only below this speed [m/s] (module docstring).
        stall_radius: a robot this close to its free matched target that has all but stopped
            (slower than ``stall_speed``) starts docking too [m] (module docstring, "How near";
            0 turns this tier off). A detour ends this close to a target, or within
            ``capture_radius`` where that is larger (with the tier off).
        stall_speed: see ``stall_radius`` [m/s].
        detour_after_s: a robot held in place (within 2 cm) this long away from every target, its
            policy pushing, is led round what holds it (:mod:`controllers.detour`) [s]; 0 turns
            detours off.
    """

    enabled: bool = True
    capture_radius: float = 0.06
    release_radius: float = 0.14
    free_margin: float = 0.01
    kp: float = 6.0
    kd: float = 4.0
    capture_speed: float = 0.2
    stall_radius: float = 0.12
    stall_speed: float = 0.1
    detour_after_s: float = 1.0

    def __post_init__(self) -> None:
        check_numbers(self, ("capture_radius", "release_radius", "free_margin", "kp", "kd", "capture_speed",
                             "stall_radius", "stall_speed", "detour_after_s"), "docking", DockingConfigError)
        for name in ("capture_radius", "stall_radius"):
            if self.release_radius < getattr(self, name):
                raise DockingConfigError(f"docking.release_radius ({self.release_radius}) must be >= "
                                         f"{name} ({getattr(self, name)})")


class Docking:
    """Per-robot docking state, keyed by robot id (module docstring)."""

    def __init__(self, robot_radius: float, accel_limit: float, config: DockingConfig | None = None):
        self.radius, self.accel_limit = float(robot_radius), float(accel_limit)
        self.config = config or DockingConfig()
        cfg = self.config
        self._consts = tuple(float(x) for x in (cfg.capture_radius, cfg.release_radius,
                                                 2 * self.radius + cfg.free_margin, cfg.capture_speed,
                                                 cfg.stall_radius, cfg.stall_speed,
                                                 cfg.kp, cfg.kd, self.accel_limit))
        self.reset()

    def reset(self) -> None:
        self._docking: set[str] = set()

    def __call__(self, ids: tuple[str, ...], pos: np.ndarray, vel: np.ndarray, targets: np.ndarray,
                 a_nom: np.ndarray, movable: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
        """(N, 2) commands with docking robots' rows replaced, and (N,) bool of those rows.

        ``pos``, ``vel``, ``targets``, ``a_nom``: (N, 2) [m, m/s, m, m/s^2]; ``movable`` (N,)
        bool: robots that may dock (default all; stale robots are braked by the stack anyway).
        """
        cfg, n = self.config, len(pos)
        docking = np.zeros(n, dtype=bool)
        if not cfg.enabled or n == 0 or len(targets) != n:
            self._docking.clear()
            return a_nom, docking
        require_shapes("Docking", pos=(pos, (n, 2)), vel=(vel, (n, 2)), targets=(targets, (n, 2)),
                       a_nom=(a_nom, (n, 2)))
        return self._dock(ids, f64(pos), f64(vel), f64(targets), a_nom, movable)

    def _dock(self, ids: tuple[str, ...], pos: np.ndarray, vel: np.ndarray, targets: np.ndarray,
              a_nom: np.ndarray, movable: np.ndarray | None) -> tuple[np.ndarray, np.ndarray]:
        """:meth:`__call__` for N >= 1 robots with N targets, compiled
        (:mod:`controllers.docking_kernels`), scipy's assignment where the nearest targets clash."""
        cfg, n = self.config, len(pos)
        docking = np.zeros(n, dtype=bool)
        dist = np.empty((n, n))
        if docking_kernels.target_distances(pos, targets, dist) >= cfg.release_radius:
            self._docking.clear()            # no robot near any target: the assignment cannot make one dock
            return a_nom, docking
        match = least_distance_matching(dist)
        was = np.array([rid in self._docking for rid in ids], dtype=bool)
        movable = np.ones(n, dtype=bool) if movable is None else np.ascontiguousarray(movable, dtype=bool)
        out = np.empty((n, 2))
        anyone = docking_kernels.dock(pos, vel, targets, dist, match, was, movable, *self._consts, f64(a_nom),
                                      out, docking)
        self._docking = {rid for rid, d in zip(ids, docking, strict=True) if d}
        return (out if anyone else a_nom), docking


def least_distance_matching(dist: np.ndarray) -> np.ndarray:
    """(N,) each robot's target under the matching of least total distance, for (N, N)
    robot-target distances [m]: each robot's nearest where no two share one and none ties
    (compiled), else scipy's assignment (rows come sorted)."""
    match = np.empty(len(dist), dtype=np.int64)
    if not docking_kernels.strict_nearest_matching(dist, match):
        match[:] = linear_sum_assignment(dist)[1]
    return match


__all__ = ["Docking", "DockingConfig", "DockingConfigError", "least_distance_matching"]
