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

    predict:    v^- = clip_norm((1 - c dt) v_hat + dt (u_prev + d_hat), speed_limit),   d^- = d_hat
    update:     e = y - v^-,   v_hat = v^- + K_v e,   d_hat = clip_norm(d^- + K_d e, max_disturbance)
    compensate: u = clip_norm(a_safe - c, accel_limit),   c = d_hat shrunk by its noise (Noise)

so the plant achieves ``u + d ~= a_safe``: it follows the nominal model under the safe command.
A gain error (a plant achieving only ``g u``) is the disturbance ``d = (g - 1) u``; the loop then
settles at ``u = a_safe / g`` unless that exceeds the actuator limit (status ``CLIPPED``).
With the default noise levels the closed-loop estimator poles are at |0.34| and ``d_hat``
follows a step to within 5 % from the second tick after it (see the tests for the hand-check).

**Delay.** A command sent at tick k may act only at tick k + delta (transport, actuation). An
observer that feeds ``u_{k-1}`` into the prediction of a robot that ran ``u_{k-1-delta}`` reads
the difference of the two commands as a disturbance and feeds it back: at one tick of delay the
loop oscillated and tracked 10x worse than no compensation. So the compensator runs a bank of
observers side by side, one per delay hypothesis ``delta = 0 .. max_delay_ticks``, each with the
prediction ``v^- = (1 - c dt) v_hat + dt (u_{k-1-delta} + d_hat)`` on the commands it sent, and
scores each by its exponentially forgotten squared innovation
``J_delta <- lambda J_delta + |e_delta|^2``. Per robot, one hypothesis is in charge (first
``delta = 0``): it supplies ``d_hat`` and is the measured delay (:attr:`MecResult.delay_ticks`).
Another takes over when its score is below ``switch_ratio`` times the one in charge: in the first
ticks after a disturbance step a delayed command and the step look alike, and the hysteresis
keeps the bank from chasing that; while commands are steady all hypotheses agree, and once
they change the right one separates within a few ticks.

**Gate.** When even the best hypothesis explains the velocity badly (its mean squared
innovation per axis above ``gate_ratio`` times the innovation variance the Kalman model expects,
``H P H^T + R``: contacts, a delay beyond the bank, a bad model), that robot's compensation is
switched off (``d_hat`` is not applied, status ``GATED``) until the score falls back below it.

**Noise.** A gain designed for ``sigma_y`` = 5 mm/s turns 2 cm/s of velocity noise into
``d_hat`` noise of several tenths of m/s^2, which the compensation then injects (tracking became
worse than without it). So each robot's observer measures its own noise. The innovations
would mix noise with model error (a gain error is a disturbance that changes with the command),
so it uses the one-step residual ``r_k = y_k - (1 - c dt) y_{k-1} - dt u`` (``u`` the command
of the hypothesis in charge), which is ``dt d + n_k - (1 - c dt) n_{k-1}``: its change from tick
to tick has the variance ``(1 + (2 - c dt)^2 + (1 - c dt)^2) sigma^2`` plus what a changing
disturbance adds (small: ``dt`` times its change). Averaged (a plain mean over the first ticks,
then forgetting ``NOISE_FORGET``), it selects the level ``sigma_y 2^l`` nearest to it (in
ratio), and with it that level's steady-state gain. Even then an estimate
of a disturbance that is not there wanders by ``sigma_dhat``, the standard deviation that the
level's measurement noise alone gives ``d_hat`` (the steady state of
``e' = (I - K H) F e - K n``, a discrete Lyapunov equation), and compensating it drives the robot on a random
walk: with 2 cm/s of noise the MEC tracked 30 mm worse than none. So only the part of ``d_hat``
beyond ``SIGNIFICANCE`` = 5.26 standard deviations of the wander that the measured noise
``sigma^`` gives the gain in use, in excess of what the design noise gives it, is compensated
(a soft threshold on its norm; none at or below the design noise, so a gain error is
compensated in full there; ``w_l = sigma_dhat,l / sigma_y,l``, the wander per unit noise)::

    c = d_hat max(0, 1 - theta / |d_hat|),   theta = k w_l sqrt(max(sigma^2 - sigma_y^2, 0))

