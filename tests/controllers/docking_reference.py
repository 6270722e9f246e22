"""Docking's tick in its numpy formulation: the reference its compiled kernels
(:mod:`controllers.docking_kernels`) must match to the last bit (tests/controllers/test_docking_kernels.py)."""

from __future__ import annotations

import numpy as np
from scipy.optimize import linear_sum_assignment

from controllers.docking import Docking
from sim.scenario import clip_norm


class NumpyDocking(Docking):
    """:class:`Docking` with the tick computed by numpy expressions and scipy's assignment (the
    checks before it are the class's own)."""

    def _dock(self, ids: tuple[str, ...], pos: np.ndarray, vel: np.ndarray, targets: np.ndarray,
              a_nom: np.ndarray, movable: np.ndarray | None) -> tuple[np.ndarray, np.ndarray]:
        """:meth:`Docking._dock` by numpy expressions and scipy's assignment."""
        cfg, n = self.config, len(pos)
        docking = np.zeros(n, dtype=bool)
        diff = pos[:, None] - targets[None]
        dist = np.hypot(diff[..., 0], diff[..., 1])                             # (robot, target)
        if dist.min() >= cfg.release_radius:                 # no robot near any target: the
            self._docking.clear()                            # assignment cannot make one dock
            return a_nom, docking
        _, match = linear_sum_assignment(dist)                                 # rows come sorted
        gap = dist[np.arange(n), match]
        near = dist[:, match].T < 2 * self.radius + cfg.free_margin            # (target of i, robot)
        np.fill_diagonal(near, False)
        taken = near.any(axis=1)
        matched = targets[match]
        was = np.array([rid in self._docking for rid in ids], dtype=bool)
        speed = np.hypot(vel[:, 0], vel[:, 1])
        capture = ((gap < cfg.capture_radius) & (speed < cfg.capture_speed)) | (
            (gap < cfg.stall_radius) & (speed < cfg.stall_speed))
        docking = np.where(was, gap < cfg.release_radius, capture) & ~taken
        if movable is not None:
            docking &= np.asarray(movable, dtype=bool)
        self._docking = {rid for rid, d in zip(ids, docking, strict=True) if d}
        if not docking.any():
            return a_nom, docking
        law = clip_norm(cfg.kp * (matched - pos) - cfg.kd * vel, self.accel_limit)
        return np.where(docking[:, None], law, a_nom), docking
