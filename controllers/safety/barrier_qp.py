r"""The centralised safety filter: distances -> barrier rows -> one OSQP QP -> post-check.

For N robots the decision variable is ``u`` in R^{2N}, ``u = (u_0x, u_0y, u_1x, ...)`` [m/s^2]::

    minimise    || u - a_nom ||^2                      (P = 2 I, q = -2 a_nom)
    subject to  n_k . (u_i - u_j) >= b_k + tighten    every pair, robot-object, robot-wall row k
                |u_ix|, |u_iy|     <= R cos(pi/8)      actuator octagon inscribed in the circle
                |u_ix +- u_iy|     <= sqrt(2) R cos(pi/8)   of radius R = accel_fraction * accel_limit

with the rows and bounds ``b_k`` of :mod:`controllers.safety.barrier` (the braking-distance
barrier of Wang, Ames and Egerstedt, IEEE T-RO 2017, derived there for damped double integrators
with a safety margin). ``a_nom`` is first clipped to the actuator limit, as the plant would.

Geometry and rows come from the fused fast path (:mod:`controllers.safety.fused`, the default
``geometry="fused"``: closed-form distances, rows and sweep check in one vectorised pass, FCL's
exact capsule distance verifying the object sweep of robots near contact) or from the reference
path (``"fcl"``: the FCL scene, or ``"analytic"``; then :func:`barrier_terms` and the
:class:`SweepChecker`). Both give the same rows and answers (tests hold them equal).

Solve path, every outcome an explicit :class:`SafetyStatus`:

1. ``UNCHANGED``: the clipped nominal command already satisfies every barrier row; returned as is.
2. ``INTERVENED``: when the rows the nominal breaks share no robot, the QP's optimum in closed
   form (:mod:`controllers.safety.projection`: each broken row moves its robots along its own
   normal, every other robot goes to the nearest point of its octagon), used only when it meets
   every tightened row and every octagon (then it is the optimum; ``solver="projection"``);
   otherwise OSQP (one problem per N, set up once with a fixed sparsity pattern, then only
   ``update(q=, l=, Ax=)`` per tick, warm-started, eps 1e-7 with polishing; no setup on the hot
   path) solved and its answer satisfies
   every row within 1e-6. With fixed robots (silent, stale, tracked discs: held at ``u = 0``) it
   solves the same QP over the listening robots alone (:mod:`controllers.safety.reduced_qp`).
3. ``SLACK``: OSQP failed or was infeasible: the QP with one slack ``sigma_k >= 0`` per barrier row
   (``n_k . (u_i - u_j) + sigma_k >= b_k + tighten``, cost ``+ sum_k w_k sigma_k^2``, the
   actuator octagon kept hard) on the exact active-set solver DAQP via qpsolvers. ``w_k`` is
   ``slack_weight`` for a pair row and ``static_slack_factor`` times that for an object or wall
   row: a pair row can be met by either robot's command, a static one by one robot's alone, so
   a robot squeezed between another robot and the object holds off the object; rows with a
   fixed robot of a latency prediction (not listening: a grown disc, not a wall) weigh
   ``FIXED_SLACK_DISCOUNT`` times less, so a robot caught inside such a disc gets out of it
   without giving way on walls, the object or listening robots.
4. ``FALLBACK_BRAKE``: that failed too, or the input was not finite, or the post-check
   (:mod:`controllers.safety.postcheck`) replaced some robot's command by maximum braking.

The output is never NaN and never exceeds the actuator limit; the filter does not raise on data,
only on shapes that break the call's contract.
"""

from __future__ import annotations

import math
import time
from collections import OrderedDict
from dataclasses import dataclass, field
from enum import StrEnum

import numpy as np
import osqp
import qpsolvers
import scipy.sparse as sp

from controllers.array_kernels import all_finite
from controllers.jit import f64
from controllers.safety import fused_kernels
from controllers.safety.barrier import BarrierTerms, SafetyConfig, barrier_terms, octagon_accel
from controllers.safety.fused import FusedScene, FusedTerms
from controllers.safety.geometry import CollisionScene, SceneDistances, analytic_distances
from controllers.safety.latency import Prediction, row_sums
from controllers.safety.postcheck import SweepChecker, braking_acceleration, clip_norm
from controllers.safety.projection import projected_optimum
from controllers.safety.reduced_qp import ReducedQP
from sim.scenario import Scenario

