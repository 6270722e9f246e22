r"""Model error compensator (MEC): a Kalman disturbance observer that makes each robot act nominal.

After H. Okajima and N. Matsunaga (SICE JCMSI 6(4), 2013): a nominal model runs beside the
plant, and the error between the two is fed back into the plant input so that the plant behaves
like the nominal model. Here the error is an acceleration disturbance ``d`` [m/s^2] ("achieved
minus commanded acceleration"), estimated per robot and axis by a Kalman filter on the nominal
damped double integrator (:class:`sim.scenario.Dynamics`, period ``dt``, damping ``c``).

Per robot and axis (x and y are independent and share one model), state ``x = [v, d]``::

    v_{k+1} = (1 - c dt) v_k + dt (u_k + d_k) + w_v,     w_v ~ N(0, sigma_v^2)   [m/s]
    d_{k+1} = d_k + w_d,                                  w_d ~ N(0, sigma_d^2)   [m/s^2]
    y_k     = v_k + n_k,                                  n_k ~ N(0, sigma_y^2)   (measured velocity)

    F = [[1 - c dt, dt], [0, 1]],  B = [dt, 0]^T,  H = [1, 0],  Q = diag(sigma_v^2, sigma_d^2),  R = sigma_y^2

``u_k`` is the command actually sent. The filter uses the steady-state gain
``K = P H^T / (H P H^T + R)``, where ``P`` (the a-priori covariance) solves the discrete algebraic
Riccati equation ``P = F P F^T - F P H^T (H P H^T + R)^{-1} H P F^T + Q``; the tests check it
against a filterpy ``KalmanFilter`` run to convergence. One tick, for all N robots and both axes
at once (arrays (N, 2))::

    predict:    v^- = (1 - c dt) v_hat + dt (u_prev + d_hat),      d^- = d_hat
    update:     e = y - v^-,   v_hat = v^- + K_v e,   d_hat = clip_norm(d^- + K_d e, max_disturbance)
    compensate: u = clip_norm(a_safe - d_hat, accel_limit)

so the plant achieves ``u + d ~= a_safe``: it follows the nominal model under the safe command.
A gain error (a plant achieving only ``g u``) is the disturbance ``d = (g - 1) u``; the loop then
settles at ``u = a_safe / g`` unless that exceeds the actuator limit (status ``CLIPPED``).
With the default noise levels the closed-loop estimator poles are at |0.34| and ``d_hat``
follows a step to within 5 % from the second tick after it (see the tests for the hand-check).

A robot whose velocity is not finite keeps its prediction (no update) and the tick reports
``INVALID_MEASUREMENT``; a non-finite ``a_safe`` row gives a zero command for that robot and
``INVALID_COMMAND``. The output is never NaN.
"""

from __future__ import annotations

import math
import time
from dataclasses import dataclass
from enum import StrEnum

import numpy as np
import scipy.linalg

from sim.scenario import Dynamics


class MecStatus(StrEnum):
    """What the compensator did this tick (the worst case over robots)."""

    OK = "ok"
    RESET = "reset"                             # first tick or new robot count: no estimate yet
    CLIPPED = "clipped"                         # a compensated command hit the actuator limit
    INVALID_MEASUREMENT = "invalid_measurement"  # some velocity was not finite: estimate held
    INVALID_COMMAND = "invalid_command"          # some a_safe was not finite: zero command sent


@dataclass(frozen=True)
class MecConfig:
    """Noise levels of the disturbance observer.

    Attributes:
        velocity_noise: sigma_y, standard deviation of the measured velocity [m/s].
        velocity_process_noise: sigma_v, unmodelled velocity change per tick [m/s].
        disturbance_rate: sigma_d, change of the disturbance per tick [m/s^2].
        max_disturbance: bound on |d_hat| [m/s^2] (None: the actuator limit), against wind-up
            while a robot rides its speed limit.
    """

    velocity_noise: float = 0.005
    velocity_process_noise: float = 0.002
    disturbance_rate: float = 0.2
    max_disturbance: float | None = None

    def __post_init__(self) -> None:
        for name in ("velocity_noise", "velocity_process_noise", "disturbance_rate"):
            value = getattr(self, name)
            if not (isinstance(value, int | float) and math.isfinite(value) and value > 0):
                raise ValueError(f"mec.{name} must be a positive finite number, got {value!r}")
        if self.max_disturbance is not None and not (
                math.isfinite(self.max_disturbance) and self.max_disturbance > 0):
            raise ValueError(f"mec.max_disturbance must be positive or None, got {self.max_disturbance!r}")


