"""The fused path's barrier rows compiled (:mod:`controllers.jit`).

The maths is that of :mod:`controllers.safety.fused` (its docstring: row layout, geometry,
barrier) and of the latency tightening (:meth:`controllers.safety.fused.FusedScene.terms`);
these loops compute it with the same operations in the same order as its numpy formulation
(kept by the tests as the reference). Row layout, K = P + N Q + 4N: pairs ``i < j`` in
``np.triu_indices`` order, robot-object rows (Q per robot, one per convex piece of the object),
robot-wall rows, both robot-major. The kernels that only read rows take each row's robots
``row_i``, ``row_j`` (K,) (``row_j = -1`` on rows of one robot) and do not depend on the layout.
"""

from __future__ import annotations

import math

import numpy as np

from controllers.array_kernels import clip_factor, clip_rows
from controllers.jit import kernel, register_warm_up


@kernel
def object_rows(pos, ax, ay, by, ex, ey, inv_len2, ex_over_ey, convex, box, box_center, box_half,
                radius, s_out, n_out, k_out):
    """Disc-object signed distances ``s_out`` (N,), unit normals ``n_out`` (N, 2) and curvatures
    ``k_out`` (N,) of (N, 2) centres (:meth:`controllers.safety.fused.FusedScene.object_geometry`).

    ``ax .. ex_over_ey`` (M,): per-edge constants of the counter-clockwise polygon; ``box``: it
    is an axis-aligned box of ``box_center``, ``box_half`` (2,), whose closed form applies while
    every centre is outside it.
    """
    n, m = pos.shape[0], ax.shape[0]
    if box:
        outside = True
        for i in range(n):
            o0 = np.maximum(abs(pos[i, 0] - box_center[0]) - box_half[0], 0.0)
            o1 = np.maximum(abs(pos[i, 1] - box_center[1]) - box_half[1], 0.0)
            outside = outside and math.hypot(o0, o1) > 1e-12
        if outside:
            for i in range(n):
                r0, r1 = pos[i, 0] - box_center[0], pos[i, 1] - box_center[1]
                o0, o1 = np.maximum(abs(r0) - box_half[0], 0.0), np.maximum(abs(r1) - box_half[1], 0.0)
                rho = math.hypot(o0, o1)
                n_out[i, 0], n_out[i, 1] = math.copysign(o0, r0) / rho, math.copysign(o1, r1) / rho
                k_out[i] = 1.0 / np.maximum(rho, 1e-9) if (o0 != 0.0 and o1 != 0.0) else 0.0
                s_out[i] = rho - radius
            return
    for i in range(n):
        px, py = pos[i, 0], pos[i, 1]
        best_d2, best_dx, best_dy, best_t = np.inf, 0.0, 0.0, 0.0
        all_left, crossings = True, 0
        for e in range(m):
            rx, ry = px - ax[e], py - ay[e]
            t = np.minimum(np.maximum((rx * ex[e] + ry * ey[e]) * inv_len2[e], 0.0), 1.0)
            dx, dy = rx - t * ex[e], ry - t * ey[e]
            d2 = dx * dx + dy * dy
            if e == 0 or d2 < best_d2:
                best_d2, best_dx, best_dy, best_t = d2, dx, dy, t
            all_left = all_left and ex[e] * ry - ey[e] * rx > 0
            if ((ay[e] > py) != (by[e] > py)) and rx < ry * ex_over_ey[e]:
                crossings += 1
        rho = math.sqrt(best_d2)
        inside = all_left if convex else crossings % 2 == 1
        sign = -1.0 if inside else 1.0
        scale = sign / (rho if rho > 1e-12 else 1.0)
        if rho > 1e-12:
            n_out[i, 0], n_out[i, 1] = best_dx * scale, best_dy * scale
        else:                                                    # centre on the boundary
            n_out[i, 0], n_out[i, 1] = 1.0, 0.0
        vertex = (best_t <= 0.0 or best_t >= 1.0) and not inside and rho > 0
        k_out[i] = 1.0 / np.maximum(rho, 1e-9) if vertex else 0.0
        s_out[i] = sign * rho - radius


