"""Fixed discs that cannot bind a listening robot this tick stay out of the QP, and leaving them
out changes no answer (controllers.safety.relevance)."""

from __future__ import annotations

import math

import numpy as np
import qpsolvers
from hypothesis import given, settings
from hypothesis import strategies as st

from controllers.safety import SafetyConfig, SafetyFilter
from controllers.safety.barrier_qp import MAX_CACHED_PROBLEMS
from controllers.safety.prediction import Prediction
from controllers.safety.relevance import binding_fixed_rows, without_idle_fixed_rows
from sim.scenario import make_scenario

SCENARIO = make_scenario("paper-3")
DYN = SCENARIO.dynamics
R = SCENARIO.robot_radius
CONFIG = SafetyConfig()


def _one_robot_one_disc(gap: float, speed: float, unsure: bool = False) -> Prediction:
    """A listening robot at (0.1, 0.15) moving along +x at ``speed`` [m/s] and a fixed disc of
    robot size on the x axis ``gap`` [m] clear of it; nothing grown, no closing allowance."""
    pos = np.array([[0.1, 0.15], [0.1 + 2 * R + gap, 0.15]])
    vel = np.array([[speed, 0.0], [0.0, 0.0]])
    return Prediction(pos=pos, vel=vel, grow=np.zeros(2), closing=np.zeros(2), fixed=np.array([False, True]),
                      horizon=np.zeros(2, dtype=np.int64), unsure=np.array([unsure, False]))


def test_a_disc_binds_by_its_gap_the_approach_speed_and_the_robots_gain():
    """alpha = 0.5 * 0.999 cos(pi/8) = 0.4615 m/s^2. Gap 0.42 m, head-on at 0.4 m/s: root =
    sqrt(2 alpha 0.41) = 0.6152, h = 0.2152, drift = (alpha / root - 0.5)(-0.4) = -0.1000, so
    b = -6 h + 0.1 = -1.19 (idle: below -1.001) with gamma 6 but -3 h + 0.1 = -0.55 (binds) for
    an unsure robot's gamma 3. Moving away, or at rest, it is idle; at a 0.2 m gap head-on,
    b = -6 (0.0188) + 0.2408 = +0.13: it binds."""
    alpha = 0.5 * 0.999 * math.cos(math.pi / 8)
    root = math.sqrt(2 * alpha * (0.42 - CONFIG.margin))
    assert -6 * (root - 0.4) - (alpha / root - 0.5) * -0.4 < -1.001 < -3 * (root - 0.4) - (alpha / root - 0.5) * -0.4
    assert binding_fixed_rows(_one_robot_one_disc(0.42, 0.4), 1, CONFIG, DYN, R).tolist() == [False]
    assert binding_fixed_rows(_one_robot_one_disc(0.42, 0.4, unsure=True), 1, CONFIG, DYN, R).tolist() == [True]
    assert binding_fixed_rows(_one_robot_one_disc(0.42, -0.4, unsure=True), 1, CONFIG, DYN, R).tolist() == [False]
    assert binding_fixed_rows(_one_robot_one_disc(0.2, 0.4), 1, CONFIG, DYN, R).tolist() == [True]
    assert binding_fixed_rows(_one_robot_one_disc(0.2, 0.0), 1, CONFIG, DYN, R).tolist() == [False]
    # within the post-check's sweep (dt 0.4 + dt^2 (1 + 0.5 |v|) / 2 = 0.0213 m) a disc always
    # binds, even one the robot leaves at 0.4 m/s, whose barrier row is idle (b = -5.3)
    assert binding_fixed_rows(_one_robot_one_disc(0.015, -0.4), 1, CONFIG, DYN, R).tolist() == [True]
    assert binding_fixed_rows(_one_robot_one_disc(0.025, -0.4), 1, CONFIG, DYN, R).tolist() == [False]


