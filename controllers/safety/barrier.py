r"""Braking-distance control barrier functions for damped double-integrator discs.

Each robot ``i`` has position ``p_i`` [m] and velocity ``v_i`` [m/s] and follows the continuous-time
model behind :class:`sim.scenario.Dynamics`::

    dp_i/dt = v_i,        dv_i/dt = u_i - c v_i          (u_i: commanded acceleration [m/s^2])

with damping ``c`` [1/s]. For every robot pair ``(i, j)``, every robot and the object, and every
robot and each of the four walls, let ``s`` be the signed distance between the two shapes [m]
(from :mod:`controllers.safety.geometry`) and ``n`` its gradient with respect to ``p_i`` (the unit
normal pointing towards robot i). With the relative velocity ``w = v_i - v_j`` (``w = v_i`` for the
object and walls, which are static), the clearance rate and its derivative are::

    s_dot  = n . w
    s_ddot = n . (u_i - u_j) - c s_dot + kappa |w_t|^2,      |w_t|^2 = |w|^2 - s_dot^2

where ``kappa`` is the curvature of the distance function (1/centre distance for a disc or a
polygon vertex, 0 for an edge or a wall; the term is never negative).

**Barrier** (Wang, Ames, Egerstedt, IEEE T-RO 2017, "Safety barrier certificates for
collision-free multirobot systems"), with a safety margin ``m`` [m] and ``z = s - m``::

    h = phi(z) + s_dot,        phi(z) = sqrt(2 alpha z)

``h >= 0`` says the approach speed ``-s_dot`` is no more than what a constant deceleration
``alpha`` [m/s^2] can cancel within the remaining clearance ``z``, so ``s`` stays above ``m``.
``alpha`` is the braking the barrier may count on: ``2 * braking_share * a_box`` for a pair (both
robots brake) and ``static_braking_share * a_box`` for the object and the walls, where ``a_box``
is the acceleration every robot can produce in any direction inside the QP's actuator octagon.
With ``braking_share = 0.5`` one robot alone can meet a pair's demand, so a robot pinned at a wall
does not make its neighbour's constraint infeasible. Two static rows on their boundaries whose
normals are ``theta`` apart (a robot heading into a corner) ask ``n_1 . u >= alpha`` and
``n_2 . u >= alpha`` at worst, which ``|u| <= a_box`` meets while ``alpha <= a_box cos(theta /
2)``: ``static_braking_share = 1/sqrt(2)`` keeps the arena's corners (90 degrees) jointly
feasible; a robot heading diagonally into a corner counting on the whole ``a_box`` could not stop
on both axes. Half the actuator (before) also covered wedges up to 120 degrees (the object close
to a wall) and cost its robots time: a 3-5-robot generalist reached its targets 0.31 ticks later
on a clean link and, with a robot freezing mid-episode, succeeded in 0.603 of 600 episodes
against 0.610 bare (now 0.610). The margin it gave up matters on a noisy link, which the
approach allowance of the measured velocity noise covers
(:attr:`~controllers.safety.latency.LatencyConfig.measured_velocity_sigmas`).
Damping only adds deceleration while approaching
(``-c s_dot > 0`` when ``s_dot < 0``), so it is left out of ``alpha`` and kept in ``h_dot``.

To keep ``h`` finite and differentiable at ``z <= 0`` (a robot already inside the margin), ``phi``
continues below ``z_f`` (``sqrt_floor``) along its tangent:
``phi(z) = sqrt(2 alpha z_f) + alpha / sqrt(2 alpha z_f) (z - z_f)`` for ``z < z_f``. The safe set
``h >= 0`` then guarantees ``s >= m - z_f`` (when ``s_dot = 0``).

**Derivative** (``phi'(z) = alpha / sqrt(2 alpha max(z, z_f))``)::

    h_dot = n . (u_i - u_j) + drift,       drift = (phi'(z) - c) s_dot + kappa |w_t|^2

**Constraint** ``h_dot >= -K(h)`` with the class-K function ``K(h) = gamma h`` (linear, default)
or ``gamma h^3`` (as in the paper), i.e. one row per pair, linear in the accelerations::

    n . u_i - n . u_j >= b,        b = -K(h) - drift

Feasibility on the boundary ``h = 0``: there ``s_dot = -phi(z)``, so ``b = alpha - c phi(z) -
kappa |w_t|^2 <= alpha``, which the braking budget above covers, for each row alone. Two rows of
one robot at their boundaries with opposite normals (a robot pinned between the object and a
neighbour driving at it) can ask more than any split of the budget gives: there the QP is
infeasible and the slack QP and the post-check answer. Continuous-time invariance of
``h >= 0`` then follows from the comparison lemma; the discrete 20 Hz zero-order hold and the
speed limit are absorbed by the margin ``m`` and caught by the post-check.

**The gain.** ``gamma`` sets how far ahead of the braking curve ``h = 0`` the filter starts to
brake: a robot may close on the curve at ``h_dot = -gamma h``, so with a larger gain it is braked
later, and harder, near the curve (``gamma dt < 1`` keeps the sampled ``h`` from overshooting
zero: 0.3 at 6 and 20 Hz). With ``gamma = 3`` a trained policy that never touches anything on its
own was changed on 26 of 128 ticks an episode on a clean link (30 paper-3/4/5 episodes), and its
robots came within 5 cm of their targets 2.7 ticks later than without the filter; with 6, on 9
ticks and 1.2 ticks later. Raised on every row, 6 touched in 1 of 340 adversarial episodes with a
delay that jitters (``bench/safety.py`` conditions; 0 of 340 in each of the others): there a
brake the prediction counted on may be overtaken by a newer command and never act. So the rows of
a robot whose delay is not known to hold (:attr:`~controllers.safety.latency.Prediction.unsure`)
keep ``gamma_unsure = 3``.

**Objects that are not convex.** The object rows take the object as the union of its convex
pieces (:func:`~controllers.safety.polygon.convex_pieces`), one row per robot and piece: the
distance to the union is the least distance to a piece, so all rows holding keeps the robot off the
object, and each piece's distance is convex, with the gradient and curvature above. One row for the
whole polygon (its nearest face) does not: in a re-entrant corner the face a robot heads for is not
the nearest until the robot is upon it, and the two faces ask for two rows at once, as the arena's
corners do (an L-shaped object on a clean link: 24 of 60 adversarial episodes touched, 1.0-1.4 mm).

Row layout (K = P + N Q + 4N rows for N robots, P = N(N-1)/2 pairs and an object of Q convex
pieces, Q = 1 for a convex object): pairs in ``np.triu_indices`` order, then robot-object
robot-major (robot i, piece q at row ``P + Q i + q``), then robot-wall robot-major (robot i, walls
x = 0, x = W, y = 0, y = H at rows ``P + N Q + 4 i + w``).
"""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

