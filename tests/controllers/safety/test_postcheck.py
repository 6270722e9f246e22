"""One-tick sweep check: hand-worked cases, agreement with the batched world, soundness."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch
from hypothesis import given, settings
from hypothesis import strategies as st

from controllers.safety import CollisionScene, analytic_distances, postcheck, predict_step
from controllers.safety.latency import Prediction
from controllers.safety.postcheck import (
    SweepChecker,
    braking_acceleration,
    no_worse_than_braking,
    segment_origin_distance,
)
from sim.batched_env import BatchedFormationEnv
from sim.scenario import transport_scenario
from tests.controllers.safety.fcl_child import run_child

SCENARIO = transport_scenario(3)      # box [0.4, 0.6] x [0.35, 0.65]
DYN = SCENARIO.dynamics
R = SCENARIO.robot_radius


def checker_for(pos):
    scene = CollisionScene(SCENARIO, len(pos))
    scene.update(pos)
    return SweepChecker(scene.object_parts, R, SCENARIO.arena, DYN), scene.distances().object_distance


def test_segment_origin_distance_by_hand():
    start = np.array([[-1.0, 1.0], [1.0, 0.0], [3.0, 4.0], [-3.0, -4.0]])
    end = np.array([[1.0, 1.0], [2.0, 0.0], [3.0, 4.0], [3.0, 4.0]])
    np.testing.assert_allclose(segment_origin_distance(start, end), [1.0, 1.0, 5.0, 0.0])


def test_predict_step_matches_the_batched_world():
    rng = np.random.default_rng(0)
    env = BatchedFormationEnv(SCENARIO, 1, dtype=torch.float64)
    pos = np.array([[0.2, 0.2], [0.8, 0.3], [0.3, 0.8]])
    for _ in range(10):
        vel = rng.normal(0, 0.3, (3, 2))
        acc = rng.normal(0, 1.5, (3, 2))
        env.set_state(torch.from_numpy(pos)[None], torch.from_numpy(vel)[None])
        env.step(torch.from_numpy(acc)[None])
        end, bulge = predict_step(pos, vel, acc, DYN)
        np.testing.assert_allclose(end, env.pos[0].numpy(), atol=1e-12)
        assert np.all(bulge <= 0.5 * DYN.dt**2 * (DYN.accel_limit + DYN.damping * 0.3 * 5))


def test_head_on_pair_is_braked_and_unavoidable_touch_is_reported():
    # gap 0.01 m, closing at 0.8 m/s: even full braking (v' = 0.4 - 0.05 * 1.2 = 0.34 m/s,
    # 0.017 m each) closes more than the gap
    pos = np.array([[0.30, 0.2], [0.39, 0.2], [0.8, 0.9]])
    vel = np.array([[0.4, 0.0], [-0.4, 0.0], [0.0, 0.0]])
    checker, clearance = checker_for(pos)
    out = checker.check(pos, vel, np.zeros((3, 2)), clearance)
    np.testing.assert_array_equal(out.braked, [True, True, False])
    np.testing.assert_array_equal(out.contact, [True, True, False])
    np.testing.assert_allclose(out.acc[:2], [[-1.0, 0.0], [1.0, 0.0]])
    np.testing.assert_allclose(out.acc[2], [0.0, 0.0])


def test_slow_pair_is_saved_by_braking():
    # gap 0.008 m closing at 0.2 m/s: coasting travels 2 * 0.0975 * 0.05 = 0.00975 m > gap;
    # braking (a = -1) gives v' = 0.0475 m/s: 0.00475 m plus widening 2 * 0.0013125 m < 0.008 m
    pos = np.array([[0.30, 0.2], [0.388, 0.2], [0.8, 0.9]])
    vel = np.array([[0.1, 0.0], [-0.1, 0.0], [0.0, 0.0]])
    checker, clearance = checker_for(pos)
    out = checker.check(pos, vel, np.zeros((3, 2)), clearance)
    np.testing.assert_array_equal(out.braked, [True, True, False])
    assert not out.contact.any()


def test_sweep_catches_a_corner_that_both_end_points_clear():
    """Passing the box corner (0.4, 0.35) on a chord 0.0395 m from it, ends 0.04075 m from it."""
    corner = np.array([0.4, 0.35])
    direction = np.array([1.0, -1.0]) / math.sqrt(2)
    middle = corner + 0.0395 * np.array([-1.0, -1.0]) / math.sqrt(2)
    start = middle - 0.01 * direction
    vel = 0.4 * direction                        # 0.02 m per tick at the speed limit
    acc = DYN.damping * vel                      # holds the speed: no widening
    pos = np.array([start, [0.9, 0.9], [0.1, 0.9]])
    vels = np.array([vel, [0, 0], [0, 0]])
    accs = np.array([acc, [0, 0], [0, 0]])
    end, bulge = predict_step(pos, vels, accs, DYN)
    assert bulge[0] == pytest.approx(0.0, abs=1e-15)
    ends = analytic_distances(np.array([start, end[0]]), R, SCENARIO.arena, SCENARIO.polygon)
    assert np.all(ends.object_distance > 0.0007)             # both end points are clear
    checker, clearance = checker_for(pos)
    assert checker.failing(pos, vels, accs, clearance)[0]     # the swept capsule is not
    out = checker.check(pos, vels, accs, clearance)
    assert out.braked[0] and not out.braked[1:].any()
    np.testing.assert_allclose(out.acc[0], braking_acceleration(vels, DYN)[0])


def test_wall_approach_is_braked():
    pos = np.array([[0.05, 0.5], [0.5, 0.9], [0.9, 0.1]])
    vel = np.array([[-0.4, 0.0], [0.0, 0.0], [0.0, 0.0]])
    checker, clearance = checker_for(pos)
    out = checker.check(pos, vel, np.array([[-1.0, 0.0], [0, 0], [0, 0]]), clearance)
    np.testing.assert_array_equal(out.braked, [True, False, False])


def test_braking_stops_slow_robots_without_reversing():
    vel = np.array([[0.01, 0.0], [0.0, -0.4], [0.0, 0.0]])
    a = braking_acceleration(vel, DYN)
    v_next = vel + DYN.dt * (a - DYN.damping * vel)
    np.testing.assert_allclose(v_next[0], 0.0, atol=1e-15)     # stops exactly
    np.testing.assert_allclose(a[1], [0.0, 1.0])               # full thrust against v
    np.testing.assert_allclose(a[2], 0.0)
    assert np.all(np.isfinite(braking_acceleration(np.array([[np.nan, 1.0]]), DYN)))


def test_passing_the_check_means_no_contact_along_the_tick():
    """Soundness: robots the check lets through touch nothing on the continuous path or at the end."""
    rng = np.random.default_rng(7)
    passed = flagged = 0
    times = np.linspace(0.0, DYN.dt, 41)
    for _ in range(400):
        pos = rng.uniform(0.03, 0.97, (3, 2))
        start = analytic_distances(pos, R, SCENARIO.arena, SCENARIO.polygon)
        if not 0 <= start.min_clearance() < 0.02:          # near contact: where the check matters
            continue
        vel = rng.uniform(-0.4, 0.4, (3, 2))
        acc = rng.uniform(-1.5, 1.5, (3, 2))
        checker, clearance = checker_for(pos)
        bad = checker.failing(pos, vel, acc, clearance)
        flagged += int(bad.sum())
        a = acc * np.minimum(1.0, DYN.accel_limit / np.linalg.norm(acc, axis=1))[:, None]
        a_eff = a - DYN.damping * vel
        end, _ = predict_step(pos, vel, acc, DYN)
        paths = [pos + vel * t + 0.5 * a_eff * t**2 for t in times] + [end]
        for p in paths:
            d = analytic_distances(p, R, SCENARIO.arena, SCENARIO.polygon)
            touching = d.object_distance < 0
            touching |= (d.wall_distance < 0).any(axis=1)
            for k in np.flatnonzero(d.pair_distance < 0):
                touching[d.pair_i[k]] = touching[d.pair_j[k]] = True
            assert not np.any(touching & ~bad)
        passed += int((~bad).sum())
    assert passed > 100 and flagged > 20                 # both outcomes were exercised


def grown(pos, grow, vel_error=0.0):
    """A latency prediction of robots at rest with discs grown by ``grow`` [m]."""
    n = len(pos)
    return Prediction(pos=pos, vel=np.zeros((n, 2)), grow=np.full(n, grow), closing=np.zeros(n),
                      fixed=np.zeros(n, dtype=bool), horizon=np.zeros(n, dtype=np.int64),
                      velocity_error=np.full(n, vel_error))


def test_a_pair_inside_its_grown_distance_may_move_apart_but_not_closer_or_past():
    """Robots at rest 0.09 m apart (centres), discs grown by 6 mm each: the start already breaks
    ``2 r + g = 0.092 m``, and braking (0 at rest) fails for good. Pushed apart at 1 m/s^2 each,
    ``Delta = (-2, 0)``: ``d . Delta = 0.18 >= g |Delta| = 0.024``, accepted. Sliding past
    (``d . Delta = 0``) and closing are braked. Apart at an angle (``Delta = (-1.2, 1.6)``,
    ``d . Delta = 0.108``) passes with exact velocities (``0.012 * 2``) and is braked when each
    velocity may be off by 0.5 m/s (``(0.012 + 1.0 * 0.05) * 2 = 0.124``)."""
    pos = np.array([[0.30, 0.2], [0.39, 0.2], [0.8, 0.9]])
    vel = np.zeros((3, 2))
    checker, clearance = checker_for(pos)
    apart = np.array([[-1.0, 0.0], [1.0, 0.0], [0.0, 0.0]])
    past = np.array([[0.0, 1.0], [0.0, -1.0], [0.0, 0.0]])
    slanted = np.array([[-0.6, 0.8], [0.6, -0.8], [0.0, 0.0]])
    prediction = grown(pos, 0.006)
    for acc in (apart, slanted):
        assert not checker.check(pos, vel, acc, clearance, prediction).braked.any()
    for acc in (past, -apart):
        np.testing.assert_array_equal(checker.check(pos, vel, acc, clearance, prediction).braked,
                                      [True, True, False])
    unsure = grown(pos, 0.006, vel_error=0.5)
    assert not checker.check(pos, vel, apart, clearance, unsure).braked.any()
    np.testing.assert_array_equal(checker.check(pos, vel, slanted, clearance, unsure).braked,
                                  [True, True, False])


def test_without_the_excuse_the_pair_moving_apart_is_braked(monkeypatch):
    """Teeth of the case above: the same command, the rule switched off."""
    pos = np.array([[0.30, 0.2], [0.39, 0.2], [0.8, 0.9]])
    checker, clearance = checker_for(pos)
    monkeypatch.setattr(postcheck, "excuses", lambda pos, *rest: (np.zeros(3, dtype=bool),
                                                                  np.zeros((3, 4), dtype=bool)))
    apart = np.array([[-1.0, 0.0], [1.0, 0.0], [0.0, 0.0]])
    out = checker.check(pos, np.zeros((3, 2)), apart, clearance, grown(pos, 0.006))
    np.testing.assert_array_equal(out.braked, [True, True, False])


def test_a_robot_inside_its_wall_margin_may_leave_but_not_go_further_in():
    pos = np.array([[0.045, 0.5], [0.5, 0.9], [0.9, 0.1]])       # 5 mm from x = 0, grown by 6
    checker, clearance = checker_for(pos)
    vel = np.zeros((3, 2))
    prediction = grown(pos, 0.006)
    away = np.array([[1.0, 0.0], [0, 0], [0, 0]])
    assert not checker.check(pos, vel, away, clearance, prediction).braked.any()
    out = checker.check(pos, vel, -away, clearance, prediction)
    np.testing.assert_array_equal(out.braked, [True, False, False])


vec = st.tuples(st.floats(-1.0, 1.0), st.floats(-1.0, 1.0))


@settings(max_examples=300, deadline=None)
@given(d=vec, w0=vec, diff=vec, brake=vec, g=st.floats(0.0, 0.03), u=st.floats(0.0, 0.5),
       seed=st.integers(0, 2**31))
def test_an_excused_pair_stays_as_far_apart_as_braking_from_any_state_it_may_truly_be_in(
        d, w0, diff, brake, g, u, seed):
    """Whenever :func:`no_worse_than_braking` accepts, every true relative position ``d'`` within
    ``g`` of ``d`` and velocity offset ``delta`` within ``u`` keep the command's relative path at
    least as far from contact as the brake's along the tick: ``|x(t) + Delta t^2 / 2| >= |x(t)|``,
    ``x(t) = d' + (w0 + delta) t + b t^2 / 2``."""
    d, w0, diff, b = 0.2 * np.array(d), 0.8 * np.array(w0), 3.0 * np.array(diff), 3.0 * np.array(brake)
    dt = DYN.dt
    if not no_worse_than_braking(d[None], w0[None], diff[None], b[None], np.array([g + u * dt]),
                                 np.array([True]), dt)[0]:
        return
    rng = np.random.default_rng(seed)
    t = np.linspace(0.0, dt, 26)[:, None]
    for _ in range(20):
        off = rng.normal(size=2)
        off *= g * rng.uniform() ** 0.5 / max(np.hypot(*off), 1e-12)
        delta = rng.normal(size=2)
        delta *= u / max(np.hypot(*delta), 1e-12)
        braking = d + off + (w0 + delta) * t + 0.5 * b * t**2
        command = braking + 0.5 * diff * t**2
        assert (np.hypot(*command.T) >= np.hypot(*braking.T) - 1e-12).all()