@kernel
def barrier_rows(pos, vel, pair_i, pair_j, s_obj, obj_n, k_obj, radius, wall_offset, wall_normal_xy, alpha,
                 two_alpha, predicted, grow, closing, unsure, fixed, share_alpha, margin, floor_s, damping,
                 gamma, gamma_unsure, cubic, normal_xy, dist, h, drift, bound, pair_delta):
    """Every row's normal, distance, ``h``, drift and bound (module docstring of
    :mod:`controllers.safety.fused`; ``predicted``: tightened by ``grow``, ``closing``,
    ``unsure`` and ``fixed`` (N,) of a prediction).

    Args:
        s_obj, obj_n, k_obj: (N Q,), (N Q, 2), (N Q,) the object rows' distances, normals and
            curvatures (:func:`object_rows` per piece, robot-major).
        wall_offset: (4,) ``(0, W, 0, H) - r``; wall_normal_xy: (2, 4N) fixed wall normals.
        alpha, two_alpha: (K,) braking allowances of the rows without fixed robots (the object and
            wall rows keep theirs with fixed robots about).
        floor_s: ``margin + sqrt_floor`` [m]; cubic: the class-K function is ``h^3``.
        normal_xy (2, K), dist, h, drift, bound (K,), pair_delta (2, P): written.
    """
    n, p, q_rows = pos.shape[0], pair_i.shape[0], s_obj.shape[0]
    pieces = q_rows // n
    k_rows = p + q_rows + 4 * n
    curv = np.empty(k_rows)
    any_fixed, any_unsure = False, False
    if predicted:
        for i in range(n):
            any_fixed, any_unsure = any_fixed or fixed[i], any_unsure or unsure[i]
    for k in range(k_rows):
        if k < p:
            i, j = pair_i[k], pair_j[k]
            d0, d1 = pos[i, 0] - pos[j, 0], pos[i, 1] - pos[j, 1]
            pair_delta[0, k], pair_delta[1, k] = d0, d1
            centre = math.hypot(d0, d1)
            if centre > 1e-12:
                normal_xy[0, k], normal_xy[1, k] = d0 / np.maximum(centre, 1e-12), d1 / np.maximum(centre, 1e-12)
            else:                                                # coincident centres
                normal_xy[0, k], normal_xy[1, k] = 1.0, 0.0
            dist[k] = centre - 2.0 * radius
            curv[k] = 1.0 / np.maximum(centre, 1e-9)
            w0, w1 = vel[i, 0] - vel[j, 0], vel[i, 1] - vel[j, 1]
        elif k < p + q_rows:
            i, j = (k - p) // pieces, -1
            normal_xy[0, k], normal_xy[1, k] = obj_n[k - p, 0], obj_n[k - p, 1]
            dist[k], curv[k] = s_obj[k - p], k_obj[k - p]
            w0, w1 = vel[i, 0], vel[i, 1]
        else:
            i, j = (k - p - q_rows) // 4, -1
            wall = (k - p - q_rows) % 4
            normal_xy[0, k], normal_xy[1, k] = (wall_normal_xy[0, k - p - q_rows],
                                                wall_normal_xy[1, k - p - q_rows])
            coord = pos[i, 0] if wall < 2 else pos[i, 1]
            dist[k] = (coord if wall % 2 == 0 else -coord) + wall_offset[wall]
            curv[k] = 0.0
            w0, w1 = vel[i, 0], vel[i, 1]
        sdot = normal_xy[0, k] * w0 + normal_xy[1, k] * w1
        tang = np.maximum((w0 * w0 + w1 * w1) - sdot * sdot, 0.0)
        sdot_drift, row_alpha, row_two_alpha, row_gamma, dropped = sdot, alpha[k], two_alpha[k], gamma, False
        if predicted:
            if any_unsure and (unsure[i] or (j >= 0 and unsure[j])):
                row_gamma = gamma_unsure
            dist[k] = dist[k] - (grow[i] + grow[j] if j >= 0 else grow[i])
            allowance = closing[i] + closing[j] if j >= 0 else closing[i]
            sdot_drift = sdot - np.minimum(np.maximum(sdot, 0.0), allowance)
            sdot = sdot - allowance
            if any_fixed:
                free = (0.0 if fixed[i] else 1.0) + ((0.0 if fixed[j] else 1.0) if j >= 0 else 0.0)
                dropped = free == 0
                row_alpha = share_alpha * np.maximum(free, 1.0) if k < p else alpha[k]
                row_two_alpha = 2.0 * row_alpha
        clamped = np.maximum(dist[k], floor_s)
        root = math.sqrt(row_two_alpha * (clamped - margin))
        slope = row_alpha / root
        h[k] = root + slope * (dist[k] - clamped) + sdot
        drift[k] = (slope - damping) * sdot_drift + curv[k] * tang
        bound[k] = -(row_gamma * (h[k] * h[k] * h[k] if cubic else h[k])) - drift[k]
        if dropped:
            bound[k], h[k] = -np.inf, np.inf


