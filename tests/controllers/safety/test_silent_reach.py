"""Where a silent robot can be, from the commands it was sent (controllers/safety/silent_reach.py)."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from controllers.safety.latency import LatencyConfig, LatencyPredictor
from controllers.safety.silent_reach import Sighting, branch_paths, narrowed, silent_paths
from controllers.scripted import ScriptedController
from sim.pymunk_world import ModelError, PymunkWorld
from sim.scenario import Dynamics, clip_norm, make_scenario
from stack.pipeline import ControlStack, StackConfig
from tests.frozen_neighbour import beside_a_frozen_robot

DYN = Dynamics()


def test_the_branches_of_a_robot_at_rest_asked_one_push_hand_worked():
    """u_0 = 0, u_1 = (1, 0), W = 1, dt 0.05, c 0.5. Branches (s, w): (0, 0) and (0, 1) stay;
    (1, 0): v = 0.05, x = 0.0025, then the brake stops it in one tick; (1, 1): the push held a
    tick more, v = 0.05 + 0.05 (1 - 0.025) = 0.09875, x = 0.0074375, then braking at the limit
    (-1) to v = 0.0462813, x = 0.0097516, then to rest."""
    commands = np.array([[0.0, 0.0], [1.0, 0.0]])
    paths = branch_paths(np.zeros(2), np.zeros(2), commands, np.zeros(2, dtype=bool), 1, DYN)
    assert paths.shape[0] == 4
    np.testing.assert_allclose(paths[:, -1, 0], [0.0, 0.0, 0.0025, 0.0097516], atol=1e-7)
    np.testing.assert_allclose(paths[:, :, 1], 0.0)
    np.testing.assert_allclose(paths[3, 1:3, 0], [0.0025, 0.0074375], atol=1e-9)


def test_a_command_sent_as_brake_is_the_braking_law_whatever_was_recorded():
    """A BRAKE row brakes the robot from its own velocity; the recorded vector is not applied."""
    commands = np.array([[0.0, 0.0], [1.0, 0.0]])
    paths = branch_paths(np.zeros(2), np.array([0.2, 0.0]), commands, np.array([False, True]), 0, DYN)
    by_brake = branch_paths(np.zeros(2), np.array([0.2, 0.0]), commands[:1], np.array([False]), 0, DYN)
    np.testing.assert_allclose(paths[1, -1], by_brake[0, -1], atol=1e-12)


@st.composite
def silent_robot(draw):
    m = draw(st.integers(0, 6))
    hold = draw(st.integers(0, 2))
    rng = np.random.default_rng(draw(st.integers(0, 2**31)))
    speed = draw(st.floats(0.0, DYN.speed_limit))
    angle = rng.uniform(0, 2 * np.pi)
    vel0 = speed * np.array([np.cos(angle), np.sin(angle)])
    commands = clip_norm(rng.normal(0, 0.8, (m + 1, 2)), DYN.accel_limit)
    braking = rng.random(m + 1) < 0.2
    s, w = int(rng.integers(0, m + 1)), int(rng.integers(0, hold + 1))
    accel_error = draw(st.floats(0.0, 0.5))
    return vel0, commands, braking, hold, s, w, accel_error, rng


@settings(max_examples=200, deadline=None)
@given(silent_robot())
def test_the_disc_holds_a_robot_on_any_branch_with_any_acceleration_error(case):
    """A robot that follows any branch ``(s, w)`` and misses every asked acceleration by up to
    ``A``, and the braking law by up to ``accel_uncertainty`` at full braking (in proportion
    below it: a robot at rest stays at rest), lies in the disc at every tick."""
    vel0, commands, braking, hold, s, w, accel_error, rng = case
    brake_error = 0.05
    paths = silent_paths(np.zeros(2), vel0, [(commands, braking)], hold, accel_error, brake_error, 0.0, DYN)
    p, v = np.zeros((1, 2)), vel0[None].copy()
    for n in range(1, int(round(paths.settled_s / DYN.dt)) + 6):
        acting = n <= s + w
        index = n if n <= s else s
        brakes = not acting or braking[index]
        asked = DYN.brake(v) if brakes else commands[index][None]
        bound = brake_error * np.linalg.norm(asked) / DYN.accel_limit if brakes else accel_error
        direction = rng.normal(size=2)
        error = bound * rng.uniform(0, 1) * direction / np.linalg.norm(direction)
        p, v = DYN.step_np(p, v, asked + error)
        centre, _, radius, _ = paths.disc(n * DYN.dt)
        assert np.linalg.norm(p[0] - centre) <= radius + 1e-9, (n, s, w)
        cover = paths.cover(n * DYN.dt, 0.01, 4)
        if cover is not None:
            assert len(cover[1]) <= 4
            assert (np.linalg.norm(p[0] - cover[0], axis=1) - cover[1]).min() <= 1e-9, (n, s, w)


def test_a_robot_that_went_on_along_its_heading_is_covered_by_narrow_discs_along_it():
    """At 0.3 m/s along x, asked nothing, three commands pending and two ticks of hold: its
    twelve branches come to rest on the x axis between 33 mm (braking at once) and 95 mm
    (coasting five ticks first, slowed by the damping), 61.5 mm apart (the disc of them all:
    half that and more). Once every branch has stopped, the cover is
    discs centred on the axis, each holding its rest points within ``e + merge``, all of them
    held, none wider than half the one disc."""
    commands, braking = np.zeros((4, 2)), np.zeros(4, dtype=bool)
    paths = silent_paths(np.zeros(2), np.array([0.3, 0.0]), [(commands, braking)], 2, 0.05, 0.05, 0.0, DYN)
    rest = paths.points[:, -1]
    assert np.ptp(rest[:, 1]) == 0.0 and 0.061 < np.ptp(rest[:, 0]) < 0.062
    assert paths.cover(paths.settled_s - DYN.dt, 0.01, 6) is None
    t = paths.settled_s + 0.5
    centres, radii = paths.cover(t, 0.01, 6)
    _, _, radius, _ = paths.disc(t)
    error = paths.error(int(round(t / DYN.dt)) + 1)
    assert radius > 0.5 * np.ptp(rest[:, 0])
    assert np.abs(centres[:, 1]).max() == 0.0 and len(radii) <= 6
    assert radii.max() <= error + 0.01 + 1e-12 and radii.max() < 0.5 * radius
    assert ((np.abs(rest[:, None, 0] - centres[None, :, 0]) <= radii - error + 1e-12).any(axis=1)).all()
    assert len(paths.cover(t, 0.01, 2)[1]) <= 2 and paths.cover(t, 0.01, 2)[1].max() > radii.max()


def test_a_robot_at_rest_asked_alternating_pushes_is_a_small_disc_not_a_ball():
    """At rest, asked +-1 m/s^2 in turn, silent from t = 0.8 s: at 1.5 s the ball of the
    largest command has grown it past 0.1 m; its commands keep it within 3 cm (a push held for the two
    ticks of the watchdog moves it 1.5 cm before it brakes; the branches
    are taken when it first counts as stale, at 1.0 s, and kept for that last state)."""
    pred = LatencyPredictor(DYN, LatencyConfig())
    ids = ("r",)
    for k in range(pred.depth):
        pred.record(ids, np.array([[1.0 if k % 2 else -1.0, 0.0]]))
    pos, vel, a_nom = np.array([[0.5, 0.5]]), np.zeros((1, 2)), np.zeros((1, 2))
    first = pred.predict(ids, pos, vel, np.array([0.2]), a_nom, pending=np.array([4]), now=1.0)
    for _ in range(14):
        pred.record(ids, np.zeros((1, 2)), np.array([True]))
    ball = pred.predict(ids, pos, vel, np.array([0.7]), a_nom, pending=np.array([18]))
    branches = pred.predict(ids, pos, vel, np.array([0.7]), a_nom, pending=np.array([18]), now=1.5)
    assert first.fixed[0] and ball.fixed[0] and branches.fixed[0]
    assert ball.grow[0] > 0.1
    assert first.grow[0] < 0.03 and branches.grow[0] < 0.03
    assert np.linalg.norm(branches.pos[0] - pos[0]) < 0.01


def test_without_the_history_of_a_robot_the_ball_stands():
    """A robot seen stale from its first tick has no commands on record: it may be doing
    anything the actuator allows, so it keeps the ball of ``accel_limit``."""
    pred = LatencyPredictor(DYN, LatencyConfig())
    ids = ("new",)
    pos, vel, age = np.array([[0.5, 0.5]]), np.zeros((1, 2)), np.array([0.2])
    ball = pred.predict(ids, pos, vel, age, np.zeros((1, 2)), pending=np.array([4]))
    with_now = pred.predict(ids, pos, vel, age, np.zeros((1, 2)), pending=np.array([4]), now=1.0)
    np.testing.assert_allclose(with_now.grow, ball.grow)


def _frozen_misses(seed: int, config: LatencyConfig) -> int:
    """Ticks at which the frozen robot's true centre lay outside the disc the stack predicted
    for that tick (pymunk, scripted controller, a robot frozen mid-motion)."""
    sc = make_scenario(("paper-3", "paper-4", "paper-5")[seed % 3])
    rng = np.random.default_rng(seed)
    robot, tick = int(rng.integers(sc.num_robots)), int(rng.integers(8, 30))
    world = PymunkWorld(sc, ModelError(freeze=(robot, tick)))
    stack = ControlStack(sc, ScriptedController(sc), StackConfig(latency=config))
    predictions = []
    predict = stack.predictor.predict
    stack.predictor.predict = lambda *a, **k: predictions.append(predict(*a, **k)) or predictions[-1]
    state, due, misses = world.reset(seed=seed), {}, 0
    stack.reset()
    ahead = int(round(config.command_delay_s / sc.dynamics.dt))
    for k in range(tick + 30):
        result = stack.tick(state)
        if result.stale[robot]:
            covers = [(c, r) for row, c, r in predictions[-1].covers if row == robot]
            centres, radii = covers[0] if covers else (predictions[-1].pos[robot][None], predictions[-1].grow[robot:robot + 1])
            due[k + ahead] = (centres.copy(), radii.copy())
        world.send_accelerations(result.a_cmd)
        state = world.step()
        if k + 1 in due:
            centres, radii = due.pop(k + 1)
            true = world.true_state().positions[robot]
            misses += bool((np.linalg.norm(true - centres, axis=1) - radii).min() > 1e-9)
    return misses


@pytest.mark.parametrize("seed", range(6))
def test_the_disc_of_a_frozen_pymunk_robot_holds_its_true_centre(seed):
    """The pymunk robot frozen mid-motion (silent and deaf, its last command held two ticks,
    then its watchdog brakes it): the disc from its commands (its cover, once it is at rest)
    holds its true centre at every tick it is predicted for, so the branches line up with the
    world's ticks and commands."""
    assert _frozen_misses(seed, LatencyConfig()) == 0


