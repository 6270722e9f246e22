r"""Latency in the safety filter: predict every robot over the delay, tighten by what is unknown.

A command computed now acts on the robot only after a latency: the age ``tau_i`` of the state
it was computed from (transport of the STATE, a lost update) plus the command's own delay ``L``
(transport of the CMD, the robot's actuation), which may jitter tick to tick. Meanwhile the
robot goes on executing commands that are already in flight. A barrier evaluated at the
measured state therefore judges a state the robot has left; with a delay of two ticks that made
the filter collide in every adversarial episode.

**Prediction.** The filter is evaluated at the state where the new command takes effect. When
the fleet says which commands each robot had yet to act on when it was measured
(``FleetState.commands_pending``: ``m_i``, from the wire's ``last_cmd_seq``), that is after
exactly those: the nominal model (:meth:`sim.scenario.Dynamics.step_np`) run from the measured
``(p_i, v_i)`` through the last ``m_i`` accelerations this controller asked of robot ``i``
(oldest first)::

    (p^_i, v^_i) = step^{m_i}(p_i, v_i; u_{k-m_i}, ..., u_{k-1})

exact (to rounding, tested) while the link keeps its delay. Without the count, ``m_i = h_i =
ceil((tau_i + L) / dt)``: the latest the command can act, through as many commands as the bound
allows (zeros before the first one: a robot at rest holds no command). That counts commands that
already acted a second time when the delay is shorter than the bound: with the count, 0 of 340
adversarial episodes touch at 1 tick of delay under the 3-tick bound, 2 without; predicting
on to ``h_i`` past the pending commands (holding the newest, or the centre of the window) made
the delay-free conditions touch in 17-131 of 340, because the new command then acts where the
prediction did not look. A robot with more pending commands than ``h_i`` acts on commands older
than the bound allows (its command link is down): it is not listening (below).

**Tightening.** What the prediction cannot know, per robot:

* which of the recent commands acted at each of the ``h_i`` ticks until the new one does (the
  delay is only bounded: a jittering delay runs newer commands earlier, skips some, holds
  others), so each tick's acceleration may differ from the predicted one by up to the spread
  ``D_i`` of the window: the diagonal of the box around the last ``max(h_i, m_i + 1)`` commands
  (those the bound allows in flight, and the one the robot acts on now) and the new nominal
  command;
* the model error left after the compensator, ``|a_achieved - a_asked| <= delta_a``
  (``accel_uncertainty``);
* measurement noise bounded by ``sigma_p``, ``sigma_v`` (``position_noise``, ``velocity_noise``);
  the stack adds to ``sigma_p`` of each robot the standard deviation its position estimator
  leaves (:mod:`controllers.position_estimator`: 0 on an exact link, ~3 mm under 1 cm of noise),
  and to the approach allowance ``measured_velocity_sigmas`` (2) standard deviations of the
  velocity noise the compensator measures per robot (0 on an exact link). Without it, with the
  static rows counting on ``a_box / sqrt(2)`` (:mod:`controllers.safety.barrier`), a robot under
  2 cm / 4 cm/s of measurement noise crept into the object in one of the 30 episodes of
  ``tests/stack/test_link_safety.py``'s noise test; with one or more, none did.

With ``A_i = D_i + delta_a`` the semi-implicit Euler steps give the bounds after ``h`` ticks::

    e_v,i = A_i dt h + sigma_v                                       [m/s]
    e_p,i = A_i dt^2 h (h + 1) / 2 + sigma_v dt h + sigma_p          [m]

Without the pending count, those bounds hold whichever commands of the window acted at each
tick, in any order and with repeats (tested with hypothesis); with it, they bound the order of
the pending ones, not the drift of a command that arrives later than the link showed. They are worst cases, and the spread is weighted by
``spread_weight`` (``A_i = w D_i + delta_a``): a policy reacting to noisy measurements changes
its command every tick, and the full worst case then kept robots off targets that lie 3 cm from
the object and 4.5 cm from each other. Measured on the pymunk conditions of ``bench/safety.py``
(adversarial episodes of 3-16 robots, 48 a setting, and 12 scripted paper-3/4/5 episodes):
``w = 0`` collided in 8 of 48 at one tick of delay (the prediction over 3 ticks then double-counts
commands that already acted), ``w = 0.25`` in none at 1, 2 or 3 ticks, jittering delay or dropped
states, with the scripted controller succeeding as often as without the filter; ``w = 0.5``
cost a third of the scripted successes. 0.25 is the default. A robot whose observed delay (pending
commands less the ticks its state aged) changed within the last few ticks, or whose pending
count is unknown, gets ``jitter_spread_weight`` = 0.5 instead: a delay that jitters between 1
and 3 ticks, the robot acting on the newest command that arrived, touched in 38 of 340
adversarial episodes at 0.25, in 10 at 0.5, and in more at 0.75 (13) and 1 (17), where the
tightening leaves the QP infeasible more often. What remains is a command skipped: a newer one
overtook it, so a brake the prediction counted on never acted. A robot with a playout buffer
(it acts on each command exactly ``L`` after it was sent; the CMD's ``state_seq`` names the
tick it answers) turns any delay up to ``L`` into exactly ``L``: 0 of 340 then.

The filter then grows robot ``i``'s disc by ``e_p,i`` (every signed distance of a row drops by
the sum over its robots) and counts ``e_v,i`` as approach speed (``s_dot`` in ``h`` drops by the
sum), see :meth:`controllers.safety.fused.FusedScene.terms`. The barrier and the QP are
otherwise those of :mod:`controllers.safety.barrier`.

**Robots that are not listening.** A robot whose state is older than ``stale_after_s``, that
has more pending commands than ``h_i`` (:meth:`LatencyPredictor.late`; the stack sends it
BRAKE), or that has left the link (``FleetState.silent``), cannot be relied on to obey: it is kept as a fixed
obstacle (its acceleration is not a decision variable; rows between two fixed robots are
dropped; a row with one fixed robot counts on the other robot's braking alone) at its
estimate, with its disc grown by its reachable set since that state: the disc of radius ``R``
round ``centre`` that holds it ``t`` after that state, whatever it was asked (:func:`reach`, the
maths in :mod:`controllers.safety.reach`), taken where the new command acts::

    grow = R(tau + L) + sigma_p,   closing = dR/dt + sigma_v,   velocity = dcentre/dt

so a robot silent for good stays an obstacle of bounded size where it must have stopped.

That ball ignores what the robot was asked. Where the stack passes ``now`` and the history
holds every command the robot may still act on (the pending ones and the one it was acting
on), a robot stale by age, silent or of unknown state is bounded instead by the branches of
those commands (:mod:`controllers.safety.silent_reach`: it acted on them in order until it
stopped hearing, held the last for at most ``watchdog_s``, then braked), computed once per
last state; the ball stays for a robot never commanded and for a robot :meth:`late` (its
state is fresh: the ball from it is small). Once such a robot must be at rest, the filter takes
a few narrow discs round its branches' rest points instead of the one (:meth:`SilentPaths.cover`,
:attr:`Prediction.covers`), and the policy and docking are shown it at its disc's centre
(:meth:`LatencyPredictor.dead_reckoned`), not at its last report; a tracker's sighting taken
once it is at rest narrows those discs (``predict(seen=)``; silent_reach, Seen at rest). What
each step gained on the frozen-robot condition: docs/safety.md, "A silent robot seen where it
stopped" and "A silent robot the tracker sees".

**Braking a robot that is not listening.** The stack sends such a robot BRAKE every tick; one
that still hears it acts on it after the commands in flight. A robot that takes BRAKE as an
acceleration to achieve (a pymunk robot, which has no braking law of its own) must get the
braking law at the velocity it will have then: its measured velocity carried through the
commands it had yet to act on when measured, as a listening robot is carried (``m_i``
commands, ``h_i`` where the count is unknown), the brakes already sent to it among them
(:attr:`Prediction.brake_vel` of its row; a row with more of them than the history holds keeps
its disc's velocity, at rest by then). From the last measured velocity itself, every BRAKE
cancels the same velocity, 0.15 s or more behind the robot: on an exact link a robot at
0.2 m/s along +y that had been pushed along -x since was never braked along x and turned round
along y on the fourth BRAKE (``tests/stack/test_pipeline.py``); with jitter, noise and drops
at once a robot sliding round the object's corner, its velocity turned from (-0.06, 0.22) to
(-0.17, 0.13) m/s by the commands in flight, was pushed at (0.25, -0.97) m/s^2 into the face
below it for three ticks and touched (``bench/safety.py``, seed 223).

**Robots whose state is late.** A robot whose state is a tick or more old but not stale may
still listen (its updates were lost) or may have stopped acting on commands at its last state
(it froze): the prediction above assumes the first. With ``cover_late`` (default) its disc
also holds the second from the first late tick: the disc it would get as an obstacle (its
branches, or the ball), taken at the time its prediction is for (``m_i`` ticks after its
state; ``h_i`` when the pending count is unknown), joins its row's ``grow`` and ``closing``
round the listening centre, which stays (:mod:`controllers.safety.late_cover` gives the maths:
``g = max(g_1, |c_2 - p| + g_2)`` and the allowance that keeps the stopped disc inside one tick
on). Before, that disc appeared only once the state was stale, at once 12-44 mm wide round a
neighbour already inside it, and a neighbour braking two or three ticks late at 70 % of its
acceleration touched (``bench/safety.py`` seeds 130 and 278 of gain 0.7, two ticks of delay and
a frozen robot).
"""

