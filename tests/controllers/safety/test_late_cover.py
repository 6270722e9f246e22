"""A robot whose state is late, covered listening and stopped (controllers/safety/late_cover.py)."""

from __future__ import annotations

import numpy as np
import pytest

from controllers.docking import DockingConfig
from controllers.safety.late_cover import cover_both
from controllers.safety.latency import LatencyConfig, LatencyPredictor
from sim.pymunk_world import ModelError, PymunkWorld
from sim.scenario import Dynamics, transport_scenario
from stack.pipeline import ControlStack, StackConfig

DYN = Dynamics()            # dt 0.05 s, damping 0.5 1/s, accel limit 1, speed limit 0.4


def test_the_disc_grows_to_hold_the_stopped_one_hand_worked():
    # row 0: stopped disc 10 mm behind, falling behind at 0.15 m/s
    #   g = max(0.004, 0.010 + 0.006) = 0.016
    #   c = max(0.03, (|-0.010 + (0.05 - 0.2) 0.05| + 0.006 - 0.016) / 0.05 + 0.05) = 0.0075 / 0.05 + 0.05 = 0.2
    # row 1: stopped disc inside the listening one with room to spare: both unchanged
    pos, vel = np.array([[0.0, 0.0], [0.0, 0.0]]), np.array([[0.2, 0.0], [0.2, 0.0]])
    grow, closing = np.array([0.004, 0.004]), np.array([0.03, 0.03])
    centre, centre_vel = np.array([[-0.010, 0.0], [0.001, 0.0]]), np.array([[0.05, 0.0], [0.2, 0.0]])
    g, c = cover_both(pos, vel, grow, closing, centre, centre_vel, np.array([0.006, 0.001]),
                      np.array([0.05, 0.01]), 0.05)
    np.testing.assert_allclose(g, [0.016, 0.004])
    np.testing.assert_allclose(c, [0.2, 0.03])


@pytest.mark.parametrize("seed", range(5))
def test_the_row_holds_the_stopped_disc_now_and_one_tick_on(seed):
    """Whatever the two discs, the row's disc holds the listening one and the stopped one now,
    and, moved by ``v dt`` and grown by ``c dt``, the stopped one moved by its own velocity and
    rate (module docstring, One disc for both)."""
    rng, k, dt = np.random.default_rng(seed), 200, 0.05
    pos, vel, centre, centre_vel = (rng.normal(0, s, (k, 2)) for s in (0.05, 0.3, 0.05, 0.3))
    grow, closing, grow2, closing2 = (rng.uniform(0, s, k) for s in (0.03, 0.3, 0.03, 0.3))
    g, c = cover_both(pos, vel, grow, closing, centre, centre_vel, grow2, closing2, dt)
    assert (g >= grow).all() and (c >= closing).all()
    assert (np.linalg.norm(centre - pos, axis=1) + grow2 <= g + 1e-12).all()
    ahead = centre + centre_vel * dt - (pos + vel * dt)
    assert (np.linalg.norm(ahead, axis=1) + grow2 + closing2 * dt <= g + c * dt + 1e-12).all()


def _late_and_stopped(config: LatencyConfig) -> tuple[float, float]:
    """A robot pushed along +x (u_0 = +1) is sent three brakes (-1) after its last state, which
    arrives one tick late: it was measured at 0.3 m/s and froze there, holding +1 for the two
    ticks of its watchdog, then braking. Returns its true centre's distance from the predicted
    one and the prediction's growth [m], at the tick the prediction is for."""
    pred, ids = LatencyPredictor(DYN, config), ("a",)
    push, brake = np.array([[1.0, 0.0]]), np.array([[-1.0, 0.0]])
    for u in (push, push, push, brake, brake, brake):
        pred.record(ids, u)
    pos, vel = np.array([[0.5, 0.5]]), np.array([[0.3, 0.0]])
    out = pred.predict(ids, pos, vel, np.array([DYN.dt]), brake, pending=np.array([3]), now=1.0)
    assert not out.fixed[0] and out.horizon[0] == 4          # listening, late: (0.05 + 0.15) / 0.05
    p, v = pos, vel
    for n in range(3):                                       # p is 3 ticks (the pending count) on
        p, v = DYN.step_np(p, v, push if n < 2 else DYN.brake(v))
    return float(np.linalg.norm(p[0] - out.pos[0])), float(out.grow[0])


def test_a_late_robot_that_stopped_acting_lies_in_its_disc():
    """Listening, it brakes three ticks; frozen, it goes on pushing two of them: the true centre
    lies 25 mm ahead of the predicted one. The listening disc alone (``cover_late=False``, 14 mm)
    misses it; the cover (39 mm) holds it."""
    miss, grow = _late_and_stopped(LatencyConfig(cover_late=False))
    assert miss > 0.01 and grow < miss
    miss, grow = _late_and_stopped(LatencyConfig())
    assert miss <= grow


def chase(config: LatencyConfig, ticks: int = 40) -> tuple[bool, float]:
    """Two robots of ``transport_scenario(2)`` in pymunk, gain 0.7 and two ticks of command delay:
    robot 0 starts at rest at (0.3, 0.3) and thrusts along +y at 1 m/s^2; robot 1 starts 30 mm
    behind it (20 mm aside) and thrusts at robot 0 at full acceleration. Robot 0 freezes at tick
    10 (0.3 m/s): its state stops, it holds its push two ticks and brakes. Returns whether the
    world recorded a contact and the smallest gap between the two discs [m] (true state)."""
    sc = transport_scenario(2)
    world = PymunkWorld(sc, ModelError(gain=0.7, delay_ticks=2, freeze=(0, 10)))
    world.reset(seed=0)
    r = sc.robot_radius
    world.set_state(np.array([[0.3, 0.3], [0.32, 0.3 - 2 * r - 0.03]]), np.zeros((2, 2)))
    state = world.read_state()

    def policy(s):
        d = s.positions[0] - s.positions[1]
        return np.array([[0.0, 1.0], d / np.linalg.norm(d)])

    stack = ControlStack(sc, policy, StackConfig(latency=config, docking=DockingConfig(enabled=False)))
    gap = np.inf
    for _ in range(ticks):
        result = stack.tick(state)
        world.send_accelerations(result.a_cmd)
        state = world.step()
        true = world.true_state().positions
        gap = min(gap, float(np.linalg.norm(true[0] - true[1])) - 2 * r)
    return world.collision_counts.any, gap


def test_a_neighbour_driving_at_a_robot_that_froze_is_held_off_from_its_first_late_tick():
    """Without the cover robot 1 is kept off robot 0's listening disc until robot 0 is stale
    (three ticks), then brakes two ticks late at 70 % and touches (0.3 mm); with it robot 1 is
    held back from the first late tick and stays 32 mm off."""
    touched, gap = chase(LatencyConfig())
    assert not touched and gap > 0.02
