"""Compiled row checks of the control tick (:mod:`controllers.jit`): finiteness and the norm clip.

At five robots ``np.isfinite(x).all()`` or a norm clip costs 2-10 us of numpy call overhead for
ten numbers; these loops do the same in one call, with the same IEEE operations (tests hold them
equal to their numpy formulations, NaN and infinities included). Inputs: C-contiguous float64
(N, 2) arrays (:func:`controllers.jit.f64`).
"""

from __future__ import annotations

import math

import numpy as np

from controllers.jit import kernel, register_warm_up


@kernel
def all_finite(x):
    """``np.isfinite(x).all()`` for an (N, 2) array."""
    for i in range(x.shape[0]):
        if not (math.isfinite(x[i, 0]) and math.isfinite(x[i, 1])):
            return False
    return True


@kernel
def all_rows_within(x, limit):
    """Every row of an (N, 2) array finite with norm <= ``limit`` (False for NaN or inf)."""
    limit2 = limit * limit
    for i in range(x.shape[0]):
        if not x[i, 0] * x[i, 0] + x[i, 1] * x[i, 1] <= limit2:
            return False
    return True


@kernel
def non_finite_rows(pos, vel, out):
    """``out = ~(isfinite(pos).all(1) & isfinite(vel).all(1))`` (N,) bool for (N, 2) ``pos``,
    ``vel``; returns how many rows are not finite."""
    count = 0
    for i in range(pos.shape[0]):
        bad = not (math.isfinite(pos[i, 0]) and math.isfinite(pos[i, 1])
                   and math.isfinite(vel[i, 0]) and math.isfinite(vel[i, 1]))
        out[i] = bad
        count += bad
    return count


@kernel
def clip_factor(x, y, limit):
    """``limit / maximum(hypot(x, y), limit)``: the factor of :func:`sim.scenario.clip_norm` for
    one row (numpy's NaN-propagating maximum)."""
    return limit / np.maximum(math.hypot(x, y), limit)


@kernel
def clip_rows(x, limit, out):
    """``out = clip_norm(x, limit)`` per (N, 2) row: ``x * clip_factor(x, limit)``."""
    for i in range(x.shape[0]):
        scale = clip_factor(x[i, 0], x[i, 1], limit)
        out[i, 0] = x[i, 0] * scale
        out[i, 1] = x[i, 1] * scale


def clip_norm_rows(x: np.ndarray, limit: float) -> np.ndarray:
    """:func:`sim.scenario.clip_norm` of a C-contiguous (N, 2) float64 array, compiled."""
    out = np.empty_like(x)
    clip_rows(x, float(limit), out)
    return out


@register_warm_up
def _warm_up() -> None:
    x = np.zeros((2, 2))
    all_finite(x)
    all_rows_within(x, 1.0)
    non_finite_rows(x, x, np.empty(2, dtype=bool))
    clip_factor(3.0, 4.0, 1.0)
    clip_rows(x, 1.0, np.empty((2, 2)))


__all__ = ["all_finite", "all_rows_within", "clip_factor", "clip_norm_rows", "clip_rows", "non_finite_rows"]
