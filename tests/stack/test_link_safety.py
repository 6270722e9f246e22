"""Forward invariance on an imperfect link: the default stack (filter + MEC) in pymunk, with teeth.

Each condition is a :class:`sim.model_error.ModelError` of a real link: command delay of 1-3
ticks, a delay that jitters 1-3 ticks from command to command, measurement noise (1 cm, 2 cm/s),
20 % of the states lost, a robot that freezes mid-episode. Robots (3-8, random starts inside
the safe set of the default latency bound) keep adversarial modes: full thrust at the nearest
robot, at the object, at the nearest wall, or along a random direction. The default
``StackConfig()`` never lets two shapes touch; the same episodes with the latency terms switched
off (``LatencyConfig(enabled=False)``: the filter judges the state it is given, as before) do.
Docking is off in every adversarial episode (:func:`adversarial`): near a free target it would
take the robot over from the adversary, whose commands are the point.
"""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from controllers.docking import DockingConfig
from controllers.safety import SafetyConfig, SafetyFilter, analytic_distances
from controllers.safety.latency import LatencyConfig
from sim.fleet import FleetState
from sim.pymunk_world import ModelError, PymunkWorld
from sim.scenario import transport_scenario
from stack.pipeline import ControlStack, StackConfig, run_episode

STEPS = 60
WALL_DIRS = np.array([[-1.0, 0.0], [1.0, 0.0], [0.0, -1.0], [0.0, 1.0]])
CONDITIONS = {
    "delay1": ModelError(delay_ticks=1),
    "delay2": ModelError(delay_ticks=2),
    "delay3": ModelError(delay_ticks=3),
    "delay_jitter": ModelError(delay_ticks=1, delay_jitter_ticks=2),
    "noise": ModelError(position_noise_std=0.01, velocity_noise_std=0.02),
    "drops": ModelError(state_drop=0.2),
}
NO_LATENCY = StackConfig(latency=LatencyConfig(enabled=False))


NO_DOCKING = DockingConfig(enabled=False)


def adversarial(config: StackConfig, docking: DockingConfig = NO_DOCKING) -> StackConfig:
    """``config`` without docking (or with ``docking``): the adversary's commands reach the filter
    unreplaced."""
    return dataclasses.replace(config, docking=docking)


class Adversary:
    """FleetState -> (N, 2): each robot keeps one mode (module docstring) for the episode."""

    def __init__(self, scenario, rng):
        n = scenario.num_robots
        self.scenario, self.rng = scenario, rng
        self.modes = rng.integers(0, 4, n)
        self.fixed = rng.normal(size=(n, 2))

    def __call__(self, state: FleetState) -> np.ndarray:
        pos, n = state.positions, state.num_robots
        d = np.linalg.norm(pos[:, None] - pos[None], axis=-1) + np.eye(n) * 1e9
        walls = np.stack([pos[:, 0], 1 - pos[:, 0], pos[:, 1], 1 - pos[:, 1]], 1)
        thrust = np.stack([pos[np.argmin(d, axis=1)] - pos, self.scenario.object_center - pos,
                           WALL_DIRS[np.argmin(walls, axis=1)], self.fixed])[self.modes, np.arange(n)]
        return thrust / np.maximum(np.linalg.norm(thrust, axis=1, keepdims=True), 1e-12)


def start(world: PymunkWorld, rng, coast_ticks: int = 3) -> FleetState:
    """Positions 3 cm apart, velocities scaled until h >= 0 holds at the state and at every state
    the robots coast to over ``coast_ticks`` (no robot can brake before its first command)."""
    sc = world.scenario
    filt = SafetyFilter(sc)
    pos = np.zeros((0, 2))
    while len(pos) < sc.num_robots:
        cand = np.vstack([pos, rng.uniform(0.06, 0.94, (1, 2))])
        if analytic_distances(cand, sc.robot_radius, sc.arena, sc.polygon).min_clearance() >= 0.03:
            pos = cand
    vel = rng.normal(0.0, 0.15, pos.shape)

    def safe(p, v):
        for _ in range(coast_ticks + 1):
            if filt.barrier(p, v).h.min() < 0:
                return False
            p, v = sc.dynamics.step_np(p, v, np.zeros_like(v))
        return True

    while not safe(pos, vel):
        vel *= 0.8
    world.set_state(pos, vel)
    return world.read_state()