def test_the_disc_it_keeps_changes_the_answer():
    """Teeth of the property below: a binding disc left out gives another command."""
    with_disc = _one_robot_one_disc(0.2, 0.4)
    a_nom = np.array([[1.0, 0.0], [0.0, 0.0]])
    kept = SafetyFilter(SCENARIO).filter(with_disc.pos, with_disc.vel, a_nom, prediction=with_disc).a_safe[0]
    alone = with_disc.rows(np.array([True, False]))
    dropped = SafetyFilter(SCENARIO).filter(alone.pos, alone.vel, a_nom[:1], prediction=alone).a_safe[0]
    assert dropped[0] > 0.99 and kept[0] < 0.5


def _random_scene(seed: int, n: int, k: int) -> tuple[Prediction, np.ndarray]:
    """``n`` listening robots anywhere in the arena (up to 0.4 m/s, grown up to 2 cm, closing up to
    0.1 m/s, half unsure) and ``k`` fixed discs (grown up to 6 cm, closing up to 0.3 m/s), free
    to overlap anything; nominal commands up to 1.5 m/s^2."""
    rng = np.random.default_rng(seed)
    m = n + k
    pos = rng.uniform(R + 1e-3, 1 - R - 1e-3, (m, 2))
    speed, heading = rng.uniform(0, 0.4, n), rng.uniform(0, 2 * np.pi, n)
    vel = np.zeros((m, 2))
    vel[:n] = speed[:, None] * np.column_stack([np.cos(heading), np.sin(heading)])
    grow = np.concatenate([rng.uniform(0, 0.02, n), rng.uniform(0, 0.06, k)])
    closing = np.concatenate([rng.uniform(0, 0.1, n), rng.uniform(0, 0.3, k)])
    fixed = np.arange(m) >= n
    unsure = (rng.random(m) < 0.5) & ~fixed
    a_nom = np.zeros((m, 2))
    a_nom[:n] = rng.uniform(-1.5, 1.5, (n, 2))
    return Prediction(pos=pos, vel=vel, grow=grow, closing=closing, fixed=fixed,
                      horizon=np.zeros(m, dtype=np.int64), unsure=unsure), a_nom


@settings(max_examples=60, deadline=None)
@given(seed=st.integers(0, 2**31), n=st.integers(1, 5), k=st.integers(1, 30))
def test_leaving_out_the_idle_discs_changes_no_answer(seed, n, k):
    """Every listening robot's command, braking and contact flags are those of the filter that
    takes every disc (to OSQP's tolerance)."""
    full, a_nom = _random_scene(seed, n, k)
    pruned, kept = without_idle_fixed_rows(full, n, CONFIG, DYN, R)
    want = SafetyFilter(SCENARIO).filter(full.pos, full.vel, a_nom, prediction=full)
    got = SafetyFilter(SCENARIO).filter(pruned.pos, pruned.vel, a_nom[kept], prediction=pruned)
    np.testing.assert_allclose(got.a_safe[:n], want.a_safe[:n], atol=1e-5)
    assert got.braked[:n].tolist() == want.braked[:n].tolist()
    assert got.contact[:n].tolist() == want.contact[:n].tolist()


def test_far_discs_are_left_out_and_near_ones_kept():
    """Robots at rest in the lower half, 200 discs in the top tenth: none binds; one disc 1 cm
    from a robot does."""
    rng = np.random.default_rng(0)
    robots = np.array([[0.3, 0.2], [0.5, 0.3], [0.7, 0.2]])
    discs = np.vstack([rng.uniform([0.05, 0.9], [0.95, 0.95], (200, 2)), [[0.3 + 2 * R + 0.01, 0.2]]])
    m = len(robots) + len(discs)
    p = Prediction(pos=np.vstack([robots, discs]), vel=np.zeros((m, 2)), grow=np.zeros(m), closing=np.zeros(m),
                   fixed=np.arange(m) >= 3, horizon=np.zeros(m, dtype=np.int64))
    binding = binding_fixed_rows(p, 3, CONFIG, DYN, R)
    assert np.flatnonzero(binding).tolist() == [200]


