"""A policy that reads its own target marked (``actor.own_target``), from export to the robot:
the files say so, the golden file holds the marked tokens and the assignment, the robot runtime
(numpy + onnxruntime) works the assignment out as training did, and the ControlStack marks the
tokens it gives the network."""

from __future__ import annotations

import numpy as np
import pytest
import torch
from hypothesis import given, settings
from hypothesis import strategies as st

from controllers.docking import DockingConfig
from controllers.policy import ActorConfig
from deploy.export import check_export, export_policy, load_exported
from deploy.robot import RobotPolicy, detour_distances, least_squares_assignment, robot_tokens
from sim.fleet import FleetState
from sim.geometry import DetourDistance, Polygon
from sim.observations import mark_own_targets, own_assignment, own_target_paths, tokens
from sim.scenario import make_scenario
from tests.deploy.test_npz_policy import scaled_actor

pytestmark = pytest.mark.filterwarnings("ignore:.*torch.jit.*:DeprecationWarning")
SCENARIO = make_scenario("paper-5")


def own_actor(own: bool = True):
    return scaled_actor(ActorConfig(embed_dim=32, velocity_damping=2.0, own_target=own), seed=5)


@pytest.fixture(scope="module")
def exported(tmp_path_factory):
    torch.set_num_threads(1)
    stem = tmp_path_factory.mktemp("own") / "policy"
    reports = export_policy(own_actor(), stem, dt=0.05, trained_robots=5, formats=("onnx", "npz"))
    return {r.meta["file_format"]: r.path for r in reports}


def fleet(n: int, seed: int):
    rng = np.random.default_rng(seed)
    return rng.uniform(0.05, 0.95, (n, 2)), rng.uniform(-0.4, 0.4, (n, 2)), rng.uniform(0.05, 0.95, (n, 2))


def exact_own(pos, targets):
    """The assignment by the exact detour (what export's golden file and the robot runtime use)."""
    paths = own_target_paths(Polygon(torch.from_numpy(SCENARIO.polygon)), torch.from_numpy(targets),
                             SCENARIO.robot_radius)
    return own_assignment(paths(torch.from_numpy(pos))[None])[0]


def eager_marked(actor, pos, vel, targets):
    """The eager actor on marked tokens (the reference), bounded in norm as the files are."""
    as_t = [torch.from_numpy(x)[None] for x in (pos, vel, targets)]
    toks, mask = tokens(*as_t, torch.from_numpy(SCENARIO.polygon), SCENARIO.arena)
    toks = mark_own_targets(toks, exact_own(pos, targets)[None])
    with torch.no_grad():
        a = actor(toks.float(), mask)[0]
    return (a * torch.clamp(1.0 / torch.linalg.vector_norm(a, dim=-1, keepdim=True), max=1.0)).numpy()


@settings(max_examples=30, deadline=None)
@given(st.integers(1, 21), st.integers(0, 2**31 - 1))
def test_the_robot_runtimes_hungarian_method_is_the_assignment_training_solves(n, seed):
    """Least total squared path: numpy's Hungarian method against :func:`sim.observations.own_assignment`."""
    path = np.random.default_rng(seed).uniform(0.0, 1.0, (n, n))
    want = own_assignment(torch.from_numpy(path)[None])[0].numpy()
    assert np.array_equal(least_squares_assignment(path), want)


@settings(max_examples=40, deadline=None)
@given(st.integers(3, 8), st.integers(0, 2**31 - 1), st.floats(0.0, 0.1))
def test_the_robot_runtimes_detour_is_the_projects(m, seed, margin):
    """numpy's taut string round a convex polygon (random, and paper-5's box) against
    :class:`sim.geometry.DetourDistance`, from points inside and outside the inflated object."""
    rng = np.random.default_rng(seed)
    angles = np.sort(rng.uniform(0, 2 * np.pi, m))
    polygon = 0.5 + rng.uniform(0.05, 0.2) * np.stack((np.cos(angles), np.sin(angles)), -1)
    for poly in (polygon, np.asarray(SCENARIO.polygon)):
        points, targets = rng.uniform(0.0, 1.0, (40, 2)), rng.uniform(0.0, 1.0, (6, 2))
        want = DetourDistance(Polygon(torch.from_numpy(poly)), torch.from_numpy(targets), margin)(
            torch.from_numpy(points)).numpy()
        assert np.abs(detour_distances(points, targets, poly, margin) - want).max() <= 1e-12


def test_every_file_says_it_reads_its_own_target_and_its_golden_file_holds_the_marks(exported):
    for path in exported.values():
        policy = load_exported(path)
        assert policy.meta["own_target"] is True and policy.own_target is True
        assert check_export(path).max_abs_diff <= 1e-5
    with np.load(path.with_name("policy.golden.npz")) as golden:
        toks, own = golden["n5_tokens"][0], golden["n5_own"][0]
        marked = toks[np.arange(5), 1 + own, 2:4]
        assert np.abs(marked).min(initial=1.0) >= 0 and np.linalg.norm(marked, axis=1).min() > 0
        others = np.ones(toks.shape[:2], dtype=bool)
        others[np.arange(5), 1 + own] = False
        assert np.all(toks[:, 1:6][others[:, 1:6]][:, 2:4] == 0)      # only the own target is marked


