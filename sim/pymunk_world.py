"""PymunkWorld: the formation-change scenario as rigid bodies in pymunk, with a real robot's model error.

The "real" side of sim-to-real: contacts are physical (robots cannot pass through each other, the
object or the walls) and the actuators are imperfect. It implements :class:`sim.fleet.Fleet`::

    world = PymunkWorld(make_scenario("paper-3"), ModelError(gain=0.7))
    state = world.reset(seed=0)             # FleetState as measured (noisy if configured)
    world.send_accelerations(a_cmd)         # (N, 2) m/s^2, held until the next call
    state = world.step()                    # advances dt

Bodies
    * Robots: dynamic discs of radius ``scenario.robot_radius``, unit mass, infinite moment of
      inertia (holonomic discs: heading is irrelevant and friction must not spin them).
    * The object: a **static** body with the scenario polygon (convex pieces if the polygon is not
      convex). The task is the formation change *before* transport: the object rests on the floor
      and the batched world, the observation tokens, the metrics and the safety layer all use the
      fixed ``scenario.polygon``; a static body keeps that one geometry true here, and behaves like
      an object too heavy for a robot to push. ``FleetState.object_pose`` is its centroid, heading 0.
    * Walls: four static segments lying outside the arena whose inner faces are the lines
      x = 0, x = W, y = 0, y = H (thick segments: nothing tunnels through them).
    * Contacts use Coulomb friction ``contact_friction`` and restitution ``contact_elasticity``;
      ``collision_slop`` is 1e-4 m. Pymunk resolves a contact once shapes overlap: with the
      default 10 substeps a robot driven at full acceleration overlaps a wall or the object by
      under 1 mm and another robot by under 2 mm (1 substep: ~9 mm and ~18 mm). Any overlap
      beyond 1e-6 m is a collision event, as everywhere else: at the end of a tick, and at any
      substep (a contact pymunk opens and resolves within one tick is one too).

Dynamics per control tick (``dt`` = ``scenario.dynamics.dt``), per robot, with
:class:`~sim.model_error.ModelError`::

    u_k     = the newest command that has arrived by tick k: command j arrives at tick
              j + delay_ticks + J_j, J_j ~ U{0..delay_jitter_ticks}  (0 before the first) [m/s^2]
              (a robot with a playout buffer acts on it at max(that, j + D_i): D_i = playout_ticks,
              or with adaptive_playout the largest delay robot i has seen this episode, if larger)
    u_k     = clip_norm(u_k, accel_limit)
    a_act  += alpha * (gain_i * u_k - a_act),  alpha = 1 - exp(-dt / lag_tau)   (alpha = 1 if tau = 0)
    a       = a_act + disturbance + w_k,       w_k ~ N(0, disturbance_std^2) per axis
    v_free  = v + dt * (a - damping * v)
    v_free  = v_free * max(0, 1 - dt * floor_friction / |v_free|)        (Coulomb floor friction)
    v'      = clip_norm(v_free, speed_limit)                             [m/s]

``v'`` becomes the body velocity and pymunk advances ``substeps`` steps of ``dt / substeps``:
without contact the position moves by exactly ``dt * v'`` (the scenario's semi-implicit Euler),
with contact pymunk's impulses change velocity and position. With ``ModelError()`` (no error) and
no contact the motion equals :class:`sim.batched_env.BatchedFormationEnv` to rounding (measured ~4e-15 m over 40 ticks).

Measurements (``read_state`` / ``step``) add N(0, position_noise_std^2) and
N(0, velocity_noise_std^2) per axis, drawn once per tick; ``true_state`` is noise free.
The link can lose them: with ``state_drop`` p each robot's new measurement is lost with
probability p per tick, and the controller reads that robot's last delivered one; a robot frozen
by ``freeze = (robot, tick)`` delivers no state from that tick on, ignores every later command,
holds the last command it had for ``FROZEN_HOLD_TICKS`` more ticks and then brakes to rest with
:meth:`sim.scenario.Dynamics.brake` (its own watchdog) and stays there. Whenever a drop or a
freeze is configured, the state carries ``state_age_s``: the age of each delivered measurement.
Every state carries ``commands_pending``, as a robot's STATE carries ``last_cmd_seq``: the
commands sent after the newest one the robot had acted on when its delivered row was measured.
Collision events come from :func:`sim.metrics.collision_events` on the true positions after each
tick, joined by every overlap pymunk met at a substep of the tick (its contact depth beyond
``CONTACT_EPS``), counted as onsets (robot, step) per kind like the batched world.

Randomness: ``reset(seed)`` seeds five independent numpy streams (start jitter, per-robot gain,
disturbance noise, measurement noise, and the link: delay jitter and dropped states draw from
this one) spawned from ``numpy.random.SeedSequence(seed)``, so turning one knob never changes the
draws of another, but for the two link knobs: with jitter on, turning drops on changes the
jitter's draws. ``reset()`` without a seed continues the streams.
The same seed does not always repeat an episode bit for bit in another process: Chipmunk keys
its contact cache by shape pointers (``CP_HASH_PAIR`` of the two shapes), so the order in which
it resolves the contacts of a tick follows memory addresses. Seen in one of 12 open-loop replays
with jittering delay, in 2 of 6 processes: the last bits of one tick differed and the episode's
tracking error then by ~1e-7 of itself. Seeded runs reproduce to rounding where several contacts
meet.
"""

