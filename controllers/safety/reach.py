r"""Where a robot that is not listening can be: a disc from its last state, whatever it was asked.

The safety filter keeps a robot that cannot be relied on to obey as a fixed obstacle
(:mod:`controllers.safety.latency`, Robots that are not listening); :func:`reach` bounds where
it can be from its last state and the largest acceleration it may have been asked.
``stale_after_s``, ``watchdog_s`` and ``L`` below are those of
:class:`~controllers.safety.latency.LatencyConfig`; :mod:`controllers.safety.silent_reach`
bounds such a robot tighter from the commands it was sent, where those are known.

A robot executes only commands it was sent and brakes on its own when they stop (its watchdog:
the contract of the wire format), so until braking must have begun it accelerates by at most
``a``, the largest command of its last fresh ticks plus ``delta_a`` (``accel_limit`` for a robot
never seen fresh), before braking must have begun, ``T_b = max(stale_after_s, watchdog_s) + L``
after its last state (a robot that still hears the controller is sent BRAKE once it is stale,
which acts within ``L``; one that hears nothing brakes on its own ``watchdog_s`` after its last
command, which it had within ``L`` of its last state), and then brakes at ``a_max = accel_limit``
to rest; it may also brake at once. Along its last heading it is
therefore between ``D_near`` (braking at once) and ``D_far`` (coasting at its last speed
``v_0`` until ``T_b``, then braking), and off that line by what ``a`` adds; with
``t_c = min(t, T_b)``, ``t_b = max(t - T_b, 0)``::

    D_far  = |v_0| t_c + |v_0| t_s - a_max t_s^2 / 2,     t_s = min(t_b, |v_0| / a_max)
    D_near = |v_0| t_n - a_max t_n^2 / 2,                 t_n = min(t, |v_0| / a_max)
    centre = p_0 + (v_0 / |v_0|) (D_far + D_near) / 2
    R      = (D_far - D_near) / 2 + a t_c^2 / 2 + (a T_b) min(t_b, (|v_0| + a T_b) / a_max)

so a robot silent for good stays an obstacle of bounded size where it must have stopped.
"""

from __future__ import annotations

import numpy as np

from sim.scenario import Dynamics


def reach(pos0: np.ndarray, vel0: np.ndarray, t: np.ndarray, brake_after: float, dynamics: Dynamics,
          accel: np.ndarray | float | None = None) -> tuple[np.ndarray, ...]:
    """Where a robot that is not listening can be ``t`` seconds after its last state (module docstring).

    Args:
        pos0, vel0: (M, 2) last known centres [m] and velocities [m/s].
        t: (M,) times since that state [s]; ``brake_after`` = ``T_b`` [s].
        accel: (M,) the acceleration bound ``a`` until ``T_b`` [m/s^2] (default ``accel_limit``).

    Returns:
        ``(centre (M, 2), centre velocity (M, 2), radius R (M,), dR/dt (M,))``: the disc of
        radius ``R`` around ``centre`` holds the robot's centre.
    """
    brake = dynamics.accel_limit
    a = np.maximum(np.asarray(brake if accel is None else accel, dtype=np.float64), 1e-9)
    t = np.asarray(t, dtype=np.float64)
    speed = np.minimum(np.hypot(vel0[:, 0], vel0[:, 1]), dynamics.speed_limit)
    heading = vel0 / np.maximum(speed, 1e-12)[:, None]
    coast = np.minimum(t, brake_after)
    t_b = np.maximum(t - brake_after, 0.0)
    stop = np.minimum(t_b, speed / brake)
    far = speed * coast + speed * stop - 0.5 * brake * stop * stop           # braking at T_b
    far_speed = np.where(t < brake_after, speed, np.maximum(speed - brake * t_b, 0.0))
    now = np.minimum(t, speed / brake)                                     # braking at once
    near = speed * now - 0.5 * brake * now * now
    near_speed = np.maximum(speed - brake * t, 0.0)
    spread_v = a * brake_after                                  # velocity error when braking starts
    t_err = np.minimum(t_b, (speed + spread_v) / brake)
    radius = 0.5 * (far - near) + 0.5 * a * coast * coast + spread_v * t_err
    rate = 0.5 * (far_speed - near_speed) + np.where(
        t < brake_after, a * t, np.where(t_b < (speed + spread_v) / brake, spread_v, 0.0))
    centre = pos0 + heading * (0.5 * (far + near))[:, None]
    return centre, heading * (0.5 * (far_speed + near_speed))[:, None], radius, rate


__all__ = ["reach"]
