"""Barrier values and rows against an independent formula and finite differences along the dynamics."""

from __future__ import annotations

import math

import numpy as np
import pytest

from controllers.safety.barrier import (
    SafetyConfig,
    SafetyConfigError,
    _phi,
    barrier_terms,
    octagon_accel,
)
from controllers.safety.geometry import analytic_distances
from sim.scenario import transport_scenario

SCENARIO = transport_scenario(5)
DYN = SCENARIO.dynamics
R = SCENARIO.robot_radius


DEFAULT = SafetyConfig()


def terms_at(pos, vel, config=DEFAULT):
    return barrier_terms(analytic_distances(pos, R, SCENARIO.arena, SCENARIO.polygon), vel, DYN, config)


def random_state(rng, n, min_clearance):
    while True:
        pos = rng.uniform(0.05, 0.95, (n, 2))
        d = analytic_distances(pos, R, SCENARIO.arena, SCENARIO.polygon)
        if d.min_clearance() > min_clearance:
            return pos, rng.normal(0.0, 0.2, (n, 2))


def test_pair_h_matches_the_paper_formula():
    """h_ij = sqrt(2 alpha (|dp| - 2r - m)) + dp.dv / |dp| with alpha = 2 * share * a_box."""
    rng = np.random.default_rng(0)
    cfg = SafetyConfig()
    pos, vel = random_state(rng, 5, 0.02)
    terms = terms_at(pos, vel, cfg)
    alpha = 2 * cfg.braking_share * octagon_accel(DYN, cfg)
    for k, (i, j) in enumerate(zip(*np.triu_indices(5, 1), strict=True)):
        dp, dv = pos[i] - pos[j], vel[i] - vel[j]
        dist = math.hypot(*dp)
        want = math.sqrt(2 * alpha * (dist - 2 * R - cfg.margin)) + dp @ dv / dist
        assert terms.h[k] == pytest.approx(want, rel=1e-12)
    # a wall row by hand: robot 0, wall x = 0, alpha = a_box / sqrt(2)
    p = 10
    alpha_s = octagon_accel(DYN, cfg) / math.sqrt(2)
    want = math.sqrt(2 * alpha_s * (pos[0, 0] - R - cfg.margin)) + vel[0, 0]
    assert terms.h[p + 5] == pytest.approx(want, rel=1e-12)


def _evolve(pos, vel, u, eps):
    """The continuous dynamics p' = v, v' = u - c v, exact to second order in eps."""
    acc = u - DYN.damping * vel
    return pos + eps * vel + 0.5 * eps**2 * acc, vel + eps * acc


@pytest.mark.parametrize("class_k", ["linear", "cubic"])
def test_hdot_and_jacobian_match_finite_differences(class_k):
    rng = np.random.default_rng(1)
    cfg = SafetyConfig(class_k=class_k)
    eps, delta = 1e-6, 1e-3
    for _ in range(20):
        n = int(rng.integers(2, 6))
        pos, vel = random_state(rng, n, 0.02)
        u = rng.uniform(-0.6, 0.6, (n, 2))
        terms = terms_at(pos, vel, cfg)

        def hdot_fd(u_, pos=pos, vel=vel, n=n):
            plus = terms_at(*_evolve(pos, vel, u_, eps), cfg).h
            minus = terms_at(*_evolve(pos, vel, u_, -eps), cfg).h
            return (plus - minus) / (2 * eps)

        analytic = terms.rows_times(u) + terms.drift
        np.testing.assert_allclose(analytic, hdot_fd(u), rtol=1e-5, atol=1e-6)
        # Jacobian of h_dot with respect to every acceleration component
        dense = terms.dense(n)
        for col in range(2 * n):
            step = np.zeros(2 * n)
            step[col] = delta
            jac = (hdot_fd(u + step.reshape(n, 2)) - hdot_fd(u - step.reshape(n, 2))) / (2 * delta)
            np.testing.assert_allclose(dense[:, col], jac, atol=1e-5)
        np.testing.assert_allclose(dense @ u.ravel(), terms.rows_times(u), atol=1e-12)
        # the bound is exactly the class-K condition: h_dot >= -K(h)
        k_of_h = cfg.gamma * (terms.h if class_k == "linear" else terms.h**3)
        np.testing.assert_allclose(terms.bound, -k_of_h - terms.drift, atol=1e-12)


def test_hdot_near_an_object_vertex_includes_curvature():
    pos = np.array([[0.33, 0.27], [0.9, 0.9]])            # diagonal from the corner (0.4, 0.35)
    vel = np.array([[0.25, -0.1], [0.0, 0.0]])            # sliding past the corner
    u = np.array([[0.3, 0.2], [0.0, 0.0]])
    terms = terms_at(pos, vel)
    eps = 1e-6
    fd = (terms_at(*_evolve(pos, vel, u, eps)).h - terms_at(*_evolve(pos, vel, u, -eps)).h) / (2 * eps)
    row = 1                                               # P = 1 pair, then the object row of robot 0
    assert terms.rows_times(u)[row] + terms.drift[row] == pytest.approx(fd[row], rel=1e-6)
    # without the curvature term kappa |w_t|^2 the derivative would be visibly wrong here
    d = analytic_distances(pos, R, SCENARIO.arena, SCENARIO.polygon)
    sdot = d.object_normal[0] @ vel[0]
    curvature_term = d.object_curvature[0] * (vel[0] @ vel[0] - sdot**2)
    assert curvature_term > 0.1
    assert abs(terms.rows_times(u)[row] + terms.drift[row] - curvature_term - fd[row]) > 0.1