from __future__ import annotations

import math
from collections import deque
from dataclasses import dataclass

import numpy as np
import pymunk
import torch
from pymunk.autogeometry import convex_decomposition

from sim.fleet import FleetState, check_accelerations
from sim.geometry import Polygon
from sim.metrics import CONTACT_EPS, EpisodeOutcome, collision_events, episode_outcome
from sim.model_error import ModelError
from sim.scenario import Scenario, clip_norm

WALL_THICKNESS = 0.05      # [m] half-thickness of the wall segments, all outside the arena
FROZEN_HOLD_TICKS = 2      # ticks a frozen robot keeps its last command before its watchdog brakes
COLLISION_SLOP = 1e-4      # [m] overlap pymunk leaves in resting contact
ROBOT, WALL, OBJECT = 1, 2, 3   # shape collision types; columns 0, 2, 1 of the contact flags


@dataclass(frozen=True)
class Contacts:
    """Collision events of one instant, each (N,) bool (see :func:`sim.metrics.collision_events`)."""

    robot: np.ndarray
    object: np.ndarray
    wall: np.ndarray

    @property
    def any(self) -> np.ndarray:
        """(N,) bool: the robot touches anything."""
        return self.robot | self.object | self.wall


@dataclass(frozen=True)
class CollisionCounts:
    """Collision onsets this episode per kind: a robot entering contact counts once per entry."""

    robot: int = 0
    object: int = 0
    wall: int = 0

    @property
    def any(self) -> bool:
        """True when any collision happened this episode (the episode then fails)."""
        return self.robot + self.object + self.wall > 0


