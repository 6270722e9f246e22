r"""Position estimator: a per-robot Kalman filter that measures its own position noise.

A policy and a safety filter that read raw noisy positions react to the noise: with 1 cm of
position noise the filter saw neighbours jump by centimetres from tick to tick, its QP was
infeasible in a third of the ticks of a crowded episode, and robots crept into each other
(3 contact episodes of 340 in ``bench/safety.py --only conditions``, condition ``noise``).
Telling the filter the noise instead (growing every disc by 1 cm) kept them apart but cost
the scripted controller 40 % of its successes: targets lie 3 cm from the object.

**Model.** Per robot and axis, the kinematic relation of the robots' semi-implicit Euler step
(exact for :class:`sim.scenario.Dynamics` and the pymunk world, to rounding) drives the
estimate, with the measured velocity as the input (unbiased, its noise white)::

    p_k = p_{k-1} + g_k v_k + w_k,     w_k ~ N(0, (g_k sigma_v)^2)     (g_k: time since the last measurement)
    y_k = p_k + n_k,                   n_k ~ N(0, sigma_p^2)

    predict:  p^- = p^_{k-1} + g_k v_k,          P^- = P_{k-1} + (g_k sigma_v)^2
    update:   K = P^- / (P^- + sigma_p^2),       p^_k = p^- + K (y_k - p^-),   P_k = (1 - K) P^-

It needs no command and no delay model (the velocity carries both), so a wrong model or a late
command does not bias it. ``sigma_v`` is the velocity noise the caller knows (the compensator
measures it per robot, :attr:`controllers.mec.ModelErrorCompensator.noise_var`).

**Noise.** ``sigma_p`` is measured per robot from the one-step residual of two consecutive
measurements, ``r_k = y_k - y_{k-1} - dt v^y_k`` with the measured velocity ``v^y``: noise-free
it is 0, otherwise ``n_k - n_{k-1} - dt n^v_k``, of variance ``2 sigma_p^2 + dt^2 sigma_v^2``
per axis, so ``sigma_p^2 <= E|r|^2 / 4`` (a plain mean over the first residuals, then forgetting
``FORGET``). At or below ``NOISE_FLOOR`` the measurement passes through unchanged (``K = 1``):
on an exact link the estimator changes nothing. An innovation beyond ``RESET_SIGMAS`` standard
deviations (a contact, a robot moved by hand) restarts the robot at its measurement.

With 1 cm of position noise and 2 cm/s of velocity noise (20 Hz) the steady state is
``K ~ 0.1`` and a posterior standard deviation of ~3 mm per axis, which the safety filter
adds to the robot's disc (:meth:`PositionEstimator.update` returns it).

Estimates are keyed by robot id; a robot that joins starts at its first measurement.
"""

from __future__ import annotations

import numpy as np

NOISE_FLOOR = 1e-4     # [m] measured position noise at or below this: measurements pass through
FORGET = 0.95          # forgetting factor of the measured residual variance
RESET_SIGMAS = 6.0     # an innovation this many standard deviations out restarts the robot


