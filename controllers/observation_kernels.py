"""The policy's tokens for one fleet, compiled (:mod:`controllers.jit`).

The layout is that of :func:`sim.observations.fleet_tokens_np` (and of the batched torch path):
per robot ``i`` a row of ``2N + 1`` tokens of 4 numbers, ``[own state relative to the arena
centre, N targets relative to i, N - 1 other robots' states relative to i, the object: its
centroid and its nearest boundary point relative to i]``. This loop computes it with the same
float64 operations in the same order and writes float32, as the numpy function does into a
float32 buffer; the tests hold the two equal. The numpy function stays: the robot runtime
(:mod:`deploy.robot`) needs numpy only.
"""

from __future__ import annotations

import numpy as np

from controllers.jit import kernel, register_warm_up


@kernel
def fleet_tokens(pos, vel, targets, centroid, ax, ay, ex, ey, inv_len2, box, box_centre, box_half,
                 half_w, half_h, out):
    """Write the tokens of (N, 2) ``pos``, ``vel``, ``targets`` into ``out`` (N, 2N+1, 4).

    Args:
        centroid: (2,) the object's centroid [m]; ``ax, ay, ex, ey, inv_len2`` (M,): its edges'
            start points, vectors and inverse squared lengths; ``box``: it is the axis-aligned box
            ``box_centre``, ``box_half`` (2,), whose clamp gives the nearest point while every
            centre is strictly outside it.
        half_w, half_h: half the arena's width and height [m].
    """
    n, m = pos.shape[0], ax.shape[0]
    for i in range(n):
        out[i, 0, 0], out[i, 0, 1] = pos[i, 0] - half_w, pos[i, 1] - half_h
        out[i, 0, 2], out[i, 0, 3] = vel[i, 0] - 0.0, vel[i, 1] - 0.0
        for j in range(n):
            out[i, 1 + j, 0], out[i, 1 + j, 1] = targets[j, 0] - pos[i, 0], targets[j, 1] - pos[i, 1]
            out[i, 1 + j, 2] = out[i, 1 + j, 3] = 0.0
        q = n + 1
        for j in range(n):
            if j == i:
                continue
            out[i, q, 0], out[i, q, 1] = pos[j, 0] - pos[i, 0], pos[j, 1] - pos[i, 1]
            out[i, q, 2], out[i, q, 3] = vel[j, 0] - vel[i, 0], vel[j, 1] - vel[i, 1]
            q += 1
        out[i, 2 * n, 0], out[i, 2 * n, 1] = centroid[0] - pos[i, 0], centroid[1] - pos[i, 1]
    outside = box
    if box:
        for i in range(n):
            r0, r1 = pos[i, 0] - box_centre[0], pos[i, 1] - box_centre[1]
            o0 = np.minimum(np.maximum(r0, -box_half[0]), box_half[0]) - r0
            o1 = np.minimum(np.maximum(r1, -box_half[1]), box_half[1]) - r1
            out[i, 2 * n, 2], out[i, 2 * n, 3] = o0, o1
            outside = outside and (o0 != 0.0 or o1 != 0.0)
    if outside:
        return
    for i in range(n):
        best, best_dx, best_dy = np.inf, 0.0, 0.0
        for e in range(m):
            rx, ry = pos[i, 0] - ax[e], pos[i, 1] - ay[e]
            t = np.minimum(np.maximum((rx * ex[e] + ry * ey[e]) * inv_len2[e], 0.0), 1.0)
            dx, dy = t * ex[e] - rx, t * ey[e] - ry
            d2 = dx * dx + dy * dy
            if e == 0 or d2 < best:
                best, best_dx, best_dy = d2, dx, dy
        out[i, 2 * n, 2], out[i, 2 * n, 3] = best_dx, best_dy


@register_warm_up
def _warm_up() -> None:
    n = 2
    pos = np.array([[0.1, 0.1], [0.9, 0.9]])
    edges = [np.ones(4) for _ in range(5)]
    fleet_tokens(pos, pos, pos, np.zeros(2), *edges, True, np.full(2, 0.5), np.full(2, 0.1), 0.5, 0.5,
                 np.empty((n, 2 * n + 1, 4), dtype=np.float32))


__all__ = ["fleet_tokens"]
