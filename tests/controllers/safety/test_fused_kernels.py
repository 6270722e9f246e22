"""The compiled barrier rows equal their numpy formulation bit for bit, on any scene."""

from __future__ import annotations

import numpy as np
from hypothesis import given, settings
from hypothesis import strategies as st

from controllers.safety import fused_kernels
from controllers.safety.barrier import SafetyConfig
from controllers.safety.fused import FusedScene
from controllers.safety.geometry import CollisionScene
from controllers.safety.latency import Prediction
from controllers.safety.polygon import convex_pieces
from controllers.safety.postcheck import SweepChecker, braking_acceleration, clip_norm
from sim.scenario import Dynamics, make_scenario
from tests.controllers.safety.fused_reference import NumpyFusedScene

DYN = Dynamics()
SCENARIO = make_scenario("paper-5")
R = SCENARIO.robot_radius
FIELDS = ("h", "drift", "bound", "normal_xy", "distance", "pair_delta", "pair_normal", "object_normal")
SHAPES = {
    "box": np.asarray(SCENARIO.polygon),
    "rotated box": np.array([[0.5, 0.35], [0.65, 0.5], [0.5, 0.65], [0.35, 0.5]]),
    "L (not convex)": np.array([[0.35, 0.35], [0.65, 0.35], [0.65, 0.45], [0.45, 0.45], [0.45, 0.65],
                                [0.35, 0.65]]),
}
SHAPES["L (pieces)"] = convex_pieces(SHAPES["L (not convex)"])


@settings(max_examples=80, deadline=None)
@given(seed=st.integers(0, 2**31 - 1), n=st.integers(1, 8), shape=st.sampled_from(sorted(SHAPES)),
       speed=st.sampled_from([0.0, 0.3, 1e3, 1e160]), predicted=st.booleans(), cubic=st.booleans())
def test_compiled_rows_equal_numpy_formulation(seed, n, shape, speed, predicted, cubic):
    """Centres anywhere (inside the object, on each other, near the walls), speeds up to far out
    of range, predictions with grown discs, fixed and unsure robots, both class-K functions."""
    rng = np.random.default_rng(seed)
    pos = rng.uniform(0.0, 1.0, (n, 2))
    if n > 1 and rng.random() < 0.2:
        pos[1] = pos[0]                                         # coincident centres
    if rng.random() < 0.2:
        first = SHAPES[shape][0] if isinstance(SHAPES[shape], list) else SHAPES[shape]
        pos[0] = first[0]                                       # on a vertex
    vel = rng.normal(0.0, speed + 1e-12, (n, 2))
    prediction = None
    if predicted:
        prediction = Prediction(pos=pos, vel=vel, grow=rng.uniform(0, 0.02, n), closing=rng.uniform(0, 0.1, n),
                                fixed=rng.random(n) < 0.3, horizon=np.full(n, 3),
                                unsure=rng.random(n) < 0.5 if rng.random() < 0.7 else None)
    config = SafetyConfig(class_k="cubic" if cubic else "linear")
    polygon = SHAPES[shape]
    pieces = polygon if isinstance(polygon, list) else [polygon]
    args = (R, SCENARIO.arena, DYN, config, n, len(pieces))
    with np.errstate(all="ignore"):
        got = FusedScene(*args).terms(pos, vel, polygon, prediction)
        want = NumpyFusedScene(*args).terms(pos, vel, polygon, prediction)
    for name in FIELDS:
        np.testing.assert_array_equal(getattr(got, name), getattr(want, name), err_msg=name)
    u = rng.normal(0.0, 1.0, (n, 2))                             # the rows' values: one product in numpy
    np.testing.assert_array_equal(got.rows_times(u), (want.normal_xy * (u.T @ want.gather_t)).sum(axis=0))
    for piece in pieces:
        geometry = FusedScene(*args).object_geometry(pos, piece), NumpyFusedScene(*args).object_geometry(pos, piece)
        for a, b in zip(*geometry, strict=True):
            np.testing.assert_array_equal(a, b)


def test_the_reference_is_not_the_compiled_code():
    assert NumpyFusedScene.terms is not FusedScene.terms
    assert NumpyFusedScene._sweep is not FusedScene._sweep


@settings(max_examples=150, deadline=None)
@given(seed=st.integers(0, 2**31 - 1), n=st.integers(1, 7), spread=st.sampled_from([0.0, 0.15, 0.4, 1.0, "chain"]),
       speed=st.sampled_from([0.1, 0.4, 0.8]), widened=st.booleans(), excused=st.booleans(),
       margin=st.sampled_from([0.0, 0.003]))
