"""The position estimator's tick in its numpy formulation: the reference its compiled kernel
(:mod:`controllers.position_estimator_kernels`) must match to the last bit
(tests/controllers/test_position_estimator_kernels.py)."""

from __future__ import annotations

import numpy as np

from controllers.position_estimator import FORGET, NOISE_FLOOR, RESET_SIGMAS, PositionEstimator


class NumpyPositionEstimator(PositionEstimator):
    """:class:`PositionEstimator` with the tick computed by numpy expressions (re-keying and the
    shape checks are the class's own)."""

    def _estimate(self, pos: np.ndarray, vel: np.ndarray, time_s: np.ndarray, new: np.ndarray,
                  velocity_noise_var: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """:meth:`PositionEstimator._estimate` by numpy expressions."""
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