TOUCHING = [  # (start, end, radius): discs and swept discs that end touching paper-3's box
    ((0.5, 0.25), (0.5, 0.25), 0.1),        # the disc that aborted `formation eval --intruder ...`
    ((0.5, 0.31), (0.5, 0.31), 0.04),       # bottom edge
    ((0.36, 0.5), (0.36, 0.5), 0.04),       # left edge
    ((0.5, 0.2), (0.5, 0.31), 0.04),        # a sweep that ends on the bottom edge
    ((0.3, 0.69), (0.5, 0.69), 0.04),       # a sweep along the top edge
]


def test_a_disc_touching_the_object_is_reported_without_aborting_the_process():
    """On touching shapes FCL's signed query (EPA) throws a C++ std::logic_error that
    python-fcl does not catch, and the process aborted (SIGABRT: a controller node gone). The
    checks run in a child process, so that a regression fails here instead of killing the run:
    each touching sweep reads 0 to within 1e-9 m (the query's tolerance; -1 where it calls it an
    overlap), and the same sweeps 1 mm thinner read their gap (GJK on the object's prism: to
    4e-5 m here, the same with the signed query while apart)."""
    out = run_child(f"""
        import json
        import numpy as np
        from controllers.safety import CollisionScene
        from controllers.safety.postcheck import SweepChecker
        from sim.scenario import transport_scenario
        sc = transport_scenario(3)
        scene = CollisionScene(sc, 1)
        scene.update(np.array([[0.1, 0.1]]))
        checker = SweepChecker(scene.object_parts, sc.robot_radius, sc.arena, sc.dynamics)
        out = []
        for start, end, radius in {TOUCHING!r}:
            out.append([checker.capsule_clearance(np.array(start), np.array(end), radius),
                        checker.capsule_clearance(np.array(start), np.array(end), radius - 1e-3)])
        print(json.dumps(out))
    """)
    touching, apart = np.array(out).T
    assert (touching <= 1e-9).all() and (touching < 0).any(), touching
    np.testing.assert_allclose(apart, 1e-3, atol=1e-4)