The norm of a wander of ``sigma`` per axis is Rayleigh, ``P(|d_hat| > k sigma) = exp(-k^2 / 2)``,
so ``k = sqrt(2 ln 1e6) = 5.26`` lets pure wander through once in a million robot-ticks
(``FALSE_ALARM``). ``k = 4`` (once in 3000: about once an episode of 5 robots) had the MEC
track 1.86 mm worse than none under 2 cm/s of noise (``tracking_error_mm("noise", 30, 100)`` of
bench/_safety_conditions.py), 5.26 1.03 mm. Without noise the threshold is 0 but for the change
of a gain error's disturbance. In the first ticks the measured noise rests on a few residual
changes (each a chi-square of 2 degrees of freedom, so after ``n`` of them the variance estimate
has a relative standard deviation of ``1 / sqrt(n)``); the threshold uses the upper bound
``sigma^2 (1 + NOISE_UPPER_SIGMAS / sqrt(n))``, ``NOISE_UPPER_SIGMAS`` = 3 standard deviations
of the estimate. Measured (``tracking_error_mm(name, 12, 0)`` of bench/_safety_conditions.py and
part (b) of bench/safety.py, the open-loop gain-0.7 bench, 12 episodes): with 2 standard
deviations a few lucky residual changes read a noisy robot as quiet, and under pure noise the MEC
tracked 0.50 mm against 0.43 without it; with 2.5 0.46; with 3 0.43, as without, while part (b)
keeps a 61 % cut (62 % with 2) and gain 0.7 with 100 ms of delay 19.6 against 155 mm (16.0 with
2; 4 standard deviations gave 57). Waiting for 2 residual changes before compensating instead
cut part (b) by only 40 %.
    u = clip_norm(a_safe - c, accel_limit)

With 2 cm/s of noise a robot with a real gain error is then left uncompensated unless the error
stands out of the noise: less compensation, never a random walk. A robot's first
``WARMUP_UPDATES`` measurements only estimate (its noise level is not known before).

A row without a new measurement (NaN: dropped on the way) only predicts, so what
:meth:`~ModelErrorCompensator.update` returns for it is a prediction to now, through the
commands of the hypothesis in charge. A caller that carries the robot on from its last
measurement itself, through the commands sent since (the latency prediction of
:mod:`controllers.safety.latency` does), reads :attr:`~ModelErrorCompensator.v_measured`
instead: the estimate as of that measurement. Fed the prediction to now, it counts those
commands twice.

Estimates are keyed by robot id (``ids`` of :meth:`ModelErrorCompensator.step`): a robot that
leaves takes its estimate with it, a robot that joins starts afresh, and rows may reorder.

