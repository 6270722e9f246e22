"""The position estimator: exact links pass through, noisy ones are filtered as the Kalman
recursion says, estimates follow robot ids."""

from __future__ import annotations

import math

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from controllers.position_estimator import NOISE_FLOOR, PositionEstimator

DT = 0.05


def run(est: PositionEstimator, truth: np.ndarray, vel: np.ndarray, noise_p: float, noise_v: float,
        rng: np.random.Generator, ids=("a",)) -> tuple[np.ndarray, np.ndarray]:
    """Feed (T, N, 2) true positions and velocities with white noise; estimates and stds (T, N[, 2])."""
    out, stds = [], []
    for k in range(len(truth)):
        y = truth[k] + rng.normal(0, noise_p, truth[k].shape)
        v = vel[k] + rng.normal(0, noise_v, vel[k].shape)
        n = len(truth[k])
        p, s = est.update(ids, y, v, np.full(n, k * DT), np.ones(n, bool), np.full(n, noise_v**2))
        out.append(p)
        stds.append(s)
    return np.array(out), np.array(stds)


def trajectory(steps: int, n: int, rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray]:
    """Semi-implicit Euler paths under random accelerations: p_k = p_{k-1} + dt v_k."""
    p, v = rng.uniform(0.2, 0.8, (n, 2)), rng.normal(0, 0.1, (n, 2))
    ps, vs = [], []
    for _ in range(steps):
        v = v + DT * rng.normal(0, 0.5, (n, 2))
        p = p + DT * v
        ps.append(p)
        vs.append(v)
    return np.array(ps), np.array(vs)


@settings(max_examples=40, deadline=None)
@given(seed=st.integers(0, 2**31 - 1), n=st.integers(1, 6))
def test_an_exact_link_passes_through_unchanged(seed, n):
    rng = np.random.default_rng(seed)
    truth, vel = trajectory(30, n, rng)
    est = PositionEstimator(DT)
    out, stds = run(est, truth, vel, 0.0, 0.0, rng, ids=tuple(f"r{i}" for i in range(n)))
    np.testing.assert_array_equal(out, truth)
    assert stds.max() <= NOISE_FLOOR


def test_noise_is_measured_and_filtered_to_the_kalman_steady_state():
    rng = np.random.default_rng(3)
    sp, sv = 0.01, 0.02
    truth, vel = trajectory(400, 20, rng)
    est = PositionEstimator(DT)
    out, stds = run(est, truth, vel, sp, sv, rng, ids=tuple(f"r{i}" for i in range(20)))
    # measured noise: E|r|^2 / 4 = sigma_p^2 + dt^2 sigma_v^2 / 4 per axis
    assert math.sqrt(est.noise_var.mean()) == pytest.approx(math.hypot(sp, DT * sv / 2), rel=0.1)
    # hand-worked steady state: P- solves P-^2 - q P- - q r = 0, P = P- r / (P- + r)
    q, r = (DT * sv) ** 2, est.noise_var.mean()
    prior = (q + math.sqrt(q * q + 4 * q * r)) / 2
    posterior = prior * r / (prior + r)
    assert stds[-1].mean() ** 2 / (1 + 2 / math.sqrt(399)) == pytest.approx(posterior, rel=0.1)
    err = out[100:] - truth[100:]
    raw_rms = sp * math.sqrt(2)
    est_rms = math.sqrt((err ** 2).sum(axis=-1).mean())
    assert est_rms < 0.4 * raw_rms                       # 14 mm -> ~3 mm
    # the reported std describes the error it leaves (per axis)
    assert 0.7 < math.sqrt((err ** 2).mean()) / stds[100:].mean() < 1.5


def test_a_robot_moved_by_hand_restarts_at_its_measurement():
    rng = np.random.default_rng(0)
    truth, vel = trajectory(60, 1, rng)
    est = PositionEstimator(DT)
    run(est, truth, vel, 0.01, 0.02, rng)
    moved = truth[-1] + np.array([[0.2, 0.0]])
    p, _ = est.update(("a",), moved, vel[-1], np.array([60 * DT]), np.array([True]), np.array([0.02**2]))
    np.testing.assert_array_equal(p, moved)


def test_estimates_follow_ids_and_a_new_robot_starts_at_its_measurement():
    rng = np.random.default_rng(1)
    truth, vel = trajectory(40, 2, rng)
    est = PositionEstimator(DT)
    out, _ = run(est, truth, vel, 0.01, 0.02, rng, ids=("a", "b"))
    kept = est.p_hat.copy()
    p, s = est.update(("c", "b", "a"), np.array([[0.5, 0.5], [9.0, 9.0], [9.0, 9.0]]), np.zeros((3, 2)),
                      np.full(3, 40 * DT), np.array([True, False, False]), np.full(3, 4e-4))
    np.testing.assert_array_equal(p[0], [0.5, 0.5])          # new: its measurement
    np.testing.assert_array_equal(p[1:], kept[::-1])         # not new: the estimate stays, re-keyed
    assert s[0] == 0.0 and s[1] > 0.0


def test_a_dropped_state_predicts_over_the_gap():
    est = PositionEstimator(DT)
    ids, v = ("a",), np.array([[0.1, 0.0]])
    rng = np.random.default_rng(2)
    for k in range(30):
        y = np.array([[0.1 * k * DT, 0.0]]) + rng.normal(0, 0.01, (1, 2))
        est.update(ids, y, v, np.array([k * DT]), np.array([True]), np.array([1e-6]))
    before = est.p_hat.copy()
    y = np.array([[0.1 * 32 * DT, 0.0]])                  # two ticks lost: the gap is 3 dt
    p, _ = est.update(ids, y, v, np.array([32 * DT]), np.array([True]), np.array([1e-6]))
    assert abs(p[0, 0] - y[0, 0]) < abs(before[0, 0] - y[0, 0])
    assert abs(p[0, 0] - (before[0, 0] + 3 * DT * 0.1)) < 0.01
