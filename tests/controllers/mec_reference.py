"""The compensator's tick in its numpy formulation: the reference its compiled kernels
(:mod:`controllers.mec_kernels`) must match to the last bit (tests/controllers/test_mec_kernels.py)."""

from __future__ import annotations

import numpy as np

from controllers.mec import (
    NOISE_FORGET,
    NOISE_UPPER_SIGMAS,
    SIGNIFICANCE,
    WARMUP_UPDATES,
    ModelErrorCompensator,
)


def _clip_rows(x: np.ndarray, limit: float) -> np.ndarray:
    """(..., 2) rows scaled down to norm <= limit (``x`` itself when none exceeds it)."""
    sq = x[..., 0] * x[..., 0] + x[..., 1] * x[..., 1]
    if sq.max(initial=0.0) <= limit * limit:
        return x
    return x * np.minimum(1.0, limit / np.sqrt(np.maximum(sq, 1e-300)))[..., None]


def _clip_norm(x: np.ndarray, limit: float) -> tuple[np.ndarray, np.ndarray]:
    """Rows of (N, 2) ``x`` scaled down to norm <= limit, and (N,) which rows were scaled."""
    norm = np.hypot(x[:, 0], x[:, 1])
    clipped = norm > limit
    if not clipped.any():
        return x, clipped
    return x * np.minimum(1.0, limit / np.maximum(norm, 1e-300))[:, None], clipped


class NumpyMec(ModelErrorCompensator):
    """:class:`ModelErrorCompensator` with the observer bank and the compensation computed by
    numpy expressions (validation, re-keying and the status are the class's own)."""

    def _observe(self, vel: np.ndarray, update: np.ndarray) -> np.ndarray:
        """:meth:`ModelErrorCompensator._observe` by numpy expressions."""
        if not self._reset_tick:
            self._update(vel, update)
        rows = np.arange(len(vel))
        best = np.argmin(self.score, axis=0)                            # (N,)
        take = self.score[best, rows] < self.config.switch_ratio * self.score[self.charge, rows]
        self.charge = np.where(take, best, self.charge)
        return self.v_hat[self.charge, rows]

    def _compensate(self, target: np.ndarray) -> tuple[np.ndarray, ...]:
        """:meth:`ModelErrorCompensator._compensate` by numpy expressions."""
        rows = np.arange(len(target))
        best = self.charge
        d_hat = self.d_hat[best, rows]
        gated = self.score[best, rows] > self.gate_level[self.level]
        norm = np.hypot(d_hat[:, 0], d_hat[:, 1])
        # the wander of this level's gain under the measured noise, beyond that at the design noise
        upper = self.noise_var * (1.0 + NOISE_UPPER_SIGMAS / np.sqrt(np.maximum(self.noise_count, 1.0)))
        excess = np.maximum(upper - self.config.velocity_noise**2, 0.0)
        threshold = SIGNIFICANCE * self.level_wander[self.level] * np.sqrt(excess)
        if not self.config.adapt_noise:
            threshold = np.zeros(len(target))
        keep = np.maximum(0.0, 1.0 - threshold / np.maximum(norm, 1e-300))
        warming = (self.noise_count < WARMUP_UPDATES) & self.config.adapt_noise   # noise not known yet
        compensation = np.where((gated | warming)[:, None], 0.0, d_hat * keep[:, None])
        good_all = bool(np.isfinite(target).all())
        desired = target - compensation
        if not good_all:
            desired = np.where(np.isfinite(target).all(axis=1)[:, None], desired, 0.0)
        a_cmd, clipped = _clip_norm(desired, self.dynamics.accel_limit)
        self.replace_last_command(a_cmd, shift=True)
        return a_cmd, d_hat.copy(), gated, compensation, good_all, bool(clipped.any())

    def _update(self, vel: np.ndarray, update: np.ndarray) -> None:
        """One predict/update of every hypothesis for the (N,) robots in ``update``."""
        dt, c = self.dynamics.dt, self.dynamics.damping
        b = self.hypotheses
        # hypothesis delta ran the command sent delta + 1 ticks ago: sent[-1 - delta]
        u = self.sent[::-1][:b]                                         # (B, N, 2)
        v_pred = (1.0 - c * dt) * self.v_hat + dt * (u + self.d_hat)
        v_pred = _clip_rows(v_pred, self.dynamics.speed_limit)               # the plant's speed limit
        everyone = bool(update.all())
        innovation = vel[None] - v_pred
        if not everyone:
            innovation = np.where(update[None, :, None], innovation, 0.0)
        gain = self.level_gain[self.level]                                  # (N, 2)
        self.v_hat = v_pred + gain[None, :, :1] * innovation
        self.d_hat = _clip_rows(self.d_hat + gain[None, :, 1:] * innovation, self.max_disturbance)
        sq = (innovation * innovation).sum(axis=2)
        score = self.config.forget * self.score + sq
        self.score = score if everyone else np.where(update[None], score, self.score)
        self._track_noise(vel, update, u[self.charge, np.arange(len(vel))])

    def _track_noise(self, vel: np.ndarray, update: np.ndarray, u: np.ndarray) -> None:
        """Measurement noise from the change of the one-step residual (module docstring, Noise)."""
        dt, c = self.dynamics.dt, self.dynamics.damping
        residual = vel - (1.0 - c * dt) * self.y_prev - dt * u           # dt d + n_k - (1 - c dt) n_{k-1}
        change = residual - self.r_prev                                  # dt (d_k - d_{k-1}) + noise
        own = 0.5 * (change * change).sum(axis=1) / (1.0 + (2.0 - c * dt) ** 2 + (1.0 - c * dt) ** 2)
        good = update & np.isfinite(own)
        self.noise_count = self.noise_count + good               # a plain mean until it forgets
        weight = np.maximum(1.0 - NOISE_FORGET, 1.0 / np.maximum(self.noise_count, 1.0))
        self.noise_var = np.where(good, (1 - weight) * self.noise_var + weight * own, self.noise_var)
        if update.all():
            self.y_prev, self.r_prev = vel, residual
        else:
            self.y_prev = np.where(update[:, None], vel, np.nan)
            self.r_prev = np.where(update[:, None], residual, np.nan)
        # the nearest level in ratio: above the geometric midpoint of two levels, the upper one
        self.level = (self.noise_var[:, None] > self.level_midpoints[None]).sum(axis=1)

