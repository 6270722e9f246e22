"""The latency prediction of the robots that listen, compiled (:mod:`controllers.jit`).

The maths is that of :mod:`controllers.safety.latency` (its docstring: Prediction, Tightening);
these loops compute it with the same operations in the same order as its numpy formulation (kept
by the tests as the reference). Robots that are obstacles (``fixed``) get ``h = 0`` here; the
caller replaces their discs by their reachable sets.
"""

from __future__ import annotations

import math

import numpy as np

from controllers.array_kernels import clip_factor
from controllers.jit import kernel, register_warm_up


@kernel
def predict_listening(pos, vel, ages, a_nom, pending, given_fixed, sigma_p, history, delay_seen,
                      jitter_left, accel_bound, delay, dt, dt2, speed_limit2, stale_after, damping,
                      speed_limit, accel_limit, spread_weight, jitter_weight, accel_uncertainty,
                      velocity_noise, p, v, grow, closing, fixed, h, jittering):
    """Every robot through its pending commands, with its tightening (module docstring).

    Args:
        pos, vel: (N, 2) measured centres [m] and velocities [m/s]; ``ages`` (N,) [s].
        a_nom: (N, 2) nominal commands, clipped to ``accel_limit`` [m/s^2].
        pending: (N,) int64 commands pending (-1: unknown); given_fixed: (N,) bool.
        sigma_p: (N,) position error bound [m] (config plus estimator).
        history: (D, N, 2) commands asked, oldest first [m/s^2].
        delay_seen, jitter_left: (N,) int64, the jitter record, updated in place.
        accel_bound: (N,) updated in place for robots not fixed [m/s^2].
        dt2, speed_limit2: ``dt**2`` and ``speed_limit**2`` as the caller computes them.
        p, v (N, 2), grow, closing (N,), fixed, jittering (N,) bool, h (N,) int64: written.
    """
    depth, n = history.shape[0], history.shape[1]
    w_unsure = max(jitter_weight, spread_weight)
    steps = 0
    for i in range(n):
        horizon = horizon_ticks(ages[i], delay, dt)
        fixed[i] = ages[i] > stale_after or pending[i] > horizon or given_fixed[i]
        h[i] = 0 if fixed[i] else min(horizon, depth - 1)
        steps = max(steps, h[i])
    common = True
    m = np.empty(n, dtype=np.int64)
    for i in range(n):
        m[i] = min(pending[i], h[i]) if pending[i] >= 0 else h[i]
        common = common and m[i] == m[0]
    _roll_forward(pos, vel, m, history, common and m[0] > 0, dt, damping, speed_limit, speed_limit2,
                  accel_limit, p, v)
    for i in range(n):
        known = pending[i] >= 0
        # the jitter record: the observed delay is the pending count less the ticks the state aged
        observed = pending[i] - np.int64(np.rint(ages[i] / dt)) if known else -1
        changed = known and delay_seen[i] >= 0 and observed != delay_seen[i]
        jitter_left[i] = depth if changed else max(jitter_left[i] - 1, 0)
        if known:
            delay_seen[i] = observed
        jittering[i] = jitter_left[i] > 0
        # the window box: the newest max(h, m + 1) commands (h when the count is unknown) and a_nom
        start = depth - max(h[i], m[i] + 1) if known else depth - h[i]
        lo0, lo1, hi0, hi1 = np.inf, np.inf, -np.inf, -np.inf
        if h[i] > 0:
            for t in range(start, depth):
                lo0, lo1 = np.minimum(lo0, history[t, i, 0]), np.minimum(lo1, history[t, i, 1])
                hi0, hi1 = np.maximum(hi0, history[t, i, 0]), np.maximum(hi1, history[t, i, 1])
        lo0, lo1 = np.minimum(lo0, a_nom[i, 0]), np.minimum(lo1, a_nom[i, 1])
        hi0, hi1 = np.maximum(hi0, a_nom[i, 0]), np.maximum(hi1, a_nom[i, 1])
        weight = w_unsure if (jittering[i] or not known) else spread_weight
        accel = weight * math.hypot(hi0 - lo0, hi1 - lo1) + accel_uncertainty
        grow[i] = accel * dt2 * h[i] * (h[i] + 1) / 2 + velocity_noise * dt * h[i] + sigma_p[i]
        closing[i] = accel * dt * h[i] + velocity_noise
        largest = math.hypot(a_nom[i, 0], a_nom[i, 1])
        for t in range(depth - steps, depth):
            largest = np.maximum(largest, math.sqrt(history[t, i, 0] * history[t, i, 0]
                                             + history[t, i, 1] * history[t, i, 1]))
        if not fixed[i]:
            accel_bound[i] = np.minimum(largest + accel_uncertainty, accel_limit)