_ROW_CHECK_TOL = 1e-6
FIXED_SLACK_DISCOUNT = 1e-4
"""Slack weight of rows with a fixed (not listening) robot, relative to ``slack_weight``."""
MAX_CACHED_PROBLEMS = 32
"""Problems (one per row count N) a filter keeps set up, the least recently used dropped first."""
MAX_CACHED_MASKS = 8
"""Problems without their fixed robots (one per fixed mask) each of those keeps set up."""


class SafetyStatus(StrEnum):
    """What the safety filter did to the nominal command."""

    UNCHANGED = "unchanged"
    INTERVENED = "intervened"
    SLACK = "slack"
    FALLBACK_BRAKE = "fallback_brake"


@dataclass
class SafetyResult:
    """The filter's answer for N robots.

    Attributes:
        a_safe: (N, 2) safe accelerations [m/s^2], finite and within the actuator limit.
        status: see :class:`SafetyStatus`.
        reason: why the status is not ``UNCHANGED`` / ``INTERVENED`` ("" otherwise).
        solver: what answered the QP: ``"projection"`` (its closed form, when the broken rows
            share no robot: :mod:`controllers.safety.projection`), ``"osqp"``, ``"daqp"`` (the
            slack QP); "" when none ran.
        braked: (N,) bool, robots commanded to brake by the fallback or the post-check.
        contact: (N,) bool, robots the post-check predicts to touch something even when braking.
        min_barrier: smallest barrier value h over all rows [m/s] (nan when not computed).
        min_clearance: smallest signed distance between shapes [m] (nan when not computed).
        max_slack: largest slack of the slack QP [m/s^2] (0 otherwise).
        solve_time_s: time in the QP solvers [s].
        total_time_s: time of the whole call [s].
        terms: the barrier rows judged (None when the filter braked before building them).
    """

    a_safe: np.ndarray
    status: SafetyStatus
    reason: str = ""
    solver: str = ""
    braked: np.ndarray = field(default_factory=lambda: np.zeros(0, dtype=bool))
    contact: np.ndarray = field(default_factory=lambda: np.zeros(0, dtype=bool))
    min_barrier: float = math.nan
    min_clearance: float = math.nan
    max_slack: float = 0.0
    solve_time_s: float = 0.0
    total_time_s: float = 0.0
    terms: BarrierTerms | None = None

    @property
    def modified(self) -> bool:
        """True when the command differs from the (clipped) nominal one."""
        return self.status is not SafetyStatus.UNCHANGED