class PymunkWorld:
    """The scenario in pymunk with :class:`ModelError` (see the module docstring).

    Args:
        scenario: the task (arena, object, slots, dynamics).
        model_error: the robot's departure from the nominal model.
        substeps: pymunk steps per control tick (contact resolution; motion is unaffected).
        contact_friction: Coulomb friction coefficient of every contact.
        contact_elasticity: restitution of every contact, in [0, 1].
        seed: seeds the first episode when ``reset()`` is called without a seed.

    Attributes (besides the :class:`sim.fleet.Fleet` calls):
        gains: (N,) actuator gain of each robot this episode.
        applied_accelerations: (N, 2) acceleration the actuators produced in the last tick,
            disturbance included, before damping and floor friction [m/s^2].
        space: the ``pymunk.Space`` (read it; changing it voids the guarantees above).
    """

    def __init__(self, scenario: Scenario, model_error: ModelError = ModelError(), *,
                 substeps: int = 10, contact_friction: float = 0.5, contact_elasticity: float = 0.0,
                 seed: int | None = None):
        if not isinstance(model_error, ModelError):
            raise TypeError(f"model_error must be a ModelError, got {type(model_error).__name__}")
        if isinstance(substeps, bool) or not isinstance(substeps, int) or substeps < 1:
            raise ValueError(f"substeps must be a positive integer, got {substeps!r}")
        if not (math.isfinite(contact_friction) and contact_friction >= 0):
            raise ValueError(f"contact_friction must be >= 0, got {contact_friction!r}")
        if not (math.isfinite(contact_elasticity) and 0 <= contact_elasticity <= 1):
            raise ValueError(f"contact_elasticity must be in [0, 1], got {contact_elasticity!r}")
        model_error.check_team(scenario)
        self.scenario = scenario
        self.model_error = model_error
        self.substeps = substeps
        n = scenario.num_robots
        dyn = scenario.dynamics
        self._lag_alpha = 1.0 if model_error.lag_tau == 0 else 1.0 - math.exp(-dyn.dt / model_error.lag_tau)
        self._polygon = Polygon(torch.as_tensor(scenario.polygon, dtype=torch.float64))
        self._targets = scenario.targets
        center = scenario.object_center
        self._object_pose = np.array([center[0], center[1], 0.0])

        self._material = (contact_friction, contact_elasticity)
        self._build_space()
        self._counts = np.zeros(3, dtype=np.int64)
        self._seed_streams(seed)
        self._command = np.zeros((n, 2))
        self.reset()

    # ----------------------------------------------------------------- set-up
    def _build_space(self) -> None:
        """A new space: the robots' bodies, then the walls and the object (in this order)."""
        self.space = pymunk.Space()
        self.space.collision_slop = COLLISION_SLOP
        self._robots: list[pymunk.Body] = []
        self._robot_of: dict[pymunk.Shape, int] = {}
        for i in range(self.scenario.num_robots):
            body = pymunk.Body(mass=1.0, moment=float("inf"))
            shape = pymunk.Circle(body, self.scenario.robot_radius)
            shape.collision_type = ROBOT
            self._set_material(shape, *self._material)
            self.space.add(body, shape)
            self._robots.append(body)
            self._robot_of[shape] = i
        for shape in self._static_shapes():
            self._set_material(shape, *self._material)
            self.space.add(shape)
        self._substep_contact = np.zeros((self.scenario.num_robots, 3), dtype=bool)
        self.space.on_collision(ROBOT, None, pre_solve=self._overlap)

    def _overlap(self, arbiter: pymunk.Arbiter, space: pymunk.Space, data) -> None:
        """Mark the robots of a contact deeper than ``CONTACT_EPS`` at a substep (columns: robot,
        object, wall, as :class:`Contacts`)."""
        if min(p.distance for p in arbiter.contact_point_set.points) >= -CONTACT_EPS:
            return
        a, b = arbiter.shapes
        flags = self._substep_contact
        if b.collision_type == ROBOT:
            flags[self._robot_of[a], 0] = flags[self._robot_of[b], 0] = True
        else:
            flags[self._robot_of[a], 1 if b.collision_type == OBJECT else 2] = True

    @staticmethod
    def _set_material(shape: pymunk.Shape, friction: float, elasticity: float) -> None:
        shape.friction = friction
        shape.elasticity = elasticity

    def _static_shapes(self) -> list[pymunk.Shape]:
        w, h = self.scenario.arena
        t = WALL_THICKNESS
        body = self.space.static_body
        walls = [pymunk.Segment(body, a, b, t) for a, b in (
            ((-t, -t), (-t, h + t)), ((w + t, -t), (w + t, h + t)),
            ((-t, -t), (w + t, -t)), ((-t, h + t), (w + t, h + t)))]
        verts = [tuple(p) for p in self.scenario.polygon]
        if self._polygon.convex_ccw:
            pieces = [verts]
        else:
            pieces = [[tuple(v) for v in hull[:-1]] for hull in convex_decomposition(verts + [verts[0]], 0.0)]
        parts = [pymunk.Poly(body, piece) for piece in pieces]
        for shape, kind in [(wall, WALL) for wall in walls] + [(part, OBJECT) for part in parts]:
            shape.collision_type = kind
        return walls + parts

    def _seed_streams(self, seed: int | None) -> None:
        # the first four children are those of spawn(4): adding the link stream changed no draw
        jitter, gain, disturbance, noise, link = np.random.SeedSequence(seed).spawn(5)
        self._rng_link = np.random.default_rng(link)
        self._rng_jitter = np.random.default_rng(jitter)
        self._rng_gain = np.random.default_rng(gain)
        self._rng_disturbance = np.random.default_rng(disturbance)
        self._rng_noise = np.random.default_rng(noise)

    @property
    def dt(self) -> float:
        """Control period [s]."""
        return self.scenario.dynamics.dt

    def reset(self, seed: int | None = None) -> FleetState:
        """Start an episode: jittered start slots at rest, fresh gains, empty actuators and delay line.

        After an episode with a contact the space is built anew: Chipmunk keeps each body's
        penetration-correction velocity past a reset, which moved robots at rest (about 20 um in
        the first tick); a world reused so runs as a fresh one would."""
        if seed is not None:
            self._seed_streams(seed)
        if self._counts.any():
            self._build_space()
        s, me = self.scenario, self.model_error
        n = s.num_robots
        j = s.start_jitter
        starts = s.starts + self._rng_jitter.uniform(-j, j, size=(n, 2))
        self.gains = me.gain + self._rng_gain.uniform(-me.gain_spread, me.gain_spread, size=n)
        self._command = np.zeros((n, 2))
        self._pending: deque[tuple[np.ndarray, int, int, np.ndarray]] = deque()  # (arrival (N,), sent tick, seq, cmd)
        self._sent = 0
        self._playout = np.full(n, me.playout_ticks, dtype=np.int64)   # D_i [ticks]
        self._held = np.zeros((n, 2))            # the newest command each robot has received
        self._held_seq = np.zeros(n, dtype=np.int64)
        self._delivered_seq = np.zeros(n, dtype=np.int64)  # held seq when the delivered row was measured
        self._delivered: tuple[np.ndarray, np.ndarray] | None = None
        self._age_ticks = np.zeros(n, dtype=np.int64)
        self._actuator = np.zeros((n, 2))
        self.applied_accelerations = np.zeros((n, 2))
        self._step = 0
        self._prev_contact = np.zeros((n, 3), dtype=bool)
        self._counts = np.zeros(3, dtype=np.int64)
        self.set_state(starts)
        return self.read_state()

    def set_state(self, positions: np.ndarray, velocities: np.ndarray | None = None) -> None:
        """Place the robots: (N, 2) true positions [m] and velocities [m/s] (default at rest).

        For tests and scripted starts; the step count and collision tallies are kept.
        """
        n = self.scenario.num_robots
        pos = np.asarray(positions, dtype=np.float64)
        vel = np.zeros((n, 2)) if velocities is None else np.asarray(velocities, dtype=np.float64)
        for name, x in (("positions", pos), ("velocities", vel)):
            if x.shape != (n, 2) or not np.all(np.isfinite(x)):
                raise ValueError(f"{name} must be a finite ({n}, 2) array, got shape {x.shape}")
        for body, p, v in zip(self._robots, pos, vel, strict=True):
            body.position = (float(p[0]), float(p[1]))
            body.velocity = (float(v[0]), float(v[1]))
            self.space.reindex_shapes_for_body(body)
        self._delivered = None                   # placed robots: every measurement is delivered
        self._after_motion()

    # ------------------------------------------------------------- fleet API
    def send_accelerations(self, accelerations: np.ndarray) -> None:
        """Command (N, 2) accelerations [m/s^2]; held until the next call."""
        self._command = check_accelerations(accelerations, self.scenario.num_robots).copy()

    def step(self) -> FleetState:
        """Advance one control tick (see the module docstring) and return the measured state."""
        dyn, me = self.scenario.dynamics, self.model_error
        u = clip_norm(self._receive_commands(), dyn.accel_limit)
        target = self.gains[:, None] * u
        if self._lag_alpha == 1.0:
            self._actuator = target
        else:
            self._actuator = self._actuator + self._lag_alpha * (target - self._actuator)
        a = self._actuator + np.asarray(me.disturbance)
        if me.disturbance_std > 0:
            a = a + self._rng_disturbance.normal(0.0, me.disturbance_std, size=a.shape)
        self.applied_accelerations = a

        vel = self._true_vel
        v = vel + dyn.dt * (a - dyn.damping * vel)
        if me.floor_friction > 0:
            speed = np.linalg.norm(v, axis=-1, keepdims=True)
            keep = np.maximum(0.0, 1.0 - dyn.dt * me.floor_friction / np.maximum(speed, 1e-300))
            v = v * keep
        v = clip_norm(v, dyn.speed_limit)
        for body, vi in zip(self._robots, v, strict=True):
            body.velocity = (float(vi[0]), float(vi[1]))
        h = dyn.dt / self.substeps
        self._substep_contact[:] = False
        for _ in range(self.substeps):
            self.space.step(h)

        self._step += 1
        self._after_motion()
        contact = np.stack((self.contacts.robot, self.contacts.object, self.contacts.wall), -1)
        if self._substep_contact.any():
            contact |= self._substep_contact
            self._contacts = Contacts(robot=contact[:, 0], object=contact[:, 1], wall=contact[:, 2])
        self._counts += (contact & ~self._prev_contact).sum(0)
        self._prev_contact = contact
        return self.read_state()

    def read_state(self) -> FleetState:
        """The state as measured at this tick (noise) and delivered (drops, freeze), if configured."""
        me = self.model_error
        if me.state_drop == 0 and me.freeze is None:
            return self._state(self._meas_pos, self._meas_vel)
        pos, vel = self._delivered
        state = self._state(pos, vel)
        state.state_age_s = self._age_ticks * self.dt
        return state

    @property
    def frozen(self) -> np.ndarray:
        """(N,) bool: robots frozen by ``ModelError.freeze`` at this tick."""
        out = np.zeros(self.scenario.num_robots, dtype=bool)
        if self.model_error.freeze is not None and self._step >= self.model_error.freeze[1]:
            out[self.model_error.freeze[0]] = True
        return out

    def true_state(self) -> FleetState:
        """The noise-free state at this tick."""
        return self._state(self._true_pos, self._true_vel, self._held_seq)

    # ------------------------------------------------------------- judging
    @property
    def contacts(self) -> Contacts:
        """Collision events at the current true positions."""
        return self._contacts

    @property
    def collision_counts(self) -> CollisionCounts:
        """Collision onsets since reset (``.any``: the episode has collided)."""
        r, o, w = (int(c) for c in self._counts)
        return CollisionCounts(robot=r, object=o, wall=w)

    def outcome(self) -> EpisodeOutcome:
        """:func:`sim.metrics.episode_outcome` of the current true positions (batch of 1)."""
        pos = torch.from_numpy(self._true_pos).unsqueeze(0)
        return episode_outcome(pos, torch.from_numpy(self._targets).unsqueeze(0),
                               torch.tensor([self.collision_counts.any]),
                               self.scenario.target_tolerance)

    # ------------------------------------------------------------- internals
    def _receive_commands(self) -> np.ndarray:
        """(N, 2) command each robot acts on this tick (module docstring: delay, jitter, freeze)."""
        me, n, k = self.model_error, self.scenario.num_robots, self._step
        frozen = self.frozen
        self._sent += 1           # the held command goes out again every tick (zero-order hold)
        jitter = self._rng_link.integers(0, me.delay_jitter_ticks + 1, n) if me.delay_jitter_ticks else 0
        self._pending.append((k + me.delay_ticks + jitter + np.zeros(n, dtype=np.int64), k,
                              self._sent, self._command))
        if me.adaptive_playout:
            for arrival, sent_tick, _, _ in self._pending:
                arrived = (arrival <= k) & ~frozen
                self._playout[arrived] = np.maximum(self._playout[arrived], arrival[arrived] - sent_tick)
        for arrival, sent_tick, seq, cmd in self._pending:
            take = (np.maximum(arrival, sent_tick + self._playout) <= k) & (seq > self._held_seq) & ~frozen
            self._held[take] = cmd[take]
            self._held_seq[take] = seq
        while self._pending and (np.maximum(self._pending[0][0], self._pending[0][1] + self._playout) <= k).all():
            self._pending.popleft()
        if frozen.any():
            since = k - me.freeze[1]
            if since >= FROZEN_HOLD_TICKS:
                self._held[frozen] = self.scenario.dynamics.brake(self._true_vel[frozen])
        return self._held

    def _deliver(self) -> None:
        """The measurement the controller gets: last delivered one for dropped or frozen robots."""
        me = self.model_error
        if me.state_drop == 0 and me.freeze is None:
            self._delivered_seq = self._held_seq.copy()
            return
        n = self.scenario.num_robots
        if self._delivered is None:
            self._delivered = (self._meas_pos.copy(), self._meas_vel.copy())
            self._delivered_seq = self._held_seq.copy()
            self._age_ticks = np.zeros(n, dtype=np.int64)
            return
        lost = self.frozen.copy()
        if me.state_drop > 0:
            lost |= self._rng_link.random(n) < me.state_drop
        pos, vel = self._delivered
        pos[~lost], vel[~lost] = self._meas_pos[~lost], self._meas_vel[~lost]
        self._delivered_seq = np.where(lost, self._delivered_seq, self._held_seq)
        self._age_ticks = np.where(lost, self._age_ticks + 1, 0)

    def _after_motion(self) -> None:
        """Read the bodies, judge contacts, take this tick's measurement."""
        self._true_pos = np.array([tuple(b.position) for b in self._robots], dtype=np.float64)
        self._true_vel = np.array([tuple(b.velocity) for b in self._robots], dtype=np.float64)
        ev = collision_events(torch.from_numpy(self._true_pos).unsqueeze(0), self._polygon,
                              self.scenario.robot_radius, self.scenario.arena)
        self._contacts = Contacts(robot=ev.robot[0].numpy(), object=ev.object[0].numpy(),
                                  wall=ev.wall[0].numpy())
        me = self.model_error
        self._meas_pos, self._meas_vel = self._true_pos, self._true_vel
        if me.position_noise_std > 0:
            self._meas_pos = self._true_pos + self._rng_noise.normal(0, me.position_noise_std, (len(self._robots), 2))
        if me.velocity_noise_std > 0:
            self._meas_vel = self._true_vel + self._rng_noise.normal(0, me.velocity_noise_std, (len(self._robots), 2))
        self._deliver()

    def _state(self, pos: np.ndarray, vel: np.ndarray, acted_seq: np.ndarray | None = None) -> FleetState:
        return FleetState(time=self._step * self.dt, step=self._step, positions=pos.copy(),
                          velocities=vel.copy(), targets=self._targets.copy(),
                          object_pose=self._object_pose.copy(),
                          commands_pending=self._sent - (self._delivered_seq if acted_seq is None else acted_seq))
