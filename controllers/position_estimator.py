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

from controllers import position_estimator_kernels
from controllers.jit import f64, require_shapes

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
        n = len(ids)
        require_shapes("PositionEstimator.update", pos=(pos, (n, 2)), vel=(vel, (n, 2)), time_s=(time_s, (n,)),
                       new=(new, (n,)), velocity_noise_var=(velocity_noise_var, (n,)))
        return self._estimate(pos, vel, time_s, new, velocity_noise_var)

    def _estimate(self, pos: np.ndarray, vel: np.ndarray, time_s: np.ndarray, new: np.ndarray,
                  velocity_noise_var: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """:meth:`update` for rows already keyed to the robots, compiled
        (:func:`controllers.position_estimator_kernels.estimate`)."""
        n = len(pos)
        out_pos, out_std = np.empty((n, 2)), np.empty(n)
        position_estimator_kernels.estimate(
            f64(pos), f64(vel), f64(time_s), np.ascontiguousarray(new, dtype=bool),
            f64(velocity_noise_var), self.dt, float(FORGET), float(NOISE_FLOOR**2), float(RESET_SIGMAS**2), self.p_hat,
            self.var, self.y_prev, self.t_prev, self.noise_var, self.passed, self.count, out_pos, out_std)
        return out_pos, out_std



__all__ = ["FORGET", "NOISE_FLOOR", "RESET_SIGMAS", "PositionEstimator"]