def observer_model(dynamics: Dynamics, config: MecConfig) -> tuple[np.ndarray, ...]:
    """``(F, B, H, Q, R)`` of the per-axis model in the module docstring."""
    dt, c = dynamics.dt, dynamics.damping
    f = np.array([[1.0 - c * dt, dt], [0.0, 1.0]])
    b = np.array([[dt], [0.0]])
    h = np.array([[1.0, 0.0]])
    q = np.diag([config.velocity_process_noise**2, config.disturbance_rate**2])
    r = np.array([[config.velocity_noise**2]])
    return f, b, h, q, r


def steady_state_gain(dynamics: Dynamics, config: MecConfig) -> np.ndarray:
    """The steady-state Kalman gain ``(K_v, K_d)`` (2,) of the per-axis observer."""
    f, _, h, q, r = observer_model(dynamics, config)
    p = scipy.linalg.solve_discrete_are(f.T, h.T, q, r)
    return (p @ h.T / (h @ p @ h.T + r)).ravel()


def _clip_norm(x: np.ndarray, limit: float) -> tuple[np.ndarray, np.ndarray]:
    """Rows of (N, 2) ``x`` scaled down to norm <= limit, and (N,) which rows were scaled."""
    norm = np.hypot(x[:, 0], x[:, 1])
    clipped = norm > limit
    if not clipped.any():
        return x, clipped
    return x * np.minimum(1.0, limit / np.maximum(norm, 1e-300))[:, None], clipped


@dataclass
class MecResult:
    """One tick of the compensator for N robots.

    Attributes:
        a_cmd: (N, 2) compensated command to send [m/s^2], finite, within the actuator limit.
        d_hat: (N, 2) estimated acceleration disturbance [m/s^2].
        status: see :class:`MecStatus`.
        time_s: time of the call [s].
    """

    a_cmd: np.ndarray
    d_hat: np.ndarray
    status: MecStatus
    time_s: float


class ModelErrorCompensator:
    """Stacked steady-state Kalman disturbance observer for N robots (see the module docstring).

    Call :meth:`step` once per control tick with the velocities measured at the start of the tick
    and the safe acceleration to realise; send the returned ``a_cmd``.
    """

    def __init__(self, dynamics: Dynamics, config: MecConfig | None = None):
        self.dynamics = dynamics
        self.config = config or MecConfig()
        self.gain = steady_state_gain(dynamics, self.config)
        self.max_disturbance = (self.config.max_disturbance if self.config.max_disturbance is not None
                                else dynamics.accel_limit)
        self.v_hat: np.ndarray | None = None
        self.d_hat: np.ndarray | None = None
        self.u_prev: np.ndarray | None = None

    def reset(self) -> None:
        """Forget the estimate (the next :meth:`step` starts afresh)."""
        self.v_hat = self.d_hat = self.u_prev = None

    def step(self, velocity: np.ndarray, a_safe: np.ndarray) -> MecResult:
        """Update the estimate with measured (N, 2) velocities [m/s] and compensate (N, 2) ``a_safe``."""
        start = time.perf_counter()
        vel = np.asarray(velocity, dtype=np.float64)
        target = np.asarray(a_safe, dtype=np.float64)
        if vel.ndim != 2 or vel.shape[1] != 2 or target.shape != vel.shape:
            raise ValueError(f"ModelErrorCompensator.step: velocity and a_safe must both have shape "
                             f"(num_robots, 2), got {vel.shape} and {target.shape}")
        n = len(vel)
        all_valid = bool(np.isfinite(vel).all())          # the common case: no per-row masking
        valid = all_valid or np.isfinite(vel).all(axis=1)
        status = MecStatus.OK
        if self.d_hat is None or len(self.d_hat) != n:
            self.v_hat = vel.copy() if all_valid else np.where(valid[:, None], vel, 0.0)
            self.d_hat = np.zeros((n, 2))
            status = MecStatus.RESET
        else:
            dt, c = self.dynamics.dt, self.dynamics.damping
            v_pred = (1.0 - c * dt) * self.v_hat + dt * (self.u_prev + self.d_hat)
            innovation = vel - v_pred
            if not all_valid:
                innovation = np.where(valid[:, None], innovation, 0.0)
            self.v_hat = v_pred + self.gain[0] * innovation
            self.d_hat, _ = _clip_norm(self.d_hat + self.gain[1] * innovation, self.max_disturbance)
        good_all = bool(np.isfinite(target).all())
        desired = target - self.d_hat
        if not good_all:
            desired = np.where(np.isfinite(target).all(axis=1)[:, None], desired, 0.0)
        a_cmd, clipped = _clip_norm(desired, self.dynamics.accel_limit)
        self.u_prev = a_cmd
        if not good_all:
            status = MecStatus.INVALID_COMMAND
        elif not all_valid:
            status = MecStatus.INVALID_MEASUREMENT
        elif status is MecStatus.OK and clipped.any():
            status = MecStatus.CLIPPED
        return MecResult(a_cmd=a_cmd, d_hat=self.d_hat.copy(), status=status,
                         time_s=time.perf_counter() - start)
