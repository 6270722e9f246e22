r"""ControlStack: one control tick from a fleet state to the commands sent to the robots.

Data path of :meth:`ControlStack.tick` for N robots (N may change from one tick to the next;
every per-robot estimate is keyed by robot id)::

    FleetState (positions, velocities, targets (N, 2) numpy float64; object pose; per-row state
                ages; silent robots; a measured command delay)
      -> rows:     a row with a non-finite state stands in at its id's last finite state (none
                   yet: nobody moves this tick); a row older than the latency config's
                   ``stale_after_s``, or standing in, is *stale*: an obstacle, sent braking
      -> MEC in:   controllers.mec.ModelErrorCompensator.update(vel, ids) (optional): a bank of
                   Kalman observers over command delays 0..3 ticks, noise-adaptive; its velocity
                   estimate replaces the measured one for policy and filter
                   (``estimated_velocity``); dropped or stale rows only predict, and a dropped
                   row reads the estimate as of its last measurement (``v_measured``), as its
                   position and age are: the latency prediction carries it on from there through
                   the commands sent since. The prediction to now already holds them (under the
                   observer's delay hypothesis); carried through them again, a robot coasting at
                   0.175 m/s towards a wall 4 cm off was judged at 0.084 m/s one tick after the
                   start and let accelerate into it (``bench/safety.py``, jitter, noise and drops
                   at once, seed 292)
      -> positions: controllers.position_estimator.PositionEstimator (``estimated_position``):
                   a Kalman filter per robot on the measured positions, driven by the measured
                   velocity, that measures its own noise (exact measurements pass unchanged);
                   its estimate replaces the measured position for policy and filter, and its
                   standard deviation grows the robot's disc in the filter
      -> stale seen: a stale row is shown to the policy and docking where it must be now,
                   the centre of its branches' disc (LatencyPredictor.dead_reckoned, from the
                   commands it was sent), not where it last reported itself; the filter keeps
                   the whole disc
      -> team:     silent robots whose targets are known join docking's view after the N
                   rows, where they must have stopped (stack.team_view), and the policy's when
                   it runs N + M robots (their actions are dropped)
      -> observe:  sim.observations tokens (1, N, 2N+1, 4) + mask (1, N, 2N+1), torch float32
                   (or the flat vector (1, N, 4N+2) for an actor with obs_kind == "flat")
      -> policy:   eager nn.Module or TorchScript module ``forward(obs, mask) -> (1, N, 2)``,
                   run under torch.inference_mode (an eager typed actor by the compiled kernel
                   of npz files instead, stack.policy_io.ModuleKernel, unless
                   ``StackConfig.policy_kernel`` is off); an exported file of any format
                   (:class:`deploy.export.ExportedPolicy`, its rows ``(N, 2N+1, 4)``, rows it
                   flags not valid count as non-finite); or a plain callable FleetState -> (N, 2)
                   => a_nom (N, 2) [m/s^2] (the tokens are written by a compiled kernel into a
                   float32 buffer kept per N; a network whose forward accepts it gets mask=None)
      -> docking:  controllers.docking.Docking: a robot near its free matched target gets a PD
                   law onto it instead (``docking``); the filter judges it like any command
      -> detour:   controllers.detour.Detour: a robot held in place away from every target while
                   its policy pushes is led round what holds it on a grid path (``detour``)
      -> latency:  controllers.safety.latency.LatencyPredictor: every robot (silent ones
                   appended) predicted to where the new command acts, over its state age plus
                   the command delay, through the commands in flight; discs grown by what the
                   prediction cannot know; stale and silent robots fixed obstacles with their
                   reachable disc
      -> obstacles: FleetState.obstacles (a tracker's sightings, stack.seen) appended as fixed
                   discs grown by how far each may move (Prediction.with_obstacles); a sighting
                   of one of the robots bounds it only once it is silent and at rest; only
                   discs that can bind this tick go on (controllers.safety.relevance)
      -> safety:   controllers.safety.SafetyFilter.filter(..., prediction=) (optional)
                   => a_safe (N, 2), SafetyStatus
      -> MEC out:  ModelErrorCompensator.compensate(a_safe) => a_cmd = clip_norm(a_safe - c)
      -> re-check: controllers.safety.recheck: a_cmd must satisfy the barrier rows too, else
                   its robots' compensation is withdrawn
      -> commands  a_cmd (N, 2) numpy float64, always finite; stale rows the braking law at the
                   velocity the prediction carries them to (controllers.safety.latency, Braking a
                   robot that is not listening), not at their last measured one; the
                   acceleration each robot is to achieve is recorded for the next prediction
                   (a caller that sends BRAKE instead says so: :meth:`ControlStack.sent_braking`)

Non-finite values never pass on. A non-finite policy output replaces the policy's output with
the maximum-braking command ``clip_norm(c v - v / dt, accel_limit)`` (``v`` non-finite -> 0) and
says so in :attr:`TickResult.policy_status`; a non-finite final command (which no stage should
produce) is replaced the same way with :attr:`TickResult.brake_reason` set. Exceptions raised
by a policy propagate: a bug is not a data error.

Compiled stages: the compensator, the position estimator, the tokens, docking, the latency
prediction, the fused filter's rows and sweep and the checks between the stages run as numba
kernels (:mod:`controllers.jit`, :mod:`controllers.array_kernels`), each bit for bit its numpy
formulation (parity tests; ``bench/tick_kernels.py`` compares the two ticks' commands): numpy's
per-call cost, not arithmetic, was the time (0.77 -> 0.33-0.37 ms p50 at five robots with an
ONNX policy). They are compiled or loaded from the on-disk cache when the first ControlStack is
built (:func:`controllers.jit.warm_up`), never inside a tick.

Threads: torch's intra-op thread count is the caller's choice; for one fleet call
``torch.set_num_threads(1)`` once before the loop (more threads only add synchronisation cost).

:func:`run_episode` (:mod:`stack.episodes`) drives any :class:`sim.fleet.Fleet` with a stack
and judges the episode.
"""