from __future__ import annotations

from collections.abc import Mapping
from typing import NamedTuple

import numpy as np

from controllers.jit import f64, require_shapes
from controllers.safety import latency_kernels
from controllers.safety.late_cover import cover_both
from controllers.safety.latency_config import LatencyConfig, LatencyConfigError
from controllers.safety.prediction import Prediction
from controllers.safety.reach import reach
from controllers.safety.silent_reach import Sighting, SilentPaths, narrowed, silent_paths
from sim.scenario import Dynamics, clip_norm


def horizon_ticks(age_s: np.ndarray, delay_s: float, dt: float) -> np.ndarray:
    """(N,) ticks ``ceil((tau + L) / dt)`` from each measurement to the new command acting."""
    return np.maximum(np.ceil((np.asarray(age_s) + delay_s) / dt - 1e-9).astype(np.int64), 0)


def row_sums(x: np.ndarray, pair_i: np.ndarray, pair_j: np.ndarray, pieces: int = 1) -> np.ndarray:
    """(K,) per-row sums of a per-robot (N,) quantity in the row layout of
    :mod:`controllers.safety.barrier`: ``x_i + x_j`` on pairs, ``x_i`` on the object rows (one per
    convex piece of the object, ``pieces`` of them per robot) and on the wall rows."""
    return np.concatenate([x[pair_i] + x[pair_j], np.repeat(x, pieces), np.repeat(x, 4)])