def test_the_filter_keeps_the_problems_it_used_last():
    safety = SafetyFilter(SCENARIO)
    first = safety.problem(1)
    for n in range(2, MAX_CACHED_PROBLEMS + 1):
        safety.problem(n)
    assert safety.problem(1) is first                  # used again: now the newest
    safety.problem(MAX_CACHED_PROBLEMS + 1)
    assert len(safety._problems) == MAX_CACHED_PROBLEMS and 2 not in safety._problems
    assert safety.problem(1) is first


def _pinned_qp(terms, a_nom: np.ndarray, fixed: np.ndarray, a_box: float) -> np.ndarray | None:
    """The barrier QP of the module docstring of controllers.safety.barrier_qp over every robot,
    the fixed ones pinned at u = 0 by their bounds, solved exactly (DAQP, dense): the reference."""
    m = len(a_nom)
    live = np.isfinite(terms.bound)
    diag = np.zeros((2 * m, 2 * m))
    for i in range(m):
        diag[2 * i, 2 * i] = diag[2 * i, 2 * i + 1] = diag[2 * i + 1, 2 * i] = 1.0
        diag[2 * i + 1, 2 * i + 1] = -1.0
    g = np.vstack([-terms.dense(m)[live], diag, -diag])
    h = np.concatenate([-(terms.bound[live] + CONFIG.tighten), np.full(4 * m, math.sqrt(2) * a_box)])
    bound = np.where(np.repeat(fixed, 2), 0.0, a_box)
    x = qpsolvers.solve_qp(2.0 * np.eye(2 * m), -2.0 * a_nom.ravel(), g, h, lb=-bound, ub=bound, solver="daqp")
    return None if x is None else x.reshape(m, 2)


@settings(max_examples=100, deadline=None)
@given(seed=st.integers(0, 2**31), n=st.integers(1, 5), k=st.integers(1, 12))
def test_the_qp_without_its_fixed_robots_has_the_full_qps_answer(seed, n, k):
    """OSQP over the listening robots only (controllers.safety.reduced_qp) against the full
    problem with the fixed robots pinned at 0 (solved exactly), on the rows the filter builds:
    wherever the full problem is feasible, the same answer (about one scene in five: the rest
    overlap, infeasible for both)."""
    scene, a_nom = _random_scene(seed, n, k)
    prob = SafetyFilter(SCENARIO).problem(n + k)
    terms = prob.fused.terms(scene.pos, scene.vel, prob.posed_pieces(None), scene)
    a_nom = np.where(scene.fixed[:, None], 0.0, np.clip(a_nom, -0.6, 0.6))
    want = _pinned_qp(terms, a_nom, scene.fixed, prob.a_box)
    got, status = prob.solve(terms, a_nom, CONFIG.tighten, scene.fixed)
    if want is not None:
        assert got is not None, status
        np.testing.assert_allclose(got, want, atol=1e-5)
        assert np.abs(got[scene.fixed]).max(initial=0.0) == 0.0


@settings(max_examples=60, deadline=None)
@given(seed=st.integers(0, 2**31), n=st.integers(1, 5), k=st.integers(1, 30), unit=st.booleans())
def test_every_row_of_a_disc_left_out_holds_for_any_command(seed, n, k, unit):
    """The rows the filter builds (controllers.safety.fused) for a disc left out: each one's
    bound plus the tightening is at most -accel_limit (met by any command the stack sends), and
    its gap exceeds one tick's sweep; for the cubic class-K function too."""
    config = SafetyConfig(class_k="cubic") if unit else CONFIG
    scene, _ = _random_scene(seed, n, k)
    binding = binding_fixed_rows(scene, n, config, DYN, R)
    safety = SafetyFilter(SCENARIO, config)
    prob = safety.problem(n + k)
    terms = prob.fused.terms(scene.pos, scene.vel, prob.posed_pieces(None), scene)
    idle_rows = np.isin(terms.pair_j, n + np.flatnonzero(~binding)) & (terms.pair_i < n)
    assert np.all(terms.bound[:len(terms.pair_i)][idle_rows] + config.tighten <= -DYN.accel_limit)
    assert np.all(terms.distance[:len(terms.pair_i)][idle_rows] > DYN.dt * DYN.speed_limit)