@kernel
def _roll_forward(pos, vel, m, history, common, dt, damping, speed_limit, speed_limit2, accel_limit, p, v):
    """Each robot ``i`` through the newest ``m_i`` recorded commands, oldest first, into ``p, v``.

    ``common`` (every ``m_i`` equal and positive): the damped step on the already clipped
    commands, the speed clipped only when some robot exceeds it (as the numpy fast path); else
    :meth:`sim.scenario.Dynamics.step_np` per robot.
    """
    depth, n = history.shape[0], history.shape[1]
    p[:] = pos
    v[:] = vel
    if common:
        keep, vmax2 = 1.0 - damping * dt, speed_limit2
        for t in range(depth - m[0], depth):
            over = False
            for i in range(n):
                v[i, 0] = keep * v[i, 0] + dt * history[t, i, 0]
                v[i, 1] = keep * v[i, 1] + dt * history[t, i, 1]
                over = over or v[i, 0] * v[i, 0] + v[i, 1] * v[i, 1] > vmax2
            for i in range(n):
                if over:
                    sq = v[i, 0] * v[i, 0] + v[i, 1] * v[i, 1]
                    scale = np.minimum(1.0, speed_limit / math.sqrt(np.maximum(sq, 1e-300)))
                    v[i, 0] *= scale
                    v[i, 1] *= scale
                p[i, 0] = p[i, 0] + dt * v[i, 0]
                p[i, 1] = p[i, 1] + dt * v[i, 1]
        return
    for i in range(n):
        for t in range(m[i]):
            k = min(depth - m[i] + t, depth - 1)
            ka = clip_factor(history[k, i, 0], history[k, i, 1], accel_limit)
            a0, a1 = history[k, i, 0] * ka, history[k, i, 1] * ka
            w0 = v[i, 0] + dt * (a0 - damping * v[i, 0])
            w1 = v[i, 1] + dt * (a1 - damping * v[i, 1])
            kv = clip_factor(w0, w1, speed_limit)
            v[i, 0], v[i, 1] = w0 * kv, w1 * kv
            p[i, 0], p[i, 1] = p[i, 0] + dt * v[i, 0], p[i, 1] + dt * v[i, 1]


@kernel
def horizon_ticks(age, delay, dt):
    """Ticks ``max(int64(ceil((tau + L) / dt - 1e-9)), 0)`` from a measurement to the new command
    acting (:func:`controllers.safety.latency.horizon_ticks` for one robot), and 0 where numpy's
    float-to-int64 cast has no value (NaN, +-inf, beyond 2^63: it gives INT64_MIN there, which
    the max lifts to 0)."""
    x = np.ceil((age + delay) / dt - 1e-9)
    if x == x and -9.223372036854775808e18 <= x < 9.223372036854775808e18:
        return max(np.int64(x), 0)
    return np.int64(0)


@kernel
def late_rows(pending, ages, delay, dt, out):
    """``out = pending > horizon_ticks(ages, delay, dt)`` (N,) bool
    (:meth:`controllers.safety.latency.LatencyPredictor.late`)."""
    for i in range(ages.shape[0]):
        out[i] = pending[i] > horizon_ticks(ages[i], delay, dt)


@kernel
def record_rows(accel, limit, braking, history, braked, recorded, depth):
    """One tick into the command history (:meth:`controllers.safety.latency.LatencyPredictor.record`),
    in place: ``history`` (D, N, 2) and ``braked`` (D, N) shift one tick older, their newest rows
    become ``clip_norm(accel, limit)`` and ``braking`` (N,); ``recorded`` (N,) counts up to ``depth``."""
    ticks, n = history.shape[0], history.shape[1]
    for t in range(ticks - 1):
        for i in range(n):
            history[t, i, 0] = history[t + 1, i, 0]
            history[t, i, 1] = history[t + 1, i, 1]
            braked[t, i] = braked[t + 1, i]
    for i in range(n):
        scale = clip_factor(accel[i, 0], accel[i, 1], limit)
        history[ticks - 1, i, 0] = accel[i, 0] * scale
        history[ticks - 1, i, 1] = accel[i, 1] * scale
        braked[ticks - 1, i] = braking[i]
        recorded[i] = min(recorded[i] + 1, depth)


@register_warm_up
def _warm_up() -> None:
    n, depth = 2, 6
    z2, z1 = np.zeros((n, 2)), np.zeros(n)
    predict_listening(z2, z2, z1, z2, np.full(n, -1, dtype=np.int64), np.zeros(n, dtype=bool), z1,
                      np.zeros((depth, n, 2)), np.full(n, -1, dtype=np.int64), np.zeros(n, dtype=np.int64),
                      np.ones(n), 0.15, 0.05, 0.0025, 0.16, 0.15, 0.5, 0.4, 1.0, 0.25, 0.5, 0.05, 0.0,
                      np.empty((n, 2)), np.empty((n, 2)), np.empty(n), np.empty(n), np.empty(n, dtype=bool),
                      np.empty(n, dtype=np.int64), np.empty(n, dtype=bool))
    late_rows(np.zeros(n, dtype=np.int64), z1, 0.15, 0.05, np.empty(n, dtype=bool))
    # called on its own too: a fixed robot's BRAKE velocity (LatencyPredictor._carried)
    _roll_forward(z2, z2, np.zeros(n, dtype=np.int64), np.zeros((depth, n, 2)), False, 0.05, 0.5, 0.4, 0.16, 1.0,
                  np.empty((n, 2)), np.empty((n, 2)))
    record_rows(z2, 1.0, np.zeros(n, dtype=bool), np.zeros((depth, n, 2)), np.zeros((depth, n), dtype=bool),
                np.zeros(n, dtype=np.int64), depth)


__all__ = ["late_rows", "predict_listening", "record_rows"]