def collided(seed: int, model_error: ModelError | None, config: StackConfig,
             robots: tuple[int, int] = (3, 8)) -> bool:
    """One adversarial episode of ``robots[0] .. robots[1]`` robots; ``model_error`` None: a
    random robot freezes at tick 10-30."""
    rng = np.random.default_rng(seed)
    sc = transport_scenario(robots[0] + seed % (robots[1] - robots[0] + 1))
    if model_error is None:
        model_error = ModelError(freeze=(int(rng.integers(sc.num_robots)), int(rng.integers(10, 30))))
    world = PymunkWorld(sc, model_error)
    stack = ControlStack(sc, Adversary(sc, rng), adversarial(config))
    return run_episode(world, stack, seed, STEPS, start=lambda w: start(w, rng)).collided


# (condition, robots, episodes, extra seeds): one tick of delay and dropped states take a crowd
# (8-14 robots) before the filter without latency terms is caught out (1 of 16 episodes each,
# measured). Since the post-check excuses commands no worse than braking, the filter without
# latency terms touches under dropped states in 1 of seeds 16-95 only (57, measured): it joins
# the seeds, as a case that must not touch with the terms and that gives the test its teeth.
CASES = [("delay1", (8, 14), 16, ()), ("delay2", (3, 8), 10, ()), ("delay3", (3, 8), 10, ()),
         ("delay_jitter", (3, 8), 10, ()), ("noise", (3, 8), 10, ()), ("drops", (8, 14), 16, (57,))]


@pytest.mark.slow
@pytest.mark.parametrize(("name", "robots", "episodes", "extra"), CASES)
def test_no_contact_on_an_imperfect_link_and_contacts_without_the_latency_terms(name, robots, episodes, extra):
    seeds = [*range(episodes), *extra]
    on = [s for s in seeds if collided(s, CONDITIONS[name], StackConfig(), robots)]
    assert on == [], f"{name}: seeds {on} collided with the default stack"
    off = sum(collided(s, CONDITIONS[name], NO_LATENCY, robots) for s in seeds)
    assert off >= 1, f"{name}: no teeth, the filter without latency terms never collided"


@pytest.mark.slow
def test_a_frozen_robot_is_kept_clear_of_and_is_run_into_without_the_latency_terms():
    seeds = range(20)
    on = [s for s in seeds if collided(s, None, StackConfig())]
    assert on == []
    assert sum(collided(s, None, NO_LATENCY) for s in seeds) >= 1


@pytest.mark.slow
def test_two_centimetres_of_position_noise_are_filtered_out_and_touch_without_the_noise_terms(monkeypatch):
    """2 cm / 4 cm/s of measurement noise. The stack's two answers to it: the position estimator
    (filtered positions, its standard deviation grows the discs) and two standard deviations of
    the measured velocity noise counted as approach speed. Without both, seeds 1, 9, 10, 17, 19,
    23, 26, ... of 0-63 touch (14 of 64, measured); without the velocity allowance alone, seed 19
    does (a robot creeping into the object: the static rows count on ``a_box / sqrt(2)``)."""
    noisy = ModelError(position_noise_std=0.02, velocity_noise_std=0.04)
    touched_bare = (17, 19, 23, 26)          # of seeds 16-63, the first that touch without both
    seeds = [*range(16), *touched_bare]
    on = [s for s in seeds if collided(s, noisy, StackConfig())]
    assert on == [], f"seeds {on} collided with the default stack"
    no_allowance = LatencyConfig(measured_velocity_sigmas=0.0)
    assert collided(19, noisy, StackConfig(latency=no_allowance)), "no teeth: the velocity allowance"
    # as the filter was when these seeds were found: one slack weight for every row (with the
    # static rows' weight alone, seed 26 stays clear) and no object excuse in the post-check
    # (with it, robots braked beside the object may leave it: 17, 19 and 23 stay clear)
    no_object_excuse(monkeypatch)
    bare_filter = SafetyConfig(static_slack_factor=1.0)
    raw = [s for s in touched_bare if collided(s, noisy, StackConfig(estimated_position=False, latency=no_allowance,
                                                                    safety_config=bare_filter))]
    assert raw == list(touched_bare), "no teeth: the filter on raw noisy positions did not collide"