@pytest.mark.parametrize("name", ["onnx", "npz"])
def test_the_robot_runtime_marks_the_target_its_team_gives_it(exported, name):
    """``act`` with no ``own_target`` finds the robot's own target from the positions it sees and
    matches the eager actor on marked tokens; the unmarked tokens would give other actions."""
    policy, actor = RobotPolicy(exported[name]), own_actor()
    assert policy.own_target and policy.golden_diff <= 1e-5
    for n, seed in ((1, 0), (4, 1), (7, 2)):
        pos, vel, targets = fleet(n, seed)
        want = eager_marked(actor, pos, vel, targets)
        got, unmarked = [], []
        sigma = exact_own(pos, targets).numpy()
        for i in range(n):
            others = [j for j in range(n) if j != i]
            args = (pos[i], vel[i], targets, pos[others], vel[others], SCENARIO.polygon, SCENARIO.arena)
            got.append(policy.act(*args, index=i).accel)
            assert np.array_equal(policy.act(*args, own_target=int(sigma[i])).accel, got[-1])
            unmarked.append(policy._forward(robot_tokens(*args)[None])[0][0])
        assert np.abs(np.array(got) - want).max() <= 1e-5
        assert np.abs(np.array(unmarked) - want).max() > 1e-4      # 10x the tolerance: the mark counts


@pytest.mark.parametrize("lost", [np.nan, np.inf, 1e200])
def test_a_target_the_robot_cannot_place_makes_it_brake_at_once(exported, lost):
    """One target not finite (a tracker that lost it), or so far that its squared path overflows:
    the robot brakes (zero, invalid) at once. Before, the Hungarian search never ended and the
    robot's control loop hung."""
    policy = RobotPolicy(exported["onnx"])
    targets = np.array([[0.2, 0.2], [lost, 0.2], [0.5, 0.9]])
    action = policy.act([0.1, 0.5], [0.0, 0.0], targets, [[0.3, 0.7], [0.7, 0.7]], np.zeros((2, 2)),
                        SCENARIO.polygon, SCENARIO.arena)
    assert action.accel.tolist() == [0.0, 0.0] and not action.valid
    with pytest.raises(ValueError, match="every path length must be finite"):
        least_squares_assignment(np.array([[1.0, np.inf], [2.0, 1.0]]))


def test_a_policy_without_the_mark_refuses_an_own_target_and_a_bad_one_is_refused(exported, tmp_path):
    export_policy(own_actor(own=False), tmp_path / "plain", dt=0.05, trained_robots=5, formats=("onnx",))
    policy = RobotPolicy(tmp_path / "plain.onnx")
    assert policy.own_target is False
    with pytest.raises(ValueError, match="does not read an own target"):
        policy.act([0.2, 0.2], [0, 0], [[0.5, 0.5]], np.zeros((0, 2)), np.zeros((0, 2)),
                   SCENARIO.polygon, SCENARIO.arena, own_target=0)
    with pytest.raises(ValueError, match="must index one of the 1 targets"):
        RobotPolicy(next(iter(exported.values()))).act([0.2, 0.2], [0, 0], [[0.5, 0.5]], np.zeros((0, 2)),
                                                       np.zeros((0, 2)), SCENARIO.polygon, SCENARIO.arena,
                                                       own_target=3)


@pytest.mark.parametrize("source", ["network", "onnx"])
def test_the_control_stack_gives_an_own_target_policy_marked_tokens(exported, source):
    """The stack's nominal command (no filter, no MEC) equals the eager actor on marked tokens,
    for the network itself and for its exported file."""
    from stack.pipeline import ControlStack, StackConfig

    actor = own_actor()
    policy = actor if source == "network" else exported["onnx"]
    stack = ControlStack(SCENARIO, policy, StackConfig(safety=False, mec=False, docking=DockingConfig(enabled=False)))
    assert stack.own_target
    pos, vel, targets = fleet(5, 3)
    state = FleetState(time=0.0, step=0, positions=pos, velocities=vel, targets=targets,
                       object_pose=np.array([*SCENARIO.object_center, 0.0]))
    got = stack.tick(state).a_nom
    assert np.abs(got - eager_marked(actor, pos, vel, targets)).max() <= 1e-5
    toks, _ = stack.observe(state)
    sigma = exact_own(pos, targets).numpy()
    assert np.allclose(toks[0, np.arange(5), 1 + sigma, 0:2].numpy(), toks[0, np.arange(5), 1 + sigma, 2:4].numpy()
                       * np.maximum(np.linalg.norm(targets[sigma] - pos, axis=1), 0.1)[:, None] / 0.1, atol=1e-6)