from controllers.checks import check_numbers
from controllers.safety.geometry import SceneDistances
from controllers.safety.latency import Prediction, row_sums
from sim.scenario import Dynamics


class SafetyConfigError(ValueError):
    """A safety-filter setting that cannot work; the message names the field and the fix."""


@dataclass(frozen=True)
class SafetyConfig:
    """Settings of the safety filter (barrier, QP, post-check).

    Attributes:
        margin: clearance the barrier keeps between shapes beyond contact [m].
        gamma: gain of the class-K function [1/s for linear; s/m^2 for cubic]: how far ahead
            of the braking curve the filter starts to brake (larger: later).
        gamma_unsure: the gain for the rows of a robot whose command delay is not known to hold
            (it jittered lately, or the fleet does not report its pending commands; see
            :attr:`controllers.safety.latency.Prediction.unsure`): a brake the prediction counts
            on may be overtaken by a newer command, so these rows start braking earlier.
        class_k: ``"linear"`` (``gamma h``) or ``"cubic"`` (``gamma h^3``, as in the paper).
        braking_share: fraction of one robot's acceleration the pair rows count on each robot
            braking with (the pair counts on ``2 * braking_share``).
        static_braking_share: fraction of one robot's acceleration the object and wall rows count on
            (module docstring).
        sqrt_floor: ``z_f``, below it the square root continues linearly [m].
        accel_fraction: the QP's actuator octagon is inscribed in a circle of
            ``accel_fraction * accel_limit`` (so the plant's norm clip never bites).
        tighten: the QP solves the barrier rows with ``b + tighten`` (solver tolerance) [m/s^2].
        eps: OSQP absolute and relative tolerance.
        max_iter: OSQP iteration limit.
        slack_weight: penalty on squared barrier slack in the fallback QP.
        static_slack_factor: the object and wall rows' slack weighs this many times
            ``slack_weight`` (:mod:`controllers.safety.barrier_qp`, ``SLACK``): where the rows
            cannot all hold, a robot pressed between another robot and the object or a wall
            holds off the static shape, and the pair row, which the other robot's command can
            meet too, gives way first. With 1 (one weight for every row), a 15-robot adversarial
            crowd on a jittering link put a robot into the object (``bench/safety.py``
            ``delay_jitter`` seed 122, 0.2 mm; 1 of 4080 episodes); with 100, none of them.
        geometry: ``"fused"`` (default: closed-form distances, barrier rows and the sweep check
            in one vectorised pass, :mod:`controllers.safety.fused`, FCL verifying the object sweep
            near contact), or the reference path: ``"fcl"`` (FCL scene) or ``"analytic"``
            (closed-form numpy) distances, then :func:`barrier_terms` and the
            :class:`~controllers.safety.postcheck.SweepChecker`. All three give the same answers.
        postcheck: check the one-tick sweep and brake robots that would touch.
        postcheck_margin: clearance the post-check demands [m] (0 = no contact).
        exact_projection: answer the QP in closed form when its broken rows share no robot
            (:mod:`controllers.safety.projection`; the optimum itself, checked before use), else
            OSQP; False: OSQP always.
    """

    margin: float = 0.01
    gamma: float = 6.0
    gamma_unsure: float = 3.0
    class_k: str = "linear"
    braking_share: float = 0.5
    static_braking_share: float = math.sqrt(0.5)
    sqrt_floor: float = 1e-3
    accel_fraction: float = 0.999
    tighten: float = 1e-3
    eps: float = 1e-7
    max_iter: int = 4000
    slack_weight: float = 1e6
    static_slack_factor: float = 100.0
    geometry: str = "fused"
    postcheck: bool = True
    postcheck_margin: float = 0.0
    exact_projection: bool = True

    def __post_init__(self) -> None:
        check_numbers(self, ("gamma", "gamma_unsure", "braking_share", "static_braking_share", "sqrt_floor",
                             "accel_fraction", "eps", "slack_weight", "static_slack_factor"),
                      "safety", SafetyConfigError, positive=True)
        check_numbers(self, ("margin", "tighten", "postcheck_margin"), "safety", SafetyConfigError)
        for name in ("braking_share", "static_braking_share"):
            if getattr(self, name) > 1:
                raise SafetyConfigError(f"safety.{name} must be in (0, 1], got {getattr(self, name)}")
        if self.accel_fraction > 1:
            raise SafetyConfigError(f"safety.accel_fraction must be in (0, 1], got {self.accel_fraction}")
        if self.class_k not in ("linear", "cubic"):
            raise SafetyConfigError(f"safety.class_k must be 'linear' or 'cubic', got {self.class_k!r}")
        if self.geometry not in ("fused", "fcl", "analytic"):
            raise SafetyConfigError(f"safety.geometry must be 'fused', 'fcl' or 'analytic', "
                                    f"got {self.geometry!r}")
        if not (isinstance(self.max_iter, int) and self.max_iter > 0):
            raise SafetyConfigError(f"safety.max_iter must be a positive integer, got {self.max_iter!r}")

    @classmethod
    def from_dict(cls, data: dict) -> SafetyConfig:
        known = {f.name for f in dataclasses.fields(cls)}
        unknown = set(data) - known
        if unknown:
            raise SafetyConfigError(f"unknown safety field(s) {sorted(unknown)}; known: {sorted(known)}")
        return cls(**data)