def test_without_the_hold_branches_a_deaf_robot_holding_its_push_is_missed():
    """At rest, asked u_0 = +1 then u_1 = -1 along x, deaf at once: it holds u_0 for the two
    ticks of its watchdog (x = 0.0074 m), then brakes. The branches with the hold hold it;
    without them (W = 0) every branch stays at x <= 0 and the disc misses it."""
    commands, braking = np.array([[1.0, 0.0], [-1.0, 0.0]]), np.zeros(2, dtype=bool)
    p, v = np.zeros((1, 2)), np.zeros((1, 2))
    truth = []
    for n in range(12):
        p, v = DYN.step_np(p, v, commands[:1] if n < 2 else DYN.brake(v))
        truth.append(p[0].copy())
    for hold, expected in ((2, 0), (0, 1)):
        paths = silent_paths(np.zeros(2), np.zeros(2), [(commands, braking)], hold, 0.05, 0.05, 0.0, DYN)
        missed = [n for n, x in enumerate(truth, 1)
                  if np.linalg.norm(x - paths.disc(n * DYN.dt)[0]) > paths.disc(n * DYN.dt)[2]]
        assert bool(missed) == bool(expected), (hold, missed)


def _beside_a_frozen_robot(discs: int) -> tuple[float, float]:
    """:func:`tests.frozen_neighbour.beside_a_frozen_robot` with robot 1's goal at (0.36, 0.78),
    103 mm from where robot 0 comes to rest, off its heading, and ``discs`` cover discs."""
    return beside_a_frozen_robot((0.36, 0.78), StackConfig(latency=LatencyConfig(cover_discs=discs)), 80)


