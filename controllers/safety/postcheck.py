r"""One-tick post-check of commanded accelerations, and maximum braking.

Motion over one tick (dt) of robot i under the command ``a_i`` [m/s^2], from ``p_i`` [m] and
``v_i`` [m/s], as the worlds integrate it (:class:`sim.scenario.Dynamics`)::

    a'  = clip_norm(a_i, accel_limit)
    v'  = clip_norm(v_i + dt (a' - c v_i), speed_limit)
    p'  = p_i + dt v'

The swept region is the chord ``[p_i, p']`` widened by ``e_i = dt^2 |a' - c v_i| / 2``: the
continuous zero-order-hold path ``p_i + v_i t + (a' - c v_i) t^2 / 2`` lies within ``e_i`` of
that chord for ``t in [0, dt]`` (its gap to the chord is ``|a' - c v_i| t (dt - t/2)``), so both
the discrete step and the continuous motion are covered. Checks:

* robot-robot: the relative chord ``[p_i - p_j, p'_i - p'_j]`` passes the origin at no less than
  ``2 r + e_i + e_j + margin`` (closest point of a segment, analytic and vectorised);
* robot-wall: both chord ends keep ``r + e_i + margin`` from every wall (a half-plane is convex);
* robot-object: first the FCL clearance at the start of the tick against the travel bound
  ``|p' - p_i| + e_i``; only robots that fail it get the exact test, the FCL signed distance of
  the swept capsule (radius ``r + e_i``, the chord as its axis) to the object. FCL's
  ``continuousCollide`` is not used: it misses real contacts.

A pair or wall that fails is excused when its command is *no worse than the brake* that
failing would give it, at every instant of the tick and for every state the prediction allows.
Without this, robots stopped inside their grown or margin distance (by an earlier brake) were
braked in place for good, even while the QP pushed them apart: a deadlock. Both commands start
from the same state, so the brake's relative path is ``x(t) = d' + delta t + D_b(t)`` (true
relative position ``d'`` within ``g = grow_i + grow_j`` of the predicted ``d = p_i - p_j``, a
velocity error ``|delta| <= u = u_i + u_j``, :attr:`~controllers.safety.latency.Prediction.velocity_error`;
``D_b(t) = w_0 t + b t^2 / 2`` with the brake's relative effective acceleration ``b``), and the
command's is ``x(t) + Delta t^2 / 2``, with ``Delta = (a'_i - a^b_i) - (a'_j - a^b_j)`` the
relative difference of the clipped commands (the damping ``c v`` cancels; below the speed limit,
where the velocity stays affine in ``t``; the discrete end differs by ``Delta dt^2``, the same
direction). ``|x + y|^2 = |x|^2 + 2 x . y + |y|^2 >= |x|^2`` whenever ``x . y >= 0``, and::

    x(t) . Delta >= d . Delta + min(0, w_0 . Delta) dt + min(0, b . Delta) dt^2 / 2 - (g + u dt) |Delta|

so a pair whose right-hand side is >= 0 (and ``Delta != 0``) keeps at least the brake's distance
throughout (:func:`no_worse_than_braking`). A wall is a plane: the command's distance minus the
brake's is ``n . Delta_i t^2 / 2`` exactly, so ``n . Delta_i >= 0`` suffices, whatever the
errors (:func:`no_worse_walls`). The object is a union of convex pieces ``P_k`` (its FCL
parts); the distance to a convex set is a convex function, so with ``g(x)`` its gradient (the
outward normal of the face or corner nearest ``x``) ``dist(x + y, P) >= dist(x, P) + g(x) . y``.
The command's path is the brake's plus ``Delta_i t^2 / 2``, so it keeps at least the brake's
distance to ``P`` whenever ``g . Delta_i >= 0`` for every gradient the brake's path can meet:
its centres lie within ``rho = grow + (|v| + u) dt + (|a_b - c v| + c u) dt^2 / 2`` of the
predicted start ``p``, their nearest points within ``dist(p, P) + 2 rho`` of ``p``, and a
corner's normals lie between those of its two faces. So the object is excused when ``Delta_i``
points into none of the faces within that reach, on every piece that can be the nearest (a
piece at ``dist(p, P_k) >= min_j dist(p, P_j) + 2 rho + |Delta_i| dt^2 / 2`` cannot be:
:func:`no_worse_object`). A robot whose centre may be inside a piece is not excused. Robots
that are not the post-check's to brake (fixed ones) keep their command in all three.

A robot that fails a check gets the maximum-braking command (both robots of a failing pair), and
the check repeats until nothing changes, because a braking robot can block one behind it.
Robots that still fail are reported in ``contact``: even braking cannot avoid the touch.

Maximum braking aims at standstill after one tick, ``v' = 0``, i.e. ``a = c v - v / dt``, clipped
to the actuator limit along the same direction (so a slow robot stops instead of reversing).
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import fcl
import numpy as np

from controllers.safety.latency import Prediction
from sim.scenario import Dynamics, clip_norm


def braking_acceleration(vel: np.ndarray, dynamics: Dynamics,
                         prediction: Prediction | None = None) -> np.ndarray:
    """(N, 2) maximum-braking command for (N, 2) velocities [m/s]: :meth:`Dynamics.brake`, the
    one braking law of the robots and the filter; non-finite velocities give 0.

    With a latency ``prediction`` the velocity braked is ``prediction.braking_velocity()`` (the
    predicted one, or the measured one of a robot whose delay jitters), and ``vel`` (which the
    callers pass as ``prediction.vel``) is not read. It is a prediction ``h`` ticks ahead, and the command
    may act up to ``h`` ticks earlier, on a robot that has already braked: stopping in one tick
    from the predicted velocity then overshoots and the next tick brakes back (robots at a
    standstill chattered into contact). So a robot slow enough to stop within one tick
    (``|c v - v / dt| < accel_limit``) spreads its stop over ``h + 1`` ticks,
    ``c v - v / ((h + 1) dt)``; a faster one brakes at the limit, as :meth:`Dynamics.brake`
    (spreading that too let a robot brake slower than the one ahead of it stopped)."""
    if prediction is not None:
        vel = prediction.braking_velocity()
    one_tick = dynamics.brake(vel)
    if prediction is None or not prediction.horizon.any():
        return one_tick
    v = np.where(np.isfinite(vel), vel, 0.0)
    ticks = (prediction.horizon + 1.0)[:, None]
    slow = np.hypot(*(dynamics.damping * v - v / dynamics.dt).T) < dynamics.accel_limit
    return np.where(slow[:, None], dynamics.damping * v - v / (ticks * dynamics.dt), one_tick)


def predict_step(pos: np.ndarray, vel: np.ndarray, acc: np.ndarray,
                 dynamics: Dynamics) -> tuple[np.ndarray, np.ndarray]:
    """End positions (N, 2) [m] and chord widening ``e`` (N,) [m] of one tick (module docstring)."""
    a = clip_norm(acc, dynamics.accel_limit)
    a_eff = a - dynamics.damping * vel
    v1 = clip_norm(vel + dynamics.dt * a_eff, dynamics.speed_limit)
    bulge = 0.5 * dynamics.dt**2 * np.hypot(a_eff[:, 0], a_eff[:, 1])
    return pos + dynamics.dt * v1, bulge


def no_worse_than_braking(start: np.ndarray, w0: np.ndarray, diff: np.ndarray, brake_rel: np.ndarray,
                          slack: np.ndarray, unclipped: np.ndarray, dt: float) -> np.ndarray:
    """(K,) bool: pairs whose commands keep them at least as far apart as braking both would,
    all tick long (module docstring).

    ``start`` (K, 2) relative positions ``d = p_i - p_j`` [m]; ``w0`` (K, 2) relative velocities
    [m/s]; ``diff`` (K, 2) ``Delta``, the relative command minus the relative brake (clipped)
    [m/s^2]; ``brake_rel`` (K, 2) ``b``, the relative effective brake acceleration [m/s^2];
    ``slack`` (K,) ``g + u dt`` [m]; ``unclipped`` (K,) bool, no speed clip for either robot."""
    def dot(x, y):
        return x[:, 0] * y[:, 0] + x[:, 1] * y[:, 1]
    norm = np.hypot(diff[:, 0], diff[:, 1])
    lhs = (dot(start, diff) + np.minimum(dot(w0, diff), 0.0) * dt
           + np.minimum(dot(brake_rel, diff), 0.0) * (0.5 * dt * dt))
    return unclipped & (norm > 1e-12) & (lhs >= slack * norm)


def no_worse_walls(diff: np.ndarray) -> np.ndarray:
    """(N, 4) bool: robots whose command minus brake ``Delta_i`` (N, 2) [m/s^2] is nonzero and
    does not point into the walls ``x = 0, x = W, y = 0, y = H`` (in that order)."""
    moved = (np.abs(diff) > 1e-12).any(axis=1)[:, None]
    return moved & (np.stack([diff[:, 0], -diff[:, 0], diff[:, 1], -diff[:, 1]], axis=1) >= 0.0)


def no_worse_object(start: np.ndarray, diff: np.ndarray, rho: float, pieces: list[np.ndarray],
                    dt: float) -> bool:
    """True when a robot whose command minus brake is ``diff`` (2,) [m/s^2] keeps at least the
    brake's distance to every convex piece (K, 2) (counter-clockwise, [m]) all tick long: no
    face within reach of the brake's path, whose centres lie within ``rho`` [m] of ``start``
    (2,) [m], has ``n . diff < 0`` (module docstring)."""
    norm = float(np.hypot(*diff))
    if norm <= 1e-12 or not pieces:
        return False
    near, dists = [], []
    for piece in pieces:
        a, b = piece, np.roll(piece, -1, axis=0)
        edge = b - a
        length2 = np.sum(edge * edge, axis=1)
        t = np.clip(np.sum((start - a) * edge, axis=1) / length2, 0.0, 1.0)
        d = np.hypot(*(start - (a + t[:, None] * edge)).T)                  # (K,) to each face
        normal = np.stack([edge[:, 1], -edge[:, 0]], 1) / np.sqrt(length2)[:, None]
        if np.all(np.sum((start - a) * normal, axis=1) <= 0.0):             # inside the piece
            return False
        near.append((d, normal))
        dists.append(float(d.min()))
    closest = min(dists)
    for (d, normal), dist in zip(near, dists, strict=True):
        if dist >= closest + 2 * rho + 0.5 * norm * dt * dt:
            continue                                                       # never the nearest
        faces = d <= dist + 2 * rho
        if np.any(normal[faces] @ diff < 0.0):
            return False
    return True


def excuses(pos: np.ndarray, vel: np.ndarray, acc: np.ndarray, brake: np.ndarray, pi: np.ndarray,
            pj: np.ndarray, grow: np.ndarray | None, vel_error: np.ndarray | None,
            dynamics: Dynamics) -> tuple[np.ndarray, np.ndarray]:
    """``(pair_ok (P,), wall_ok (N, 4))``: the pairs ``pi, pj`` and robot-walls whose command
    ``acc`` is no worse than ``brake`` (module docstring); shared by both sweep paths."""
    dt, limit = dynamics.dt, dynamics.accel_limit
    a_cmd, a_brake = clip_norm(acc, limit), clip_norm(brake, limit)
    diff = a_cmd - a_brake
    free = _below_speed_limit(vel, a_cmd, dynamics) & _below_speed_limit(vel, a_brake, dynamics)
    wall_ok = no_worse_walls(diff) & free[:, None]
    if not len(pi):
        return np.zeros(0, dtype=bool), wall_ok
    b = a_brake - dynamics.damping * vel
    g = 0.0 if grow is None else grow[pi] + grow[pj]
    u = 0.0 if vel_error is None else vel_error[pi] + vel_error[pj]
    slack = np.broadcast_to(g + u * dt, (len(pi),))
    pair_ok = no_worse_than_braking(pos[pi] - pos[pj], vel[pi] - vel[pj], diff[pi] - diff[pj],
                                    b[pi] - b[pj], slack, free[pi] & free[pj], dt)
    return pair_ok, wall_ok


def _below_speed_limit(vel: np.ndarray, clipped_acc: np.ndarray, dynamics: Dynamics) -> np.ndarray:
    """(N,) bool: robots whose end-of-tick velocity needs no speed clip under the (N, 2)
    commands already clipped to the actuator limit (module docstring)."""
    raw = vel + dynamics.dt * (clipped_acc - dynamics.damping * vel)
    return np.hypot(raw[:, 0], raw[:, 1]) <= dynamics.speed_limit


def segment_origin_distance(start: np.ndarray, end: np.ndarray) -> np.ndarray:
    """(K,) distance from the origin to the segments ``[start_k, end_k]`` given as (K, 2) ends."""
    d = end - start
    dd = np.sum(d * d, axis=1)
    t = np.clip(-np.sum(start * d, axis=1) / np.where(dd > 0, dd, 1.0), 0.0, 1.0)
    closest = start + t[:, None] * d
    return np.hypot(closest[:, 0], closest[:, 1])


@dataclass
class PostcheckResult:
    """Outcome of :func:`postcheck` for N robots.

    Attributes:
        acc: (N, 2) the checked command: the input, with failing robots set to maximum braking.
        braked: (N,) bool, robots whose command was replaced by braking.
        contact: (N,) bool, robots whose sweep still fails even when braking.
    """

    acc: np.ndarray
    braked: np.ndarray
    contact: np.ndarray


class SweepChecker:
    """Checks one tick of motion against robots, the object and the walls.

    Args:
        object_parts: FCL collision objects of the object (posed), see
            :class:`controllers.safety.geometry.CollisionScene`.
        object_pieces: returns those parts as convex counter-clockwise (K, 2) polygons in the
            world frame [m] (``CollisionScene.object_pieces``), for the object's excuse.
        radius: disc radius [m]; arena: (W, H) [m]; dynamics: the plant model; margin [m].
    """

    def __init__(self, object_parts: list[fcl.CollisionObject], radius: float,
                 arena: tuple[float, float], dynamics: Dynamics, margin: float = 0.0,
                 object_pieces: Callable[[], list[np.ndarray]] | None = None):
        self.object_parts = object_parts
        self.object_pieces = object_pieces    # the parts' convex polygons now; None: no object excuse
        self.radius = radius
        self.arena = arena
        self.dynamics = dynamics
        self.margin = margin
        self._request = fcl.DistanceRequest()     # plain: see capsule_clearance
        self._pairs: dict[int, tuple[np.ndarray, np.ndarray]] = {}

    def failing(self, pos: np.ndarray, vel: np.ndarray, acc: np.ndarray,
                object_clearance: np.ndarray, grow: np.ndarray | None = None,
                vel_error: np.ndarray | None = None, brake: np.ndarray | None = None) -> np.ndarray:
        """(N,) bool: robots whose one-tick sweep touches something.

        ``object_clearance`` (N,) is each disc's signed distance to the object at ``pos`` [m];
        ``grow`` (N,) [m] widens each disc and ``vel_error`` (N,) [m/s] bounds the error of
        ``vel`` (a latency prediction's, see :mod:`controllers.safety.latency`). ``brake``
        (N, 2): what failing robots would get; pairs and walls no worse than it are excused
        (module docstring). None: no excuses.
        """
        n, r, m = len(pos), self.radius, self.margin
        end, bulge = predict_step(pos, vel, acc, self.dynamics)
        if grow is not None:
            bulge = bulge + grow
            object_clearance = object_clearance - grow
        bad = np.zeros(n, dtype=bool)
        if n not in self._pairs:
            self._pairs[n] = np.triu_indices(n, 1)
        pi, pj = self._pairs[n]
        w, h = self.arena
        reach = (r + bulge + m)[:, None]
        ends = np.stack([pos, end])                                           # (2, N, 2)
        wall_gap = np.stack([ends[..., 0], w - ends[..., 0], ends[..., 1], h - ends[..., 1]], -1)
        wall_hit = wall_gap.min(axis=0) < reach
        hit = np.zeros(len(pi), dtype=bool)
        if n > 1:
            gap = segment_origin_distance(pos[pi] - pos[pj], end[pi] - end[pj])
            hit = gap < 2 * r + bulge[pi] + bulge[pj] + m
        if brake is not None and (hit.any() or wall_hit.any()):
            pair_ok, wall_ok = excuses(pos, vel, acc, brake, pi, pj, grow, vel_error, self.dynamics)
            hit &= ~pair_ok
            wall_hit &= ~wall_ok
        bad[pi[hit]] = True
        bad[pj[hit]] = True
        bad |= np.any(wall_hit, axis=1)
        travel = np.hypot(*(end - pos).T) + bulge
        for i in np.flatnonzero(object_clearance - m <= travel):
            if self.capsule_clearance(pos[i], end[i], r + bulge[i]) < m:
                bad[i] |= not self.object_excused(i, pos, vel, acc, brake, grow, vel_error)
        return bad

    def object_excused(self, i: int, pos: np.ndarray, vel: np.ndarray, acc: np.ndarray,
                       brake: np.ndarray | None, grow: np.ndarray | None,
                       vel_error: np.ndarray | None) -> bool:
        """Whether robot ``i``'s command is no worse than ``brake`` against the object (module
        docstring; arguments as :meth:`failing`); False without a brake or object pieces."""
        if brake is None or self.object_pieces is None:
            return False
        dyn, dt = self.dynamics, self.dynamics.dt
        one = slice(i, i + 1)
        a_cmd, a_brake = clip_norm(acc[one], dyn.accel_limit), clip_norm(brake[one], dyn.accel_limit)
        if not (_below_speed_limit(vel[one], a_cmd, dyn) & _below_speed_limit(vel[one], a_brake, dyn))[0]:
            return False
        u = 0.0 if vel_error is None else float(vel_error[i])
        rho = ((0.0 if grow is None else float(grow[i])) + (float(np.hypot(*vel[i])) + u) * dt
               + (float(np.hypot(*(a_brake[0] - dyn.damping * vel[i]))) + dyn.damping * u) * 0.5 * dt * dt)
        return no_worse_object(pos[i], a_cmd[0] - a_brake[0], rho, self.object_pieces(), dt)

    def capsule_clearance(self, start: np.ndarray, end: np.ndarray, radius: float) -> float:
        """FCL distance between the object and the disc of ``radius`` swept from start to end [m]:
        exact while they are apart, -1 when they touch or overlap (all that ``< margin`` needs).

        The plain query, not the signed one: on touching shapes the signed query's EPA throws a
        C++ ``std::logic_error`` ("the origin is outside of the polytope", FCL issues #390, #408,
        #445; the fix, PR #632, is not merged) that python-fcl does not catch, so the process
        aborted (a disc of 0.1 m at (0.5, 0.25) against paper-5's object, whose edge is y = 0.35:
        ``formation eval --world pymunk --intruder radius=0.06,x=0.5,y=1.1,vy=-0.2,enter=20``)."""
        chord = end - start
        length = float(np.hypot(*chord))
        if length < 1e-12:
            shape, rot = fcl.Sphere(radius), np.eye(3)
        else:
            ux, uy = chord / length
            # columns: x -> e_z, y -> e_z x u, z -> u (the capsule axis along the chord)
            rot = np.array([[0.0, uy, ux], [0.0, -ux, uy], [1.0, 0.0, 0.0]])
            shape = fcl.Capsule(radius, length)
        mid = 0.5 * (start + end)
        swept = fcl.CollisionObject(shape, fcl.Transform(rot, np.array([mid[0], mid[1], 0.0])))
        return min(fcl.distance(swept, part, self._request, fcl.DistanceResult())
                   for part in self.object_parts)

    def check(self, pos: np.ndarray, vel: np.ndarray, acc: np.ndarray,
              object_clearance: np.ndarray, prediction=None) -> PostcheckResult:
        """Brake every robot that fails (repeating until stable); see the module docstring.
        Fixed robots of a latency ``prediction`` are never braked here (not listening)."""
        acc = acc.copy()
        braked = np.zeros(len(pos), dtype=bool)
        grow = None if prediction is None else prediction.grow
        vel_error = None if prediction is None else prediction.velocity_error
        mine = np.ones(len(pos), dtype=bool) if prediction is None else ~prediction.fixed
        brake = np.where(mine[:, None], braking_acceleration(vel, self.dynamics, prediction), acc)
        bad = self.failing(pos, vel, acc, object_clearance, grow, vel_error, brake)
        for _ in range(len(pos)):
            new = bad & ~braked & mine
            if not new.any():
                break
            braked |= new
            acc[new] = brake[new]
            bad = self.failing(pos, vel, acc, object_clearance, grow, vel_error, brake)
        return PostcheckResult(acc=acc, braked=braked, contact=bad)
