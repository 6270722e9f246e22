r"""The fused fast path of the safety filter: distances, barrier rows and the one-tick sweep in one go.

The reference path of :class:`controllers.safety.SafetyFilter` builds a
:class:`~controllers.safety.geometry.SceneDistances` (FCL or closed form), then
:func:`~controllers.safety.barrier.barrier_terms`, then runs
:class:`~controllers.safety.postcheck.SweepChecker`: about a hundred small numpy calls per tick.
This module computes the same numbers for the whole scene at once, with index arrays and buffers
prepared once per robot count N, so the cost per tick is a few dozen array operations whatever N.
The maths are those of :mod:`controllers.safety.barrier` and :mod:`controllers.safety.postcheck`;
only the arrangement differs. Tests hold it equal to the FCL path on random scenes.

Row layout (the one of :mod:`controllers.safety.barrier`, K = P + N Q + 4N rows for an object of Q
convex pieces): pairs ``i < j`` in ``np.triu_indices`` order, robot-object rows (one per robot and
piece) and robot-wall rows, both robot-major. Every row ``k`` reads
the robots through a gather matrix ``G`` (K, N) with ``+1`` at robot ``i_k`` and ``-1`` at robot
``j_k`` (pair rows only), so that for any (N, 2) array ``x`` the product ``G x`` is ``x_i - x_j``
on pair rows and ``x_i`` on object and wall rows. With the unit normals ``n_k`` (stored as
planes (2, K)) and signed distances ``s_k``::

    w      = G v                                     relative velocities (K, 2) [m/s]
    s_dot  = n . w,   |w_t|^2 = max(|w|^2 - s_dot^2, 0)
    h      = phi(s - m) + s_dot,   drift = (phi'(s - m) - c) s_dot + kappa |w_t|^2
    b      = -K(h) - drift,        row k of the QP:  n_k . (G u)_k >= b_k

Geometry per row (closed form, exact for discs, half-planes and simple polygons):

* pairs: ``d = p_i - p_j``, ``s = |d| - 2r``, ``n = d / |d|``, ``kappa = 1 / |d|``;
* object, per convex piece: each centre projected onto every edge of the piece (clamped), the nearest projection
  gives the boundary point ``q``; inside by the edge cross products (convex polygon) or the
  crossing number (simple polygon); ``s = +-|p - q| - r``, ``n = +-(p - q) / |p - q|`` (minus
  inside), ``kappa = 1 / |p - q|`` when ``q`` is a vertex and ``p`` is outside, else 0;
* walls: ``s = (x, W - x, y, H - y) - r`` with the constant inward normals.

An axis-aligned box (the transport object at heading 0) with every centre outside it takes the
shorter closed form of :meth:`FusedScene.object_geometry`; a rotated or other polygon, or a centre
inside the box, the edge projections.

Why FCL stays, and where (python-fcl 0.7): the closed forms above are exact for this scene
(discs, a polygon prism and four walls), and FCL's own signed distances are not (GJK is off by
up to 7e-4 m, EPA depths by ~1e-6 m; the reference path re-projects FCL's witness points onto the
polygon edges to get them exact). So the fast path does not ask FCL for distances. FCL remains
the collision geometry of the filter in two places: (1) the posed object prism lives in the FCL
scene (:class:`~controllers.safety.geometry.CollisionScene`), and the sweep check below hands
every robot whose one-tick travel bound cannot rule out touching the object
(``clearance - margin <= travel + widening``) to FCL's exact signed distance between the swept
capsule and the prism: near contact, FCL decides; far from it, the triangle inequality alone
proves clearance (a swept disc cannot reach further than its travel). (2) The FCL scene is the
reference backend (``SafetyConfig(geometry="fcl")``) that the tests hold this path equal to.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from controllers.jit import f64, require_shapes
from controllers.safety import fused_kernels
from controllers.safety.barrier import BarrierTerms, SafetyConfig, octagon_accel, row_robots
from controllers.safety.geometry import WALL_NORMALS
from controllers.safety.latency import Prediction
from controllers.safety.polygon import is_convex_ccw
from controllers.safety.postcheck import (
    PostcheckResult,
    SweepChecker,
    braking_acceleration,
    excuses,
)
from sim.scenario import Dynamics

_SLACK = 1e-9
"""[m] added to the travel bounds of the sweep check, so that rounding can only make it ask the
exact tests more often, never less."""



@dataclass
class FusedTerms(BarrierTerms):
    """:class:`BarrierTerms` of the fused path, plus what the sweep check reuses.

    Attributes (besides those of :class:`BarrierTerms`):
        normal_xy: (2, K) row normals as x and y planes.
        gather_t: (N, K) the transposed gather matrix ``G^T`` (module docstring).
        row_i, row_j: (K,) the robots of every row (``row_j = -1`` on rows of one robot).
        distance: (K,) signed distances of every row [m].
        pair_delta: (2, P) centre differences ``p_i - p_j`` of the pairs [m].
    """

    normal_xy: np.ndarray = None        # type: ignore[assignment]
    gather_t: np.ndarray = None         # type: ignore[assignment]
    row_i: np.ndarray = None            # type: ignore[assignment]
    row_j: np.ndarray = None            # type: ignore[assignment]
    distance: np.ndarray = None         # type: ignore[assignment]
    pair_delta: np.ndarray = None       # type: ignore[assignment]

    def rows_times(self, u: np.ndarray) -> np.ndarray:
        """(K,) row values ``n_k . (G u)_k`` for (N, 2) accelerations ``u`` (compiled)."""
        if u.shape != (self.gather_t.shape[0], 2):
            raise ValueError(f"FusedTerms.rows_times: u must have shape ({self.gather_t.shape[0]}, 2), "
                             f"got {u.shape}")
        out = np.empty(self.normal_xy.shape[1])
        fused_kernels.rows_times(self.normal_xy, self.row_i, self.row_j, f64(u), out)
        return out

    def row_robots(self) -> tuple[np.ndarray, np.ndarray]:
        """``(row_i, row_j)``, prepared once per scene."""
        return self.row_i, self.row_j

    def object_distance(self) -> np.ndarray:
        """(N,) disc-object signed distances [m] (the nearest piece of each robot)."""
        p = len(self.pair_i)
        rows = self.distance[p:p + len(self.object_normal)]
        return rows if self.pieces == 1 else rows.reshape(-1, self.pieces).min(axis=1)


class FusedScene:
    """Prepared index arrays and buffers for N robots in one scenario (see the module docstring).

    Args:
        radius: disc radius r [m]; arena: (W, H) [m]; dynamics: the plant model.
        config: the filter settings (margin, gamma, class-K, braking share, floor, ...).
        num_robots: N >= 1.
        pieces: Q >= 1, the convex pieces of the object (object rows per robot).
    """

    def __init__(self, radius: float, arena: tuple[float, float], dynamics: Dynamics,
                 config: SafetyConfig, num_robots: int, pieces: int = 1):
        n = self.n = int(num_robots)
        q = self.pieces = int(pieces)
        self.radius, self.arena, self.dynamics, self.config = float(radius), arena, dynamics, config
        self.pair_i, self.pair_j = np.triu_indices(n, 1)
        p = self.p = len(self.pair_i)
        self.wall_start = p + n * q
        k = self.k = p + n * q + 4 * n
        self.row_i, self.row_j = row_robots(self.pair_i, self.pair_j, n, q)
        gather = np.zeros((k, n))
        gather[np.arange(k), self.row_i] = 1.0
        gather[np.arange(p), self.pair_j] = -1.0
        self.gather_t = np.ascontiguousarray(gather.T)                       # (N, K)
        self.pair_gather_t = np.ascontiguousarray(gather[:p].T)              # (N, P)
        self.pair_both_t = np.abs(self.pair_gather_t)                        # (N, P): e_i + e_j
        self.gather_abs_t = np.abs(self.gather_t)                            # (N, K): sums per row
        a_box = octagon_accel(dynamics, config)
        self.share_alpha = config.braking_share * a_box
        alpha = np.full(k, config.static_braking_share * a_box)
        alpha[:p] = 2.0 * config.braking_share * a_box
        self.alpha = alpha
        self.two_alpha = 2.0 * alpha
        # wall distances of centres: pos @ wall_map + wall_offset = (x, W - x, y, H - y) - r
        self.wall_map = np.array([[1.0, -1.0, 0.0, 0.0], [0.0, 0.0, 1.0, -1.0]])
        self.wall_offset = np.array([0.0, arena[0], 0.0, arena[1]]) - self.radius
        self.rows = np.arange(n)
        self._polygon: np.ndarray | None = None
        self._shape_cache: dict[int, tuple] = {}
        self._wall_normal = WALL_NORMALS.copy()
        self._wall_normal_xy = np.tile(WALL_NORMALS.T, n)                    # (2, 4N) fixed
        self._wall_zeros = np.zeros(4 * n)
        self._zeros, self._false = np.zeros(n), np.zeros(n, dtype=bool)
        self._sweep_consts = (float(dynamics.dt), float(0.5 * dynamics.dt**2), float(dynamics.damping),
                              float(dynamics.accel_limit), float(dynamics.speed_limit))
        self.pair_i, self.pair_j = self.pair_i.astype(np.int64), self.pair_j.astype(np.int64)
        self._row_consts = (float(self.share_alpha), float(config.margin), float(config.margin + config.sqrt_floor),
                            float(dynamics.damping), float(config.gamma), float(config.gamma_unsure),
                            config.class_k != "linear")

    # ------------------------------------------------------------------ polygon
    def _set_polygon(self, polygon: np.ndarray) -> None:
        """Per-edge constants of the (M, 2) counter-clockwise polygon as (1, M) rows (kept per
        polygon object: the pieces of an object take turns)."""
        hit = self._shape_cache.get(id(polygon))
        if hit is None or hit[0] is not polygon:
            if len(self._shape_cache) >= 4 * self.pieces + 4:
                self._shape_cache.clear()
            self._compute_shape(polygon)
            hit = self._shape_cache[id(polygon)] = (polygon, self._edges, self._edge_rows, self._convex, self._m,
                                                    self._box, self._box_center, self._box_half, self._shape_args)
        (self._polygon, self._edges, self._edge_rows, self._convex, self._m, self._box, self._box_center,
         self._box_half, self._shape_args) = hit

    def _compute_shape(self, polygon: np.ndarray) -> None:
        ax, ay = polygon[:, 0][None].copy(), polygon[:, 1][None].copy()
        bx, by = np.roll(ax, -1, axis=1), np.roll(ay, -1, axis=1)
        ex, ey = bx - ax, by - ay
        self._edges = (ax, ay, by, ex, ey, 1.0 / (ex * ex + ey * ey), ex / np.where(ey == 0, 1.0, ey))
        self._edge_rows = tuple(np.ascontiguousarray(x[0]) for x in self._edges)    # (M,) each
        self._convex = is_convex_ccw(polygon)
        self._m = len(polygon)
        lo, hi = polygon.min(axis=0), polygon.max(axis=0)
        on_box = ((polygon == lo) | (polygon == hi)).all(axis=1)
        self._box = len(polygon) == 4 and self._convex and bool(on_box.all())
        self._box_center, self._box_half = (lo + hi) / 2, (hi - lo) / 2
        self._shape_args = (*self._edge_rows, bool(self._convex), bool(self._box),
                            np.ascontiguousarray(self._box_center, dtype=np.float64),
                            np.ascontiguousarray(self._box_half, dtype=np.float64), self.radius)

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
        n = len(pos)
        s_out, normal, curvature = np.empty(n), np.empty((n, 2)), np.empty(n)
        fused_kernels.object_rows(np.ascontiguousarray(pos, dtype=np.float64), *self._shape_args,
                                  s_out, normal, curvature)
        return s_out, normal, curvature

    def object_section(self, pos: np.ndarray, pieces: np.ndarray | tuple | list
                       ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """The object rows of (N, 2) centres: ``(s (N Q,), normal (N Q, 2), curvature (N Q,))``,
        robot-major, :meth:`object_geometry` of each convex piece. ``pieces``: the Q pieces, or
        one (M, 2) polygon when Q = 1."""
        if isinstance(pieces, np.ndarray) and pieces.ndim == 2:
            pieces = (pieces,)
        if len(pieces) != self.pieces:
            raise ValueError(f"FusedScene: the object has {len(pieces)} convex pieces, this scene was "
                             f"built for {self.pieces}")
        if self.pieces == 1:
            return self.object_geometry(pos, pieces[0])
        per_piece = [self.object_geometry(pos, piece) for piece in pieces]
        s_obj, normal, curvature = (np.stack(x, axis=1) for x in zip(*per_piece, strict=True))
        return s_obj.ravel(), normal.reshape(-1, 2), curvature.ravel()

    # ------------------------------------------------------------------ barrier
    def terms(self, pos: np.ndarray, vel: np.ndarray, pieces: np.ndarray | tuple | list,
              prediction: Prediction | None = None) -> FusedTerms:
        """Barrier values and rows of (N, 2) centres [m] and velocities [m/s] (module docstring),
        for the object's convex ``pieces`` (:meth:`object_section`).

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
        p, k, n = self.p, self.k, self.n
        if not pos.shape == vel.shape == (n, 2):
            require_shapes("FusedScene.terms", pos=(pos, (n, 2)), vel=(vel, (n, 2)))
        if prediction is not None:
            prediction.require_rows(n, "FusedScene.terms")
        s_obj, obj_n, k_obj = self.object_section(f64(pos), pieces)
        normal, dist, h = np.empty((2, k)), np.empty(k), np.empty(k)
        drift, bound, delta = np.empty(k), np.empty(k), np.empty((2, p))
        if prediction is None:
            grow = closing = self._zeros
            unsure = fixed = self._false
        else:
            grow, closing = f64(prediction.grow), f64(prediction.closing)
            fixed = np.ascontiguousarray(prediction.fixed, dtype=bool)
            unsure = self._false if prediction.unsure is None else np.ascontiguousarray(prediction.unsure, dtype=bool)
        fused_kernels.barrier_rows(
            f64(pos), f64(vel), self.pair_i, self.pair_j, s_obj, obj_n, k_obj, self.radius, self.wall_offset,
            self._wall_normal_xy, self.alpha, self.two_alpha, prediction is not None, grow, closing, unsure,
            fixed, *self._row_consts, normal, dist, h, drift, bound, delta)
        return self.wrap_terms(normal, dist, h, drift, bound, delta, obj_n)

    def wrap_terms(self, normal: np.ndarray, dist: np.ndarray, h: np.ndarray, drift: np.ndarray,
                   bound: np.ndarray, delta: np.ndarray, obj_n: np.ndarray) -> FusedTerms:
        """The :class:`FusedTerms` of the rows computed by :meth:`terms`."""
        return FusedTerms(pair_i=self.pair_i, pair_j=self.pair_j, pair_normal=normal[:, :self.p].T,
                          object_normal=obj_n, wall_normal=self._wall_normal, h=h, drift=drift,
                          bound=bound, pieces=self.pieces, normal_xy=normal, gather_t=self.gather_t,
                          row_i=self.row_i, row_j=self.row_j, distance=dist, pair_delta=delta)

    # ------------------------------------------------------------------ sweep
    def failing(self, checker: SweepChecker, pos: np.ndarray, vel: np.ndarray, acc: np.ndarray,
                terms: FusedTerms, grow: np.ndarray | None = None,
                vel_error: np.ndarray | None = None, brake: np.ndarray | None = None) -> np.ndarray:
        """(N,) bool: robots whose one-tick sweep touches something; the checks and maths of
        :meth:`controllers.safety.postcheck.SweepChecker.failing` (same end points, widening and
        excuses, bit for bit), with the start-of-tick geometry taken from ``terms``, and one
        shortcut: with ``T = max_i (|p'_i - p_i| + e_i)``, every check passes when each static
        row has ``s >= T + m`` and each pair row ``s >= 2 T + m`` (a chord end moves at most
        ``|p' - p|`` from its start, a relative chord at most the sum of two), so none runs.
        Object: the FCL capsule test wherever the travel bound cannot rule out contact.
        ``grow`` (N,) [m] widens each robot's disc (a prediction's; ``terms`` already hold the
        grown start distances); ``vel_error`` (N,) [m/s] bounds the error of ``vel``; ``brake``
        (N, 2), what failing robots would get (None: no excuses)."""
        dyn, r, m, n = self.dynamics, self.radius, checker.margin, self.n
        widen = self._zeros if grow is None else f64(grow)
        bad = np.zeros(n, dtype=bool)
        clear, end, bulge, travel, hit, wall_hit = self._sweep(pos, vel, acc, widen, terms, m)
        if clear:
            return bad
        if brake is not None and (np.count_nonzero(hit) or np.count_nonzero(wall_hit)):
            pair_ok, wall_ok = excuses(pos, vel, acc, brake, self.pair_i, self.pair_j, grow,
                                       vel_error, dyn)
            hit &= ~pair_ok
            wall_hit &= ~wall_ok
        bad[self.pair_i[hit]] = True
        bad[self.pair_j[hit]] = True
        bad |= wall_hit.any(axis=1)
        near = terms.object_distance() - m <= travel + _SLACK
        if np.count_nonzero(near):
            for i in np.flatnonzero(near):
                if checker.capsule_clearance(pos[i], end[i], r + bulge[i] + widen[i]) < m:
                    bad[i] |= not checker.object_excused(i, pos, vel, acc, brake, grow, vel_error)
        return bad

    def _sweep(self, pos: np.ndarray, vel: np.ndarray, acc: np.ndarray, widen: np.ndarray,
               terms: FusedTerms, margin: float) -> tuple[bool, np.ndarray, ...]:
        """``(clear, end (N, 2), bulge (N,), travel (N,), hit (P,), wall_hit (N, 4))`` of
        :meth:`failing`, compiled (:func:`controllers.safety.fused_kernels.sweep_rows`): ``clear``
        when the travel bound rules every pair and wall out (``hit``, ``wall_hit`` then all False)."""
        n = self.n
        if not (pos.shape == vel.shape == acc.shape == (n, 2) and widen.shape == (n,)):
            require_shapes("FusedScene check", pos=(pos, (n, 2)), vel=(vel, (n, 2)), acc=(acc, (n, 2)),
                           widen=(widen, (n,)))
        end, bulge, travel = np.empty((n, 2)), np.empty(n), np.empty(n)
        hit, wall_hit = np.empty(self.p, dtype=bool), np.empty((n, 4), dtype=bool)
        clear = fused_kernels.sweep_rows(
            f64(pos), f64(vel), f64(acc), widen, terms.distance, terms.pair_delta, self.pair_i, self.pair_j,
            self.wall_start, self.wall_offset, self.radius, float(margin), _SLACK, *self._sweep_consts, end, bulge, travel,
            hit, wall_hit)
        return clear, end, bulge, travel, hit, wall_hit

    def check(self, checker: SweepChecker, pos: np.ndarray, vel: np.ndarray, acc: np.ndarray,
              terms: FusedTerms, prediction: Prediction | None = None) -> PostcheckResult:
        """Brake every robot that fails, repeating until stable (as :meth:`SweepChecker.check`);
        fixed robots of a ``prediction`` are never braked here (they are not listening)."""
        n = self.n
        grow = None if prediction is None else prediction.grow
        vel_error = None if prediction is None else prediction.velocity_error
        braked = np.zeros(n, dtype=bool)
        bad = self.failing(checker, pos, vel, acc, terms, grow, vel_error)
        if not np.count_nonzero(bad):         # excuses only ever clear failures
            return PostcheckResult(acc=acc, braked=braked, contact=bad)
        mine = np.ones(n, dtype=bool) if prediction is None else ~prediction.fixed
        acc = acc.copy()
        brake = np.where(mine[:, None], braking_acceleration(vel, self.dynamics, prediction), acc)
        bad = self.failing(checker, pos, vel, acc, terms, grow, vel_error, brake)
        for _ in range(n):
            new = bad & ~braked & mine
            if not new.any():
                break
            braked |= new
            acc[new] = brake[new]
            bad = self.failing(checker, pos, vel, acc, terms, grow, vel_error, brake)
        return PostcheckResult(acc=acc, braked=braked, contact=bad)

