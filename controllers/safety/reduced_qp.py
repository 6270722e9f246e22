r"""The barrier QP without its fixed robots: what OSQP solves when some rows are obstacles.

The filter's QP (:mod:`controllers.safety.barrier_qp`) has the variables of all M robots and a
row for every pair. A fixed robot (a silent robot, a stale one, a tracker's disc) is held at
``u_j = 0`` by closing its actuator rows to [0, 0], and its rows with other fixed robots, the
object and the walls are dropped (bound ``-inf``). OSQP still carries all of them: with F fixed
discs the problem has ``F (F - 1) / 2`` rows that constrain nothing and ``2 F`` variables pinned
at zero, and on a cluttered tick it ran out of iterations on those (``bench/safety.py --only
clutter``).

With ``L`` listening robots, substituting ``u_j = 0`` gives the same QP over ``2 L`` variables::

    minimise    || u_L - a_nom_L ||^2
    subject to  n_k . (u_i - u_j) >= b_k + tighten      pairs of two listening robots
                n_k . u_i          >= b_k + tighten      pairs of a listening and a fixed robot
                object, wall, actuator octagon rows      of the listening robots

(every row that holds a listening robot, with the fixed robot's entries removed). Same feasible
set, same objective: the same optimum, to OSQP's tolerance. :class:`ReducedQP` keeps one
problem per fixed mask, set up once, so a mask that holds tick to tick (a silent robot) costs
only OSQP's ``update`` afterwards.
"""

from __future__ import annotations

import numpy as np
import osqp
import scipy.sparse as sp

from controllers.safety.barrier import SafetyConfig, row_robots


class ReducedQP:
    """The QP of one fixed mask, from the full problem's COO pattern.

    Args:
        coo_rows, coo_cols: (E,) the full problem's constraint entries (``num_rows`` rows,
            columns ``2 i + axis`` of robot ``i``).
        num_barrier: K, the barrier rows come first: pairs (``pair_i``, ``pair_j``), then object
            rows, then wall rows, robot-major; the rest are actuator rows of one robot each.
        pair_i, pair_j: (P,) the robots of each pair row.
        fixed: (M,) bool, at least one robot listening.
        config: eps and max_iter of OSQP.
        pieces: object rows per robot (one per convex piece of the object).
    """

    def __init__(self, coo_rows: np.ndarray, coo_cols: np.ndarray, num_rows: int, num_barrier: int,
                 pair_i: np.ndarray, pair_j: np.ndarray, fixed: np.ndarray, config: SafetyConfig,
                 pieces: int = 1):
        m = len(fixed)
        self.free = np.flatnonzero(~fixed)
        column = np.full(2 * m, -1)
        column[2 * self.free] = 2 * np.arange(len(self.free))
        column[2 * self.free + 1] = 2 * np.arange(len(self.free)) + 1
        robot_of_row = np.empty(num_rows, dtype=np.int64)
        p = len(pair_i)
        robot_of_row[p:] = np.concatenate([row_robots(pair_i, pair_j, m, pieces)[0][p:],
                                           _actuator_robots(m, num_rows - num_barrier)])
        live = np.ones(num_rows, dtype=bool)
        live[:p] = ~(fixed[pair_i] & fixed[pair_j])
        live[p:] = ~fixed[robot_of_row[p:]]
        self.rows = np.flatnonzero(live)
        row_index = np.full(num_rows, -1)
        row_index[self.rows] = np.arange(len(self.rows))
        entries = np.flatnonzero(live[coo_rows] & (column[coo_cols] >= 0))
        coo = sp.coo_matrix((np.arange(1, len(entries) + 1, dtype=np.float64),
                             (row_index[coo_rows[entries]], column[coo_cols[entries]])),
                            shape=(len(self.rows), 2 * len(self.free)))
        csc = coo.tocsc()
        self.perm = entries[csc.data.astype(np.int64) - 1]        # CSC slot -> full COO entry
        csc.data = np.ones(len(self.perm))
        n_var = 2 * len(self.free)
        self.solver = osqp.OSQP()
        self.solver.setup(sp.identity(n_var, format="csc") * 2.0, np.zeros(n_var), csc,
                          np.full(len(self.rows), -1.0), np.full(len(self.rows), 1.0),
                          eps_abs=config.eps, eps_rel=config.eps, max_iter=config.max_iter,
                          polishing=True, warm_starting=True, verbose=False)

    def solve(self, coo_values: np.ndarray, a_nom: np.ndarray, lower: np.ndarray, upper: np.ndarray
              ) -> tuple[np.ndarray | None, str]:
        """``(u (M, 2) with the fixed rows 0, or None; OSQP's status)`` for the full problem's COO
        entry values (E,), nominal (M, 2) and bounds (num_rows,; dropped rows at -1e20)."""
        self.solver.update(q=-2.0 * a_nom[self.free].ravel(), l=lower[self.rows], u=upper[self.rows],
                           Ax=coo_values[self.perm])
        res = self.solver.solve(raise_error=False)
        if res.info.status != "solved":
            return None, res.info.status
        if res.x is None or not np.all(np.isfinite(res.x)):
            return None, "solved but not finite"
        u = np.zeros((len(a_nom), 2))
        u[self.free] = res.x.reshape(-1, 2)
        return u, res.info.status


def _actuator_robots(m: int, count: int) -> np.ndarray:
    """(count,) the robot of each actuator row after the barrier rows: two box rows per robot
    (x, y), then two diagonal rows per robot."""
    per = np.repeat(np.arange(m), 2)
    robots = np.concatenate([per, per])
    if len(robots) != count:
        raise ValueError(f"ReducedQP: {count} actuator rows for {m} robots, expected {len(robots)}")
    return robots


__all__ = ["ReducedQP"]
