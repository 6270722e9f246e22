"""The fused fast path gives the answers of the FCL reference path (rows, sweep check, whole filter)."""

from __future__ import annotations

import dataclasses
import math

import numpy as np
import pytest
from hypothesis import example, given, settings
from hypothesis import strategies as st

from controllers.safety import (
    CollisionScene,
    SafetyConfig,
    SafetyFilter,
    SafetyStatus,
    barrier_terms,
    predict_step,
)
from controllers.safety.fused import FusedScene
from controllers.safety.geometry import analytic_distances
from controllers.safety.postcheck import SweepChecker, braking_acceleration
from sim.scenario import transport_scenario

SCENARIO = transport_scenario(8)          # box [0.4, 0.6] x [0.35, 0.65], r = 0.04, 1 x 1 arena
DYN = SCENARIO.dynamics
R = SCENARIO.robot_radius
L_SHAPE = ((0.4, 0.35), (0.6, 0.35), (0.6, 0.45), (0.5, 0.45), (0.5, 0.65), (0.4, 0.65))

# One filter per path, fed the same calls in the same order (OSQP warm-starts from its last answer).
FCL = SafetyFilter(SCENARIO, SafetyConfig(geometry="fcl"))
FUSED = SafetyFilter(SCENARIO, SafetyConfig(geometry="fused"))


def scene(rng, n, speed, spread=1.0):
    """Centres clear of the walls (FCL's wall depths are GJK/EPA estimates), free to overlap each
    other and the object; velocities up to ``speed`` [m/s]; nominal commands up to 2 m/s^2."""
    centre = np.array([0.5, 0.5])
    pos = centre + spread * rng.uniform(-0.5 + R + 1e-3, 0.5 - R - 1e-3, (n, 2))
    vel = rng.normal(size=(n, 2))
    vel *= rng.uniform(0, speed, (n, 1)) / np.maximum(np.linalg.norm(vel, axis=1, keepdims=True), 1e-9)
    return pos, vel, rng.normal(0.0, 1.0, (n, 2))