def test_phi_continues_linearly_below_the_floor():
    alpha, floor = 0.5, 1e-3
    z = np.array([floor - 1e-9, floor, floor + 1e-9, -0.01, 0.2])
    phi, slope = _phi(z, alpha, floor)
    assert phi[0] == pytest.approx(phi[1], abs=1e-7) and phi[2] == pytest.approx(phi[1], abs=1e-7)
    assert slope[0] == pytest.approx(slope[2], rel=1e-5)
    root = math.sqrt(2 * alpha * floor)
    assert phi[3] == pytest.approx(root + alpha / root * (-0.01 - floor))
    assert phi[4] == pytest.approx(math.sqrt(2 * alpha * 0.2))
    assert np.all(np.isfinite(phi)) and np.all(np.diff(_phi(np.linspace(-0.1, 0.1, 50), alpha, floor)[0]) > 0)


def test_boundary_demand_never_exceeds_the_braking_budget():
    """On h = 0 the bound is alpha - c phi - kappa |w_t|^2 <= alpha (feasibility, module docstring)."""
    cfg = SafetyConfig()
    rng = np.random.default_rng(2)
    for _ in range(50):
        pos, vel = random_state(rng, 2, 0.02)
        terms = terms_at(pos, vel, cfg)
        # set the closing speed of the pair to exactly -phi so that h = 0 on the pair row
        n = (pos[0] - pos[1]) / np.linalg.norm(pos[0] - pos[1])
        vel_on = vel.copy()
        vel_on[0] += n * (-terms.h[0])
        on = terms_at(pos, vel_on, cfg)
        assert on.h[0] == pytest.approx(0.0, abs=1e-12)
        assert on.bound[0] <= 2 * cfg.braking_share * octagon_accel(DYN, cfg) + 1e-12


def test_config_errors_name_the_field():
    with pytest.raises(SafetyConfigError, match="safety.gamma"):
        SafetyConfig(gamma=-1.0)
    with pytest.raises(SafetyConfigError, match="safety.class_k"):
        SafetyConfig(class_k="quadratic")
    with pytest.raises(SafetyConfigError, match=r"unknown safety field\(s\) \['gamma_typo'\]"):
        SafetyConfig.from_dict({"gamma_typo": 1.0})
    assert SafetyConfig.from_dict({"gamma": 2.0}).gamma == 2.0


def test_rows_of_an_unsure_robot_take_the_unsure_gain():
    """Three robots, robot 1 unsure: the pairs (0, 1) and (1, 2), and robot 1's object and wall
    rows take ``gamma_unsure``; every other row ``gamma``. The bound is -gamma_row h - drift."""
    from controllers.safety.barrier import row_gamma
    from controllers.safety.latency import Prediction, row_sums

    cfg = SafetyConfig(gamma=6.0, gamma_unsure=3.0)
    n = 3
    zeros = np.zeros(n)
    pred = Prediction(pos=np.zeros((n, 2)), vel=np.zeros((n, 2)), grow=zeros, closing=zeros,
                      fixed=np.zeros(n, dtype=bool), horizon=np.zeros(n, dtype=int),
                      unsure=np.array([False, True, False]))
    pi, pj = np.triu_indices(n, 1)                        # pairs (0, 1), (0, 2), (1, 2)
    gamma = row_gamma(cfg, pred, lambda x: row_sums(x, pi, pj))
    want = [3, 6, 3] + [6, 3, 6] + [6] * 4 + [3] * 4 + [6] * 4
    assert gamma.tolist() == want
    pred.unsure = np.zeros(n, dtype=bool)
    assert row_gamma(cfg, pred, lambda x: row_sums(x, pi, pj)) == 6.0
    rng = np.random.default_rng(3)
    pos, vel = random_state(rng, n, 0.02)
    pred.unsure = np.array([False, True, False])
    terms = barrier_terms(analytic_distances(pos, R, SCENARIO.arena, SCENARIO.polygon), vel, DYN, cfg, pred)
    np.testing.assert_allclose(terms.bound, -np.array(want) * terms.h - terms.drift, atol=1e-12)


def test_row_robots_follow_the_row_layout_with_two_object_pieces():
    from controllers.safety.barrier import row_robots
    pair_i, pair_j = np.triu_indices(3, 1)     # P = 3, then 3 x 2 object rows, then 12 wall rows
    i, j = row_robots(pair_i, pair_j, 3, pieces=2)
    assert i.tolist() == [0, 0, 1, 0, 0, 1, 1, 2, 2] + [0] * 4 + [1] * 4 + [2] * 4
    assert j.tolist() == [1, 2, 2] + [-1] * 18
