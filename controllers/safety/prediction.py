"""What the safety filter judges: every robot where the new command will act.

:class:`Prediction` is made by :class:`controllers.safety.latency.LatencyPredictor` (its module
docstring gives the maths) and read by the barrier, the QP and the post-check.
"""

from __future__ import annotations

from dataclasses import dataclass, replace

import numpy as np

from controllers.jit import require_shapes


@dataclass
class Prediction:
    """The filter's picture of N robots at the moment the new command acts.

    Attributes:
        pos, vel: (N, 2) predicted centres [m] and velocities [m/s] (fixed robots: last
            position, zero velocity).
        grow: (N,) disc growth ``e_p`` (or the reachable radius) [m].
        closing: (N,) approach-speed allowance ``e_v`` (or the reach speed bound) [m/s].
        fixed: (N,) bool, robots that are obstacles, not decision variables.
        horizon: (N,) ticks predicted.
        brake_vel: (N, 2) the velocity a braking command aims to stop [m/s]: ``vel``, or the
            measured velocity of a robot whose delay jitters (:mod:`controllers.safety.latency`, Braking);
            for a fixed robot, its last state carried through the commands in flight, which the
            BRAKE the stack sends it cancels (ibid., Braking a robot that is not listening);
            None: ``vel``.
        velocity_error: (N,) bound on the error of ``vel`` [m/s]: ``closing`` plus
            ``VELOCITY_NOISE_BOUND`` times the velocity noise the caller measured; read by the
            post-check's rule that excuses commands no worse than braking. None: 0.
        unsure: (N,) bool, robots whose command delay may change under the prediction (it
            changed lately, or their pending count is unknown): their rows take the filter's
            ``gamma_unsure`` (:class:`controllers.safety.barrier.SafetyConfig`). None: none.
        covers: fixed rows bounded more tightly by several discs than by one, once silent
            robots have come to rest (:meth:`SilentPaths.cover`): ``(row, centres (C, 2),
            radii (C,))`` each, the radii grown like ``grow``; :meth:`with_covers` turns them
            into rows for the filter.
    """

    pos: np.ndarray
    vel: np.ndarray
    grow: np.ndarray
    closing: np.ndarray
    fixed: np.ndarray
    horizon: np.ndarray
    brake_vel: np.ndarray | None = None
    velocity_error: np.ndarray | None = None
    unsure: np.ndarray | None = None
    covers: tuple[tuple[int, np.ndarray, np.ndarray], ...] = ()

    def require_rows(self, n: int, where: str) -> None:
        """Raise ValueError naming the first field that does not hold ``n`` rows: the compiled
        kernels that read a prediction do not check their bounds."""
        plane, vector = (n, 2), (n,)
        if (self.pos.shape == self.vel.shape == plane
                and self.grow.shape == self.closing.shape == self.fixed.shape == self.horizon.shape == vector
                and (self.brake_vel is None or self.brake_vel.shape == plane)
                and (self.velocity_error is None or self.velocity_error.shape == vector)
                and (self.unsure is None or self.unsure.shape == vector)):
            return                                  # the tick's path: no message to build
        vectors = {name: (getattr(self, name), (n,)) for name in
                   ("grow", "closing", "fixed", "horizon", "velocity_error", "unsure")
                   if getattr(self, name) is not None}
        planes = {name: (getattr(self, name), (n, 2)) for name in ("pos", "vel", "brake_vel")
                  if getattr(self, name) is not None}
        require_shapes(f"{where}: the prediction (one row per robot of pos)", **planes, **vectors)

    def with_covers(self) -> Prediction:
        """The prediction over ``N + V`` rows for the filter: each covered row takes its first
        cover disc, the other ``V`` discs follow the N rows as fixed obstacles at rest (their
        ``closing`` that of their row: the velocity noise allowance). Without covers, itself."""
        if not self.covers:
            return self
        pos, grow, closing = self.pos.copy(), self.grow.copy(), self.closing.copy()
        extra_pos, extra_grow, extra_closing = [], [], []
        for row, centres, radii in self.covers:
            pos[row], grow[row] = centres[0], radii[0]
            extra_pos.extend(centres[1:])
            extra_grow.extend(radii[1:])
            extra_closing.extend([closing[row]] * (len(radii) - 1))
        v = len(extra_grow)
        if v == 0:
            return replace(self, pos=pos, grow=grow, covers=())

        extra_closing = np.array(extra_closing)
        return Prediction(
            pos=np.vstack([pos, np.array(extra_pos)]), vel=_appended(self.vel, 0.0, v),
            grow=np.concatenate([grow, np.array(extra_grow)]), closing=np.concatenate([closing, extra_closing]),
            fixed=_appended(self.fixed, True, v), horizon=_appended(self.horizon, 0, v), brake_vel=_appended(self.brake_vel, 0.0, v),
            velocity_error=_appended(self.velocity_error, extra_closing, v), unsure=_appended(self.unsure, False, v))

    @classmethod
    def as_measured(cls, pos: np.ndarray, vel: np.ndarray, fixed: np.ndarray) -> Prediction:
        """The rows as measured, nothing predicted or grown (the latency prediction off)."""
        m = len(pos)
        return cls(pos=np.asarray(pos, dtype=np.float64), vel=np.asarray(vel, dtype=np.float64), grow=np.zeros(m),
                   closing=np.zeros(m), fixed=np.asarray(fixed, dtype=bool).copy(), horizon=np.zeros(m, dtype=np.int64))

    def with_obstacles(self, centres: np.ndarray, radii: np.ndarray, reach_s: np.ndarray, speed: np.ndarray,
                       robot_radius: float) -> Prediction:
        """The prediction with K obstacles appended as fixed rows (:class:`sim.fleet.Obstacles`).

        An obstacle of radius ``R`` seen at ``c`` moving at most ``s`` [m/s] is, ``reach_s``
        [s] after it was seen (its age, the latency bound and the tick the command lasts),
        within ``R + s reach_s`` of ``c``. As a row of robot radius ``r``: a fixed disc at
        ``c`` (velocity 0) with ``grow = max(R - r, 0) + s reach_s`` [m] and ``closing = s``
        [m/s], so the barrier counts it as approaching at ``s`` along every row's normal and the
        post-check sweeps against its grown disc. Robots' rows with it count on their own
        braking alone, as with any fixed row; one that the obstacle outruns (``s`` above what
        braking can answer) is braked by the fallback and the post-check.

        Args:
            centres: (K, 2) [m]; radii, reach_s, speed: (K,) [m], [s], [m/s].
        """
        k = len(centres)
        if k == 0:
            return self
        speed = np.asarray(speed, dtype=np.float64)
        grow = np.maximum(np.asarray(radii, dtype=np.float64) - robot_radius, 0.0) + speed * np.asarray(reach_s)
        return Prediction(
            pos=_appended(self.pos, np.asarray(centres, dtype=np.float64), k), vel=_appended(self.vel, 0.0, k),
            grow=_appended(self.grow, grow, k), closing=_appended(self.closing, speed, k), fixed=_appended(self.fixed, True, k),
            horizon=_appended(self.horizon, 0, k), brake_vel=_appended(self.brake_vel, 0.0, k),
            velocity_error=_appended(self.velocity_error, speed, k), unsure=_appended(self.unsure, False, k),
            covers=self.covers)

    def rows(self, kept: np.ndarray) -> Prediction:
        """The prediction over the rows where ``kept`` (M,) bool is True, in order (covers follow
        their rows, which must be kept)."""
        kept = np.asarray(kept, dtype=bool)
        index = np.cumsum(kept) - 1
        if any(not kept[row] for row, _, _ in self.covers):
            raise ValueError("Prediction.rows: a covered row must be kept")

        def take(x: np.ndarray | None) -> np.ndarray | None:
            return None if x is None else x[kept]

        return Prediction(pos=self.pos[kept], vel=self.vel[kept], grow=self.grow[kept], closing=self.closing[kept],
                          fixed=self.fixed[kept], horizon=self.horizon[kept], brake_vel=take(self.brake_vel),
                          velocity_error=take(self.velocity_error), unsure=take(self.unsure),
                          covers=tuple((int(index[row]), centres, radii) for row, centres, radii in self.covers))

    def braking_velocity(self) -> np.ndarray:
        """(N, 2) :attr:`brake_vel`, or :attr:`vel` where it is not set."""
        return self.vel if self.brake_vel is None else self.brake_vel


def _appended(x: np.ndarray | None, rows: np.ndarray | float, k: int) -> np.ndarray | None:
    """``x`` (M, ...) with ``k`` rows of ``rows`` (a value, or (k, ...) values) after it; None stays None."""
    if x is None:
        return None
    return np.concatenate([x, np.broadcast_to(np.asarray(rows, dtype=x.dtype), (k, *x.shape[1:]))])


__all__ = ["Prediction"]