L_SHAPE = transport_scenario(1, object_vertices=[(0.35, 0.35), (0.65, 0.35), (0.65, 0.45), (0.45, 0.45),
                                                   (0.45, 0.65), (0.35, 0.65)])


def _distance_to_pieces(points: np.ndarray, pieces: list[np.ndarray]) -> np.ndarray:
    """(T,) distance of (T, 2) points to the union of convex counter-clockwise pieces (0 inside)."""
    best = np.full(len(points), np.inf)
    for piece in pieces:
        a, b = piece, np.roll(piece, -1, axis=0)
        edge = b - a
        rel = points[:, None, :] - a[None]
        t = np.clip(np.sum(rel * edge, -1) / np.sum(edge * edge, -1), 0.0, 1.0)
        d = np.hypot(*(rel - t[..., None] * edge).transpose(2, 0, 1)).min(1)
        inside = (edge[None, :, 0] * rel[..., 1] - edge[None, :, 1] * rel[..., 0] >= 0).all(1)
        best = np.minimum(best, np.where(inside, 0.0, d))
    return best


@settings(max_examples=400, deadline=None)
@given(shape=st.sampled_from(["box", "L"]), at=vec, v=vec, a=vec, g=st.floats(0.0, 0.02),
       u=st.floats(0.0, 0.1), seed=st.integers(0, 2**31))
