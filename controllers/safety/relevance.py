r"""Which fixed discs can touch the filter's answer this tick: the rest stay out of the QP.

A tracker may report many discs (people, boxes, clutter), and every disc the filter takes is a
row of the QP against every robot: at 200 discs one 5-robot tick cost 144 ms (p50) against 0.5
ms without them, far past the 50 ms period, with nearly all of those discs metres from any
robot. A fixed disc ``j`` (not listening: ``u_j = 0``) enters the filter only through its pair
rows with the listening robots ``i`` and their post-check, and this module keeps a disc only
when one of those can bind. Dropping the others changes no answer, exactly.

**Barrier rows** (:mod:`controllers.safety.barrier`, with a prediction as
:meth:`controllers.safety.fused.FusedScene.terms` builds them). The row of ``(i, j)`` reads
``n . u_i >= b + tighten`` with ``n`` the unit vector from ``j``'s centre to ``i``'s. Any command
the stack can send has ``|u_i| <= accel_limit`` (the filter's octagon lies inside it, the
compensated command is clipped to it), so ``n . u_i >= -accel_limit`` and the row holds for
every command once ``b + tighten <= -accel_limit``. With ``s`` the grown gap (centre distance
``- 2 r - grow_i - grow_j``), ``e = closing_i + closing_j``, ``s_dot = n . v_i`` and the row's
braking allowance ``alpha = braking_share * a_box`` (a fixed partner brakes for nobody), for
``s >= margin + sqrt_floor`` (no tangent continuation)::

    h     = sqrt(2 alpha (s - m)) + s_dot - e
    drift = (alpha / sqrt(2 alpha (s - m)) - c) (s_dot - min(max(s_dot, 0), e)) + kappa |w_t|^2
    b     = -gamma_i K(h) - drift  <=  -gamma_i K(h) - (alpha / sqrt(2 alpha (s - m)) - c) (s_dot - min(max(s_dot, 0), e))

(the curvature term is never negative), so the row is idle when ``h >= 0`` and the right-hand
side plus ``tighten`` is at most ``-accel_limit``. ``gamma_i`` is ``gamma_unsure`` for a robot
whose delay is unsure, ``K(h) = h`` or ``h^3`` (``class_k``).

**Post-check** (:mod:`controllers.safety.postcheck`): the relative chord of a robot and a fixed
disc moves only by the robot's own chord, at most ``dt speed_limit`` long and widened by
``dt^2 (accel_limit + c |v_i|) / 2``, so the pair cannot fail while
``s >= dt speed_limit + dt^2 (accel_limit + c |v_i|) / 2 + postcheck_margin``. (Where tried, a
pair the post-check could fail already binds by its barrier row; the sweep bound does not rest
on that.)

A disc far from every listening robot, or one the robots move away from, is idle on both
counts and left out. The bound is loose only where a robot heads straight at a disc at speed:
at 0.4 m/s with the default gains a disc binds from about 0.45 m ahead.
"""

from __future__ import annotations

import numpy as np

from controllers.safety.barrier import SafetyConfig, octagon_accel
from controllers.safety.prediction import Prediction
from sim.scenario import Dynamics

_SLACK = 1e-9   # [m], [m/s^2]: rounding kept on the binding side


def binding_fixed_rows(prediction: Prediction, first: int, config: SafetyConfig, dynamics: Dynamics,
                       robot_radius: float) -> np.ndarray:
    """(M - first,) bool: the fixed rows ``first..M-1`` of ``prediction`` that some barrier row or
    post-check of a listening row may bind this tick (module docstring); False rows can be left
    out of the filter without changing its answer. Rows before ``first`` are judged against,
    not judged."""
    listening = np.flatnonzero(~prediction.fixed)
    tail = np.arange(first, len(prediction.pos))
    if not len(tail):
        return np.zeros(0, dtype=bool)
    if not len(listening):
        return np.zeros(len(tail), dtype=bool)
    if not prediction.fixed[tail].all():
        raise ValueError("binding_fixed_rows: rows from `first` on must all be fixed (obstacles)")
    pos, vel = prediction.pos[listening], prediction.vel[listening]
    delta = pos[:, None, :] - prediction.pos[tail][None, :, :]              # (L, T, 2)
    centre = np.hypot(delta[..., 0], delta[..., 1])
    normal = delta / np.maximum(centre, 1e-12)[..., None]
    gap = centre - 2.0 * robot_radius - prediction.grow[listening][:, None] - prediction.grow[tail][None, :]
    dt, c = dynamics.dt, dynamics.damping
    speed = np.hypot(vel[:, 0], vel[:, 1])
    sweep = dt * dynamics.speed_limit + 0.5 * dt * dt * (dynamics.accel_limit + c * speed) + config.postcheck_margin
    swept = gap < (sweep[:, None] + _SLACK)

    floor = config.margin + config.sqrt_floor
    alpha = config.braking_share * octagon_accel(dynamics, config)
    root = np.sqrt(2.0 * alpha * np.maximum(gap - config.margin, config.sqrt_floor))
    approach = np.einsum("ltk,lk->lt", normal, vel)
    allowance = prediction.closing[listening][:, None] + prediction.closing[tail][None, :]
    h = root + approach - allowance
    sdot_drift = approach - np.minimum(np.maximum(approach, 0.0), allowance)
    unsure = np.zeros(len(listening), dtype=bool) if prediction.unsure is None else prediction.unsure[listening]
    gamma = np.where(unsure, config.gamma_unsure, config.gamma)[:, None]
    k_h = h * h * h if config.class_k != "linear" else h
    bound = -gamma * k_h - (alpha / root - c) * sdot_drift
    idle_row = (gap >= floor) & (h >= 0.0) & (bound + config.tighten <= -dynamics.accel_limit - _SLACK)
    return (swept | ~idle_row).any(axis=0)


def without_idle_fixed_rows(prediction: Prediction, first: int, config: SafetyConfig, dynamics: Dynamics,
                            robot_radius: float) -> tuple[Prediction, np.ndarray]:
    """``(prediction over rows 0..first-1 and the binding fixed rows after them, kept (M,) bool)``
    (:func:`binding_fixed_rows`); ``prediction`` itself when every row binds."""
    kept = np.ones(len(prediction.pos), dtype=bool)
    kept[first:] = binding_fixed_rows(prediction, first, config, dynamics, robot_radius)
    if kept.all():
        return prediction, kept
    return prediction.rows(kept), kept


__all__ = ["binding_fixed_rows", "without_idle_fixed_rows"]
