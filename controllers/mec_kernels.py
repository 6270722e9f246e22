"""The compensator's tick compiled (:mod:`controllers.jit`): observer bank update and compensation.

The maths is that of :mod:`controllers.mec` (its docstring); these loops compute it with the
same operations in the same order as its numpy formulation (kept by the tests as the reference),
for B hypotheses, N robots and 2 axes. State arrays are updated in place:

- ``v_hat``, ``d_hat`` (B, N, 2), ``score`` (B, N), ``sent`` (B, N, 2) (oldest first),
- ``charge``, ``level`` (N,) int64, ``noise_var``, ``noise_count`` (N,), ``y_prev``,
  ``r_prev`` (N, 2).
"""

from __future__ import annotations

import math

import numpy as np

from controllers.jit import kernel, register_warm_up


@kernel
def observe(vel, update, run, v_hat, d_hat, score, sent, charge, level, noise_var, noise_count,
            y_prev, r_prev, level_gain, level_midpoints, dt, keep, noise_scale, speed_limit,
            max_disturbance, forget, switch_ratio, noise_forget, v_out):
    """One tick of the observer bank, then the choice of the hypothesis in charge.

    Args:
        vel: (N, 2) measured velocities [m/s], 0 where not ``update``.
        update: (N,) bool, robots with a measurement to take.
        run: False on a tick where every robot starts afresh (predict nothing, only choose).
        keep: ``1 - c dt``; noise_scale: ``1 + (2 - c dt)^2 + (1 - c dt)^2`` (computed once by
            the caller, as the numpy formulation does); noise_forget: ``NOISE_FORGET``.
        v_out: (N, 2) written: the velocity estimate of the hypothesis in charge [m/s].
    """
    b, n = v_hat.shape[0], v_hat.shape[1]
    vmax2, dmax2 = speed_limit * speed_limit, max_disturbance * max_disturbance
    if run:
        # _clip_rows scales every row only when some row of the bank exceeds the limit
        v_pred = np.empty((b, n, 2))
        over = False
        for k in range(b):
            u = sent[b - 1 - k]                 # hypothesis k ran the command sent k + 1 ticks ago
            for i in range(n):
                for a in range(2):
                    v_pred[k, i, a] = keep * v_hat[k, i, a] + dt * (u[i, a] + d_hat[k, i, a])
                sq = v_pred[k, i, 0] * v_pred[k, i, 0] + v_pred[k, i, 1] * v_pred[k, i, 1]
                over = over or sq > vmax2
        if over:
            _scale_rows(v_pred, speed_limit)
        d_new = np.empty((b, n, 2))
        d_over = False
        for k in range(b):
            for i in range(n):
                g_v, g_d = level_gain[level[i], 0], level_gain[level[i], 1]
                sq = 0.0
                for a in range(2):
                    e = vel[i, a] - v_pred[k, i, a] if update[i] else 0.0
                    v_hat[k, i, a] = v_pred[k, i, a] + g_v * e
                    d_new[k, i, a] = d_hat[k, i, a] + g_d * e
                    sq = sq + e * e if a else e * e
                if update[i]:
                    score[k, i] = forget * score[k, i] + sq
                d_over = d_over or d_new[k, i, 0] * d_new[k, i, 0] + d_new[k, i, 1] * d_new[k, i, 1] > dmax2
        if d_over:
            _scale_rows(d_new, max_disturbance)
        d_hat[:] = d_new
        _track_noise(vel, update, sent, charge, level, noise_var, noise_count, y_prev, r_prev,
                     level_midpoints, dt, keep, noise_scale, noise_forget)
    for i in range(n):
        best = 0
        for k in range(1, b):
            if score[k, i] < score[best, i] or (math.isnan(score[k, i]) and not math.isnan(score[best, i])):
                best = k
        if score[best, i] < switch_ratio * score[charge[i], i]:
            charge[i] = best
        v_out[i, 0], v_out[i, 1] = v_hat[charge[i], i, 0], v_hat[charge[i], i, 1]


@kernel
def _scale_rows(x, limit):
    """Rows of (B, N, 2) ``x`` scaled by ``min(1, limit / |row|)`` in place (controllers.mec._clip_rows)."""
    for k in range(x.shape[0]):
        for i in range(x.shape[1]):
            sq = x[k, i, 0] * x[k, i, 0] + x[k, i, 1] * x[k, i, 1]
            scale = np.minimum(1.0, limit / math.sqrt(np.maximum(sq, 1e-300)))
            x[k, i, 0] *= scale
            x[k, i, 1] *= scale