def test_an_object_excuse_keeps_at_least_the_brakes_distance_from_any_state_it_may_truly_be_in(
        shape, at, v, a, g, u, seed):
    """Whenever the post-check excuses the object, every true position within ``grow`` of the
    predicted one and velocity within ``vel_error`` keep the command's continuous path at least
    as far from the object (each convex piece of it) as the brake's, all tick long."""
    sc = SCENARIO if shape == "box" else L_SHAPE
    scene = CollisionScene(sc, 1)
    checker = SweepChecker(scene.object_parts, R, sc.arena, DYN, object_pieces=scene.object_pieces)
    pos = np.array([[0.5, 0.5]]) + 0.25 * np.array([at])
    vel, acc = 0.3 * np.array([v]), np.array([a])
    brake = DYN.brake(vel)
    if not checker.object_excused(0, pos, vel, acc, brake, np.array([g]), np.array([u])):
        return
    pieces = scene.object_pieces()
    a_cmd, a_brake = postcheck.clip_norm(acc, DYN.accel_limit)[0], brake[0]
    rng = np.random.default_rng(seed)
    t = np.linspace(0.0, DYN.dt, 26)[:, None]
    for _ in range(20):
        off, delta = rng.normal(size=2), rng.normal(size=2)
        off *= g * rng.uniform() ** 0.5 / max(np.hypot(*off), 1e-12)
        delta *= u * rng.uniform() ** 0.5 / max(np.hypot(*delta), 1e-12)
        p0, v0 = pos[0] + off, vel[0] + delta
        braking = p0 + v0 * t + 0.5 * (a_brake - DYN.damping * v0) * t**2
        command = braking + 0.5 * (a_cmd - a_brake) * t**2
        assert (_distance_to_pieces(command, pieces) >= _distance_to_pieces(braking, pieces) - 1e-12).all()