@kernel
def sweep_rows(pos, vel, acc, widen, distance, pair_delta, pair_i, pair_j, wall_start, wall_offset, radius,
               margin, slack, dt, half_dt2, damping, accel_limit, speed_limit, end, bulge, travel, hit,
               wall_hit):
    """The one-tick sweep of every robot against the pairs and walls
    (:meth:`controllers.safety.fused.FusedScene.failing`, whose numpy formulation it matches).

    Args:
        acc: (N, 2) commands [m/s^2]; widen: (N,) disc growth [m]; distance: (K,) the rows'
            start distances (grown already); pair_delta: (2, P) start centre differences;
            wall_start: the first wall row (``P + N Q``);
            half_dt2: ``0.5 dt^2`` [s^2] (as the caller computes it).
        end (N, 2), bulge, travel (N,), hit (P,) bool, wall_hit (N, 4) bool: written.

    Returns:
        True when the travel bound alone clears every pair and wall row (then ``hit`` and
        ``wall_hit`` are all False and were not computed).
    """
    n, p = pos.shape[0], pair_i.shape[0]
    a_max, v_max = 0.0, 0.0
    a = np.empty((n, 2))
    v1 = np.empty((n, 2))
    for i in range(n):
        a[i, 0], a[i, 1] = acc[i, 0], acc[i, 1]
        a_max = np.maximum(a_max, math.hypot(acc[i, 0], acc[i, 1]))
    if not a_max <= accel_limit:
        for i in range(n):
            scale = clip_factor(acc[i, 0], acc[i, 1], accel_limit)
            a[i, 0], a[i, 1] = acc[i, 0] * scale, acc[i, 1] * scale
    for i in range(n):
        e0, e1 = a[i, 0] - damping * vel[i, 0], a[i, 1] - damping * vel[i, 1]
        bulge[i] = half_dt2 * math.hypot(e0, e1)
        v1[i, 0], v1[i, 1] = vel[i, 0] + dt * e0, vel[i, 1] + dt * e1
        travel[i] = math.hypot(v1[i, 0], v1[i, 1])
        v_max = np.maximum(v_max, travel[i])
    clip = not v_max <= speed_limit
    reach = -np.inf
    for i in range(n):
        speed = travel[i]
        if clip:
            scale = speed_limit / np.maximum(speed, speed_limit)
            v1[i, 0], v1[i, 1], speed = v1[i, 0] * scale, v1[i, 1] * scale, speed * scale
        end[i, 0], end[i, 1] = pos[i, 0] + dt * v1[i, 0], pos[i, 1] + dt * v1[i, 1]
        travel[i] = dt * speed + bulge[i]
        reach = np.maximum(reach, travel[i])
    reach = reach + margin + slack
    low_static, low_pair = np.inf, np.inf
    for k in range(p, distance.shape[0]):
        low_static = np.minimum(low_static, distance[k])
    for k in range(p):
        low_pair = np.minimum(low_pair, distance[k])
    if low_static >= reach and (p == 0 or low_pair >= 2.0 * reach):
        hit[:] = False
        wall_hit[:] = False
        return True
    for k in range(p):
        i, j = pair_i[k], pair_j[k]
        s0, s1 = pair_delta[0, k], pair_delta[1, k]
        c0, c1 = end[i, 0] - end[j, 0] - s0, end[i, 1] - end[j, 1] - s1
        dd = c0 * c0 + c1 * c1
        along = -(s0 * c0 + s1 * c1) / (dd if dd > 0 else 1.0)
        t = np.minimum(np.maximum(along, 0.0), 1.0)
        gap = math.hypot(s0 + t * c0, s1 + t * c1)
        hit[k] = gap < 2 * radius + ((bulge[i] + widen[i]) + (bulge[j] + widen[j])) + margin
    for i in range(n):
        for w in range(4):
            coord = end[i, 0] if w < 2 else end[i, 1]
            end_wall = ((coord if w % 2 == 0 else -coord) + wall_offset[w]) - widen[i]
            wall_hit[i, w] = np.minimum(distance[wall_start + 4 * i + w], end_wall) < bulge[i] + margin
    return False


@kernel
def rows_times(normal_xy, row_i, row_j, u, out):
    """``out[k] = n_k . (G u)_k`` (K,) for (N, 2) accelerations ``u`` (the module docstring's
    gather: ``u_i - u_j`` on pair rows, ``u_i`` on object and wall rows, ``row_j = -1``)."""
    for k in range(normal_xy.shape[1]):
        i, j = row_i[k], row_j[k]
        if j >= 0:
            w0, w1 = u[i, 0] - u[j, 0], u[i, 1] - u[j, 1]
        else:
            w0, w1 = u[i, 0], u[i, 1]
        out[k] = normal_xy[0, k] * w0 + normal_xy[1, k] * w1


