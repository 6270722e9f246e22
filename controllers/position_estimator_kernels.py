"""The position estimator's tick compiled (:mod:`controllers.jit`).

The maths is that of :mod:`controllers.position_estimator` (its docstring: Model, Noise); the
loop computes it with the same operations in the same order as its numpy formulation (kept by
the tests as the reference). State arrays, updated in place, per robot: ``p_hat`` (N, 2),
``var`` (N,), ``y_prev`` (N, 2), ``t_prev`` (N,), ``noise_var`` (N,), ``passed`` (N,) bool,
``count`` (N,).
"""

from __future__ import annotations

import math

import numpy as np

from controllers.jit import kernel, register_warm_up


@kernel
def estimate(pos, vel, time_s, new, velocity_noise_var, dt, forget, floor_var, reset_sigmas2,
             p_hat, var, y_prev, t_prev, noise_var, passed, count, out_pos, out_std):
    """One tick for N robots: noise measurement, then the Kalman step or the pass-through.

    Args:
        pos, vel: (N, 2) measured positions [m] and velocities [m/s]; ``time_s`` (N,) [s].
        new: (N,) bool, rows with a measurement not seen before.
        velocity_noise_var: (N,) ``sigma_v^2`` [m^2/s^2].
        floor_var: ``NOISE_FLOOR^2``; reset_sigmas2: ``RESET_SIGMAS^2``.
        out_pos (N, 2), out_std (N,): written, the estimate and its standard deviation per axis.
    """
    n = pos.shape[0]
    fresh, step, gaps = np.empty(n, dtype=np.bool_), np.empty(n, dtype=np.bool_), np.empty(n)
    quiet = True
    for i in range(n):
        fresh[i] = (new[i] and math.isfinite(pos[i, 0]) and math.isfinite(pos[i, 1])
                    and math.isfinite(vel[i, 0]) and math.isfinite(vel[i, 1]))
        gap = time_s[i] - t_prev[i]
        gaps[i] = gap
        step[i] = (fresh[i] and math.isfinite(p_hat[i, 0]) and math.isfinite(p_hat[i, 1])
                   and math.isfinite(gap) and gap > 0)
        r0 = pos[i, 0] - y_prev[i, 0] - dt * vel[i, 0]
        r1 = pos[i, 1] - y_prev[i, 1] - dt * vel[i, 1]
        own = 0.25 * (r0 * r0 + r1 * r1)
        good = step[i] and abs(gap - dt) < 0.5 * dt and math.isfinite(own)
        if good:
            count[i] += 1.0
        weight = np.maximum(1.0 - forget, 1.0 / np.maximum(count[i], 1.0))
        if good:
            noise_var[i] = (1 - weight) * noise_var[i] + weight * own
        quiet = quiet and fresh[i] and noise_var[i] <= floor_var
    for i in range(n):
        r = noise_var[i]
        wary = 1.0 + 2.0 / math.sqrt(np.maximum(count[i], 1.0))
        if quiet:                                           # an exact link: pass through
            p_hat[i, 0], p_hat[i, 1], var[i], passed[i] = pos[i, 0], pos[i, 1], r, True
            y_prev[i, 0], y_prev[i, 1], t_prev[i] = pos[i, 0], pos[i, 1], time_s[i]
            out_pos[i, 0], out_pos[i, 1], out_std[i] = pos[i, 0], pos[i, 1], math.sqrt(r * wary)
            continue
        g = gaps[i] if step[i] else 0.0
        prior0, prior1 = p_hat[i, 0] + g * vel[i, 0], p_hat[i, 1] + g * vel[i, 1]
        v_prior = (r if passed[i] else var[i]) + g * g * velocity_noise_var[i]
        gain = v_prior / np.maximum(v_prior + r, 1e-300)
        e0, e1 = pos[i, 0] - prior0, pos[i, 1] - prior1
        out_of_model = np.maximum(e0 * e0, e1 * e1) > reset_sigmas2 * (v_prior + r)
        exact = r <= floor_var or out_of_model or not step[i]
        if fresh[i]:
            if exact:
                p_hat[i, 0], p_hat[i, 1], var[i] = pos[i, 0], pos[i, 1], r
            else:
                p_hat[i, 0], p_hat[i, 1] = prior0 + gain * e0, prior1 + gain * e1
                var[i] = (1.0 - gain) * v_prior
            passed[i] = exact
            y_prev[i, 0], y_prev[i, 1], t_prev[i] = pos[i, 0], pos[i, 1], time_s[i]
        if math.isfinite(p_hat[i, 0]) and math.isfinite(p_hat[i, 1]):
            out_pos[i, 0], out_pos[i, 1] = p_hat[i, 0], p_hat[i, 1]
            out_std[i] = math.sqrt((r if passed[i] else var[i]) * wary)
        else:
            out_pos[i, 0], out_pos[i, 1], out_std[i] = pos[i, 0], pos[i, 1], 0.0


@register_warm_up
def _warm_up() -> None:
    n = 2
    z2, z1 = np.zeros((n, 2)), np.zeros(n)
    estimate(z2, z2, z1, np.ones(n, dtype=bool), z1, 0.05, 0.95, 1e-8, 36.0, np.full((n, 2), np.nan),
             np.zeros(n), np.full((n, 2), np.nan), np.full(n, np.nan), np.zeros(n), np.ones(n, dtype=bool),
             np.zeros(n), np.empty((n, 2)), np.empty(n))


__all__ = ["estimate"]
