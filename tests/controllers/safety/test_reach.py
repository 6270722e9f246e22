"""The ball of a robot that is not listening: hand-worked discs at rest and on the move."""

from __future__ import annotations

import numpy as np

from controllers.safety.reach import reach
from sim.scenario import Dynamics

DYN = Dynamics()            # dt 0.05 s, damping 0.5 1/s, accel limit 1, speed limit 0.4


def test_reach_of_a_robot_at_rest_and_of_one_moving_hand_worked():
    # at rest: the centre stays, R = a t^2 / 2 while t <= T_b
    centre, cvel, radius, rate = reach(np.array([[0.5, 0.5]]), np.zeros((1, 2)), np.array([0.2]), 0.3, DYN,
                                       np.array([0.5]))
    np.testing.assert_allclose(centre, [[0.5, 0.5]])
    np.testing.assert_allclose(radius, [0.5 * 0.5 * 0.04])
    np.testing.assert_allclose(rate, [0.5 * 0.2])
    # moving at 0.2 m/s along x, t = 0.5 s, T_b = 0.3 s, a = 0 (it only ever ran zero commands):
    # far: coast 0.3 s (0.06 m), then brake 0.2 s at 1 m/s^2 from 0.2 m/s: 0.04 - 0.02 = 0.02 m
    # near: brake at once, stops after 0.2 s: 0.02 m. Interval [0.02, 0.08]: centre 0.05, R 0.03
    centre, cvel, radius, rate = reach(np.array([[0.5, 0.5]]), np.array([[0.2, 0.0]]), np.array([0.5]), 0.3,
                                       DYN, np.array([0.0]))
    np.testing.assert_allclose(centre, [[0.55, 0.5]], atol=1e-12)
    np.testing.assert_allclose(radius, [0.03], atol=1e-9)
    np.testing.assert_allclose(cvel, [[0.0, 0.0]], atol=1e-12)       # both ends at rest by then
    # long silent: nothing grows any more
    later = reach(np.array([[0.5, 0.5]]), np.array([[0.2, 0.0]]), np.array([5.0]), 0.3, DYN, np.array([0.0]))
    np.testing.assert_allclose(later[2], radius, atol=1e-9)
    assert later[3][0] == 0.0