@pytest.mark.parametrize("sc", [SCENARIO, L_SHAPE], ids=["box", "L"])
def test_a_robot_at_rest_beside_the_object_may_leave_but_not_go_further_in(sc):
    """Robots at rest 3 mm off a face (or the L's inner floor), grown by 6 mm: every command used
    to be braked, straight away from the object too, so a robot parked there never left."""
    pos = np.array([[0.5, 0.65 + R + 0.003]]) if sc is SCENARIO else np.array([[0.55, 0.45 + R + 0.003]])
    scene = CollisionScene(sc, 1)
    scene.update(pos)
    checker = SweepChecker(scene.object_parts, R, sc.arena, DYN, object_pieces=scene.object_pieces)
    clearance, vel = scene.distances().object_distance, np.zeros((1, 2))
    for away, braked in (([0.0, 1.0], False), ([0.7, 0.7], False), ([0.0, -1.0], True), ([1.0, -0.2], True)):
        out = checker.check(pos, vel, np.array([away]), clearance, grown(pos, 0.006))
        assert out.braked.tolist() == [braked], away
    bare = SweepChecker(scene.object_parts, R, sc.arena, DYN)      # no pieces: no excuse (before)
    assert bare.check(pos, vel, np.array([[0.0, 1.0]]), clearance, grown(pos, 0.006)).braked.tolist() == [True]