VELOCITY_NOISE_BOUND = 3.0
"""A measured velocity noise of standard deviation sigma counts as an error bound of 3 sigma."""


class _Stopped(NamedTuple):
    """What one :meth:`LatencyPredictor.predict` knows of every robot's last state, for bounding
    robots as obstacles: (N, 2) ``pos``, ``vel``; (N,) ``ages``, ``pending``, ``sigma_p`` and the
    spread ``weight`` of their branches; the latency bound ``delay`` [s] and ``now`` (or None)."""

    pos: np.ndarray
    vel: np.ndarray
    ages: np.ndarray
    pending: np.ndarray
    sigma_p: np.ndarray
    weight: np.ndarray
    delay: float
    now: float | None


class LatencyPredictor:
    """Keeps the accelerations asked of each robot (by id) and predicts over the latency.

    Call :meth:`predict` with the tick's measured state, filter at the returned prediction, then
    :meth:`record` what was asked of every robot this tick. Ids that appear start with an empty
    history (a robot that joins holds no command); ids that vanish are forgotten.
    """

    def __init__(self, dynamics: Dynamics, config: LatencyConfig | None = None):
        self.dynamics = dynamics
        self.config = config or LatencyConfig()
        self.depth = self._depth_for(self._max_delay(None))
        # the kernel's scalars, typed once (a new type would compile a new kernel mid-run)
        cfg = self.config
        self._kernel_consts = tuple(float(x) for x in (
            dynamics.dt, dynamics.dt**2, dynamics.speed_limit ** 2, cfg.stale_after_s, dynamics.damping, dynamics.speed_limit, dynamics.accel_limit,
            cfg.spread_weight, cfg.jitter_spread_weight, cfg.accel_uncertainty, cfg.velocity_noise))
        self.reset()

    def reset(self) -> None:
        self._ids: tuple[str, ...] = ()
        self._history = np.zeros((self.depth, 0, 2))       # oldest first
        self._braked = np.zeros((self.depth, 0), dtype=bool)  # the rows sent BRAKE
        self._recorded = np.zeros(0, dtype=np.int64)       # ticks of history per robot (<= depth)
        self._paths: dict[str, SilentPaths] = {}           # per stale robot id (silent_reach)
        self._accel_bound = np.zeros(0)                    # per robot, from its last fresh tick
        self._remembered: dict[str, float] = {}            # the same by id, for ids now away
        self._delay_seen = np.zeros(0, dtype=np.int64)     # last observed delay [ticks], -1: none
        self._jitter_left = np.zeros(0, dtype=np.int64)    # ticks the robot still counts as jittering

    def _max_delay(self, measured: float | None) -> float:
        return self.config.delay_bound(measured)

    def _depth_for(self, delay: float) -> int:
        """History rows deep enough for the commands a robot may still act on when it first
        counts as stale, at a latency bound ``delay`` [s]."""
        max_age = self.config.stale_after_s + self.dynamics.dt
        return int(horizon_ticks(np.array([max_age]), delay, self.dynamics.dt)[0]) + 2

    def _deepen(self, delay: float) -> None:
        """Grow the history for a measured bound above the configured one (older rows: nothing
        recorded), so no horizon is cut to the configured depth."""
        extra = self._depth_for(delay) - self.depth
        if extra <= 0:
            return
        n = len(self._ids)
        self._history = np.concatenate([np.zeros((extra, n, 2)), self._history])
        self._braked = np.concatenate([np.zeros((extra, n), dtype=bool), self._braked])
        self.depth += extra

    def _align(self, ids: tuple[str, ...]) -> None:
        """Re-key the rows to ``ids`` (kept for known ids; new ones: no command, any acceleration)."""
        if ids == self._ids:
            return
        old = {rid: k for k, rid in enumerate(self._ids)}
        # a robot's bound outlives a tick it is missing from (it may come back as silent)
        self._remembered.update(zip(self._ids, self._accel_bound.tolist(), strict=True))
        history = np.zeros((self.depth, len(ids), 2))
        braked = np.zeros((self.depth, len(ids)), dtype=bool)
        bound = np.array([self._remembered.get(rid, self.dynamics.accel_limit) for rid in ids])
        seen, left = np.full(len(ids), -1, dtype=np.int64), np.zeros(len(ids), dtype=np.int64)
        recorded = np.zeros(len(ids), dtype=np.int64)
        for k, rid in enumerate(ids):
            if rid in old:
                history[:, k], braked[:, k] = self._history[:, old[rid]], self._braked[:, old[rid]]
                seen[k], left[k] = self._delay_seen[old[rid]], self._jitter_left[old[rid]]
                recorded[k] = self._recorded[old[rid]]
        self._ids, self._history, self._accel_bound = ids, history, bound.reshape(len(ids))
        self._braked, self._recorded = braked, recorded
        self._delay_seen, self._jitter_left = seen, left
        self._paths = {rid: paths for rid, paths in self._paths.items() if rid in ids}

    def late(self, ages: np.ndarray, pending: np.ndarray | None, measured_delay_s: float | None = None) -> np.ndarray:
        """(N,) bool: robots whose pending commands outnumber the ticks the latency bound allows
        (``pending_i > ceil((tau_i + L) / dt)``): they act on commands older than the bound, so
        they are obstacles, not listeners (a robot whose command link is down but whose state
        still arrives)."""
        if pending is None:
            return np.zeros(len(ages), dtype=bool)
        out = np.empty(len(ages), dtype=bool)
        latency_kernels.late_rows(np.ascontiguousarray(pending, dtype=np.int64), f64(ages),
                                  float(self._max_delay(measured_delay_s)), float(self.dynamics.dt), out)
        return out

    def predict(self, ids: tuple[str, ...], pos: np.ndarray, vel: np.ndarray, ages: np.ndarray,
                a_nom: np.ndarray, measured_delay_s: float | None = None,
                fixed: np.ndarray | None = None, pending: np.ndarray | None = None,
                position_noise: np.ndarray | None = None,
                velocity_noise: np.ndarray | None = None, now: float | None = None,
                seen: Mapping[int, Sighting] | None = None) -> Prediction:
        """Prediction of (N, 2) measured states of ``ages`` (N,) [s] (module docstring).

        ``a_nom`` (N, 2) joins the window whose spread bounds the unknown order of commands;
        ``fixed`` (N,) bool marks robots that are obstacles whatever their age (unknown state,
        silent), besides those older than ``stale_after_s`` and those :meth:`late`.
        ``pending`` (N,) int: commands sent after the newest one each robot had acted on when
        measured (-1: unknown; :attr:`sim.fleet.FleetState.commands_pending`).
        ``position_noise`` (N,) [m]: a per-robot position error (an estimator's) added to
        ``position_noise`` of the config. ``velocity_noise`` (N,) [m/s]: the standard deviation
        of each robot's velocity measurement (the compensator's), for
        :attr:`Prediction.velocity_error`. ``now`` [s]: the state's time; with it, a robot that is
        stale by age or given ``fixed`` is bounded by the branches of the commands it was sent
        (:mod:`controllers.safety.silent_reach`), else by :func:`reach`; a robot whose state is
        late but not stale is grown to hold that bound too (``cover_late``). ``seen``: a tracker's
        sightings by row, which narrow such a robot's bound once its branches are at rest
        (:func:`~controllers.safety.silent_reach.narrowed`).
        """
        cfg, dyn = self.config, self.dynamics
        self._align(tuple(ids))
        delay = self._max_delay(measured_delay_s)
        self._deepen(delay)
        n = len(ages)
        pending = (np.full(n, -1, dtype=np.int64) if pending is None
                   else np.ascontiguousarray(pending, dtype=np.int64))
        given_fixed = np.zeros(n, dtype=bool) if fixed is None else np.ascontiguousarray(fixed, dtype=bool)
        sigma_p = cfg.position_noise + (np.zeros(n) if position_noise is None
                                        else np.asarray(position_noise, dtype=np.float64))
        if len(ids) != n:
            raise ValueError(f"LatencyPredictor.predict: {len(ids)} ids for {n} ages")
        require_shapes("LatencyPredictor.predict", pos=(pos, (n, 2)), vel=(vel, (n, 2)), a_nom=(a_nom, (n, 2)),
                       pending=(pending, (n,)), fixed=(given_fixed, (n,)), position_noise=(sigma_p, (n,)))
        p, v, grow, closing, fixed, h, jittering = self._listening(pos, vel, ages, a_nom, pending, given_fixed,
                                                                   sigma_p, delay)
        unsure = jittering | (pending < 0)                    # the delay may change under it
        weight = np.where(unsure, max(cfg.jitter_spread_weight, cfg.spread_weight), 0.0)
        stopped = _Stopped(pos, vel, ages, pending, np.broadcast_to(sigma_p, (n,)), weight, delay, now)
        covers: list[tuple[int, np.ndarray, np.ndarray]] = []
        if np.count_nonzero(fixed):
            covers = self._not_listening(stopped, fixed, fixed & ((ages > cfg.stale_after_s) | given_fixed),
                                         seen, p, v, grow, closing)
        late = ~fixed & (ages >= dyn.dt * (1.0 - 1e-9)) & np.isfinite(ages)
        if cfg.cover_late and np.count_nonzero(late):
            rows = np.flatnonzero(late)
            ran = np.where(pending[rows] >= 0, np.minimum(pending[rows], h[rows]), h[rows])   # ticks p is ahead
            centre, centre_vel, grow_stopped, closing_stopped, _ = self._stopped(
                stopped, rows, np.ones(len(rows), dtype=bool), ran * dyn.dt, final=False)
            grow[rows], closing[rows] = cover_both(p[rows], v[rows], grow[rows], closing[rows], centre, centre_vel,
                                                   grow_stopped, closing_stopped, dyn.dt)
        brake_vel, measured = v, jittering & ~fixed
        if np.count_nonzero(fixed):
            brake_vel = self._carried(pos, vel, ages, pending, fixed, delay, v)
        if cfg.jitter_brake_measured and np.count_nonzero(measured):
            brake_vel = np.where(measured[:, None], vel, brake_vel)
        velocity_error = closing.copy()
        if velocity_noise is not None:
            sigma_v = np.asarray(velocity_noise, dtype=np.float64)
            velocity_error = closing + VELOCITY_NOISE_BOUND * sigma_v
            closing = closing + cfg.measured_velocity_sigmas * sigma_v
        return Prediction(pos=p, vel=v, grow=grow, closing=closing, fixed=fixed, horizon=h,
                          brake_vel=brake_vel, velocity_error=velocity_error,
                          unsure=unsure, covers=tuple(covers))

    def _carried(self, pos: np.ndarray, vel: np.ndarray, ages: np.ndarray, pending: np.ndarray,
                 fixed: np.ndarray, delay: float, v: np.ndarray) -> np.ndarray:
        """(N, 2) the velocity the BRAKE sent to each fixed robot is to cancel (module docstring,
        Braking a robot that is not listening): its measured velocity carried through the
        commands it had yet to act on (``pending``, ``h`` where unknown, as a listening robot is
        carried; before its first command, none: it held nothing), where the history holds them
        all; ``v`` (its disc's) for the other rows."""
        h = horizon_ticks(ages, delay, self.dynamics.dt)
        m = np.where(fixed, np.where(pending >= 0, pending, h), 0).astype(np.int64)
        held = fixed & (m <= self.depth) & np.isfinite(vel).all(axis=1)
        if not held.any():
            return v
        m = np.where(held, m, 0)
        p_out, v_out = np.empty_like(pos), np.empty_like(vel)
        dyn = self.dynamics
        latency_kernels._roll_forward(f64(pos), f64(vel), m, self._history, False, float(dyn.dt),
                                      float(dyn.damping), float(dyn.speed_limit), float(dyn.speed_limit ** 2),
                                      float(dyn.accel_limit), p_out, v_out)
        return np.where(held[:, None], v_out, v)

    def _listening(self, pos: np.ndarray, vel: np.ndarray, ages: np.ndarray, a_nom: np.ndarray,
                   pending: np.ndarray, given_fixed: np.ndarray, sigma_p: np.ndarray,
                   delay: float) -> tuple[np.ndarray, ...]:
        """``(p, v, grow, closing, fixed, h, jittering)`` of every robot through its pending
        commands with its tightening (module docstring; fixed robots get ``h = 0`` and are
        bounded by the caller), compiled (:mod:`controllers.safety.latency_kernels`); updates the
        jitter record and the acceleration bounds of the robots not fixed."""
        n = len(ages)
        p, v, grow, closing = np.empty((n, 2)), np.empty((n, 2)), np.empty(n), np.empty(n)
        fixed, h, jittering = np.empty(n, dtype=bool), np.empty(n, dtype=np.int64), np.empty(n, dtype=bool)
        latency_kernels.predict_listening(
            f64(pos), f64(vel), f64(ages), f64(a_nom), pending, given_fixed, f64(sigma_p),
            self._history, self._delay_seen, self._jitter_left, self._accel_bound, float(delay),
            *self._kernel_consts, p, v, grow, closing, fixed, h, jittering)
        return p, v, grow, closing, fixed, h, jittering

    def _not_listening(self, stopped: _Stopped, fixed: np.ndarray, silent: np.ndarray,
                       seen: Mapping[int, Sighting] | None, p: np.ndarray, v: np.ndarray, grow: np.ndarray,
                       closing: np.ndarray) -> list[tuple[int, np.ndarray, np.ndarray]]:
        """The ``fixed`` robots as obstacles (module docstring, Robots that are not listening),
        written into ``p, v, grow, closing``: the ``silent`` ones (stale by age, or given fixed)
        by their branches, their covers and sightings where the stack passes ``now``; the others
        by the ball. Returns the covers."""
        cfg = self.config
        rows = np.flatnonzero(fixed)
        p[rows], v[rows], grow[rows], closing[rows], paths = self._stopped(
            stopped, rows, silent[rows], stopped.ages[rows] + stopped.delay, final=True)
        covers = []
        for i, path in zip(rows, paths, strict=True):
            if path is None:
                continue
            t = stopped.ages[i] + stopped.delay
            cover = None if cfg.cover_discs == 1 else path.cover(t, cfg.cover_merge, cfg.cover_discs)
            cover = cover and (cover[0], cover[1] + stopped.sigma_p[i])
            sighting = seen.get(int(i)) if seen else None
            if sighting is not None and path.seen_at_rest(sighting.taken_at):
                cover, slower = narrowed(cover or (p[i][None], grow[i:i + 1]), sighting)
                p[i], v[i], grow[i], closing[i] = cover[0][0], 0.0, cover[1][0], min(closing[i], slower)
            if cover is not None and len(cover[1]) > 1:
                covers.append((int(i), *cover))
        return covers

    def _stopped(self, stopped: _Stopped, rows: np.ndarray, branches: np.ndarray, t: np.ndarray, final: bool
                 ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, list[SilentPaths | None]]:
        """Robots ``rows`` (K,) as obstacles ``t`` (K,) [s] after their last states (``tau + L``
        for those not listening): ``(centre (K, 2), centre velocity (K, 2), grow (K,), closing
        (K,), branches)``. Where ``branches`` (K,) and the history holds the commands a robot may
        act on, the disc of its branches (their
        :class:`SilentPaths` returned; ``final``: the robot is stale, see :meth:`_silent_paths`),
        else the ball of :func:`reach` (None), each grown by ``sigma_p`` and its rate by
        ``velocity_noise`` (module docstring, Robots that are not listening)."""
        cfg, s, k = self.config, stopped, len(rows)
        centre, centre_vel, grow, closing = np.empty((k, 2)), np.empty((k, 2)), np.empty(k), np.empty(k)
        paths: list[SilentPaths | None] = [None] * k
        for q, i in enumerate(rows):
            if branches[q] and s.now is not None:
                paths[q] = self._silent_paths(i, s.pos[i], s.vel[i], s.now - s.ages[i], s.pending[i], s.ages[i],
                                              s.delay, s.weight[i], final)
            if paths[q] is not None:
                centre[q], centre_vel[q], radius, rate = paths[q].disc(t[q])
                grow[q], closing[q] = radius + s.sigma_p[i], rate + cfg.velocity_noise
        ball = np.array([path is None for path in paths], dtype=bool)
        if ball.any():
            by_ball = rows[ball]
            brake_after = max(cfg.stale_after_s, cfg.watchdog_s) + s.delay
            centre[ball], centre_vel[ball], radius, rate = reach(
                s.pos[by_ball], s.vel[by_ball], t[ball], brake_after, self.dynamics,
                self._accel_bound[by_ball])
            grow[ball], closing[ball] = radius + s.sigma_p[by_ball], rate + cfg.velocity_noise
        return centre, centre_vel, grow, closing, paths

    def _silent_paths(self, i: int, pos: np.ndarray, vel: np.ndarray, measured_at: float, pending: int,
                      age: float, delay: float, spread_weight: float, final: bool = True) -> SilentPaths | None:
        """Robot ``i``'s branches from its state measured at ``measured_at``, or None where its
        history does not hold the commands it may act on. A stale robot's (``final``) are cached
        per id until a newer state: it is sent BRAKE from then on, which its branches already
        hold. A robot only late is still sent commands, so its branches are built anew each tick
        and not kept (nor read by :meth:`dead_reckoned`)."""
        rid = self._ids[i]
        cached = self._paths.get(rid)
        if final and cached is not None and abs(cached.measured_at - measured_at) < 1e-9:
            return cached
        dyn, cfg = self.dynamics, self.config
        if pending >= 0:
            counts = [int(pending)]
        else:                            # every count the latency bound allows
            ticks = int(round(age / dyn.dt))
            counts = list(range(ticks, ticks + int(np.ceil(delay / dyn.dt - 1e-9)) + 1))
        deepest = max(counts) + 1
        if not (np.isfinite(pos).all() and np.isfinite(vel).all()) or deepest > min(self._recorded[i], self.depth):
            return None
        hold = int(np.ceil(cfg.watchdog_s / dyn.dt - 1e-9))
        sequences = [(self._history[self.depth - m - 1:, i], self._braked[self.depth - m - 1:, i]) for m in counts]
        asked = self._history[self.depth - deepest:, i][~self._braked[self.depth - deepest:, i]]
        spread = float(np.hypot(*(asked.max(axis=0) - asked.min(axis=0)))) if len(asked) else 0.0
        paths = silent_paths(pos, vel, sequences, hold, cfg.accel_uncertainty + spread_weight * spread,
                             cfg.accel_uncertainty, measured_at, dyn)
        if final:
            self._paths[rid] = paths
        return paths

    def dead_reckoned(self, ids: tuple[str, ...], pos: np.ndarray, vel: np.ndarray, ages: np.ndarray,
                      stale: np.ndarray, now: float) -> tuple[np.ndarray, np.ndarray]:
        """Where the stale robots are now, for the policy and docking (not for the filter, which
        keeps the whole disc): (N, 2) positions [m] and velocities [m/s], each stale row whose
        branches a :meth:`predict` has computed from this same last state (measured at
        ``now - ages``) replaced by their disc's centre and its velocity ``ages`` after it
        (:meth:`SilentPaths.disc`); every other row as given. A robot silent for good is then
        seen where it must have stopped (0.2-15 mm from its true centre, module docstring of
        :mod:`controllers.safety.silent_reach`), not where it last reported itself on the way."""
        pos_out, vel_out = pos, vel
        for i in np.flatnonzero(stale):
            paths = self._paths.get(ids[i])
            if paths is None or abs(paths.measured_at - (now - ages[i])) >= 1e-9:
                continue
            if pos_out is pos:
                pos_out, vel_out = pos.copy(), vel.copy()
            pos_out[i], vel_out[i], _, _ = paths.disc(float(ages[i]))
        return pos_out, vel_out

    def record(self, ids: tuple[str, ...], accel: np.ndarray, braking: np.ndarray | None = None) -> None:
        """The (N, 2) accelerations [m/s^2] asked of robots ``ids`` this tick (newest last),
        clipped to the actuator limit; ``braking`` (N,) bool: the rows sent BRAKE (the robot
        applies the braking law to its own velocity; None: none)."""
        self._align(tuple(ids))
        n = len(self._ids)
        accel = f64(accel)
        braking = np.zeros(n, dtype=bool) if braking is None else np.ascontiguousarray(braking, dtype=bool)
        require_shapes("LatencyPredictor.record", accel=(accel, (n, 2)), braking=(braking, (n,)))
        latency_kernels.record_rows(accel, float(self.dynamics.accel_limit), braking, self._history,
                                    self._braked, self._recorded, self.depth)

    def record_braking(self, ids: tuple[str, ...], accel: np.ndarray) -> None:
        """A tick on which every robot was sent BRAKE and nothing else was recorded (the
        controller failed): one braking entry for ``ids``, asked ``accel`` (N, 2) [m/s^2] (the
        braking law at their velocity), and for every other id kept (0: it is not listening)."""
        accel = f64(accel)
        require_shapes("LatencyPredictor.record_braking", accel=(accel, (len(ids), 2)))
        named = set(ids)
        others = tuple(rid for rid in self._ids if rid not in named)
        self.record((*ids, *others), np.concatenate([accel, np.zeros((len(others), 2))]),
                    np.ones(len(ids) + len(others), dtype=bool))

    def mark_braking(self, ids: tuple[str, ...], braking: np.ndarray, accel: np.ndarray) -> None:
        """Correct the newest entry: the robots ``ids[k]`` with ``braking[k]`` (N,) bool were
        sent BRAKE instead of what :meth:`record` was told, and brake with ``accel[k]`` (N, 2)
        [m/s^2] (the braking law at their velocity)."""
        accel, braking = f64(accel), np.asarray(braking, dtype=bool)
        require_shapes("LatencyPredictor.mark_braking", accel=(accel, (len(ids), 2)),
                       braking=(braking, (len(ids),)))
        where = {rid: k for k, rid in enumerate(self._ids)}
        clipped = clip_norm(accel, self.dynamics.accel_limit)
        for k in np.flatnonzero(braking):
            i = where.get(ids[k])
            if i is None or self._recorded[i] == 0 or self._braked[-1, i]:
                continue
            self._history[-1, i] = clipped[k]
            self._braked[-1, i] = True
            self._paths.pop(ids[k], None)


__all__ = ["LatencyConfig", "LatencyConfigError", "LatencyPredictor", "Prediction", "horizon_ticks",
           "reach", "row_sums"]