class _Problem:
    """The OSQP problem, FCL scene, post-check and fused fast path for one robot count N (set up once)."""

    def __init__(self, scenario: Scenario, n: int, config: SafetyConfig):
        self.n = n
        dyn = scenario.dynamics
        self.scene = CollisionScene(scenario, n)
        self.checker = SweepChecker(self.scene.object_parts, scenario.robot_radius, scenario.arena,
                                    dyn, config.postcheck_margin, object_pieces=self.scene.object_pieces)
        q = self.pieces = len(self.scene.pieces_local)
        self.fused = FusedScene(scenario.robot_radius, scenario.arena, dyn, config, n, q)
        pi, pj = np.triu_indices(n, 1)
        p = len(pi)
        self.num_barrier = p + n * q + 4 * n
        robots = np.arange(n)
        object_robots = np.repeat(robots, q)
        # COO pattern: pair rows (4 entries), object rows (2), wall rows (1), box (1), diagonals (2).
        rows = [np.repeat(np.arange(p), 4), np.repeat(p + np.arange(n * q), 2),
                p + n * q + np.arange(4 * n), self.num_barrier + np.arange(2 * n),
                np.repeat(self.num_barrier + 2 * n + np.arange(2 * n), 2)]
        cols = [np.stack([2 * pi, 2 * pi + 1, 2 * pj, 2 * pj + 1], 1).ravel(),
                np.stack([2 * object_robots, 2 * object_robots + 1], 1).ravel(),
                (2 * robots[:, None] + np.array([0, 0, 1, 1])).ravel(),
                np.arange(2 * n),
                np.repeat(2 * robots, 4) + np.tile([0, 1, 0, 1], n)]
        rows, cols = np.concatenate(rows), np.concatenate(cols)
        self.coo_rows, self.coo_cols = rows, cols
        self.pair_i, self.pair_j = pi, pj
        self.config = config
        self._reduced: OrderedDict[bytes, ReducedQP] = OrderedDict()
        self.wall_values = np.tile([1.0, -1.0, 1.0, -1.0], n)
        self.const_values = np.concatenate([self.wall_values, np.ones(2 * n),
                                            np.tile([1.0, 1.0, 1.0, -1.0], n)])
        nnz = len(rows)
        coo = sp.coo_matrix((np.arange(1, nnz + 1, dtype=np.float64), (rows, cols)),
                            shape=(self.num_barrier + 4 * n, 2 * n))
        csc = coo.tocsc()
        self.perm = csc.data.astype(np.int64) - 1          # CSC slot -> COO entry
        self.a_box = octagon_accel(dyn, config)
        limits = np.concatenate([np.full(2 * n, self.a_box), np.full(2 * n, math.sqrt(2) * self.a_box)])
        self.lower = np.concatenate([np.zeros(self.num_barrier), -limits])
        self.upper = np.concatenate([np.full(self.num_barrier, np.inf), limits])
        self.solver = osqp.OSQP()
        csc.data = self._ax(np.ones((p, 2)), np.ones((n * q, 2)))
        self.solver.setup(sp.identity(2 * n, format="csc") * 2.0, np.zeros(2 * n), csc,
                          self.lower, self.upper, eps_abs=config.eps, eps_rel=config.eps,
                          max_iter=config.max_iter, polishing=True, warm_starting=True,
                          verbose=False)

    def _coo_values(self, pair_normal: np.ndarray, object_normal: np.ndarray) -> np.ndarray:
        """(E,) the constraint entries in the COO pattern's order."""
        return np.concatenate([np.concatenate([pair_normal, -pair_normal], 1).ravel(),
                               object_normal.ravel(), self.const_values])

    def _ax(self, pair_normal: np.ndarray, object_normal: np.ndarray) -> np.ndarray:
        return self._coo_values(pair_normal, object_normal)[self.perm]

    def reduced(self, fixed: np.ndarray) -> ReducedQP:
        """The QP without the ``fixed`` robots (:mod:`controllers.safety.reduced_qp`), set up once
        per mask; the ``MAX_CACHED_MASKS`` used last are kept."""
        key = fixed.tobytes()
        qp = self._reduced.get(key)
        if qp is None:
            qp = self._reduced[key] = ReducedQP(self.coo_rows, self.coo_cols, len(self.lower), self.num_barrier,
                                                self.pair_i, self.pair_j, fixed, self.config, self.pieces)
            while len(self._reduced) > MAX_CACHED_MASKS:
                self._reduced.popitem(last=False)
        else:
            self._reduced.move_to_end(key)
        return qp

    def posed_pieces(self, object_pose: np.ndarray | None) -> list[np.ndarray]:
        """The object's convex pieces in the world frame (the same list while the pose holds),
        re-posing the FCL object when the pose changed."""
        if object_pose is not None and not np.array_equal(object_pose, self.scene.object_pose):
            self.scene.set_object_pose(object_pose)
        return self.scene.pieces

    def solve(self, terms: BarrierTerms, a_nom: np.ndarray, tighten: float,
              fixed: np.ndarray | None = None) -> tuple[np.ndarray | None, str]:
        """OSQP answer (N, 2) and its status; None when not solved, not finite or breaking a row.

        Only the vectors and matrix values change between ticks: ``update(q, l, u, Ax)`` on the
        problem set up once; OSQP warm-starts from the last answer. ``fixed`` (N,) robots are
        held at ``u = 0`` by leaving the problem (:meth:`reduced`: the same optimum).
        """
        self.lower[:self.num_barrier] = np.maximum(terms.bound + tighten, -1e20)  # dropped rows
        if fixed is not None and fixed.any():
            if fixed.all():
                return self._checked(np.zeros((self.n, 2)), "solved", terms)   # nothing listens
            u, status = self.reduced(fixed).solve(self._coo_values(terms.pair_normal, terms.object_normal),
                                                  a_nom, self.lower, self.upper)
            return self._checked(u, status, terms)
        self.solver.update(q=-2.0 * a_nom.ravel(), l=self.lower, u=self.upper,
                           Ax=self._ax(terms.pair_normal, terms.object_normal))
        res = self.solver.solve(raise_error=False)
        if res.info.status != "solved":
            return None, res.info.status
        if res.x is None or not np.all(np.isfinite(res.x)):
            return None, "solved but not finite"
        return self._checked(res.x.reshape(self.n, 2), res.info.status, terms)

    @staticmethod
    def _checked(u: np.ndarray | None, status: str, terms: BarrierTerms) -> tuple[np.ndarray | None, str]:
        """``(u, status)``, or None where ``u`` breaks a barrier row beyond the tolerance."""
        if u is None:
            return None, status
        if np.any(terms.rows_times(u) < terms.bound - _ROW_CHECK_TOL):
            return None, "solved but a barrier row is violated"
        return u, status


