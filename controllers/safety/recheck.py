r"""Re-check of the command that goes out: the compensated command must satisfy the barrier too.

The filter makes ``a_safe`` satisfy every barrier row ``n_k . (G u)_k >= b_k`` (the acceleration
the robots are to *achieve*). The compensator then sends ``a_cmd = a_safe - d_hat``, trusting
its estimate ``d_hat``. Were that estimate wrong (a delay, a contact, a model change it has not
caught up with), the robots would achieve something near ``a_cmd`` instead. So the command sent
must be safe under both readings: every row that ``a_cmd`` breaks (below ``b_k`` and below the
value ``a_safe`` reaches on it, which the post-check may itself have lowered by braking) has its
robots' compensation withdrawn (``a_cmd_i = a_safe_i``), repeating until no row is broken. The
worst case is ``a_cmd = a_safe``, which passes by construction.
"""

from __future__ import annotations

import numpy as np

from controllers.jit import f64
from controllers.safety import fused_kernels
from controllers.safety.barrier import BarrierTerms
from controllers.safety.fused import FusedTerms

_TOL = 1e-9


def _row_robots(terms: BarrierTerms, rows: np.ndarray, num: int) -> np.ndarray:
    """(num,) bool: robots that take part in the given (K,) bool rows."""
    i, j = terms.row_robots()
    out = np.zeros(num, dtype=bool)
    out[i[rows]] = True
    out[j[rows & (j >= 0)]] = True
    return out


def recheck(terms: BarrierTerms | None, a_safe: np.ndarray, a_cmd: np.ndarray, keep: int) -> np.ndarray:
    """The first ``keep`` rows of ``a_cmd`` (M, 2), with compensation withdrawn where it breaks a row.

    ``a_safe`` and ``a_cmd`` are (M, 2) over every robot of ``terms`` (silent ones included,
    with equal rows); ``terms`` None (filter fell back before building rows) returns ``a_cmd``.
    """
    if terms is None:
        return a_cmd[:keep]
    out = np.array(a_cmd, dtype=np.float64)   # a C-contiguous copy, as the kernel takes
    if isinstance(terms, FusedTerms):          # compiled first test: most ticks stop here
        a_safe, floor, values = f64(a_safe), np.empty(len(terms.bound)), np.empty(len(terms.bound))
        if not fused_kernels.command_breaks_rows(terms.normal_xy, terms.row_i, terms.row_j, a_safe,
                                                 out, terms.bound, _TOL, floor, values):
            return out[:keep]
    else:
        floor = np.minimum(terms.bound, terms.rows_times(a_safe)) - _TOL
    for _ in range(len(out)):
        broken = terms.rows_times(out) < floor
        if not broken.any():
            break
        robots = _row_robots(terms, broken, len(out))
        out[robots] = a_safe[robots]
    return out[:keep]


__all__ = ["recheck"]
