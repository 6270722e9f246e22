"""SafetyFilter: unchanged when safe, idempotent, permutation-equivariant, every failure path explicit."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from controllers.safety import SafetyConfig, SafetyFilter, SafetyStatus, analytic_distances
from controllers.safety.barrier import octagon_accel
from sim.scenario import transport_scenario

SCENARIO = transport_scenario(6)
DYN = SCENARIO.dynamics
R = SCENARIO.robot_radius


def random_state(rng, n, filt):
    """Positions with clearance and velocities inside the safe set (h >= 0 on every row)."""
    while True:
        pos = rng.uniform(0.06, 0.94, (n, 2))
        if analytic_distances(pos, R, SCENARIO.arena, SCENARIO.polygon).min_clearance() < 0.03:
            continue
        vel = rng.normal(0.0, 0.2, (n, 2))
        for _ in range(30):
            if filt.barrier(pos, vel).h.min() >= 0:
                return pos, vel
            vel *= 0.7


def toward_neighbours(pos):
    """Full thrust of every robot towards its nearest neighbour."""
    d = np.linalg.norm(pos[:, None] - pos[None], axis=-1) + np.eye(len(pos)) * 1e9
    direction = pos[np.argmin(d, axis=1)] - pos
    return direction / np.linalg.norm(direction, axis=1, keepdims=True) * DYN.accel_limit


def test_safe_nominal_comes_back_unchanged():
    f = SafetyFilter(SCENARIO)
    rng = np.random.default_rng(0)
    a_nom = rng.uniform(-0.1, 0.1, (6, 2))
    result = f.filter(SCENARIO.starts, np.zeros((6, 2)), a_nom)
    assert result.status is SafetyStatus.UNCHANGED and not result.modified
    np.testing.assert_allclose(result.a_safe, a_nom, atol=1e-12)
    assert result.min_barrier > 0 and result.min_clearance == pytest.approx(0.03, abs=1e-6)
    assert not result.braked.any() and result.total_time_s > 0


def test_filtering_twice_equals_once_and_rows_hold():
    rng = np.random.default_rng(1)
    f = SafetyFilter(SCENARIO)
    intervened = 0
    for _ in range(10):
        n = int(rng.integers(3, 7))
        pos, vel = random_state(rng, n, f)
        first = f.filter(pos, vel, toward_neighbours(pos))
        assert first.status in (SafetyStatus.UNCHANGED, SafetyStatus.INTERVENED)
        intervened += first.status is SafetyStatus.INTERVENED
        terms = f.barrier(pos, vel)
        assert np.all(terms.rows_times(first.a_safe) >= terms.bound - 1e-6)
        second = f.filter(pos, vel, first.a_safe)
        assert second.status is SafetyStatus.UNCHANGED
        np.testing.assert_allclose(second.a_safe, first.a_safe, atol=1e-6)
    assert intervened >= 5


def test_permuting_robots_permutes_outputs():
    rng = np.random.default_rng(2)
    f = SafetyFilter(SCENARIO)
    for _ in range(5):
        pos, vel = random_state(rng, 6, f)
        a_nom = toward_neighbours(pos)
        base = f.filter(pos, vel, a_nom)
        perm = rng.permutation(6)
        permuted = f.filter(pos[perm], vel[perm], a_nom[perm])
        assert permuted.status is base.status
        np.testing.assert_allclose(permuted.a_safe, base.a_safe[perm], atol=1e-5)


def test_the_closed_form_answers_as_osqp_does_and_osqp_the_rest():
    """Random safe states, every robot at full thrust towards its nearest neighbour: the filter
    with the closed-form projection gives OSQP's answers (to OSQP's tolerance), answering part
    of the ticks itself and leaving rows that share a robot to OSQP."""
    rng = np.random.default_rng(7)
    both = SafetyFilter(SCENARIO)
    osqp_only = SafetyFilter(SCENARIO, SafetyConfig(exact_projection=False))
    solvers = []
    for _ in range(60):
        n = int(rng.integers(2, 7))
        pos, vel = random_state(rng, n, both)
        a_nom = toward_neighbours(pos) * rng.uniform(0.2, 1.0)
        got, want = both.filter(pos, vel, a_nom), osqp_only.filter(pos, vel, a_nom)
        assert got.status is want.status
        np.testing.assert_allclose(got.a_safe, want.a_safe, atol=1e-5)
        solvers.append(got.solver)
        assert want.solver in ("", "osqp")
    assert solvers.count("projection") >= 5 and solvers.count("osqp") >= 1, solvers


def test_robots_already_closing_too_fast_get_slack_and_bounded_commands():
    # two robots 0.1 m apart (clearance 0.02 m) closing at 0.8 m/s: h < 0, no command can satisfy it
    pos = np.array([[0.2, 0.2], [0.3, 0.2], [0.8, 0.8]])
    vel = np.array([[0.4, 0.0], [-0.4, 0.0], [0.0, 0.0]])
    a_nom = np.array([[1.0, 0.0], [-1.0, 0.0], [0.0, 0.0]])
    f = SafetyFilter(SCENARIO, SafetyConfig(postcheck=False))
    result = f.filter(pos, vel, a_nom)
    assert result.status is SafetyStatus.SLACK
    assert "OSQP: primal infeasible" in result.reason and result.max_slack > 0.1
    assert result.min_barrier < 0
    assert np.all(np.isfinite(result.a_safe))
    assert np.all(np.linalg.norm(result.a_safe, axis=1) <= DYN.accel_limit + 1e-9)
    # both brake as hard as the octagon allows along the line between them
    assert result.a_safe[0, 0] == pytest.approx(-octagon_accel(DYN, f.config), abs=1e-6)
    assert result.a_safe[1, 0] == pytest.approx(octagon_accel(DYN, f.config), abs=1e-6)
    # with the post-check on they are braked and the unavoidable touch is reported
    checked = SafetyFilter(SCENARIO).filter(pos, vel, a_nom)
    assert checked.status is SafetyStatus.FALLBACK_BRAKE
    np.testing.assert_array_equal(checked.braked, [True, True, False])


def test_osqp_failure_falls_back_to_the_exact_slack_qp():
    rng = np.random.default_rng(3)
    # gamma 3: this state and push make the barrier rows bind (with 6 the nominal is already safe)
    exact = SafetyFilter(SCENARIO, SafetyConfig(gamma=3.0))
    starved = SafetyFilter(SCENARIO, SafetyConfig(gamma=3.0, max_iter=1, exact_projection=False))
    pos, vel = random_state(rng, 5, exact)
    a_nom = toward_neighbours(pos)
    want = exact.filter(pos, vel, a_nom)
    got = starved.filter(pos, vel, a_nom)
    assert want.status is SafetyStatus.INTERVENED
    assert got.status is SafetyStatus.SLACK and "maximum iterations reached" in got.reason
    assert got.max_slack < 1e-4
    np.testing.assert_allclose(got.a_safe, want.a_safe, atol=1e-4)


@pytest.mark.parametrize("field", ["pos", "vel", "a_nom"])
def test_non_finite_input_brakes_with_a_status(field):
    f = SafetyFilter(SCENARIO)
    data = {"pos": SCENARIO.starts.copy(), "vel": np.full((6, 2), 0.2), "a_nom": np.zeros((6, 2))}
    data[field][2, 1] = np.nan if field != "a_nom" else np.inf
    result = f.filter(**data)
    assert result.status is SafetyStatus.FALLBACK_BRAKE and field in result.reason
    assert np.all(np.isfinite(result.a_safe)) and result.braked.all()
    if field != "vel":
        np.testing.assert_allclose(result.a_safe, np.full((6, 2), -np.sqrt(0.5)))   # against v
    overflow = f.filter(SCENARIO.starts, np.full((6, 2), 1e200), np.zeros((6, 2)))
    assert overflow.status is SafetyStatus.FALLBACK_BRAKE and "overflow" in overflow.reason
    assert np.all(np.isfinite(overflow.a_safe))


def test_shape_errors_name_the_argument_and_robot_count_may_change():
    f = SafetyFilter(SCENARIO)
    with pytest.raises(ValueError, match="a_nom must have shape"):
        f.filter(np.zeros((3, 2)), np.zeros((3, 2)), np.zeros((3, 3)))
    assert f.filter(np.zeros((0, 2)), np.zeros((0, 2)), np.zeros((0, 2))).a_safe.shape == (0, 2)
    for n in (2, 4, 2):
        assert f.filter(SCENARIO.starts[:n], np.zeros((n, 2)), np.zeros((n, 2))).a_safe.shape == (n, 2)


@settings(max_examples=40, deadline=None)
@given(seed=st.integers(0, 2**31), n=st.integers(1, 6), speed=st.floats(0.0, 0.4),
       geometry=st.sampled_from(["fcl", "analytic"]))
def test_output_is_always_finite_and_within_limits(seed, n, speed, geometry):
    """Any positions (even overlapping) and velocities: a finite command within the actuator limit."""
    rng = np.random.default_rng(seed)
    f = SafetyFilter(SCENARIO, SafetyConfig(geometry=geometry))
    pos = rng.uniform(-0.02, 1.02, (n, 2))
    vel = rng.normal(size=(n, 2))
    vel *= speed / np.maximum(np.linalg.norm(vel, axis=1, keepdims=True), 1e-9)
    result = f.filter(pos, vel, rng.normal(0, 2, (n, 2)))
    assert np.all(np.isfinite(result.a_safe))
    assert np.all(np.linalg.norm(result.a_safe, axis=1) <= DYN.accel_limit + 1e-9)
    assert isinstance(result.status, SafetyStatus)


@settings(max_examples=40, deadline=None)
@given(zx=st.floats(0.002, 0.1), zy=st.floats(0.002, 0.1))
def test_a_robot_on_both_wall_curves_of_a_corner_can_still_meet_both(zx, zy):
    """Heading into the arena's corner (0, 0) on the braking curve of both walls (h = 0 on each),
    full thrust into the corner: the static rows count on ``a_box / sqrt(2)``, so the two rows
    stay jointly feasible inside the octagon (module docstring of
    :mod:`controllers.safety.barrier`) and the QP answers without slack; counting on the whole
    actuator (``static_braking_share = 1``) they are not, and the slack QP has to give way."""
    margin = SafetyConfig().margin
    pos = np.array([[R + margin + zx, R + margin + zy]])
    a_nom = np.array([[-0.7, -0.7]])
    assert SafetyConfig().static_braking_share == pytest.approx(np.sqrt(0.5))
    for share, feasible in ((SafetyConfig().static_braking_share, True), (1.0, False)):
        config = SafetyConfig(static_braking_share=share)
        vel = -np.sqrt(2 * share * octagon_accel(DYN, config) * np.array([[zx, zy]]))
        f = SafetyFilter(SCENARIO, config)
        walls = f.barrier(pos, vel).h[1:5]                       # rows: object, walls x=0, W, y=0, H
        np.testing.assert_allclose(walls[[0, 2]], 0.0, atol=1e-12)
        result = f.filter(pos, vel, a_nom)
        assert (result.solver != "daqp") is feasible, (share, result.solver, result.reason)
        if feasible:
            assert result.max_slack == 0.0


_MISMATCH = """
import numpy as np
from controllers.safety import SafetyConfig, SafetyFilter
from controllers.safety.prediction import Prediction
from sim.scenario import make_scenario
f = SafetyFilter(make_scenario("paper-3"), SafetyConfig(geometry={geometry!r}))
pos = np.array([[0.15, 0.2], [0.85, 0.8], [0.2, 0.85]]); vel = np.zeros((3, 2)); a = np.full((3, 2), 0.1)
for m in (2, 4):      # a row short, a row over
    rows = np.vstack([pos, [[0.5, 0.1]]])[:m]
    pred = Prediction.as_measured(rows, np.zeros((m, 2)), np.zeros(m, bool))
    try:
        f.filter(pos, vel, a, prediction=pred)
        print("accepted", m)
    except ValueError as err:
        print("refused", m, err)
"""


@pytest.mark.parametrize("geometry", ["fused", "analytic"])
def test_a_prediction_with_another_row_count_than_pos_is_refused_by_name(geometry):
    """Before, the fused path ran its unchecked kernels on the prediction's rows: a row short read
    past the arrays (a robot stopped in open space, or IndexError), a row over wrote past them
    (free(): invalid pointer). In a child process: the parent must survive the old behaviour."""
    import subprocess
    import sys

    child = subprocess.run([sys.executable, "-c", _MISMATCH.format(geometry=geometry)], capture_output=True,
                           text=True, timeout=120)
    assert child.returncode == 0, child.stderr[-2000:]
    lines = child.stdout.strip().splitlines()
    assert [line.split()[:2] for line in lines] == [["refused", "2"], ["refused", "4"]], child.stdout
    assert all("the prediction (one row per robot of pos): pos must have shape (3, 2)" in line for line in lines)
