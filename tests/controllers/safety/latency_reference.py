"""The latency prediction in its numpy formulation: the reference its compiled kernel
(:mod:`controllers.safety.latency_kernels`) must match to the last bit
(tests/controllers/safety/test_latency_kernels.py)."""

from __future__ import annotations

import numpy as np

from controllers.safety.latency import LatencyPredictor, horizon_ticks


class NumpyPredictor(LatencyPredictor):
    """:class:`LatencyPredictor` with the listening robots predicted by numpy expressions (the
    fixed robots' reachable sets and the rest of :meth:`predict` are the class's own)."""

    def _jittering(self, pending: np.ndarray, ages: np.ndarray) -> np.ndarray:
        """(N,) bool: robots whose observed command delay (pending commands less the ticks
        the state aged) changed within the last ``depth`` ticks; updates the record."""
        known = pending >= 0
        delay = np.where(known, pending - np.rint(ages / self.dynamics.dt).astype(np.int64), -1)
        changed = known & (self._delay_seen >= 0) & (delay != self._delay_seen)
        self._jitter_left = np.where(changed, self.depth, np.maximum(self._jitter_left - 1, 0))
        self._delay_seen = np.where(known, delay, self._delay_seen)
        return self._jitter_left > 0

    def _listening(self, pos: np.ndarray, vel: np.ndarray, ages: np.ndarray, a_nom: np.ndarray,
                   pending: np.ndarray, given_fixed: np.ndarray, sigma_p: np.ndarray,
                   delay: float) -> tuple[np.ndarray, ...]:
        """:meth:`LatencyPredictor._listening` by numpy expressions."""
        cfg, dyn = self.config, self.dynamics
        horizon = horizon_ticks(ages, delay, dyn.dt)
        stale = (ages > cfg.stale_after_s) | (pending > horizon)          # old, or late (:meth:`late`)
        fixed = stale | given_fixed
        h = np.where(fixed, 0, np.minimum(horizon, self.depth - 1))
        known = pending >= 0
        m = np.where(known, np.minimum(pending, h), h)
        p, v = self._roll_forward(pos, vel, m)
        lo, hi = self._window_box(h, m, known, a_nom)
        jittering = self._jittering(pending, ages)
        unsure = jittering | ~known                           # the delay may change under it
        spread = np.hypot(hi[:, 0] - lo[:, 0], hi[:, 1] - lo[:, 1])
        weight = np.where(unsure, max(cfg.jitter_spread_weight, cfg.spread_weight), cfg.spread_weight)
        accel = weight * spread + cfg.accel_uncertainty
        grow = accel * dyn.dt**2 * h * (h + 1) / 2 + cfg.velocity_noise * dyn.dt * h + sigma_p
        closing = accel * dyn.dt * h + cfg.velocity_noise
        steps = int(h.max(initial=0))
        largest = np.hypot(a_nom[:, 0], a_nom[:, 1])            # the largest command of the window
        if steps:
            recent = self._history[self.depth - steps:]
            largest = np.maximum(largest, np.sqrt((recent * recent).sum(axis=2)).max(axis=0))
        fresh_bound = np.minimum(largest + cfg.accel_uncertainty, dyn.accel_limit)
        self._accel_bound = np.where(fixed, self._accel_bound, fresh_bound)
        return p, v, grow, closing, fixed, h, jittering

    def _roll_forward(self, pos: np.ndarray, vel: np.ndarray, m: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Each robot ``i`` through the newest ``m_i`` recorded commands, oldest first (module
        docstring, Prediction)."""
        dyn, depth = self.dynamics, self.depth
        steps = int(m.max(initial=0))
        p, v = pos.copy(), vel.copy()
        if steps and (m == steps).all():                                 # the common case
            keep, vmax2 = 1.0 - dyn.damping * dyn.dt, dyn.speed_limit ** 2
            for u in self._history[depth - steps:]:  # Dynamics.step_np; u is clipped when recorded
                v = keep * v + dyn.dt * u
                sq = v[:, 0] * v[:, 0] + v[:, 1] * v[:, 1]
                if sq.max() > vmax2:
                    v = v * np.minimum(1.0, dyn.speed_limit / np.sqrt(np.maximum(sq, 1e-300)))[:, None]
                p = p + dyn.dt * v
            return p, v
        rows = np.arange(len(m))
        for t in range(steps):
            p1, v1 = dyn.step_np(p, v, self._history[np.minimum(depth - m + t, depth - 1), rows])
            active = (t < m)[:, None]
            p, v = np.where(active, p1, p), np.where(active, v1, v)
        return p, v

    def _window_box(self, h: np.ndarray, m: np.ndarray, known: np.ndarray,
                    a_nom: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Per-axis box ``lo, hi`` (N, 2) of the commands that may act before the new one: the
        newest ``max(h_i, m_i + 1)`` recorded (``h_i`` where the count is unknown) and ``a_nom``
        (module docstring, Tightening)."""
        depth = self.depth
        start = np.where(known, depth - np.maximum(h, m + 1), depth - h)     # >= 0: m <= h < depth
        window = ((np.arange(depth)[:, None] >= start[None, :]) & (h > 0)[None, :])[..., None]
        lo = np.minimum(np.where(window, self._history, np.inf).min(axis=0), a_nom)
        hi = np.maximum(np.where(window, self._history, -np.inf).max(axis=0), a_nom)
        return lo, hi