def assert_terms_equal(got, want, atol=1e-9):
    for name in ("h", "drift", "bound"):
        np.testing.assert_allclose(getattr(got, name), getattr(want, name), rtol=0, atol=atol, err_msg=name)
    np.testing.assert_allclose(got.pair_normal, want.pair_normal, atol=atol)
    np.testing.assert_allclose(got.object_normal, want.object_normal, atol=atol)
    np.testing.assert_array_equal(got.wall_normal, want.wall_normal)
    assert got.pieces == want.pieces
    u = np.random.default_rng(0).normal(size=(len(got.object_normal) // got.pieces, 2))
    np.testing.assert_allclose(got.rows_times(u), want.rows_times(u), atol=1e-12)


@settings(max_examples=60, deadline=None)
@given(seed=st.integers(0, 2**31), n=st.integers(1, 8), speed=st.floats(0.0, 0.6))
def test_fused_rows_equal_the_fcl_rows(seed, n, speed):
    rng = np.random.default_rng(seed)
    pos, vel, _ = scene(rng, n, speed)
    assert_terms_equal(FUSED.barrier(pos, vel), FCL.barrier(pos, vel))


COMMAND_ATOL = 1e-6
"""[m/s^2] how close the two paths' commands must be where no row is softened."""


def command_atol(got, want) -> float:
    """[m/s^2] :data:`COMMAND_ATOL`, plus, on the slack QP, the multiplier times the rows' difference.

    A softened row ``n . u + sigma >= b`` pushes ``u`` with multiplier ``lambda = 2 w sigma``
    (``w`` up to ``slack_weight * static_slack_factor`` = 1e8): the command is pinned by the
    actuator octagon, and a normal ``delta`` off moves it by up to ``lambda delta`` along the
    octagon's edge. FCL's and the fused path's normals differ by ~1e-14, so with 6.6 m/s^2 of
    slack the answers differ by 6.4e-6 (seed 978538864, n=6; the object's normal is axis-aligned,
    so is the octagon's edge); DAQP itself moves 2.5e-13 for bounds 1e-13 apart.
    """
    if want.max_slack == 0.0:
        return COMMAND_ATOL
    cfg = FCL.config
    lam = 2.0 * cfg.slack_weight * cfg.static_slack_factor * max(got.max_slack, want.max_slack)
    delta = max(np.abs(got.terms.pair_normal - want.terms.pair_normal).max(initial=0.0),
                np.abs(got.terms.object_normal - want.terms.object_normal).max(initial=0.0))
    return COMMAND_ATOL + lam * delta


@settings(max_examples=80, deadline=None)
@given(seed=st.integers(0, 2**31), n=st.integers(1, 8), speed=st.floats(0.0, 0.6),
       spread=st.sampled_from([0.5, 1.0]))
@example(seed=46710636, n=6, speed=0.5, spread=1.0)
@example(seed=2889, n=7, speed=0.0, spread=0.5)
@example(seed=978538864, n=6, speed=0.35724530224024775, spread=0.5)
def test_fused_filter_gives_the_fcl_answer(seed, n, speed, spread):
    """Same status, same braked and contact robots, same command (to :func:`command_atol`),
    same reported margins."""
    rng = np.random.default_rng(seed)
    pos, vel, a_nom = scene(rng, n, speed, spread)
    want = FCL.filter(pos, vel, a_nom)
    got = FUSED.filter(pos, vel, a_nom)
    assert got.status is want.status, (got.reason, want.reason)
    assert got.reason == want.reason
    np.testing.assert_array_equal(got.braked, want.braked)
    np.testing.assert_array_equal(got.contact, want.contact)
    np.testing.assert_allclose(got.a_safe, want.a_safe, rtol=0, atol=command_atol(got, want))
    assert got.min_barrier == pytest.approx(want.min_barrier, abs=1e-9)
    assert got.min_clearance == pytest.approx(want.min_clearance, abs=1e-9)
    assert got.max_slack == pytest.approx(want.max_slack, abs=1e-6)


@settings(max_examples=40, deadline=None)
@given(seed=st.integers(0, 2**31), n=st.integers(1, 6), theta=st.floats(-math.pi, math.pi))
@example(seed=5, n=5, theta=4.868021055179901e-11)
def test_rotated_object_takes_the_polygon_path_and_still_matches_fcl(seed, n, theta):
    rng = np.random.default_rng(seed)
    pos, vel, a_nom = scene(rng, n, 0.4)
    pose = np.array([0.5, 0.5, theta])
    fcl_f = SafetyFilter(SCENARIO, SafetyConfig(geometry="fcl"))
    fused_f = SafetyFilter(SCENARIO, SafetyConfig(geometry="fused"))
    assert_terms_equal(fused_f.barrier(pos, vel, pose), fcl_f.barrier(pos, vel, pose))
    want, got = fcl_f.filter(pos, vel, a_nom, pose), fused_f.filter(pos, vel, a_nom, pose)
    assert got.status is want.status
    np.testing.assert_array_equal(got.braked, want.braked)
    np.testing.assert_allclose(got.a_safe, want.a_safe, rtol=0, atol=command_atol(got, want))


@settings(max_examples=40, deadline=None)
@given(seed=st.integers(0, 2**31), n=st.integers(1, 6))
@example(seed=6445, n=1)    # 0.56 um off the line of a vertex's edge: FCL's path took the vertex
def test_non_convex_object_matches_the_exact_closed_form_and_fcl_outside(seed, n):
    """One object row per convex piece (two for the L): equal to the analytic rows everywhere, to
    FCL outside the object (FCL's depth inside a piece may differ from the closed form's)."""
    sc = dataclasses.replace(SCENARIO, object_vertices=L_SHAPE)
    rng = np.random.default_rng(seed)
    pos, vel, _ = scene(rng, n, 0.4)
    fused = SafetyFilter(sc, SafetyConfig(geometry="fused")).barrier(pos, vel)
    assert_terms_equal(fused, SafetyFilter(sc, SafetyConfig(geometry="analytic")).barrier(pos, vel))
    assert fused.pieces == 2 and len(fused.h) == n * (n - 1) // 2 + 2 * n + 4 * n
    if analytic_distances(pos, R, sc.arena, sc.polygon).object_distance.min() > -R:
        assert_terms_equal(fused, SafetyFilter(sc, SafetyConfig(geometry="fcl")).barrier(pos, vel))


def test_box_closed_form_by_hand():
    """Edge, corner and inside cases of the disc-box geometry (box [0.4, 0.6] x [0.35, 0.65])."""
    fused = FusedScene(R, SCENARIO.arena, DYN, SafetyConfig(), 3)
    poly = SCENARIO.polygon
    s, normal, curv = fused.object_geometry(np.array([[0.3, 0.5], [0.3, 0.25], [0.7, 0.9]]), poly)
    np.testing.assert_allclose(s, [0.1 - R, math.sqrt(0.02) - R, math.hypot(0.1, 0.25) - R])
    np.testing.assert_allclose(normal[0], [-1.0, 0.0])
    np.testing.assert_allclose(normal[1], [-math.sqrt(0.5), -math.sqrt(0.5)])
    np.testing.assert_allclose(curv, [0.0, 1 / math.sqrt(0.02), 1 / math.hypot(0.1, 0.25)])
    # one centre 0.02 m inside the left edge: the edge projections take over for the whole call
    s, normal, curv = fused.object_geometry(np.array([[0.42, 0.5], [0.3, 0.25], [0.5, 0.64]]), poly)
    np.testing.assert_allclose(s, [-0.02 - R, math.sqrt(0.02) - R, -0.01 - R])
    np.testing.assert_allclose(normal[[0, 2]], [[-1.0, 0.0], [0.0, 1.0]], atol=1e-12)
    np.testing.assert_allclose(curv, [0.0, 1 / math.sqrt(0.02), 0.0])


def checker_and_terms(pos, vel, n):
    coll = CollisionScene(SCENARIO, n)
    coll.update(pos)
    checker = SweepChecker(coll.object_parts, R, SCENARIO.arena, DYN)
    fused = FusedScene(R, SCENARIO.arena, DYN, SafetyConfig(), n)
    return checker, fused, fused.terms(pos, vel, coll.polygon), coll.distances().object_distance


@settings(max_examples=80, deadline=None)
@given(seed=st.integers(0, 2**31), n=st.integers(1, 6), speed=st.floats(0.0, 0.6),
       spread=st.sampled_from([0.4, 1.0]), noisy=st.booleans())
def test_fused_sweep_check_equals_the_sweep_checker(seed, n, speed, spread, noisy):
    """Also with velocity error bounds, which narrow the post-check's no-worse-than-braking rule in both paths."""
    rng = np.random.default_rng(seed)
    pos, vel, _ = scene(rng, n, speed, spread)
    acc = rng.uniform(-1.5, 1.5, (n, 2))
    checker, fused, terms, clearance = checker_and_terms(pos, vel, n)
    vel_error = rng.uniform(0.0, 0.05, n) if noisy else None
    np.testing.assert_array_equal(fused.failing(checker, pos, vel, acc, terms, vel_error=vel_error),
                                  checker.failing(pos, vel, acc, clearance, vel_error=vel_error))
    got, want = fused.check(checker, pos, vel, acc, terms), checker.check(pos, vel, acc, clearance)
    np.testing.assert_array_equal(got.braked, want.braked)
    np.testing.assert_array_equal(got.contact, want.contact)
    np.testing.assert_array_equal(got.acc, want.acc)


class CountingChecker(SweepChecker):
    """The real checker, counting its FCL capsule queries."""

    calls = 0

    def capsule_clearance(self, start, end, radius):
        CountingChecker.calls += 1
        return super().capsule_clearance(start, end, radius)


def test_far_robots_skip_every_test_and_near_ones_ask_fcl():
    # far from everything: clearance 0.1 m >> one tick of travel (<= 0.02 m + widening)
    pos = np.array([[0.15, 0.15], [0.85, 0.15], [0.15, 0.85]])
    vel = np.array([[0.4, 0.0], [0.0, 0.4], [-0.3, 0.2]])
    coll = CollisionScene(SCENARIO, 3)
    checker = CountingChecker(coll.object_parts, R, SCENARIO.arena, DYN)
    fused = FusedScene(R, SCENARIO.arena, DYN, SafetyConfig(), 3)
    terms = fused.terms(pos, vel, coll.polygon)
    CountingChecker.calls = 0
    assert not fused.failing(checker, pos, vel, np.ones((3, 2)) * 0.7, terms).any()
    assert CountingChecker.calls == 0
    # passing the box corner (0.4, 0.35) on a chord 0.0395 m from it: both chord ends clear the
    # box by more than 0.0007 m, only FCL's swept capsule finds the touch (test_postcheck)
    corner, direction = np.array([0.4, 0.35]), np.array([1.0, -1.0]) / math.sqrt(2)
    start = corner + 0.0395 * np.array([-1.0, -1.0]) / math.sqrt(2) - 0.01 * direction
    pos = np.array([start, [0.9, 0.9], [0.1, 0.9]])
    vel = np.array([0.4 * direction, [0, 0], [0, 0]])
    acc = np.array([DYN.damping * vel[0], [0, 0], [0, 0]])
    end, _ = predict_step(pos, vel, acc, DYN)
    assert analytic_distances(np.array([start, end[0]]), R, SCENARIO.arena,
                              SCENARIO.polygon).object_distance.min() > 0.0007
    terms = fused.terms(pos, vel, coll.polygon)
    out = fused.check(checker, pos, vel, acc, terms)
    assert CountingChecker.calls >= 1
    np.testing.assert_array_equal(out.braked, [True, False, False])
    np.testing.assert_allclose(out.acc[0], braking_acceleration(vel, DYN)[0])


def test_fused_filter_statuses_by_hand():
    """Safe command unchanged, head-on pair intervened; rows of the reference formula hold."""
    f = SafetyFilter(transport_scenario(3))
    pos = np.array([[0.2, 0.2], [0.4, 0.2], [0.8, 0.8]])
    vel = np.array([[0.2, 0.0], [-0.2, 0.0], [0.0, 0.0]])
    calm = f.filter(pos, np.zeros((3, 2)), np.full((3, 2), 0.05))
    assert calm.status is SafetyStatus.UNCHANGED
    np.testing.assert_allclose(calm.a_safe, 0.05)
    assert calm.min_clearance == pytest.approx(0.15 - R)      # robot 1 is 0.15 m below the box
    push = f.filter(pos, vel, np.array([[1.0, 0.0], [-1.0, 0.0], [0.0, 0.0]]))
    assert push.status is SafetyStatus.INTERVENED
    reference = barrier_terms(analytic_distances(pos, R, SCENARIO.arena, SCENARIO.polygon), vel,
                              DYN, f.config)
    assert np.all(reference.rows_times(push.a_safe) >= reference.bound - 1e-9)
    assert push.a_safe[0, 0] < 1.0 and push.a_safe[1, 0] > -1.0        # both hold back


@settings(max_examples=60, deadline=None)
@given(seed=st.integers(0, 2**31), n=st.integers(1, 8), speed=st.floats(0.0, 0.6))
def test_fused_rows_equal_the_reference_rows_under_a_prediction(seed, n, speed):
    """Grown discs, closing allowances, fixed robots and unsure robots (their rows' gain) give the
    same rows on both paths."""
    from controllers.safety.latency import Prediction

    rng = np.random.default_rng(seed)
    pos, vel, _ = scene(rng, n, speed)
    prediction = Prediction(pos=pos, vel=vel, grow=rng.uniform(0, 0.02, n), closing=rng.uniform(0, 0.1, n),
                            fixed=rng.random(n) < 0.3, horizon=np.full(n, 3), unsure=rng.random(n) < 0.5)
    config = SafetyConfig()
    want = barrier_terms(analytic_distances(pos, R, SCENARIO.arena, SCENARIO.polygon), vel, DYN, config,
                         prediction)
    got = FusedScene(R, SCENARIO.arena, DYN, config, n).terms(pos, vel, np.asarray(SCENARIO.polygon), prediction)
    assert_terms_equal(got, want)
