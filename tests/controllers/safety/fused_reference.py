"""The fused path's barrier rows in their numpy formulation: the reference its compiled kernels
(:mod:`controllers.safety.fused_kernels`) must match to the last bit
(tests/controllers/safety/test_fused_kernels.py)."""

from __future__ import annotations

import numpy as np

from controllers.safety.barrier import row_gamma
from controllers.safety.fused import _SLACK, FusedScene, FusedTerms
from controllers.safety.latency import Prediction


def _clip_rows(x: np.ndarray, limit: float) -> tuple[np.ndarray, np.ndarray]:
    """``(clip_norm(x, limit), row norms after clipping)`` for (N, 2) ``x``: the numbers of
    :func:`sim.scenario.clip_norm` (``x`` itself when no row exceeds the limit, where its factor
    is exactly 1); the norms of clipped rows are ``norm * factor`` (equal up to rounding)."""
    norm = np.hypot(x[:, 0], x[:, 1])
    if norm.max() <= limit:
        return x, norm
    scale = limit / np.maximum(norm, limit)
    return x * scale[:, None], norm * scale


class NumpyFusedScene(FusedScene):
    """:class:`FusedScene` with the object geometry and the rows computed by numpy expressions."""

    def object_geometry(self, pos: np.ndarray, polygon: np.ndarray
                        ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Disc-object geometry of (N, 2) centres: ``(s (N,), normal (N, 2), curvature (N,))``
        as in the module docstring.

        An axis-aligned box (the transport object at heading 0) takes the closed form while every
        centre is outside it, with ``o = max(|p - c| - h, 0)`` per axis: ``|p - q| = |o|``,
        ``n = sign(p - c) o / |o|``, a vertex when both components of ``o`` are positive. Any
        other polygon, or a centre inside or on the box, takes the edge projections.
        """
        if polygon is not self._polygon:
            self._set_polygon(polygon)
        if self._box:
            rel = pos - self._box_center
            out = np.maximum(np.abs(rel) - self._box_half, 0.0)
            rho = np.hypot(out[:, 0], out[:, 1])
            if rho.min() > 1e-12:                                             # all outside
                normal = np.copysign(out, rel) / rho[:, None]
                vertex = out.all(axis=1)                                      # both components > 0
                return rho - self.radius, normal, np.where(vertex, 1.0 / np.maximum(rho, 1e-9), 0.0)
        ax, ay, by, ex, ey, inv_len2, ex_over_ey = self._edges
        px, py = pos[:, :1], pos[:, 1:]
        rx, ry = px - ax, py - ay                                            # (N, M)
        t = np.minimum(np.maximum((rx * ex + ry * ey) * inv_len2, 0.0), 1.0)
        dx, dy = rx - t * ex, ry - t * ey                                    # centre - projection
        d2 = dx * dx + dy * dy
        flat = self.rows * self._m + d2.argmin(axis=1)
        ddx, ddy, t_best = dx.take(flat), dy.take(flat), t.take(flat)
        rho = np.sqrt(d2.take(flat))
        if self._convex:
            inside = (ex * ry - ey * rx > 0).all(axis=1)
        else:
            straddles = (ay > py) != (by > py)
            inside = np.count_nonzero(straddles & (rx < ry * ex_over_ey), axis=1) % 2 == 1
        sign = np.where(inside, -1.0, 1.0)
        safe = np.where(rho > 1e-12, rho, 1.0)
        scale = sign / safe
        normal = np.stack((ddx * scale, ddy * scale), axis=1)
        if not rho.min() > 1e-12:                                            # centre on the boundary
            normal[rho <= 1e-12] = (1.0, 0.0)
        vertex = ((t_best <= 0.0) | (t_best >= 1.0)) & ~inside & (rho > 0)
        curvature = np.where(vertex, 1.0 / np.maximum(rho, 1e-9), 0.0)
        return sign * rho - self.radius, normal, curvature

    def terms(self, pos: np.ndarray, vel: np.ndarray, pieces: np.ndarray | list,
              prediction: Prediction | None = None) -> FusedTerms:
        """Barrier values and rows of (N, 2) centres [m] and velocities [m/s] (module docstring).

        With a :class:`~controllers.safety.latency.Prediction` (``pos``/``vel`` then its
        predicted ones), every row's distance drops by the ``grow`` of its robots and the
        ``s_dot`` in ``h`` by their ``closing`` ``e``. In the drift the barrier does not count on
        an opening speed it cannot be sure of, ``s_dot_drift = s_dot - min(max(s_dot, 0), e)``,
        but adds no phantom approach either: with the full ``s_dot - e`` there, robots at rest
        pushed each other apart for ever (1 cm / 2 cm/s of noise: scripted success 0.75 against
        0.83 without the filter); with the plain ``s_dot``, a robot predicted to move away was
        released towards the object on a jittering link and rocked into it (1 of 20 episodes); a pair
        row with one fixed robot counts on the other one's braking alone (``braking_share *
        a_box``), a row of two fixed robots (or of a fixed robot and the object or a wall) is
        dropped (bound -inf).
        """
        p, cfg = self.p, self.config
        # pairs
        delta = pos.T @ self.pair_gather_t                                   # (2, P)
        centre = np.hypot(delta[0], delta[1])
        pair_normal = delta / np.maximum(centre, 1e-12)
        if p and not centre.min() > 1e-12:                                  # coincident centres
            pair_normal[:, centre <= 1e-12] = np.array([[1.0], [0.0]])
        # object, walls; then every row side by side
        obj_s, obj_n, obj_k = self.object_section(pos, pieces)
        walls = pos @ self.wall_map + self.wall_offset                       # (N, 4)
        normal = np.concatenate((pair_normal, obj_n.T, self._wall_normal_xy), axis=1)
        dist = np.concatenate((centre - 2.0 * self.radius, obj_s, walls.ravel()))
        curv = np.concatenate((1.0 / np.maximum(centre, 1e-9), obj_k, self._wall_zeros))
        # barrier (controllers.safety.barrier)
        w = vel.T @ self.gather_t                                            # (2, K)
        sdot = (normal * w).sum(axis=0)
        tang = np.maximum((w * w).sum(axis=0) - sdot * sdot, 0.0)
        alpha, two_alpha, dropped, gamma = self.alpha, self.two_alpha, None, cfg.gamma
        sdot_drift = sdot
        if prediction is not None:
            gamma = row_gamma(cfg, prediction, lambda x: x @ self.gather_abs_t)
            dist = dist - prediction.grow @ self.gather_abs_t
            allowance = prediction.closing @ self.gather_abs_t
            sdot_drift = sdot - np.minimum(np.maximum(sdot, 0.0), allowance)
            sdot = sdot - allowance
            if prediction.fixed.any():
                free = (~prediction.fixed).astype(np.float64) @ self.gather_abs_t     # (K,) 0, 1, 2
                dropped = free == 0
                alpha = self.alpha.copy()
                alpha[:p] = self.share_alpha * np.maximum(free[:p], 1.0)
                two_alpha = 2.0 * alpha
        # phi with its linear floor: s_c = max(s, m + z_f), phi = sqrt(2 alpha (s_c - m)) + phi' (s - s_c)
        clamped = np.maximum(dist, cfg.margin + cfg.sqrt_floor)
        root = np.sqrt(two_alpha * (clamped - cfg.margin))
        slope = alpha / root
        h = root + slope * (dist - clamped) + sdot
        drift = (slope - self.dynamics.damping) * sdot_drift + curv * tang
        k_of_h = gamma * (h if cfg.class_k == "linear" else h * h * h)
        bound = -k_of_h - drift
        if dropped is not None and dropped.any():
            bound[dropped] = -np.inf
            h = np.where(dropped, np.inf, h)
        return self.wrap_terms(normal, dist, h, drift, bound, delta, obj_n)

    def _sweep(self, pos: np.ndarray, vel: np.ndarray, acc: np.ndarray, widen: np.ndarray,
               terms: FusedTerms, margin: float) -> tuple[bool, np.ndarray, ...]:
        """:meth:`FusedScene._sweep` by numpy expressions."""
        dyn, r, m, p, n = self.dynamics, self.radius, margin, self.p, self.n
        a = _clip_rows(acc, dyn.accel_limit)[0]
        a_eff = a - dyn.damping * vel
        bulge = (0.5 * dyn.dt**2) * np.hypot(a_eff[:, 0], a_eff[:, 1])
        v1, speed = _clip_rows(vel + dyn.dt * a_eff, dyn.speed_limit)
        end = pos + dyn.dt * v1
        travel = dyn.dt * speed + bulge
        reach = travel.max() + m + _SLACK         # start distances in terms are grown already
        hit, wall_hit = np.zeros(p, dtype=bool), np.zeros((n, 4), dtype=bool)
        if terms.distance[p:].min() >= reach and (not p or terms.distance[:p].min() >= 2.0 * reach):
            return True, end, bulge, travel, hit, wall_hit
        if p:
            start = terms.pair_delta                                          # (2, P)
            chord = end.T @ self.pair_gather_t - start
            dd = chord[0] * chord[0] + chord[1] * chord[1]
            along = -(start[0] * chord[0] + start[1] * chord[1]) / np.where(dd > 0, dd, 1.0)
            t = np.minimum(np.maximum(along, 0.0), 1.0)
            gap = np.hypot(start[0] + t * chord[0], start[1] + t * chord[1])
            hit = gap < 2 * r + (bulge + widen) @ self.pair_both_t + m
        # walls: s of both chord ends against the widening (s + r < r + e + m)
        start_walls = terms.distance[self.wall_start:].reshape(n, 4)
        end_walls = end @ self.wall_map + self.wall_offset - widen[:, None]
        wall_hit = np.minimum(start_walls, end_walls) < (bulge + m)[:, None]
        return False, end, bulge, travel, hit, wall_hit