def test_compiled_sweep_equals_numpy_formulation(seed, n, spread, speed, widened, excused, margin):
    """Crowded and spread scenes, and chains of robots (along the bottom wall: ``spread`` 0; in
    the open: "chain") whose gaps and wall clearances lie within a few millimetres of the
    margins; robots at and beyond
    the speed limit, commands beyond the actuator limit, grown discs, with and without the
    braking excuses."""
    rng = np.random.default_rng(seed)
    if spread in (0.0, "chain"):
        x = 0.1 + np.cumsum(2 * R + rng.uniform(-0.004, 0.012, n))
        pos = np.stack((x, (R if spread == 0.0 else 0.25) + rng.uniform(-0.002, 0.01, n)), axis=1)
    else:
        pos = 0.5 + spread * rng.uniform(-0.5 + R, 0.5 - R, (n, 2))
    vel = rng.normal(0.0, speed, (n, 2))
    acc = rng.normal(0.0, 1.0, (n, 2))
    grow = rng.uniform(0.0, 0.01, n) if widened else None
    vel_error = rng.uniform(0.0, 0.05, n) if widened else None
    coll = CollisionScene(SCENARIO, n)
    coll.update(pos)
    checker = SweepChecker(coll.object_parts, R, SCENARIO.arena, DYN, margin)
    compiled, reference = FusedScene(R, SCENARIO.arena, DYN, SafetyConfig(), n), \
        NumpyFusedScene(R, SCENARIO.arena, DYN, SafetyConfig(), n)
    terms = compiled.terms(pos, vel, coll.polygon)
    brake = braking_acceleration(vel, DYN) if excused else None
    got = compiled.failing(checker, pos, vel, acc, terms, grow, vel_error, brake)
    want = reference.failing(checker, pos, vel, acc, terms, grow, vel_error, brake)
    np.testing.assert_array_equal(got, want)
    widen = np.zeros(n) if grow is None else grow                 # the sweep's own numbers too
    parts = [scene._sweep(pos, vel, acc, widen, terms, margin) for scene in (compiled, reference)]
    assert parts[0][0] == parts[1][0]
    compared = 4 if parts[0][0] else 6          # hit rows are not computed when the bound clears
    for name, a, b in zip(("end", "bulge", "travel", "hit", "wall_hit")[:compared - 1], parts[0][1:compared],
                          parts[1][1:compared], strict=True):
        np.testing.assert_array_equal(a, b, err_msg=name)


@settings(max_examples=80, deadline=None)
@given(seed=st.integers(0, 2**31 - 1), n=st.integers(1, 8), scale=st.sampled_from([0.1, 1.0, 1e3, 1e200]),
       poison=st.sampled_from([None, "nan", "inf", "-inf"]))
def test_screen_equals_its_numpy_formulation(seed, n, scale, poison):
    """The filter's first look (clip, row values, minima, the bound and row tests) in one kernel
    equals the numpy lines it replaced, NaN and infinite rows included."""
    rng = np.random.default_rng(seed)
    scene = FusedScene(R, SCENARIO.arena, DYN, SafetyConfig(), n)
    terms = scene.terms(rng.uniform(0.1, 0.9, (n, 2)), rng.normal(0, 0.3, (n, 2)), SHAPES["box"])
    a_nom = rng.normal(0.0, scale, (n, 2))
    bound, distance, h = (rng.normal(0.0, 1.0, scene.k) for _ in range(3))
    if poison is not None:
        for arr in (bound, distance, h):
            arr[rng.integers(scene.k)] = float(poison)
    nominal, values = np.empty((n, 2)), np.empty(scene.k)
    low_d, low_h, bounded, met = fused_kernels.screen(terms.normal_xy, terms.row_i, terms.row_j, a_nom,
                                                      DYN.accel_limit, bound, distance, h, nominal, values)
    want_nominal = clip_norm(a_nom, DYN.accel_limit)
    np.testing.assert_array_equal(nominal, want_nominal)
    np.testing.assert_array_equal(values, (terms.normal_xy * (want_nominal.T @ terms.gather_t)).sum(axis=0))
    np.testing.assert_array_equal([low_d, low_h], [distance.min(), h.min()])
    assert bounded == bool((bound < np.inf).all())
    assert met == bool((values >= bound).all())