@kernel
def screen(normal_xy, row_i, row_j, a_nom, limit, bound, distance, h, nominal, values):
    """The filter's first look at a tick, in one call: ``nominal = clip_norm(a_nom, limit)``
    (N, 2) written into ``nominal``, its row values (:func:`rows_times`) into ``values`` (K,),
    and ``(min distance, min h, every bound < inf, every row met: values >= bound)``. The minima
    are NaN where any entry is, as numpy's ``min``; the clip is ``x * (limit / max(|x|, limit))``
    with numpy's NaN-propagating maximum."""
    clip_rows(a_nom, limit, nominal)
    rows_times(normal_xy, row_i, row_j, nominal, values)
    low_d, low_h = distance[0], h[0]
    bounded, met = True, True
    for k in range(bound.shape[0]):
        if distance[k] != distance[k] or distance[k] < low_d:
            low_d = distance[k] if low_d == low_d else low_d
        if h[k] != h[k] or h[k] < low_h:
            low_h = h[k] if low_h == low_h else low_h
        if not bound[k] < math.inf:
            bounded = False
        if not values[k] >= bound[k]:
            met = False
    return low_d, low_h, bounded, met


@kernel
def command_breaks_rows(normal_xy, row_i, row_j, a_safe, a_cmd, bound, tol, floor, values):
    """The re-check's first test (:mod:`controllers.safety.recheck`): ``floor = minimum(bound,
    rows(a_safe)) - tol`` (K,) (numpy's NaN-propagating minimum) and ``values = rows(a_cmd)``
    written out; whether any row has ``values < floor``."""
    rows_times(normal_xy, row_i, row_j, a_safe, floor)
    for k in range(bound.shape[0]):
        b = bound[k]
        floor[k] = (b if (b < floor[k] or b != b) else floor[k]) - tol
    rows_times(normal_xy, row_i, row_j, a_cmd, values)
    for k in range(bound.shape[0]):
        if values[k] < floor[k]:
            return True
    return False


@register_warm_up
def _warm_up() -> None:
    n, m = 2, 4
    pos, vel = np.array([[0.2, 0.2], [0.8, 0.8]]), np.zeros((n, 2))
    edges = [np.ones(m) for _ in range(7)]
    pair_i, pair_j = np.triu_indices(n, 1)
    pair_i, pair_j = pair_i.astype(np.int64), pair_j.astype(np.int64)
    k = 1 + 5 * n
    row_i, row_j = np.zeros(k, dtype=np.int64), np.full(k, -1, dtype=np.int64)
    z, b = np.zeros(n), np.zeros(n, dtype=bool)
    s_obj, n_obj, k_obj = np.empty(n), np.empty((n, 2)), np.empty(n)
    object_rows(pos, *edges, True, True, np.full(2, 0.5), np.full(2, 0.1), 0.04, s_obj, n_obj, k_obj)
    barrier_rows(pos, vel, pair_i, pair_j, s_obj, n_obj, k_obj, 0.04, np.zeros(4), np.zeros((2, 4 * n)),
                 np.ones(k), np.ones(k), True, z, z, b, b, 0.5, 0.005, 0.01, 0.5, 5.0, 10.0, False,
                 np.empty((2, k)), np.empty(k), np.empty(k), np.empty(k), np.empty(k), np.empty((2, 1)))
    rows_times(np.ones((2, k)), row_i, row_j, pos, np.empty(k))
    command_breaks_rows(np.ones((2, k)), row_i, row_j, pos, pos, np.ones(k), 1e-9, np.empty(k), np.empty(k))
    screen(np.ones((2, k)), row_i, row_j, pos, 1.0, np.ones(k), np.ones(k), np.ones(k), np.empty((n, 2)),
           np.empty(k))
    sweep_rows(pos, vel, vel, z, np.zeros(k), np.zeros((2, 1)), pair_i, pair_j, 1 + n, np.zeros(4), 0.04, 0.005,
               1e-9, 0.05, 0.00125, 0.5, 1.0, 0.4, np.empty((n, 2)), np.empty(n), np.empty(n),
               np.empty(1, dtype=bool), np.empty((n, 4), dtype=bool))


__all__ = ["barrier_rows", "command_breaks_rows", "object_rows", "rows_times", "screen", "sweep_rows"]