@kernel
def _track_noise(vel, update, sent, charge, level, noise_var, noise_count, y_prev, r_prev,
                 level_midpoints, dt, keep, scale, noise_forget):
    """Measured noise from the change of the one-step residual (controllers.mec, Noise)."""
    b = sent.shape[0]
    for i in range(vel.shape[0]):
        u = sent[b - 1 - charge[i], i]
        res0 = vel[i, 0] - keep * y_prev[i, 0] - dt * u[0]
        res1 = vel[i, 1] - keep * y_prev[i, 1] - dt * u[1]
        c0, c1 = res0 - r_prev[i, 0], res1 - r_prev[i, 1]
        own = 0.5 * (c0 * c0 + c1 * c1) / scale
        good = update[i] and math.isfinite(own)
        if good:
            noise_count[i] += 1.0
        weight = np.maximum(1.0 - noise_forget, 1.0 / np.maximum(noise_count[i], 1.0))
        if good:
            noise_var[i] = (1 - weight) * noise_var[i] + weight * own
        if update[i]:
            y_prev[i, 0], y_prev[i, 1], r_prev[i, 0], r_prev[i, 1] = vel[i, 0], vel[i, 1], res0, res1
        else:
            y_prev[i, 0] = y_prev[i, 1] = r_prev[i, 0] = r_prev[i, 1] = np.nan
        count = 0
        for m in range(level_midpoints.shape[0]):
            if noise_var[i] > level_midpoints[m]:
                count += 1
        level[i] = count


@kernel
def compensate(target, d_hat, score, sent, charge, level, noise_var, noise_count, gate_level,
               level_wander, design_var, significance, upper_sigmas, warmup, adapt, accel_limit,
               a_cmd, d_best, gated, compensation):
    """``a_cmd = clip_norm(a_safe - c, accel_limit)`` (controllers.mec, Noise), then the shift of
    ``sent`` with ``a_cmd`` as the newest command.

    Args:
        target: (N, 2) ``a_safe`` [m/s^2] (non-finite rows: a zero command).
        a_cmd, d_best, compensation: (N, 2) written; gated: (N,) bool written.

    Returns:
        ``(all targets finite, some command clipped)``.
    """
    n = target.shape[0]
    good_all = True
    for i in range(n):
        good_all = good_all and math.isfinite(target[i, 0]) and math.isfinite(target[i, 1])
    clipped_any = False
    for i in range(n):
        k = charge[i]
        dx, dy = d_hat[k, i, 0], d_hat[k, i, 1]
        d_best[i, 0], d_best[i, 1] = dx, dy
        gated[i] = score[k, i] > gate_level[level[i]]
        threshold = 0.0
        if adapt:
            upper = noise_var[i] * (1.0 + upper_sigmas / math.sqrt(np.maximum(noise_count[i], 1.0)))
            threshold = significance * level_wander[level[i]] * math.sqrt(np.maximum(upper - design_var, 0.0))
        keep = np.maximum(0.0, 1.0 - threshold / np.maximum(math.hypot(dx, dy), 1e-300))
        off = gated[i] or (adapt and noise_count[i] < warmup)
        compensation[i, 0], compensation[i, 1] = (0.0, 0.0) if off else (dx * keep, dy * keep)
        if math.isfinite(target[i, 0]) and math.isfinite(target[i, 1]):
            a_cmd[i, 0], a_cmd[i, 1] = target[i, 0] - compensation[i, 0], target[i, 1] - compensation[i, 1]
        else:
            a_cmd[i, 0] = a_cmd[i, 1] = 0.0
        norm = math.hypot(a_cmd[i, 0], a_cmd[i, 1])
        if norm > accel_limit:
            clipped_any = True
            scale = np.minimum(1.0, accel_limit / np.maximum(norm, 1e-300))
            a_cmd[i, 0] *= scale
            a_cmd[i, 1] *= scale
    for k in range(sent.shape[0] - 1):
        sent[k] = sent[k + 1]
    sent[-1] = a_cmd
    return good_all, clipped_any


@register_warm_up
def _warm_up() -> None:
    b, n, levels = 4, 2, 6
    vel, upd = np.zeros((n, 2)), np.ones(n, dtype=bool)
    v_hat, d_hat, sent = np.zeros((b, n, 2)), np.zeros((b, n, 2)), np.zeros((b, n, 2))
    score = np.zeros((b, n))
    charge, level = np.zeros(n, dtype=np.int64), np.zeros(n, dtype=np.int64)
    noise_var, noise_count = np.full(n, 1e-4), np.zeros(n)
    y_prev, r_prev = np.zeros((n, 2)), np.full((n, 2), np.nan)
    gain, mid = np.full((levels, 2), 0.5), np.ones(levels - 1)
    observe(vel, upd, True, v_hat, d_hat, score, sent, charge, level, noise_var, noise_count, y_prev,
            r_prev, gain, mid, 0.05, 0.975, 5.9, 0.4, 1.0, 0.7, 0.1, 0.95, np.empty((n, 2)))
    compensate(vel, d_hat, score, sent, charge, level, noise_var, noise_count, np.ones(levels),
               np.ones(levels), 2.5e-5, 5.0, 3.0, 1, True, 1.0, np.empty((n, 2)), np.empty((n, 2)),
               np.empty(n, dtype=bool), np.empty((n, 2)))


__all__ = ["compensate", "observe"]