def crowd_collided(seed: int, config: StackConfig, docking: DockingConfig = NO_DOCKING) -> bool:
    """One episode of ``bench/safety.py``'s conditions (its adversary, 3-16 robots) with a delay
    that jitters 1-3 ticks, each robot acting on the newest command that arrived; the robots
    start inside the safe set of ``config``'s filter (the bench's, for the default); docking off
    unless ``docking`` is given."""
    import sys
    from pathlib import Path
    sys.path.insert(0, str(Path(__file__).resolve().parents[2] / "bench"))
    from _adversary import MAX_ROBOTS, MIN_ROBOTS, AdversarialPolicy, random_start
    rng = np.random.default_rng(seed)
    sc = transport_scenario(int(rng.integers(MIN_ROBOTS, MAX_ROBOTS + 1)))
    world = PymunkWorld(sc, CONDITIONS["delay_jitter"])
    barrier = SafetyFilter(sc, config.safety_config)
    stack = ControlStack(sc, AdversarialPolicy(sc, rng), adversarial(config, docking))
    return run_episode(world, stack, seed, STEPS, start=lambda w: random_start(w, barrier, rng)).collided


def no_excuses(monkeypatch):
    """Switch off the post-check's rule that excuses commands no worse than braking."""
    from controllers.safety import fused, postcheck

    def never(pos, vel, acc, brake, pi, *rest):
        return np.zeros(len(pi), dtype=bool), np.zeros((len(pos), 4), dtype=bool)
    monkeypatch.setattr(fused, "excuses", never)
    monkeypatch.setattr(postcheck, "excuses", never)
    no_object_excuse(monkeypatch)


def no_object_excuse(monkeypatch):
    """Switch off the same rule for the object (the post-check before it had one)."""
    from controllers.safety import postcheck

    monkeypatch.setattr(postcheck.SweepChecker, "object_excused", lambda self, *args: False)


@pytest.mark.slow
def test_a_jittering_robot_braked_from_its_prediction_is_run_into_and_not_from_its_measurement(monkeypatch):
    """Crowds of 10-15 robots where the QP is infeasible and pairs are braked: a brake computed from
    a prediction that counts on pending commands a newer one then overtook never stops the robot
    (bench/safety.py ``delay_jitter`` seeds 3, 24, 33: each touched before the rule). Since the
    post-check excuses commands no worse than braking, these seeds stay clear even without the
    rule (so do seeds 0-79, measured); the rule's teeth are shown with the excuse off. Since the
    filter's gain is 6 (3 for unsure robots), seed 3 stays clear without the rule too, and since
    the static rows count on ``a_box / sqrt(2)`` (was ``a_box / 2``), seed 24 as well."""
    seeds = (3, 24, 33)
    old = StackConfig(latency=LatencyConfig(jitter_brake_measured=False))
    assert [s for s in seeds if crowd_collided(s, StackConfig())] == []
    no_excuses(monkeypatch)
    assert [s for s in seeds if crowd_collided(s, StackConfig())] == []
    assert [s for s in seeds if crowd_collided(s, old)] == [33]


def scripted_paper5_succeeds(seed: int) -> bool:
    """A scripted paper-5 episode under ``delay_jitter`` with the default stack (the episode of
    ``bench/safety.py --only conditions``' scripted column for ``seed``)."""
    from controllers.scripted import ScriptedController
    from sim.scenario import make_scenario
    sc = make_scenario("paper-5")
    world = PymunkWorld(sc, CONDITIONS["delay_jitter"])
    return run_episode(world, ControlStack(sc, ScriptedController(sc), StackConfig()), seed).success


def test_robots_braked_inside_their_grown_discs_move_apart_instead_of_freezing(monkeypatch):
    """Liveness of the post-check on a jittering link (bench seed 8, paper-5): robots 3 and 4
    stopped 16 mm apart, inside their discs grown by the jitter allowance (7.1 and 8.0 mm); the
    post-check braked both on 121 of 128 ticks, even while the QP pushed them apart, and the
    episode ended 0.209 m off. Excusing commands no worse than braking lets the pair move apart,
    and the episode succeeds. Since the static rows count on ``a_box / sqrt(2)`` seed 8 succeeds
    without the excuse too; seeds 2 and 12 of 0-23 do not (measured; not traced robot by robot)."""
    assert scripted_paper5_succeeds(2)
    no_excuses(monkeypatch)
    assert not scripted_paper5_succeeds(2)


