"""Docking's tick compiled (:mod:`controllers.jit`): distances, the matching shortcut, the law.

The maths is that of :mod:`controllers.docking` (its docstring); these loops compute it with the
same operations in the same order as its numpy formulation (kept by the tests as the reference).
"""

from __future__ import annotations

import math

import numpy as np

from controllers.array_kernels import clip_factor
from controllers.jit import kernel, register_warm_up


@kernel
def target_distances(pos, targets, dist):
    """``dist[i, t] = |p_i - t_t|`` (N, N) [m]; returns its smallest entry."""
    low = np.inf
    for i in range(pos.shape[0]):
        for t in range(targets.shape[0]):
            dist[i, t] = math.hypot(pos[i, 0] - targets[t, 0], pos[i, 1] - targets[t, 1])
            low = np.minimum(low, dist[i, t])
    return low


@kernel
def strict_nearest_matching(dist, match):
    """Each robot's nearest target into ``match`` (N,); True when every robot's nearest is
    strictly nearer than its others and no two robots share one: then that matching is the
    unique one of least total distance (any other gives some robot a strictly farther target
    and none a nearer one), so it is what an assignment solver returns."""
    n = dist.shape[0]
    taken = np.zeros(n, dtype=np.bool_)
    for i in range(n):
        best, second = 0, -1
        for t in range(1, n):
            if dist[i, t] < dist[i, best]:
                best, second = t, best
            elif second < 0 or dist[i, t] < dist[i, second]:
                second = t
        if (second >= 0 and not dist[i, best] < dist[i, second]) or taken[best]:
            return False
        taken[best] = True
        match[i] = best
    return True


@kernel
def dock(pos, vel, targets, dist, match, was, movable, capture_radius, release_radius, taken_within,
         capture_speed, stall_radius, stall_speed, kp, kd, accel_limit, a_nom, out, docking):
    """The docking rule and law for every robot (controllers.docking): ``out`` (N, 2) is
    ``a_nom`` with the docking rows replaced, ``docking`` (N,) bool written; returns whether any
    robot docks. ``taken_within``: ``2 r + free_margin`` [m]."""
    n = pos.shape[0]
    anyone = False
    for i in range(n):
        target = match[i]
        taken = False
        for k in range(n):
            taken = taken or (k != i and dist[k, target] < taken_within)
        gap = dist[i, target]
        speed = math.hypot(vel[i, 0], vel[i, 1])
        if was[i]:
            near = gap < release_radius
        else:
            near = (gap < capture_radius and speed < capture_speed) or (gap < stall_radius and speed < stall_speed)
        docking[i] = near and not taken and movable[i]
        out[i, 0], out[i, 1] = a_nom[i, 0], a_nom[i, 1]
        if docking[i]:
            anyone = True
            l0 = kp * (targets[target, 0] - pos[i, 0]) - kd * vel[i, 0]
            l1 = kp * (targets[target, 1] - pos[i, 1]) - kd * vel[i, 1]
            scale = clip_factor(l0, l1, accel_limit)
            out[i, 0], out[i, 1] = l0 * scale, l1 * scale
    return anyone


@register_warm_up
def _warm_up() -> None:
    n = 2
    pos, z2 = np.array([[0.1, 0.1], [0.9, 0.9]]), np.zeros((n, 2))
    dist, match, ones = np.empty((n, n)), np.empty(n, dtype=np.int64), np.ones(n, dtype=bool)
    target_distances(pos, pos, dist)
    strict_nearest_matching(dist, match)
    dock(pos, z2, pos, dist, match, ones, ones, 0.06, 0.14, 0.09, 0.2, 0.12, 0.1, 6.0, 4.0, 1.0, z2,
         np.empty((n, 2)), np.empty(n, dtype=bool))


__all__ = ["dock", "strict_nearest_matching", "target_distances"]
