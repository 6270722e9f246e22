"""The last finite state of each robot id, for ticks whose rows arrive non-finite (stack/pipeline.py)."""

from __future__ import annotations

import numpy as np


class LastKnown:
    """The last finite state of each robot id: when it was measured, and what stands in for a
    row that arrives non-finite. Rows are kept as arrays in the order of the last ids seen
    (re-keyed, with a table for the ids not in the picture, only when the ids change)."""

    def __init__(self):
        self._ids: tuple[str, ...] = ()
        self._pos, self._vel, self._measured = np.zeros((0, 2)), np.zeros((0, 2)), np.zeros(0)
        self._away: dict[str, tuple[np.ndarray, np.ndarray, float]] = {}

    def _align(self, ids: tuple[str, ...]) -> None:
        if ids == self._ids:
            return
        table = dict(self._away)
        table.update((rid, (self._pos[k], self._vel[k], self._measured[k])) for k, rid in enumerate(self._ids))
        none = (np.full(2, np.nan), np.full(2, np.nan), -np.inf)
        rows = [table.pop(rid, none) for rid in ids]
        self._ids, self._away = ids, table
        self._pos = np.array([r[0] for r in rows]).reshape(-1, 2)
        self._vel = np.array([r[1] for r in rows]).reshape(-1, 2)
        self._measured = np.array([r[2] for r in rows], dtype=np.float64)

    def new_measurement(self, ids: tuple[str, ...], ages: np.ndarray, now: float) -> np.ndarray:
        """(N,) bool: rows measured after the state last kept for their id (a dropped update
        repeats the old one: it must not count twice as news)."""
        self._align(ids)
        return now - ages > self._measured + 1e-9

    def update(self, ids: tuple[str, ...], pos: np.ndarray, vel: np.ndarray, ages: np.ndarray,
               now: float, unknown: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """Keep the finite rows; the ``unknown`` (non-finite) ones replaced by their last finite
        state, its age counted from when it was measured. Returns ``(pos, vel, ages, unplaced)``,
        ``unplaced`` (N,) bool: unknown rows with no state to stand in."""
        self._align(ids)
        if not unknown.any():
            self._pos, self._vel, self._measured = pos, vel, now - ages
            return pos, vel, ages, unknown
        keep = ~unknown
        self._pos, self._vel = np.where(keep[:, None], pos, self._pos), np.where(keep[:, None], vel, self._vel)
        self._measured = np.where(keep, now - ages, self._measured)
        unplaced = unknown & ~np.isfinite(self._measured)
        standing_in = unknown & ~unplaced
        ages = np.where(standing_in, np.maximum(now - self._measured, 0.0), ages)
        pos = np.where(unplaced[:, None], pos, self._pos)
        vel = np.where(unplaced[:, None], np.where(np.isfinite(vel), vel, 0.0), self._vel)
        return pos, vel, ages, unplaced


__all__ = ["LastKnown"]