@pytest.mark.slow
def test_robots_whose_delay_jitters_brake_earlier_and_touch_without_it():
    """The filter starts braking later (class-K gain ``gamma`` 6) except in the rows of a robot
    whose delay is not known to hold (``gamma_unsure`` 3): there a brake the prediction counted
    on may be overtaken and never act. ``bench/safety.py`` ``delay_jitter`` seed 184 (8 robots)
    touches the object (0.2 mm deep) with the raised gain on every row, not with the default. With
    the static rows at ``a_box / sqrt(2)`` and the measured velocity noise in the approach
    allowance, the raised gain touched in none of seeds 0-149 (measured), so its teeth are shown
    where the rule was made: static rows at ``a_box / 2`` and one slack weight for every row, no
    velocity allowance, and the episode as the bench ran it then, docking on at its capture
    radius of the time (6 cm). With docking off, the raised gain touches in none of seeds 0-399
    even there (measured 2026-12-05)."""

    then = DockingConfig(release_radius=0.08, stall_radius=0.0)
    before = LatencyConfig(measured_velocity_sigmas=0.0)
    assert not crowd_collided(184, StackConfig(), then)
    assert not crowd_collided(184, StackConfig(), DockingConfig())
    old_filter = SafetyConfig(static_braking_share=0.5, static_slack_factor=1.0)
    assert not crowd_collided(184, StackConfig(safety_config=old_filter, latency=before), then)
    raised = SafetyConfig(gamma_unsure=6.0, static_braking_share=0.5, static_slack_factor=1.0)
    assert crowd_collided(184, StackConfig(safety_config=raised, latency=before), then)


def test_a_robot_squeezed_against_the_object_by_another_holds_off_the_object():
    """``bench/safety.py`` ``delay_jitter`` seed 122 (15 robots, docking off): robot 6 thrusts at
    the object with robot 1 pressing behind it, and the rows cannot all hold. With one slack
    weight for every row, the slack QP met the pair row by driving robot 6 towards the object
    (0.92 m/s^2) and it touched 0.2 mm deep at tick 39; with the object and wall rows weighing
    ``static_slack_factor`` (100) times more, the pair gives way and nothing touches."""

    assert not crowd_collided(122, StackConfig())
    assert crowd_collided(122, StackConfig(safety_config=SafetyConfig(static_slack_factor=1.0)))


L_OBJECT = ((0.35, 0.35), (0.65, 0.35), (0.65, 0.45), (0.45, 0.45), (0.45, 0.65), (0.35, 0.65))
"""An L-shaped object: its re-entrant corner is at (0.45, 0.45), between the faces y = 0.45 and x = 0.45."""


def corner_contacts(model_error: ModelError) -> list[int]:
    """Which of nine single-robot approaches to the L's re-entrant corner touch the object, the
    default stack between a full-thrust command and pymunk: three slides along the floor y = 0.45
    into the wall x = 0.45 (12, 15, 20 mm over the floor), six at the corner itself from
    directions 31-59 degrees."""
    sc = transport_scenario(1, object_vertices=L_OBJECT)
    corner = np.array([0.45, 0.45])
    runs = [((0.85, 0.49 + gap), (-10.0, 0.49 + gap)) for gap in (0.012, 0.015, 0.02)]
    for dx, dy in [(1, 1), (1, 0.8), (0.8, 1), (1, 0.6), (0.6, 1), (1, 0.9)]:
        d = np.array([dx, dy]) / np.hypot(dx, dy)
        runs.append((tuple(corner + 0.04 * np.sqrt(2) + 0.25 * d), tuple(corner)))
    touched = []
    for k, (begin, aim) in enumerate(runs):
        world = PymunkWorld(sc, model_error)

        def begin_at(w, begin=begin):
            w.set_state(np.array([begin]))
            return w.read_state()

        stack = ControlStack(sc, lambda s, aim=aim: np.array([aim]) - s.positions, StackConfig())
        if run_episode(world, stack, k, STEPS, start=begin_at).collided:
            touched.append(k)
    return touched


def nearest_piece_only(monkeypatch):
    """Give every robot's object rows the row of its nearest convex piece: one row for the object
    per robot, as the filter had before."""
    from controllers.safety.fused import FusedScene

    rows = FusedScene.object_section

    def nearest(self, pos, pieces):
        s, normal, curvature = rows(self, pos, pieces)
        q = self.pieces
        pick = np.repeat(s.reshape(-1, q).argmin(axis=1) + q * np.arange(len(pos)), q)
        return s[pick], normal[pick], curvature[pick]
    monkeypatch.setattr(FusedScene, "object_section", nearest)