class PositionEstimator:
    """Per-robot steady Kalman filter on positions (module docstring), keyed by robot id.

    Args:
        dt: the control period [s] (the gap of two consecutive measurements).
    """

    def __init__(self, dt: float):
        if not (isinstance(dt, int | float) and dt > 0):
            raise ValueError(f"PositionEstimator: dt must be a positive number of seconds, got {dt!r}")
        self.dt = float(dt)
        self.reset()

    def reset(self) -> None:
        """Forget every robot."""
        self.ids: tuple[str, ...] = ()
        self.p_hat = np.zeros((0, 2))
        self.var = np.zeros(0)          # posterior variance per axis [m^2]
        self.y_prev = np.zeros((0, 2))  # the last measurement
        self.t_prev = np.zeros(0)       # its time [s]
        self.noise_var = np.zeros(0)    # measured sigma_p^2 [m^2]
        self.passed = np.zeros(0, dtype=bool)   # the last measurement passed through unfiltered
        self.count = np.zeros(0)        # residuals seen

    def _align(self, ids: tuple[str, ...]) -> np.ndarray:
        """Re-key to ``ids``; (N,) bool of robots never seen before."""
        n = len(ids)
        old = {rid: k for k, rid in enumerate(self.ids)}
        keep = np.array([old.get(rid, -1) for rid in ids], dtype=np.int64)
        fresh = keep < 0
        src = np.where(fresh, 0, keep)

        def take(x: np.ndarray, blank: float) -> np.ndarray:
            if len(x) == 0:
                return np.full((n, *x.shape[1:]), blank)
            out = x[src].copy()
            out[fresh] = blank
            return out

        self.p_hat, self.var = take(self.p_hat, np.nan), take(self.var, 0.0)
        self.y_prev, self.t_prev = take(self.y_prev, np.nan), take(self.t_prev, np.nan)
        self.noise_var, self.count = take(self.noise_var, 0.0), take(self.count, 0.0)
        self.passed = take(self.passed, True).astype(bool)
        self.ids = ids
        return fresh

    def update(self, ids: tuple[str, ...], pos: np.ndarray, vel: np.ndarray, time_s: np.ndarray,
               new: np.ndarray, velocity_noise_var: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """One tick for N robots.

        Args:
            ids: (N,) robot names.
            pos: (N, 2) measured positions [m] (finite where ``new``).
            vel: (N, 2) measured velocities (the input ``v_k`` and the noise residual's) [m/s].
            time_s: (N,) measurement times [s].
            new: (N,) bool, rows that carry a measurement not seen before.
            velocity_noise_var: (N,) ``sigma_v^2`` per axis [m^2/s^2].

        Returns:
            ``(positions (N, 2), std (N,))``: the estimate at each robot's last measurement
            (rows not ``new`` keep it; unseen rows: ``pos``) and its standard deviation per axis [m].
        """
        ids = tuple(ids)
        if ids != self.ids:
            self._align(ids)
        pos, vel, time_s = np.asarray(pos, np.float64), np.asarray(vel, np.float64), np.asarray(time_s, np.float64)
        new = np.asarray(new, dtype=bool) & np.isfinite(pos).all(axis=1) & np.isfinite(vel).all(axis=1)
        gap = time_s - self.t_prev
        step = new & np.isfinite(self.p_hat).all(axis=1) & np.isfinite(gap) & (gap > 0)
        self._measure_noise(pos, vel, step & (np.abs(gap - self.dt) < 0.5 * self.dt))
        r = self.noise_var
        wary = 1.0 + 2.0 / np.sqrt(np.maximum(self.count, 1.0))   # few residuals: an upper estimate
        if new.all() and (r <= NOISE_FLOOR**2).all():           # an exact link: pass through
            kept = pos.copy()                                   # the caller's array may change
            self.p_hat, self.var, self.passed = kept, r, np.ones(len(pos), dtype=bool)
            self.y_prev, self.t_prev = kept, time_s.copy()
            return pos, np.sqrt(r * wary)
        g = np.where(step, gap, 0.0)
        p_prior = self.p_hat + g[:, None] * vel
        # a measurement passed through carries the noise measured since, not what was known then
        v_prior = np.where(self.passed, r, self.var) + g * g * np.asarray(velocity_noise_var, np.float64)
        gain = v_prior / np.maximum(v_prior + r, 1e-300)
        innovation = pos - p_prior
        out_of_model = (innovation * innovation).max(axis=1) > RESET_SIGMAS**2 * (v_prior + r)
        exact = (r <= NOISE_FLOOR**2) | out_of_model | ~step
        p_post = np.where(exact[:, None], pos, p_prior + gain[:, None] * innovation)
        var_post = np.where(exact, r, (1.0 - gain) * v_prior)
        self.p_hat = np.where(new[:, None], p_post, self.p_hat)
        self.var = np.where(new, var_post, self.var)
        self.passed = np.where(new, exact, self.passed)
        self.y_prev = np.where(new[:, None], pos, self.y_prev)
        self.t_prev = np.where(new, time_s, self.t_prev)
        known = np.isfinite(self.p_hat).all(axis=1)
        var = np.where(self.passed, r, self.var) * wary
        return np.where(known[:, None], self.p_hat, pos), np.sqrt(np.where(known, var, 0.0))

    def _measure_noise(self, pos: np.ndarray, vel: np.ndarray, consecutive: np.ndarray) -> None:
        """Update ``sigma_p^2`` from the residual of the robots measured one tick apart (module
        docstring, Noise): ``E|r|^2 / 4`` per axis, a plain mean, then forgetting."""
        residual = pos - self.y_prev - self.dt * vel
        own = 0.25 * (residual * residual).sum(axis=1)
        good = consecutive & np.isfinite(own)
        self.count = self.count + good
        weight = np.maximum(1.0 - FORGET, 1.0 / np.maximum(self.count, 1.0))
        self.noise_var = np.where(good, (1 - weight) * self.noise_var + weight * own, self.noise_var)

__all__ = ["FORGET", "NOISE_FLOOR", "RESET_SIGMAS", "PositionEstimator"]
