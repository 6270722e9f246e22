r"""The filter's QP answered exactly, without a solver, when the rows it must move apart.

The QP of :mod:`controllers.safety.barrier_qp` is a Euclidean projection::

    u* = argmin_u || u - a ||^2   over   F = { r_k . u >= c_k  (every barrier row k) } ∩ O^N

with ``c_k = b_k + tighten`` and O the actuator octagon of every robot. Let V be the rows that
the clipped nominal ``a`` breaks. When the rows of V touch pairwise disjoint sets of robots, the
superset ``S = (∩_{k in V} H_k) ∩ O^{robots outside V}`` (H_k the half-space of row k) splits
into independent blocks, and its projection is closed-form:

* a row k of V moves its robots along its own row vector ``r_k`` (``n`` on robot i, ``-n`` on
  robot j for a pair; ``n`` on robot i for the object and the walls)::

      u = a + d_k r_k / |r_k|^2,     d_k = c_k - r_k . a > 0,    |r_k|^2 = 2|n|^2 (pair) or |n|^2

* a robot in no row of V goes to the nearest point of the octagon (itself when inside).

Since ``F ⊂ S``, the projection onto S is the QP's answer whenever it lies in F; the caller
checks exactly that (every row, tightened, and the octagon of the robots of V) and otherwise
asks OSQP. No step assumes anything the check does not verify, so the answer is as safe as
OSQP's; it is the optimum itself, where OSQP's is the optimum to its tolerance. Most ticks the
filter changes at all have one or two rows to push on; OSQP's solve (a new factorisation of its
KKT matrix each tick) costs ~0.25 ms of a 0.3 ms tick there, this ~0.02 ms.
"""

from __future__ import annotations

import math

import numpy as np

_OVERSHOOT = 1e-12
"""[m/s^2] a moved row ends this far inside its half-space, so that rounding cannot leave it a
hair outside (the optimum itself is on the boundary)."""


def octagon_vertices(a_box: float) -> np.ndarray:
    """(8, 2) counter-clockwise vertices of ``{|x|, |y| <= c, |x +- y| <= sqrt(2) c}``, c = a_box."""
    c, e = a_box, a_box * (math.sqrt(2.0) - 1.0)
    return np.array([[c, -e], [c, e], [e, c], [-e, c], [-c, e], [-c, -e], [-e, -c], [e, -c]])


def inside_octagon(u: np.ndarray, a_box: float, tol: float = 1e-12) -> np.ndarray:
    """(N,) whether each (N, 2) row lies in the octagon (within ``tol``)."""
    x, y = u[:, 0], u[:, 1]
    s = math.sqrt(2.0) * a_box + tol
    c = a_box + tol
    return (np.abs(x) <= c) & (np.abs(y) <= c) & (np.abs(x + y) <= s) & (np.abs(x - y) <= s)


def project_octagon(u: np.ndarray, a_box: float) -> np.ndarray:
    """(N, 2) nearest points of the octagon to the (N, 2) rows (the row itself when inside)."""
    out = u.copy()
    outside = ~inside_octagon(u, a_box, 0.0)
    if not outside.any():
        return out
    p = u[outside][:, None, :]                                   # (M, 1, 2)
    v0 = octagon_vertices(a_box)
    edge = np.roll(v0, -1, axis=0) - v0                          # (8, 2)
    t = np.clip(((p - v0) * edge).sum(-1) / (edge * edge).sum(-1), 0.0, 1.0)   # (M, 8)
    nearest = v0 + t[..., None] * edge                           # (M, 8, 2)
    best = ((nearest - p) ** 2).sum(-1).argmin(1)
    out[outside] = nearest[np.arange(len(best)), best]
    return out


def separable_answer(normals: np.ndarray, row_i: np.ndarray, row_j: np.ndarray, values: np.ndarray,
                     lower: np.ndarray, a: np.ndarray, a_box: float) -> np.ndarray | None:
    """The projection onto S of the module docstring, or None when the broken rows share a robot.

    Args:
        normals: (K, 2) row normals (:meth:`BarrierTerms.row_normals`); row_i, row_j: (K,) the
            robots of every row, ``row_j = -1`` on rows of one robot (:meth:`BarrierTerms.row_robots`).
        values: (K,) ``r_k . a``; lower: (K,) ``c_k``; a: (N, 2) the clipped nominal.
        a_box: the octagon's half-width [m/s^2].
    Not yet verified: :func:`projected_optimum` checks it (rows and octagon) before use.
    """
    broken = np.flatnonzero(values < lower)
    i, j = row_i[broken], row_j[broken]
    robots = np.concatenate([i, j[j >= 0]])
    if len(np.unique(robots)) != len(robots):
        return None
    u = project_octagon(a, a_box)
    u[robots] = a[robots]
    normal = normals[broken]                                       # (|V|, 2)
    pair = j >= 0
    step = (lower[broken] - values[broken] + _OVERSHOOT) / ((normal * normal).sum(1) * np.where(pair, 2.0, 1.0))
    u[i] += step[:, None] * normal
    u[j[pair]] -= step[pair, None] * normal[pair]
    return u


def projected_optimum(terms, values: np.ndarray, lower: np.ndarray, a: np.ndarray,
                      a_box: float) -> np.ndarray | None:
    """The QP's optimum in closed form when it is one, else None (OSQP's turn).

    ``terms``: the tick's :class:`~controllers.safety.barrier.BarrierTerms`; ``values`` (K,) its
    rows times ``a``; ``lower`` (K,) the tightened bounds ``c_k``; ``a`` (N, 2) the clipped
    nominal. The answer of :func:`separable_answer` is accepted only when it meets every row and
    every octagon, i.e. lies in F (module docstring)."""
    u = separable_answer(terms.row_normals(), *terms.row_robots(), values, lower, a, a_box)
    if u is None or not (terms.rows_times(u) >= lower).all() or not inside_octagon(u, a_box).all():
        return None
    return u


__all__ = ["inside_octagon", "octagon_vertices", "project_octagon", "projected_optimum",
           "separable_answer"]