def octagon_accel(dynamics: Dynamics, config: SafetyConfig) -> float:
    """``a_box``: the acceleration available in every direction inside the actuator octagon [m/s^2].

    The octagon with vertices on a circle of radius ``R = accel_fraction * accel_limit`` has the
    edges ``|u_x|, |u_y| <= R cos(pi/8)`` and ``|u_x +- u_y| <= sqrt(2) R cos(pi/8)``.
    """
    return config.accel_fraction * dynamics.accel_limit * math.cos(math.pi / 8)


@dataclass
class BarrierTerms:
    """The barrier rows of one instant (K = P + N Q + 4N, see the module docstring).

    Attributes:
        pair_normal: (P, 2) row coefficients on ``u_i`` (and minus them on ``u_j``).
        object_normal: (N Q, 2) row coefficients of the robot-object rows (robot-major).
        h: (K,) barrier values [m/s].
        drift: (K,) the part of ``h_dot`` that does not depend on ``u`` [m/s^2].
        bound: (K,) ``b``: each row demands ``coefficients . u >= b`` [m/s^2].
        pieces: Q, the object's convex pieces (object rows per robot).
    """

    pair_i: np.ndarray
    pair_j: np.ndarray
    pair_normal: np.ndarray
    object_normal: np.ndarray
    wall_normal: np.ndarray
    h: np.ndarray
    drift: np.ndarray
    bound: np.ndarray
    pieces: int = 1

    def rows_times(self, u: np.ndarray) -> np.ndarray:
        """(K,) row values ``n . (u_i - u_j)`` for (N, 2) accelerations ``u``."""
        pair = np.sum(self.pair_normal * (u[self.pair_i] - u[self.pair_j]), axis=1)
        obj = np.sum(self.object_normal * np.repeat(u, self.pieces, axis=0), axis=1)
        wall = u @ self.wall_normal.T                                  # (N, 4)
        return np.concatenate([pair, obj, wall.ravel()])

    def row_normals(self) -> np.ndarray:
        """(K, 2) the normal ``n_k`` of every row, in the row layout."""
        n = len(self.object_normal) // self.pieces
        return np.concatenate([self.pair_normal, self.object_normal, np.tile(self.wall_normal, (n, 1))])

    def row_robots(self) -> tuple[np.ndarray, np.ndarray]:
        """``(i, j)``, each (K,): the robots of every row (:func:`row_robots`)."""
        return row_robots(self.pair_i, self.pair_j, len(self.object_normal) // self.pieces, self.pieces)

    def dense(self, num_robots: int) -> np.ndarray:
        """(K, 2N) dense row matrix (for tests and the fallback QP)."""
        i, j = self.row_robots()
        normals = self.row_normals()
        a = np.zeros((len(i), 2 * num_robots))
        rows, pairs = np.arange(len(i)), j >= 0
        for axis in (0, 1):
            a[rows, 2 * i + axis] = normals[:, axis]
            a[rows[pairs], 2 * j[pairs] + axis] = -normals[pairs, axis]
        return a


def row_robots(pair_i: np.ndarray, pair_j: np.ndarray, num_robots: int, pieces: int = 1
               ) -> tuple[np.ndarray, np.ndarray]:
    """``(i, j)``, each (K,) int64: the robots of every row in the layout of the module docstring
    for N robots and an object of Q ``pieces``; ``j = -1`` on rows of one robot."""
    robots = np.arange(num_robots)
    i = np.concatenate([pair_i, np.repeat(robots, pieces), np.repeat(robots, 4)])
    j = np.concatenate([pair_j, np.full(len(i) - len(pair_j), -1)])
    return i.astype(np.int64), j.astype(np.int64)


def _phi(z: np.ndarray, alpha: float | np.ndarray, floor: float) -> tuple[np.ndarray, np.ndarray]:
    """``phi(z)`` and ``phi'(z)`` of the module docstring (square root with a linear floor)."""
    zc = np.maximum(z, floor)
    root = np.sqrt(2.0 * alpha * zc)
    slope = alpha / root
    return root + slope * np.minimum(z - floor, 0.0), slope


def row_gamma(config: SafetyConfig, prediction: Prediction | None,
              row_sum: Callable[[np.ndarray], np.ndarray]) -> float | np.ndarray:
    """The class-K gain of each row: ``gamma_unsure`` where a robot of the row is
    :attr:`~controllers.safety.latency.Prediction.unsure`, else ``gamma`` (a scalar when no
    robot is). ``row_sum`` maps a per-robot (N,) array to its (K,) per-row sums (each path's
    own: :func:`~controllers.safety.latency.row_sums`, or the fused path's gather matrix)."""
    unsure = None if prediction is None else prediction.unsure
    if unsure is None or not unsure.any():
        return config.gamma
    return np.where(row_sum(unsure.astype(np.float64)) > 0, config.gamma_unsure, config.gamma)


def barrier_terms(dist: SceneDistances, vel: np.ndarray, dynamics: Dynamics,
                  config: SafetyConfig, prediction: Prediction | None = None) -> BarrierTerms:
    """Barrier values and rows for (N, 2) velocities [m/s] and the distances of the same instant.

    A ``prediction`` tightens the rows as in :meth:`controllers.safety.fused.FusedScene.terms`
    (grown discs, approach-speed allowance, fixed robots)."""
    a_box = octagon_accel(dynamics, config)
    alpha_static = config.static_braking_share * a_box
    alpha_pair = 2.0 * config.braking_share * a_box
    c = dynamics.damping

    w_pair = vel[dist.pair_i] - vel[dist.pair_j]                           # (P, 2)
    sdot_pair = np.sum(dist.pair_normal * w_pair, axis=1)
    tang_pair = np.maximum(np.sum(w_pair * w_pair, axis=1) - sdot_pair**2, 0.0)
    vel_obj = np.repeat(vel, dist.pieces, axis=0)                          # (N Q, 2)
    sdot_obj = np.sum(dist.object_normal * vel_obj, axis=1)
    tang_obj = np.maximum(np.sum(vel_obj * vel_obj, axis=1) - sdot_obj**2, 0.0)
    sdot_wall = (vel @ dist.wall_normal.T).ravel()                         # (4N,)

    s = np.concatenate([dist.pair_distance, dist.object_distance, dist.wall_distance.ravel()])
    sdot = np.concatenate([sdot_pair, sdot_obj, sdot_wall])
    curv_term = np.concatenate([dist.pair_curvature * tang_pair, dist.object_curvature * tang_obj,
                                np.zeros(sdot_wall.shape)])
    alpha = np.empty(len(s))
    alpha[:len(sdot_pair)] = alpha_pair
    alpha[len(sdot_pair):] = alpha_static
    dropped, sdot_drift, gamma = None, sdot, config.gamma
    if prediction is not None:
        def sums(x: np.ndarray) -> np.ndarray:
            return row_sums(x, dist.pair_i, dist.pair_j, dist.pieces)

        gamma = row_gamma(config, prediction, sums)
        s = s - sums(prediction.grow)
        allowance = sums(prediction.closing)
        sdot_drift = sdot - np.minimum(np.maximum(sdot, 0.0), allowance)
        sdot = sdot - allowance
        if prediction.fixed.any():
            free = sums((~prediction.fixed).astype(np.float64))
            dropped = free == 0
            alpha[:len(sdot_pair)] = config.braking_share * a_box * np.maximum(free[:len(sdot_pair)], 1.0)

    phi, dphi = _phi(s - config.margin, alpha, config.sqrt_floor)
    h = phi + sdot
    drift = (dphi - c) * sdot_drift + curv_term
    k_of_h = gamma * (h if config.class_k == "linear" else h**3)
    bound = -k_of_h - drift
    if dropped is not None and dropped.any():
        bound[dropped], h = -np.inf, np.where(dropped, np.inf, h)
    return BarrierTerms(pair_i=dist.pair_i, pair_j=dist.pair_j, pair_normal=dist.pair_normal,
                        object_normal=dist.object_normal, wall_normal=dist.wall_normal,
                        h=h, drift=drift, bound=bound, pieces=dist.pieces)