A robot whose velocity is not finite, or faster than ``PLAUSIBLE_SPEED`` times the speed limit
(a glitch no robot can reach: one 1000 m/s reading held its noise estimate up for the rest of
an episode, one of 1e160 overflowed its score and gated it for good), keeps its prediction (no
update) and the tick reports ``INVALID_MEASUREMENT``; a non-finite ``a_safe`` row gives a zero command for that robot and
``INVALID_COMMAND``. The output is never NaN.
"""

from __future__ import annotations

import dataclasses
import math
import time
from dataclasses import dataclass
from enum import StrEnum

import numpy as np
import scipy.linalg

from controllers import mec_kernels
from controllers.array_kernels import all_rows_within
from controllers.checks import check_numbers
from controllers.jit import f64
from sim.scenario import Dynamics

NOISE_LEVELS = 6        # velocity noise levels sigma_y * 2^l, l = 0..5 (up to 32 sigma_y)
NOISE_FORGET = 0.95     # forgetting factor of the innovation variance that picks the level
FALSE_ALARM = 1e-6      # chance per robot and tick that wander alone exceeds the threshold
SIGNIFICANCE = math.sqrt(-2.0 * math.log(FALSE_ALARM))   # 5.26: |d_hat| of pure wander is Rayleigh
WARMUP_UPDATES = 1      # a robot's first updates only estimate: its noise level is not known yet
PLAUSIBLE_SPEED = 10.0  # a measured speed above this many speed limits is a glitch, not a measurement
NOISE_UPPER_SIGMAS = 3.0  # the noise variance counted: its estimate + 3 of its standard deviations


class MecStatus(StrEnum):
    """What the compensator did this tick (the worst case over robots)."""

    OK = "ok"
    RESET = "reset"                             # first tick or new robot count: no estimate yet
    CLIPPED = "clipped"                         # a compensated command hit the actuator limit
    INVALID_MEASUREMENT = "invalid_measurement"  # some velocity was not finite: estimate held
    INVALID_COMMAND = "invalid_command"          # some a_safe was not finite: zero command sent
    GATED = "gated"                              # some robot's model is off: not compensated


@dataclass(frozen=True)
class MecConfig:
    """Noise levels of the disturbance observer.

    Attributes:
        velocity_noise: sigma_y, standard deviation of the measured velocity [m/s].
        velocity_process_noise: sigma_v, unmodelled velocity change per tick [m/s].
        disturbance_rate: sigma_d, change of the disturbance per tick [m/s^2].
        max_disturbance: bound on |d_hat| [m/s^2] (None: the actuator limit), against wind-up
            while a robot rides its speed limit.
        max_delay_ticks: the largest command delay in the bank of observers [ticks] (3: 150 ms
            at 20 Hz).
        forget: ``lambda``, forgetting factor of the innovation scores, in (0, 1).
        gate_ratio: compensation is off while the best score exceeds this many times the
            expected innovation variance (module docstring, Gate).
        switch_ratio: another hypothesis takes charge when its score is below this fraction of
            the score of the one in charge, in (0, 1].
        adapt_noise: measure each robot's velocity noise and adapt gain and compensation to it
            (module docstring, Noise); False: the fixed design gain, every ``d_hat`` compensated.
    """

    velocity_noise: float = 0.005
    velocity_process_noise: float = 0.002
    disturbance_rate: float = 0.2
    max_disturbance: float | None = None
    max_delay_ticks: int = 3
    forget: float = 0.7
    gate_ratio: float = 50.0
    switch_ratio: float = 0.1
    adapt_noise: bool = True

    def __post_init__(self) -> None:
        check_numbers(self, ("velocity_noise", "velocity_process_noise", "disturbance_rate"), "mec", ValueError,
                      positive=True)
        if self.max_disturbance is not None and not (
                math.isfinite(self.max_disturbance) and self.max_disturbance > 0):
            raise ValueError(f"mec.max_disturbance must be positive or None, got {self.max_disturbance!r}")
        if isinstance(self.max_delay_ticks, bool) or not isinstance(self.max_delay_ticks, int) \
                or not 0 <= self.max_delay_ticks <= 20:
            raise ValueError(f"mec.max_delay_ticks must be an integer in 0..20, got {self.max_delay_ticks!r}")
        if not 0 < self.forget < 1:
            raise ValueError(f"mec.forget must be in (0, 1), got {self.forget!r}")
        if not self.gate_ratio > 0:
            raise ValueError(f"mec.gate_ratio must be > 0, got {self.gate_ratio!r}")
        if not 0 < self.switch_ratio <= 1:
            raise ValueError(f"mec.switch_ratio must be in (0, 1], got {self.switch_ratio!r}")


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
    return _riccati(dynamics, config)[0]


def _riccati(dynamics: Dynamics, config: MecConfig) -> tuple[np.ndarray, float, float]:
    """Steady-state gain (2,), innovation variance ``H P H^T + R`` [(m/s)^2] per axis and the
    standard deviation of ``d_hat`` driven by the measurement noise alone [m/s^2]."""
    f, _, h, q, r = observer_model(dynamics, config)
    p = scipy.linalg.solve_discrete_are(f.T, h.T, q, r)
    s = float((h @ p @ h.T + r)[0, 0])
    k = p @ h.T / s
    # the estimate's wander under measurement noise alone: e' = (I - K H) F e - K n
    closed = (np.eye(2) - k @ h) @ f
    wander = scipy.linalg.solve_discrete_lyapunov(closed, k @ k.T * r[0, 0])
    return k.ravel(), s, float(np.sqrt(wander[1, 1]))


@dataclass
class MecResult:
    """One tick of the compensator for N robots.

    Attributes:
        a_cmd: (N, 2) compensated command to send [m/s^2], finite, within the actuator limit.
        d_hat: (N, 2) estimated acceleration disturbance [m/s^2] (of the best hypothesis).
        status: see :class:`MecStatus`.
        time_s: time of the call [s].
        delay_ticks: (N,) the delay hypothesis that explains each robot best [ticks].
        gated: (N,) bool, robots whose compensation is off this tick (module docstring, Gate).
        compensation: (N, 2) what was subtracted from ``a_safe``: ``d_hat`` shrunk by its own
            noise, 0 where gated [m/s^2].
    """

    a_cmd: np.ndarray
    d_hat: np.ndarray
    status: MecStatus
    time_s: float
    delay_ticks: np.ndarray = None      # type: ignore[assignment]
    gated: np.ndarray = None            # type: ignore[assignment]
    compensation: np.ndarray = None     # type: ignore[assignment]


class ModelErrorCompensator:
    """Bank of stacked steady-state Kalman disturbance observers (see the module docstring).

    Call :meth:`step` once per control tick with the velocities measured at the start of the tick,
    the safe acceleration to realise and the robots' ids; send the returned ``a_cmd``. A command
    changed after the step (e.g. by a re-check) is told with :meth:`replace_last_command`.
    """

    def __init__(self, dynamics: Dynamics, config: MecConfig | None = None):
        self.dynamics = dynamics
        self.config = config or MecConfig()
        # noise levels the observer adapts to, sigma_y * 2^l (module docstring, Noise)
        levels = [_riccati(dynamics, dataclasses.replace(self.config, velocity_noise=self.config.velocity_noise * 2**k))
                  for k in range(NOISE_LEVELS if self.config.adapt_noise else 1)]
        self.level_gain = np.array([g for g, _, _ in levels])                # (L, 2)
        self.level_var = np.array([v for _, v, _ in levels])                 # (L,)
        self.level_d_std = np.array([sd for _, _, sd in levels])             # (L,) [m/s^2]
        self.level_noise_var = (self.config.velocity_noise * 2.0 ** np.arange(len(levels))) ** 2
        self.level_wander = self.level_d_std / np.sqrt(self.level_noise_var)   # d_hat std per unit noise
        self.level_midpoints = np.sqrt(self.level_noise_var[:-1] * self.level_noise_var[1:])
        self.max_disturbance = (self.config.max_disturbance if self.config.max_disturbance is not None
                                else dynamics.accel_limit)
        self.hypotheses = self.config.max_delay_ticks + 1
        self.gate_level = self.config.gate_ratio * 2.0 * self.level_var / (1.0 - self.config.forget)
        c_dt = dynamics.damping * dynamics.dt
        # the kernels' scalars, typed once (a new type would compile a new kernel mid-run)
        self._observe_consts = tuple(float(x) for x in (
            dynamics.dt, 1.0 - c_dt, 1.0 + (2.0 - c_dt) ** 2 + (1.0 - c_dt) ** 2, dynamics.speed_limit,
            self.max_disturbance, self.config.forget, self.config.switch_ratio, NOISE_FORGET))
        self._compensate_consts = (float(self.config.velocity_noise**2), float(SIGNIFICANCE),
                                   float(NOISE_UPPER_SIGMAS), int(WARMUP_UPDATES), bool(self.config.adapt_noise),
                                   float(dynamics.accel_limit))
        self.reset()

    def reset(self) -> None:
        """Forget every estimate (the next :meth:`step` starts afresh)."""
        self.ids: tuple[str, ...] | None = None
        self.v_hat = self.d_hat = self.score = self.sent = self.charge = self.level = None
        self.noise_var = self.noise_count = self.y_prev = self.r_prev = None
        self.v_measured: np.ndarray | None = None

    def _align(self, ids: tuple[str, ...], vel: np.ndarray, valid: np.ndarray) -> np.ndarray:
        """Re-key the estimates to ``ids``; (N,) bool of robots that start afresh this tick."""
        n, b = len(ids), self.hypotheses
        fresh = np.ones(n, dtype=bool)
        v0 = np.where(valid[:, None], vel, 0.0)
        v_hat, d_hat = np.repeat(v0[None], b, axis=0), np.zeros((b, n, 2))
        score, sent = np.zeros((b, n)), np.zeros((b, n, 2))
        charge = np.zeros(n, dtype=np.int64)
        level, noise_var = np.zeros(n, dtype=np.int64), np.full(n, self.config.velocity_noise**2)
        noise_count = np.zeros(n)
        y_prev, r_prev = np.where(valid[:, None], vel, np.nan), np.full((n, 2), np.nan)
        v_measured = v0.copy()
        if self.ids is not None:
            old = {rid: k for k, rid in enumerate(self.ids)}
            rows = [(k, old[rid]) for k, rid in enumerate(ids) if rid in old]
            if rows:
                new, prev = (np.array(x) for x in zip(*rows, strict=True))
                v_hat[:, new], d_hat[:, new] = self.v_hat[:, prev], self.d_hat[:, prev]
                score[:, new], sent[:, new] = self.score[:, prev], self.sent[:, prev]
                charge[new], level[new], noise_var[new] = self.charge[prev], self.level[prev], self.noise_var[prev]
                noise_count[new] = self.noise_count[prev]
                y_prev[new], r_prev[new] = self.y_prev[prev], self.r_prev[prev]
                v_measured[new] = self.v_measured[prev]
                fresh[new] = False
        self.ids, self.v_hat, self.d_hat, self.score, self.sent = ids, v_hat, d_hat, score, sent
        self.charge, self.level, self.noise_var, self.noise_count = charge, level, noise_var, noise_count
        self.y_prev, self.r_prev, self.v_measured = y_prev, r_prev, v_measured
        return fresh

    def step(self, velocity: np.ndarray, a_safe: np.ndarray,
             ids: tuple[str, ...] | None = None) -> MecResult:
        """:meth:`update` with measured (N, 2) velocities [m/s], then :meth:`compensate` (N, 2)
        ``a_safe``; ``ids`` names the robot of each row (default ``r0 .. r{N-1}``)."""
        self.update(velocity, ids)
        return self.compensate(a_safe)

    def update(self, velocity: np.ndarray, ids: tuple[str, ...] | None = None) -> np.ndarray:
        """Take this tick's measured (N, 2) velocities (NaN rows: no new measurement, predict
        only); returns the (N, 2) velocity estimate of the hypothesis in charge [m/s], now.
        :attr:`v_measured` keeps, per robot, that estimate as of its last measurement."""
        start = time.perf_counter()
        vel = np.asarray(velocity, dtype=np.float64)
        if vel.ndim != 2 or vel.shape[1] != 2:
            raise ValueError(f"ModelErrorCompensator.update: velocity must have shape (num_robots, 2), "
                             f"got {vel.shape}")
        n = len(vel)
        ids = tuple(ids) if ids is not None else tuple(f"r{i}" for i in range(n))
        if len(ids) != n:
            raise ValueError(f"ModelErrorCompensator.update: {len(ids)} ids for {n} robots")
        vel = f64(vel)
        plausible = PLAUSIBLE_SPEED * self.dynamics.speed_limit
        self._all_valid = all_rows_within(vel, plausible)
        valid = (np.ones(n, dtype=bool) if self._all_valid
                 else np.isfinite(vel).all(axis=1) & (np.hypot(vel[:, 0], vel[:, 1]) <= plausible))
        fresh = self._align(ids, vel, valid) if ids != self.ids else np.zeros(n, dtype=bool)
        self._reset_tick = np.count_nonzero(fresh) == n
        if not self._all_valid:
            vel = np.where(valid[:, None], vel, 0.0)
        v_out = self._observe(vel, valid & ~fresh)
        self.v_measured = v_out if self._all_valid else np.where(valid[:, None], v_out, self.v_measured)
        self._update_s = time.perf_counter() - start
        return v_out

    def _observe(self, vel: np.ndarray, update: np.ndarray) -> np.ndarray:
        """Predict/update every hypothesis for the (N,) robots in ``update`` (none on a reset
        tick), then choose the one in charge; (N, 2) velocity estimate of that one. Compiled
        (:func:`controllers.mec_kernels.observe`); ``vel`` (N, 2) is 0 where not ``update``."""
        v_out = np.empty((len(vel), 2))
        mec_kernels.observe(np.ascontiguousarray(vel), update, not self._reset_tick, self.v_hat, self.d_hat,
                            self.score, self.sent, self.charge, self.level, self.noise_var, self.noise_count,
                            self.y_prev, self.r_prev, self.level_gain, self.level_midpoints,
                            *self._observe_consts, v_out)
        return v_out

    def compensate(self, a_safe: np.ndarray) -> MecResult:
        """``a_cmd = clip_norm(a_safe - c, accel_limit)`` for (N, 2) ``a_safe`` (after :meth:`update`;
        ``time_s`` of the result is the time of both calls)."""
        start = time.perf_counter()
        target = np.asarray(a_safe, dtype=np.float64)
        if self.ids is None or target.shape != (len(self.ids), 2):
            raise ValueError(f"ModelErrorCompensator.compensate: velocity and a_safe must both have "
                             f"shape (num_robots, 2) = ({0 if self.ids is None else len(self.ids)}, 2), "
                             f"got {target.shape}; call update first")
        a_cmd, d_hat, gated, compensation, good_all, clipped = self._compensate(target)
        status = MecStatus.RESET if self._reset_tick else MecStatus.OK
        if not good_all:
            status = MecStatus.INVALID_COMMAND
        elif not self._all_valid:
            status = MecStatus.INVALID_MEASUREMENT
        elif status is MecStatus.OK and np.count_nonzero(gated):
            status = MecStatus.GATED
        elif status is MecStatus.OK and clipped:
            status = MecStatus.CLIPPED
        return MecResult(a_cmd=a_cmd, d_hat=d_hat, status=status,
                         time_s=self._update_s + time.perf_counter() - start, delay_ticks=self.charge.copy(),
                         gated=gated, compensation=compensation)

    def _compensate(self, target: np.ndarray) -> tuple[np.ndarray, ...]:
        """``(a_cmd, d_hat, gated, compensation, all targets finite, some command clipped)`` for
        (N, 2) ``target`` (module docstring, Noise), and ``a_cmd`` recorded as the newest command
        sent. Compiled (:func:`controllers.mec_kernels.compensate`)."""
        n = len(target)
        a_cmd, d_hat, compensation = np.empty((n, 2)), np.empty((n, 2)), np.empty((n, 2))
        gated = np.empty(n, dtype=bool)
        good_all, clipped = mec_kernels.compensate(
            np.ascontiguousarray(target), self.d_hat, self.score, self.sent, self.charge, self.level,
            self.noise_var, self.noise_count, self.gate_level, self.level_wander, *self._compensate_consts,
            a_cmd, d_hat, gated, compensation)
        return a_cmd, d_hat, gated, compensation, good_all, clipped

    def replace_last_command(self, a_cmd: np.ndarray, shift: bool = False) -> None:
        """Tell the observers the (N, 2) command actually sent this tick (``shift``: a new tick)."""
        if shift:
            self.sent[:-1] = self.sent[1:]
        self.sent[-1] = a_cmd