from __future__ import annotations

import time

import numpy as np

from controllers.array_kernels import all_finite, clip_norm_rows, non_finite_rows
from controllers.detour import Detour
from controllers.docking import Docking
from controllers.jit import f64, warm_up
from controllers.mec import ModelErrorCompensator
from controllers.position_estimator import PositionEstimator
from controllers.safety import SafetyFilter, braking_acceleration
from controllers.safety.latency import LatencyPredictor, Prediction
from controllers.safety.recheck import recheck
from sim.fleet import FleetState
from sim.scenario import Dynamics, Scenario, clip_norm
from stack.episodes import EpisodeMetrics, nominal_step, run_episode
from stack.last_known import LastKnown
from stack.policy_io import StackError, load_policy
from stack.policy_stage import PolicyLike, PolicyStage
from stack.seen import binding_discs, robot_sightings, with_obstacles
from stack.team_view import team_view
from stack.tick_types import PolicyStatus, SafeStage, StackConfig, TickResult


class ControlStack(PolicyStage):
    """observe -> policy -> safety -> MEC for one fleet (see the module docstring).

    Args:
        scenario: the task (arena, object polygon, dynamics); its robot count is not binding.
        policy: an ``nn.Module`` / TorchScript module with ``forward(obs, mask) -> (E, N, 2)``,
            an exported policy (:func:`deploy.export.load_exported`), the path of an exported
            file (TorchScript, .pt2, ONNX) or checkpoint, or a callable ``FleetState -> (N, 2)``.
        config: which stages run (:class:`StackConfig`).
    """

    def __init__(self, scenario: Scenario, policy: PolicyLike, config: StackConfig | None = None):
        self.scenario = scenario
        self.config = config or StackConfig()
        self.dynamics: Dynamics = scenario.dynamics
        self._init_policy(scenario, policy)
        self._static_pose_list = [*map(float, scenario.object_center), 0.0]
        self._object_moved = False             # whether a tick ever gave the filter another pose
        self.safety = SafetyFilter(scenario, self.config.safety_config) if self.config.safety else None
        self.mec = ModelErrorCompensator(self.dynamics, self.config.mec_config) if self.config.mec else None
        self.predictor = (LatencyPredictor(self.dynamics, self.config.latency)
                          if self.config.safety and self.config.latency.enabled else None)
        self.positions = PositionEstimator(self.dynamics.dt) if self.config.estimated_position else None
        self.docking = (Docking(scenario.robot_radius, self.dynamics.accel_limit, self.config.docking)
                        if self.config.docking.enabled else None)
        dock = self.config.docking
        self.detour = (Detour(scenario.robot_radius, self.dynamics.accel_limit, scenario.arena, scenario.polygon,
                              self.dynamics.dt, dock.detour_after_s, max(dock.stall_radius, dock.capture_radius))
                       if dock.enabled and dock.detour_after_s > 0 else None)
        self._last_known = LastKnown()
        self._last_prediction: Prediction | None = None   # the filter's, last tick (its fixed discs)
        self._ticked: FleetState | None = None             # the state of the last tick that returned
        self.num_robots: int | None = None
        warm_up()                       # compile or load the kernels now, not at the first tick

    def reset(self) -> None:
        """Start a new episode: forget the compensator's estimate and any callable's plan."""
        if self.mec is not None:
            self.mec.reset()
        if self.predictor is not None:
            self.predictor.reset()
        if self.positions is not None:
            self.positions.reset()
        if self.docking is not None:
            self.docking.reset()
        if self.detour is not None:
            self.detour.reset()
        self._last_known = LastKnown()
        self._last_prediction = None
        self._ticked = None
        reset = getattr(self.callable, "reset", None)
        if callable(reset):
            reset()
        self.num_robots = None

    # ------------------------------------------------------------------ stages
    def brake(self, vel: np.ndarray) -> np.ndarray:
        """(N, 2) maximum-braking command (non-finite velocities -> 0)."""
        return braking_acceleration(vel, self.dynamics)

    # -------------------------------------------------------------------- tick
    def tick(self, state: FleetState) -> TickResult:
        """One control tick for ``state`` (see the module docstring); never returns NaN."""
        t0 = time.perf_counter_ns()
        given, self._ticked = state, None
        n = state.num_robots
        if n != self.num_robots:
            self._resize(n)
        pos, vel, ages = state.positions, state.velocities, state.ages()
        ids = state.robot_ids
        unknown = np.empty(n, dtype=bool)
        any_unknown = non_finite_rows(f64(pos), f64(vel), unknown) > 0
        if not np.isfinite(ages).all():         # an infinitely old state places its robot nowhere
            unknown |= ~np.isfinite(ages)
            any_unknown = True
        news = self._last_known.new_measurement(ids, ages, state.time) & ~unknown
        pos, vel, ages, unplaced = self._last_known.update(ids, pos, vel, ages, state.time, unknown)
        stale = unknown | (ages > self.config.latency.stale_after_s)
        if self.predictor is not None and state.commands_pending is not None:
            stale |= self.predictor.late(ages, state.commands_pending, state.command_delay_s)
        pos, vel, position_std = self._estimate(ids, pos, vel, state.time - ages, stale, news)
        seen_pos, seen_vel = pos, vel           # what the policy and docking see of the fleet
        if self.predictor is not None and np.count_nonzero(stale):
            seen_pos, seen_vel = self.predictor.dead_reckoned(ids, pos, vel, ages, stale, state.time)
        policy_status, brake_reason = PolicyStatus.OK, ""
        docked, detoured = np.zeros(n, dtype=bool), np.zeros(n, dtype=bool)
        if any_unknown and unplaced.any():      # nowhere to put a robot: nobody may move
            a_nom = self.brake(vel)
            policy_status = PolicyStatus.INVALID_STATE
            brake_reason = "non-finite fleet state: policy skipped, braking"
            t_obs = t_pol = time.perf_counter_ns()
        else:
            if any_unknown or seen_vel is not state.velocities or seen_pos is not state.positions:
                state = state.replaced(positions=seen_pos, velocities=seen_vel, state_age_s=ages)
            team = team_view(state, self.predictor)           # the rows, then silent robots
            extra = team.num_robots - n
            a_nom, t_obs, t_pol = self._policy(team if extra and self._runs(n + extra) else state, t0)
            if not all_finite(f64(a_nom)):
                a_nom = self.brake(vel)
                policy_status = PolicyStatus.NON_FINITE_OUTPUT
                brake_reason = "policy output not finite: braking"
            elif self.docking is not None:
                a_nom, docked, detoured = self._terminal_modes(team, a_nom, stale)
            a_nom = a_nom[:n]
        safety_status, safety_reason, safe = None, "", None
        if self.safety is not None:
            safe = self._safety(state, pos, vel, ages, unknown, stale, a_nom, position_std)
            a_safe, safety_status, safety_reason = safe.result.a_safe[:n], safe.result.status, safe.result.reason
        else:
            a_safe = clip_norm(a_nom, self.dynamics.accel_limit)
        t_safe = time.perf_counter_ns()
        mec_status, a_cmd, achieved = None, a_safe, a_safe
        if self.mec is not None:
            mec = self.mec.compensate(a_safe)
            a_cmd, mec_status = mec.a_cmd, mec.status
            if safe is not None:                # a stale robot is held at a_safe (0) in its rows: it is braked
                held = np.where(stale[:, None], a_safe, a_cmd)
                a_cmd = recheck(safe.result.terms, safe.full(a_safe), safe.full(held), n)
            achieved = a_cmd + np.where(stale[:, None], 0.0, mec.compensation)
        if np.count_nonzero(stale):             # not listening or not seen: brake, as the robot would
            a_cmd = np.where(stale[:, None], self.brake(self._braked_velocity(vel, stale, safe)), a_cmd)
            achieved = np.where(stale[:, None], a_cmd, achieved)
        if self.mec is not None:
            self.mec.replace_last_command(a_cmd)
        t_mec = time.perf_counter_ns()
        if not all_finite(f64(a_cmd)):     # no stage should get here; the last line of defence
            a_cmd = self.brake(vel)
            brake_reason = (brake_reason + "; " if brake_reason else "") + "final command not finite: braking"
        if self.predictor is not None:         # the silent robots' rows too (asked nothing)
            named = len(safe.ids)
            braking = stale if named == n else np.concatenate([stale, np.ones(named - n, dtype=bool)])
            self.predictor.record(safe.ids, safe.full(achieved)[:named], braking)
        self._ticked = given
        return TickResult(
            a_nom=a_nom, a_safe=a_safe, a_cmd=a_cmd, policy_status=policy_status,
            safety_status=safety_status, mec_status=mec_status, safety_reason=safety_reason,
            brake_reason=brake_reason, stale=stale, docking=docked, detour=detoured,
            timings_ns={"observe": t_obs - t0, "policy": t_pol - t_obs, "safety": t_safe - t_pol,
                        "mec": t_mec - t_safe, "total": t_mec - t0})

    __call__ = tick

    def sent_braking(self, state: FleetState, braking: np.ndarray) -> None:
        """The caller sent BRAKE to the rows ``braking`` (N,) bool of ``state`` instead of this
        stack's commands (a deadline or fault rule of its own, or every row because :meth:`tick`
        raised for ``state``): the command history and the compensator learn what the robots got,
        so the counts of pending commands name the same commands. A tick that raised recorded
        nothing: every robot gets one braking entry and the compensator starts afresh."""
        braking = np.asarray(braking, dtype=bool)
        if braking.shape != (state.num_robots,):
            raise StackError(f"sent_braking: braking must have shape ({state.num_robots},), got {braking.shape}")
        brake = self.brake(state.velocities)
        if self._ticked is not state:
            if self.predictor is not None:
                self.predictor.record_braking(state.robot_ids, brake)
            if self.mec is not None:
                self.mec.reset()
            return
        if not braking.any():
            return
        if self.predictor is not None:
            self.predictor.mark_braking(state.robot_ids, braking, brake)
        if self.mec is not None and self.mec.sent is not None:
            self.mec.replace_last_command(np.where(braking[:, None], brake, self.mec.sent[-1]))

    @staticmethod
    def _braked_velocity(vel: np.ndarray, stale: np.ndarray, safe: SafeStage | None) -> np.ndarray:
        """(N, 2) the velocity each stale row's BRAKE is to cancel [m/s]: the prediction's
        (:attr:`Prediction.brake_vel`: its last state carried through the commands in flight,
        the brakes already sent among them), ``vel`` without one (and for the other rows)."""
        if safe is None or safe.prediction is None:
            return vel
        return np.where(stale[:, None], safe.prediction.braking_velocity()[:len(vel)], vel)

    def _estimate(self, ids: tuple[str, ...], pos: np.ndarray, vel: np.ndarray, measured_at: np.ndarray,
                  stale: np.ndarray, news: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray | None]:
        """The MEC's velocity and the position estimator's positions for the fresh rows (stale
        rows keep their measurement); ``(pos, vel, position_std (N,) or None)``."""
        measured_vel, n = vel, len(vel)
        any_stale = np.count_nonzero(stale) > 0         # none: the np.where below are copies
        if self.mec is not None:            # the observer's velocity: less noisy, same delay
            skip = stale | ~news
            skipped = np.count_nonzero(skip) > 0
            v_est = self.mec.update(np.where(skip[:, None], np.nan, vel) if skipped else vel, ids)
            if skipped:     # as of the row's measurement, as its position and age are (module docstring)
                v_est = np.where(skip[:, None], self.mec.v_measured, v_est)
            if self.config.estimated_velocity:
                vel = np.where(stale[:, None], vel, v_est) if any_stale else v_est
        if self.positions is None:
            return pos, vel, None
        noise = (self.mec.noise_var if self.mec is not None
                 else np.full(n, self.config.mec_config.velocity_noise**2))
        estimate, std = self.positions.update(ids, pos, measured_vel, measured_at, news & ~stale, noise)
        return (np.where(stale[:, None], pos, estimate) if any_stale else estimate), vel, std

    def _terminal_modes(self, team: FleetState, a_nom: np.ndarray,
                        stale: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Docking, then detours, over the team (the N rows, then silent robots, which neither
        moves): ``(a_nom (N, 2), docking (N,), detour (N,))`` of the rows."""
        n, extra = len(stale), team.num_robots - len(stale)
        a_team = a_nom if len(a_nom) == team.num_robots else np.vstack([a_nom, np.zeros((extra, 2))])
        movable = np.concatenate([~stale, np.zeros(extra, dtype=bool)]) if extra else ~stale
        a_team, docked = self.docking(team.robot_ids, team.positions, team.velocities, team.targets,
                                      a_team, movable=movable)
        detoured = np.zeros(len(movable), dtype=bool)
        if self.detour is not None:
            a_team, detoured = self.detour(team.robot_ids, team.positions, team.velocities, team.targets,
                                           a_team, movable & ~docked, self._fixed_discs)
        return a_team[:n], docked[:n], detoured[:n]

    def _fixed_discs(self) -> np.ndarray | None:
        """(K, 3) centre and radius [m] of every disc the filter last kept round a robot not
        listening (itself grown by what is not known of it), or None."""
        p = self._last_prediction
        if p is None:
            return None
        keep = p.fixed & np.isfinite(p.pos).all(1) & np.isfinite(p.grow)   # a new robot's NaN row: no disc
        return np.column_stack([p.pos[keep], self.scenario.robot_radius + p.grow[keep]])

    def _safety(self, state: FleetState, pos: np.ndarray, vel: np.ndarray, ages: np.ndarray,
                unknown: np.ndarray, stale: np.ndarray, a_nom: np.ndarray,
                position_std: np.ndarray | None = None) -> SafeStage:
        """Filter the N commanded robots together with the silent ones (obstacles), over the
        latency; ``position_std`` (N,) [m], the position estimator's error, grows their discs.
        ``stale`` (N,): rows that are obstacles (with the latency prediction off, held where
        measured; the prediction finds them itself)."""
        silent = state.silent if state.silent is not None and len(state.silent) else None
        ids = state.robot_ids
        velocity_std = None if self.mec is None else np.sqrt(self.mec.noise_var)
        if silent is not None:
            ids = ids + tuple(silent.ids)
            pos, vel = np.vstack([pos, silent.positions]), np.vstack([vel, silent.velocities])
            ages = np.concatenate([ages, silent.age_s])
            unknown = np.concatenate([unknown, np.ones(len(silent), dtype=bool)])
            stale = np.concatenate([stale, np.ones(len(silent), dtype=bool)])
            a_nom = np.vstack([a_nom, np.zeros((len(silent), 2))])
            if position_std is not None:
                position_std = np.concatenate([position_std, np.zeros(len(silent))])
            if velocity_std is not None:
                velocity_std = np.concatenate([velocity_std, np.zeros(len(silent))])
        prediction, seen, obstacles = None, None, state.obstacles if state.obstacles else None
        reach = self.config.latency.delay_bound(state.command_delay_s) + self.dynamics.dt
        if obstacles is not None:
            seen, obstacles = robot_sightings(obstacles, ids, state.time, reach, self.scenario.robot_radius)
        if self.predictor is not None:
            pending = state.pending()
            if silent is not None:
                pending = np.concatenate([pending, silent.pending()])
            nominal = clip_norm_rows(f64(a_nom), self.dynamics.accel_limit)
            prediction = self.predictor.predict(ids, pos, vel, ages, nominal, state.command_delay_s,
                                                fixed=unknown, pending=pending, position_noise=position_std,
                                                velocity_noise=velocity_std, now=state.time, seen=seen)
            if prediction.covers:
                prediction = prediction.with_covers()
                extra = prediction.pos[len(pos):]
                pos, vel = np.vstack([pos, extra]), np.vstack([vel, np.zeros_like(extra)])
                a_nom = np.vstack([a_nom, np.zeros_like(extra)])
        elif np.count_nonzero(stale):
            prediction = Prediction.as_measured(pos, vel, stale)
        seen_discs = prediction
        if obstacles is not None:
            seen_discs = with_obstacles(prediction, obstacles, pos, vel, unknown, reach, self.scenario.robot_radius)
            prediction, near = binding_discs(seen_discs, len(pos), obstacles.positions, self.safety.config,
                                             self.dynamics, self.scenario.robot_radius, self.config.all_tracker_discs)
            rest = np.zeros((len(near), 2))
            pos, vel, a_nom = np.vstack([pos, near]), np.vstack([vel, rest]), np.vstack([a_nom, rest])
        pose = state.object_pose
        if not self._object_moved and pose.tolist() == self._static_pose_list:
            pose = None                        # the scenes' own pose, never left: no re-posing
        else:                                  # once moved, every tick poses each N's scene
            self._object_moved = True
        result = self.safety.filter(pos, vel, a_nom, pose, prediction=prediction)
        self._last_prediction = seen_discs     # the detours of the next tick keep clear of its discs, all of them
        return SafeStage(result, prediction, len(pos), ids)

    def _resize(self, n: int) -> None:
        """A new robot count: the filter builds (once) and caches its QP for N; the compensator
        and the latency history keep their estimates per robot id; the policy runs any N."""
        if n < 1:
            raise StackError(f"the fleet state has {n} robots; a tick needs at least one")
        self.num_robots = n


__all__ = ["ControlStack", "EpisodeMetrics", "PolicyStatus", "StackConfig", "StackError", "TickResult",
           "load_policy", "nominal_step", "run_episode"]