class SafetyFilter:
    """Make nominal accelerations safe for the robots of ``scenario`` (any robot count N).

    Usage::

        safety = SafetyFilter(scenario)
        result = safety.filter(pos, vel, a_nom)        # (N, 2) each -> SafetyResult
        fleet.send_accelerations(result.a_safe)
    """

    def __init__(self, scenario: Scenario, config: SafetyConfig | None = None):
        self.scenario = scenario
        self.config = config or SafetyConfig()
        self.dynamics = scenario.dynamics
        self._problems: OrderedDict[int, _Problem] = OrderedDict()
        self._object_pose: np.ndarray | None = None

    def problem(self, n: int) -> _Problem:
        """The cached problem for N robots (built on first use). The ``MAX_CACHED_PROBLEMS`` used
        last are kept: a tracker whose disc count changes every tick must not grow a
        long-running controller's memory without end."""
        prob = self._problems.get(n)
        if prob is None:
            prob = self._problems[n] = _Problem(self.scenario, n, self.config)
            while len(self._problems) > MAX_CACHED_PROBLEMS:
                self._problems.popitem(last=False)
        else:
            self._problems.move_to_end(n)
        return prob

    def _projection(self, terms: BarrierTerms, nominal: np.ndarray, values: np.ndarray, prob: _Problem,
                    fixed: np.ndarray | None) -> np.ndarray | None:
        """The QP's answer in closed form (:mod:`controllers.safety.projection`) when it is one:
        the broken rows share no robot and the projection meets every tightened row and every
        octagon; None otherwise (and with robots held fixed), and OSQP answers. ``values`` (K,)
        are the nominal's row values."""
        if not self.config.exact_projection or (fixed is not None and fixed.any()):
            return None
        return projected_optimum(terms, values, terms.bound + self.config.tighten, nominal, prob.a_box)

    def distances(self, pos: np.ndarray, object_pose: np.ndarray | None = None) -> SceneDistances:
        """Signed distances of (N, 2) centres: the FCL scene for ``geometry="fcl"``, else closed form."""
        prob = self.problem(len(pos))
        if self.config.geometry == "fcl":
            prob.scene.update(pos, object_pose)
            return prob.scene.distances()
        return analytic_distances(pos, self.scenario.robot_radius, self.scenario.arena,
                                  prob.posed_pieces(object_pose))

    def barrier(self, pos: np.ndarray, vel: np.ndarray,
                object_pose: np.ndarray | None = None) -> BarrierTerms:
        """Barrier values and rows at (pos, vel), each (N, 2) [m, m/s]."""
        if self.config.geometry == "fused":
            pos, vel = np.asarray(pos, dtype=np.float64), np.asarray(vel, dtype=np.float64)
            prob = self.problem(len(pos))
            return prob.fused.terms(pos, vel, prob.posed_pieces(object_pose))
        return barrier_terms(self.distances(pos, object_pose), vel, self.dynamics, self.config)

    def filter(self, pos: np.ndarray, vel: np.ndarray, a_nom: np.ndarray,
               object_pose: np.ndarray | None = None, *,
               prediction: Prediction | None = None) -> SafetyResult:
        """Safe accelerations for positions [m], velocities [m/s] and nominal accelerations [m/s^2].

        Args:
            pos, vel, a_nom: (N, 2) arrays.
            object_pose: optional (3,) object centroid x, y [m] and heading [rad]; the object is
                treated as static within the tick.
            prediction: the robots where the command will act (:mod:`controllers.safety.latency`):
                the barrier, the QP and the post-check then judge its ``pos``/``vel`` (instead
                of ``pos``/``vel``) with its grown discs; its fixed robots get ``a_safe = 0``
                (the caller brakes them) and are obstacles only.
        """
        start = time.perf_counter()
        pos, vel, a_nom = f64(pos), f64(vel), f64(a_nom)
        n = len(pos)
        if not pos.shape == vel.shape == a_nom.shape == (n, 2):
            for name, arr in (("pos", pos), ("vel", vel), ("a_nom", a_nom)):
                if arr.shape != (n, 2):
                    raise ValueError(f"SafetyFilter.filter: {name} must have shape (num_robots, 2) = "
                                     f"({n}, 2), got {arr.shape}")
        if n == 0:
            return SafetyResult(np.zeros((0, 2)), SafetyStatus.UNCHANGED, total_time_s=0.0)
        if not (all_finite(pos) and all_finite(vel) and all_finite(a_nom)
                and (object_pose is None or np.isfinite(object_pose).all())):
            finite = [name for name, arr in (("pos", pos), ("vel", vel), ("a_nom", a_nom),
                                             ("object_pose", object_pose))
                      if arr is not None and not np.all(np.isfinite(arr))]
            return self._brake_all(vel, f"non-finite input in {', '.join(finite)}", start)

        prob = self.problem(n)
        fused = self.config.geometry == "fused"
        fixed = None
        if prediction is not None:
            prediction.require_rows(n, "SafetyFilter.filter")
            pos, vel, fixed = prediction.pos, prediction.vel, prediction.fixed
            if np.count_nonzero(fixed):
                a_nom = np.where(fixed[:, None], 0.0, a_nom)
        dist: SceneDistances | None = None
        if fused:                                  # compiled: no floating-point warnings
            terms = prob.fused.terms(pos, vel, prob.posed_pieces(object_pose), prediction)
            nominal, values = np.empty((n, 2)), np.empty(len(terms.bound))
            clearance, min_barrier, bounded, met = fused_kernels.screen(
                terms.normal_xy, terms.row_i, terms.row_j, a_nom, float(self.dynamics.accel_limit),
                terms.bound, terms.distance, terms.h, nominal, values)
        else:
            with np.errstate(over="ignore", invalid="ignore"):   # checked for finiteness just below
                dist = self.distances(pos, object_pose)
                terms = barrier_terms(dist, vel, self.dynamics, self.config, prediction)
            clearance, min_barrier = dist.min_clearance(), float(terms.h.min())
            bounded = bool((terms.bound < np.inf).all())
        # b = -K(h) - drift: a non-finite h (or drift) makes b non-finite too (dropped rows: -inf)
        if not bounded:                                       # NaN or +inf (dropped rows are -inf)
            return self._brake_all(vel, "barrier terms overflowed (velocities far out of range)", start,
                                   clearance, prediction=prediction)
        if not fused:
            nominal = clip_norm(a_nom, self.dynamics.accel_limit)
            values = terms.rows_times(nominal)
            met = bool((values >= terms.bound).all())
        if met:
            a, status, solver, slack, reason, solve_time = nominal, SafetyStatus.UNCHANGED, "", 0.0, "", 0.0
        else:
            a, status, solver, slack, reason, solve_time = self._solve(terms, nominal, values, prob, fixed)
            if a is None:
                return self._brake_all(vel, reason, start, clearance, terms, solve_time, prediction)
        braked, contact = np.zeros(n, dtype=bool), np.zeros(n, dtype=bool)
        if self.config.postcheck:
            if isinstance(terms, FusedTerms):
                check = prob.fused.check(prob.checker, pos, vel, a, terms, prediction)
            else:
                check = prob.checker.check(pos, vel, a, dist.object_clearance(), prediction)
            a, braked, contact = check.acc, check.braked, check.contact
            if np.count_nonzero(braked):
                status = SafetyStatus.FALLBACK_BRAKE
                reason = (reason + "; " if reason else "") + (
                    f"post-check braked robots {np.flatnonzero(braked).tolist()}")
        return SafetyResult(a_safe=a, status=status, reason=reason, solver=solver, braked=braked, contact=contact,
                            min_barrier=min_barrier, min_clearance=clearance,
                            max_slack=slack, solve_time_s=solve_time,
                            total_time_s=time.perf_counter() - start, terms=terms)

    def _solve(self, terms: BarrierTerms, nominal: np.ndarray, values: np.ndarray, prob: _Problem,
               fixed: np.ndarray | None) -> tuple[np.ndarray | None, SafetyStatus, str, float, str, float]:
        """The QP of a tick whose nominal breaks a row: the closed-form projection where it is the
        optimum, else OSQP, else the slack QP. ``(a (N, 2) or None: brake all, status, solver,
        max slack, reason, solve time [s])``; ``a`` clipped to the filter's bound, fixed rows 0."""
        t_solve = time.perf_counter()
        status, solver, osqp_status, slack, reason = SafetyStatus.INTERVENED, "projection", "", 0.0, ""
        a = self._projection(terms, nominal, values, prob, fixed)
        if a is None:
            a, osqp_status = prob.solve(terms, nominal, self.config.tighten, fixed)
            solver = "osqp"
        if a is None:
            a, slack, reason = self._slack_qp(terms, nominal, prob, fixed)
            reason = f"OSQP: {osqp_status}; {reason}"
            status, solver = SafetyStatus.SLACK, "daqp"
        solve_time = time.perf_counter() - t_solve
        if a is not None:
            a = clip_norm(a, self.config.accel_fraction * self.dynamics.accel_limit)
            if fixed is not None and np.count_nonzero(fixed):
                a[fixed] = 0.0                       # held at 0 by the QP, to solver tolerance
        return a, status, solver, slack, reason, solve_time

    # ------------------------------------------------------------------ fallbacks
    def _slack_qp(self, terms: BarrierTerms, nominal: np.ndarray, prob: _Problem,
                  fixed: np.ndarray | None = None) -> tuple[np.ndarray | None, float, str]:
        """Barrier rows softened by slack variables, solved exactly by DAQP (see module docstring)."""
        n = prob.n
        live = np.isfinite(terms.bound)                        # dropped rows (-inf bounds) go first
        a_rows = terms.dense(n)[live]
        k = len(a_rows)
        weight = np.full(prob.num_barrier, self.config.slack_weight)
        weight[len(terms.pair_i):] *= self.config.static_slack_factor      # object and wall rows
        if fixed is not None and fixed.any():
            # a robot inside a silent robot's grown disc gets out of it as fast as the other rows
            # allow: those rows give way first (the disc is a bound, the wall is a wall)
            with_fixed = row_sums(fixed.astype(np.float64), terms.pair_i, terms.pair_j, terms.pieces) > 0
            weight[with_fixed] *= FIXED_SLACK_DISCOUNT
        p_mat = 2.0 * np.diag(np.concatenate([np.ones(2 * n), weight[live]]))
        q_vec = np.concatenate([-2.0 * nominal.ravel(), np.zeros(k)])
        diag = np.zeros((2 * n, 2 * n))
        robots = np.arange(n)
        diag[2 * robots, 2 * robots] = diag[2 * robots, 2 * robots + 1] = 1.0
        diag[2 * robots + 1, 2 * robots] = 1.0
        diag[2 * robots + 1, 2 * robots + 1] = -1.0
        g_mat = np.block([[-a_rows, -np.eye(k)],
                          [diag, np.zeros((2 * n, k))],
                          [-diag, np.zeros((2 * n, k))]])
        limit = math.sqrt(2) * prob.a_box
        h_vec = np.concatenate([-(terms.bound[live] + self.config.tighten), np.full(4 * n, limit)])
        lb = np.concatenate([np.full(2 * n, -prob.a_box), np.zeros(k)])
        ub = np.concatenate([np.full(2 * n, prob.a_box), np.full(k, np.inf)])
        if fixed is not None and fixed.any():
            held = np.repeat(fixed, 2)
            lb[:2 * n][held] = ub[:2 * n][held] = 0.0
        try:
            x = qpsolvers.solve_qp(p_mat, q_vec, g_mat, h_vec, lb=lb, ub=ub, solver="daqp")
        except Exception as exc:  # any solver failure means: brake, and the reason says why
            return None, 0.0, f"DAQP raised {type(exc).__name__}: {exc}"
        if x is None or not np.all(np.isfinite(x)):
            return None, 0.0, "DAQP found no solution"
        u, sigma = x[:2 * n].reshape(n, 2), x[2 * n:]
        if np.any(np.abs(u) > prob.a_box + 1e-6):
            return None, 0.0, "DAQP answer outside the actuator limits"
        return u, float(sigma.max(initial=0.0)), "slack QP (DAQP)"

    def _brake_all(self, vel: np.ndarray, reason: str, start: float, clearance: float = math.nan,
                   terms: BarrierTerms | None = None, solve_time: float = 0.0,
                   prediction: Prediction | None = None) -> SafetyResult:
        n = len(vel)
        return SafetyResult(
            a_safe=braking_acceleration(vel, self.dynamics, prediction), status=SafetyStatus.FALLBACK_BRAKE,
            reason=reason, braked=np.ones(n, dtype=bool), contact=np.zeros(n, dtype=bool),
            min_barrier=float(terms.h.min()) if terms is not None else math.nan,
            min_clearance=clearance,
            solve_time_s=solve_time, total_time_s=time.perf_counter() - start)