def test_a_neighbour_comes_closer_beside_a_frozen_robot_under_its_cover_than_its_one_disc():
    """The frozen robot's branches come to rest along its heading (rest points spread 119 mm
    along it, 10 mm across): the one disc round them all (radius 75 mm) keeps robot 1 45 mm off
    its goal; the cover (six discs of 15-17 mm along the heading) lets it to 18 mm; neither
    lets it touch (smallest gaps 68 and 40 mm)."""
    near, gap = _beside_a_frozen_robot(6)
    far, gap_one = _beside_a_frozen_robot(1)
    assert near < 0.025 and far > 0.04
    assert gap > 0.03 and gap_one > 0.03


def test_a_sighting_narrows_a_cover_hand_worked():
    """Cover discs of grow 10 mm at x = 0, 20, 40 mm. A sighting at x = 40 mm of grow 8 mm meets
    only the last (20 mm apart > 10 + 8) and is the smaller (64 < 100 mm^2): the sighting's disc,
    closing at its speed. One of grow 30 mm at x = 45 mm meets the last two (not the first, 45 >
    40 mm away), whose 200 mm^2 beat its 900: those two, the row's own closing (inf). One at
    x = 100 mm meets none: both pictures kept."""
    cover = (np.array([[0.0, 0.0], [0.02, 0.0], [0.04, 0.0]]), np.full(3, 0.01))
    (c, r), closing = narrowed(cover, Sighting(np.array([0.04, 0.0]), 0.008, 0.02, 1.0))
    np.testing.assert_allclose(c, [[0.04, 0.0]])
    np.testing.assert_allclose(r, [0.008])
    assert closing == 0.02
    (c, r), closing = narrowed(cover, Sighting(np.array([0.045, 0.0]), 0.03, 0.02, 1.0))
    np.testing.assert_allclose(c, [[0.02, 0.0], [0.04, 0.0]])
    np.testing.assert_allclose(r, [0.01, 0.01])
    assert closing == np.inf
    (c, r), _ = narrowed(cover, Sighting(np.array([0.1, 0.0]), 0.008, 0.02, 1.0))
    assert len(r) == 4 and r[-1] == 0.008


@settings(max_examples=300, deadline=None)
@given(st.integers(1, 6), st.integers(0, 2**32 - 1))
def test_a_point_in_the_cover_and_the_sighting_stays_in_the_narrowed_discs(k, seed):
    rng = np.random.default_rng(seed)
    centres, radii = rng.uniform(0, 0.1, (k, 2)), rng.uniform(0.001, 0.03, k)
    j = int(rng.integers(k))
    point = centres[j] + radii[j] * rng.uniform(0, 1) * np.array([np.cos(a := rng.uniform(0, 6.3)), np.sin(a)])
    grow = float(rng.uniform(0.001, 0.05))
    sighting = Sighting(point + grow * rng.uniform(0, 1) * np.array([np.cos(b := rng.uniform(0, 6.3)), np.sin(b)]),
                        grow, 0.0, 0.0)
    (c, r), _ = narrowed((centres, radii), sighting)
    assert (np.linalg.norm(c - point, axis=1) - r).min() <= 1e-12