@pytest.mark.slow
def test_a_robot_driven_into_a_re_entrant_corner_of_the_object_stays_off_it(monkeypatch):
    """The filter keeps one object row per robot and convex piece of the object. With one row per
    robot (its nearest face), the face the robot heads for in the L's corner got its row too
    late: on a clean link 5 of the 9 approaches touched (about 1 mm deep); on a link with one
    tick of delay that jitters by two, 1 cm / 2 cm/s of noise and a fifth of the states dropped,
    1 of the 9 (measured)."""
    link = ModelError(delay_ticks=1, delay_jitter_ticks=2, position_noise_std=0.01,
                      velocity_noise_std=0.02, state_drop=0.2)
    assert corner_contacts(ModelError()) == []
    assert corner_contacts(link) == []
    nearest_piece_only(monkeypatch)
    assert len(corner_contacts(ModelError())) >= 3


JITTER_NOISE_DROPS = ModelError(delay_ticks=1, delay_jitter_ticks=2, position_noise_std=0.01,
                                velocity_noise_std=0.02, state_drop=0.2)


def combined_collided(seed: int, model_error: ModelError = JITTER_NOISE_DROPS) -> bool:
    """``bench/safety.py``'s adversarial episode ``seed`` (its adversary, 3-16 robots, docking
    off, the default stack) with, by default, a delay that jitters 1-3 ticks, 1 cm / 2 cm/s of
    measurement noise and 20 % of the states lost, all at once."""
    import sys
    from pathlib import Path
    sys.path.insert(0, str(Path(__file__).resolve().parents[2] / "bench"))
    from _adversary import MAX_ROBOTS, MIN_ROBOTS, AdversarialPolicy, random_start
    rng = np.random.default_rng(seed)
    sc = transport_scenario(int(rng.integers(MIN_ROBOTS, MAX_ROBOTS + 1)))
    world = PymunkWorld(sc, model_error)
    barrier = SafetyFilter(sc)
    stack = ControlStack(sc, AdversarialPolicy(sc, rng), adversarial(StackConfig()))
    return run_episode(world, stack, seed, STEPS, start=lambda w: random_start(w, barrier, rng)).collided


@pytest.mark.slow
def test_lost_and_stale_states_are_carried_through_the_commands_in_flight_on_a_poor_link(monkeypatch):
    """Jitter, noise and drops at once: two of the bench's seeds that touched, each with its rule
    switched off. Seed 292 (16 robots): a robot's state lost one tick after the start read the
    MEC's velocity predicted to now, which the latency prediction carried through the command
    sent since a second time; coasting at 0.175 m/s 4 cm from a wall, it was judged at 0.084
    m/s and let accelerate into it (0.14 mm deep). Seed 223 (7 robots): a robot sliding round
    the object's corner went stale and was sent BRAKE from its last measured velocity, 0.15 s
    behind the commands in flight, three ticks along a direction into the object's face
    (0.46 mm; it needed both rules). Since a late robot's disc also covers it having stopped
    (``cover_late``), seed 223 stays clear without the second rule, whose teeth are shown on
    seed 131 of noise and drops without jitter: a robot whose state was lost seven ticks running
    got the BRAKE of its last measured velocity five ticks running and was driven into a wall."""
    from controllers.mec import ModelErrorCompensator
    from controllers.safety.latency import LatencyPredictor
    assert not combined_collided(292)
    assert not combined_collided(223)
    noise_drops = ModelError(position_noise_std=0.01, velocity_noise_std=0.02, state_drop=0.2)
    assert not combined_collided(131, noise_drops)
    predict_to_now = ModelErrorCompensator.update

    def update(self, velocity, ids=None):
        out = predict_to_now(self, velocity, ids)
        self.v_measured = out
        return out
    with monkeypatch.context() as off:
        off.setattr(ModelErrorCompensator, "update", update)
        assert combined_collided(292)
    with monkeypatch.context() as off:
        off.setattr(LatencyPredictor, "_carried", lambda self, pos, vel, ages, pending, fixed, delay, v:
                    np.where(fixed[:, None], vel, v))
        assert combined_collided(131, noise_drops)
