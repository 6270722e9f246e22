"""The latency prediction in its numpy formulation: the reference its compiled kernel
(:mod:`controllers.safety.latency_kernels`) must match to the last bit
(tests/controllers/safety/test_latency_kernels.py)."""

from __future__ import annotations

import numpy as np

from controllers.safety.latency import (
    VELOCITY_NOISE_BOUND,
    LatencyPredictor,
    Prediction,
    horizon_ticks,
    reach,
)


class NumpyPredictor(LatencyPredictor):
    """:class:`LatencyPredictor` with the listening robots predicted by numpy expressions."""

    def _jittering(self, pending: np.ndarray, ages: np.ndarray) -> np.ndarray:
        """(N,) bool: robots whose observed command delay (pending commands less the ticks
        the state aged) changed within the last ``depth`` ticks; updates the record."""
        known = pending >= 0
        delay = np.where(known, pending - np.rint(ages / self.dynamics.dt).astype(np.int64), -1)
        changed = known & (self._delay_seen >= 0) & (delay != self._delay_seen)
        self._jitter_left = np.where(changed, self.depth, np.maximum(self._jitter_left - 1, 0))
        self._delay_seen = np.where(known, delay, self._delay_seen)
        return self._jitter_left > 0

    def predict(self, ids: tuple[str, ...], pos: np.ndarray, vel: np.ndarray, ages: np.ndarray,
                a_nom: np.ndarray, measured_delay_s: float | None = None,
                fixed: np.ndarray | None = None, pending: np.ndarray | None = None,
                position_noise: np.ndarray | None = None,
                velocity_noise: np.ndarray | None = None, now: float | None = None) -> Prediction:
        """Prediction of (N, 2) measured states of ``ages`` (N,) [s] (module docstring).

        ``a_nom`` (N, 2) joins the window whose spread bounds the unknown order of commands;
        ``fixed`` (N,) bool marks robots that are obstacles whatever their age (unknown state,
        silent), besides those older than ``stale_after_s`` and those :meth:`late`.
        ``pending`` (N,) int: commands sent after the newest one each robot had acted on when
        measured (-1: unknown; :attr:`sim.fleet.FleetState.commands_pending`).
        ``position_noise`` (N,) [m]: a per-robot position error (an estimator's) added to
        ``position_noise`` of the config. ``velocity_noise`` (N,) [m/s]: the standard deviation
        of each robot's velocity measurement (the compensator's), for
        :attr:`Prediction.velocity_error`. ``now`` [s]: the state's time; with it, a robot that is
        stale by age or given ``fixed`` is bounded by the branches of the commands it was sent
        (:mod:`controllers.safety.silent_reach`), else by :func:`reach`.
        """
        cfg, dyn = self.config, self.dynamics
        self._align(tuple(ids))
        delay = self._max_delay(measured_delay_s)
        horizon = horizon_ticks(ages, delay, dyn.dt)
        pending = np.full(len(ages), -1) if pending is None else np.asarray(pending)
        stale = (ages > cfg.stale_after_s) | (pending > horizon)          # old, or late (:meth:`late`)
        given_fixed = np.zeros(len(ages), dtype=bool) if fixed is None else np.asarray(fixed, dtype=bool)
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
        sigma_p = cfg.position_noise + (0.0 if position_noise is None else np.asarray(position_noise))
        grow = accel * dyn.dt**2 * h * (h + 1) / 2 + cfg.velocity_noise * dyn.dt * h + sigma_p
        closing = accel * dyn.dt * h + cfg.velocity_noise
        steps = int(h.max(initial=0))
        largest = np.hypot(a_nom[:, 0], a_nom[:, 1])            # the largest command of the window
        if steps:
            recent = self._history[self.depth - steps:]
            largest = np.maximum(largest, np.sqrt((recent * recent).sum(axis=2)).max(axis=0))
        fresh_bound = np.minimum(largest + cfg.accel_uncertainty, dyn.accel_limit)
        self._accel_bound = np.where(fixed, self._accel_bound, fresh_bound)
        if fixed.any():
            sigma = np.broadcast_to(sigma_p, (len(p),))
            by_ball = fixed.copy()
            if now is not None:
                silent = fixed & ((ages > cfg.stale_after_s) | given_fixed)
                unsure_weight = np.where(unsure, max(cfg.jitter_spread_weight, cfg.spread_weight), 0.0)
                for i in np.flatnonzero(silent):
                    paths = self._silent_paths(i, pos[i], vel[i], now - ages[i], pending[i], ages[i],
                                               delay, unsure_weight[i])
                    if paths is None:
                        continue
                    p[i], v[i], radius, rate = paths.disc(ages[i] + delay)
                    grow[i], closing[i] = radius + sigma[i], rate + cfg.velocity_noise
                    by_ball[i] = False
            if by_ball.any():
                brake_after = max(cfg.stale_after_s, cfg.watchdog_s) + delay
                centre, centre_vel, radius, rate = reach(pos[by_ball], vel[by_ball], ages[by_ball] + delay,
                                                         brake_after, dyn, self._accel_bound[by_ball])
                p[by_ball], v[by_ball] = centre, centre_vel
                grow[by_ball] = radius + sigma[by_ball]
                closing[by_ball] = rate + cfg.velocity_noise
        brake_vel, measured = v, jittering & ~fixed
        if cfg.jitter_brake_measured and measured.any():
            brake_vel = np.where(measured[:, None], vel, v)
        velocity_error = closing + (0.0 if velocity_noise is None else
                                    VELOCITY_NOISE_BOUND * np.asarray(velocity_noise))
        return Prediction(pos=p, vel=v, grow=grow, closing=closing, fixed=fixed, horizon=h,
                          brake_vel=brake_vel, velocity_error=velocity_error,
                          unsure=unsure)

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
