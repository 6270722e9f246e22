import numpy as np
import pytest
import torch
from hypothesis import given, settings
from hypothesis import strategies as st

from sim import observations as obs
from sim.geometry import closest_point_on_polygon
from sim.scenario import make_scenario, transport_scenario

POLY = torch.as_tensor(make_scenario("paper-3").polygon, dtype=torch.float64)


def reference_tokens(pos, vel, targets, poly):
    """Token layout written out with plain loops, straight from the module docstring."""
    e, n, _ = pos.shape
    c = torch.tensor([0.5, 0.5], dtype=pos.dtype)  # centroid of the default box
    out = torch.zeros(e, n, 2 * n + 1, 4, dtype=pos.dtype)
    for b in range(e):
        for i in range(n):
            p, v = pos[b, i], vel[b, i]
            out[b, i, 0] = torch.cat((p - 0.5, v))
            for k in range(n):
                out[b, i, 1 + k, :2] = targets[b, k] - p
            others = [j for j in range(n) if j != i]
            for slot, j in enumerate(others):
                out[b, i, n + 1 + slot] = torch.cat((pos[b, j] - p, vel[b, j] - v))
            _, s = closest_point_on_polygon(p, poly)
            out[b, i, 2 * n] = torch.cat((c - p, s - p))
    return out


@settings(max_examples=25, deadline=None)
@given(st.integers(1, 6), st.integers(0, 2**31 - 1))
def test_tokens_match_the_documented_layout(n, seed):
    g = torch.Generator().manual_seed(seed)
    pos = torch.rand(2, n, 2, generator=g, dtype=torch.float64)
    vel = torch.rand(2, n, 2, generator=g, dtype=torch.float64) - 0.5
    targets = torch.as_tensor(transport_scenario(n).targets).expand(2, -1, -1)
    toks, mask = obs.tokens(pos, vel, targets, POLY, (1.0, 1.0))
    assert toks.shape == (2, n, obs.num_tokens(n), obs.TOKEN_DIM)
    assert mask.all() and mask.shape == toks.shape[:-1]
    assert torch.allclose(toks, reference_tokens(pos, vel, targets, POLY))


def test_token_types():
    assert obs.token_types(3).tolist() == [0, 1, 1, 1, 2, 2, 3]
    assert obs.token_types(1).tolist() == [0, 1, 3]


def test_permuting_robots_permutes_token_sets():
    n = 4
    g = torch.Generator().manual_seed(0)
    pos = torch.rand(1, n, 2, generator=g, dtype=torch.float64)
    vel = torch.rand(1, n, 2, generator=g, dtype=torch.float64)
    targets = torch.as_tensor(transport_scenario(n).targets).unsqueeze(0)
    perm = torch.tensor([2, 0, 3, 1])
    a, _ = obs.tokens(pos, vel, targets, POLY, (1.0, 1.0))
    b, _ = obs.tokens(pos[:, perm], vel[:, perm], targets, POLY, (1.0, 1.0))
    for i in range(n):
        mine, theirs = a[0, perm[i]], b[0, i]
        assert torch.allclose(mine[: n + 1], theirs[: n + 1])       # self + targets unchanged
        assert torch.allclose(mine[-1], theirs[-1])                   # object
        # other robots: the same set, maybe in another order
        sa = sorted(map(tuple, mine[n + 1:2 * n].round(decimals=9).tolist()))
        sb = sorted(map(tuple, theirs[n + 1:2 * n].round(decimals=9).tolist()))
        assert sa == sb


def test_flat_vector_by_hand():
    pos = torch.tensor([[[0.7, 0.4], [0.7, 0.6]]])
    vel = torch.tensor([[[0.1, 0.0], [0.0, -0.2]]])
    targets = torch.tensor([[[0.3, 0.4], [0.3, 0.6]]])
    f = obs.flat(pos, vel, targets)
    assert f.shape == (1, 2, obs.flat_dim(2)) == (1, 2, 10)
    # P, V, G_1, G_2, R_1 for robot 0
    assert np.allclose(f[0, 0].numpy(), [0.7, 0.4, 0.1, 0.0, -0.4, 0.0, -0.4, 0.2, 0.0, 0.2])


def test_shape_errors_name_the_argument():
    pos = torch.zeros(2, 3, 2)
    with pytest.raises(ValueError, match="vel must have the shape of pos"):
        obs.tokens(pos, torch.zeros(2, 4, 2), pos, POLY, (1.0, 1.0))
    with pytest.raises(ValueError, match=r"pos must have shape \(num_envs, num_robots, 2\)"):
        obs.flat(torch.zeros(3, 2), torch.zeros(3, 2), torch.zeros(3, 2))


def test_own_target_mark_by_hand():
    """Robot 0 of two is told target 1 (offset (0.3, 0.4), 0.5 m: the mark is clipped to 0.1 m),
    robot 1 target 0 (offset (0.03, -0.04), 5 cm: the mark is the offset itself)."""
    pos = torch.tensor([[[0.2, 0.1], [0.57, 0.54]]], dtype=torch.float64)
    targets = torch.tensor([[[0.6, 0.5], [0.5, 0.5]]], dtype=torch.float64)
    toks, _ = obs.tokens(pos, torch.zeros_like(pos), targets, POLY, (1.0, 1.0))
    marked = obs.mark_own_targets(toks, torch.tensor([[1, 0]]))
    assert torch.allclose(marked[0, 0, 2], torch.tensor([0.3, 0.4, 0.06, 0.08], dtype=torch.float64))
    assert torch.allclose(marked[0, 1, 1], torch.tensor([0.03, -0.04, 0.03, -0.04], dtype=torch.float64))
    unmarked = torch.ones_like(toks[..., 0], dtype=torch.bool)
    unmarked[0, 0, 2] = unmarked[0, 1, 1] = False
    assert torch.equal(marked[unmarked], toks[unmarked])          # nothing else changes
    with pytest.raises(ValueError, match="long assignment"):
        obs.mark_own_targets(toks, torch.tensor([[1.0, 0.0]]))


@settings(max_examples=40, deadline=None)
@given(st.integers(1, 6), st.integers(0, 2**31 - 1))
def test_own_assignment_is_the_least_total_squared_path(n, seed):
    """Against every permutation (CAPT's rule on the given path lengths); one-to-one per row."""
    import itertools

    path = torch.rand(3, n, n, generator=torch.Generator().manual_seed(seed), dtype=torch.float64)
    sigma = obs.own_assignment(path)
    for row, told in zip(path, sigma, strict=True):
        assert sorted(told.tolist()) == list(range(n))

        def cost(perm, row=row):
            return sum(float(row[i, k] ** 2) for i, k in enumerate(perm))

        assert cost(told.tolist()) <= min(cost(p) for p in itertools.permutations(range(n))) + 1e-12


def test_the_fleets_own_targets_are_tabulated_before_the_first_tick_and_match_the_worlds():
    """:class:`FleetOwnTargets` builds its table for the targets it is given up front (~0.3 s,
    not at the first tick), keeps it while the targets stay, and assigns as the batched world."""
    from sim.batched_env import BatchedFormationEnv

    sc = make_scenario("paper-5")
    fleet = obs.FleetOwnTargets(sc.polygon, sc.robot_radius, sc.arena, sc.targets)
    table = fleet._table
    assert table is not None
    env = BatchedFormationEnv(sc, 1, dtype=torch.float64, own_target=True)
    rng = np.random.default_rng(0)
    for _ in range(20):
        pos = rng.uniform(0.05, 0.95, (5, 2))
        want = obs.own_assignment(env._own_paths(torch.from_numpy(pos)[None]))[0].numpy()
        assert np.array_equal(fleet(pos, sc.targets), want)
    assert fleet._table is table
    fleet(pos, np.asarray(sc.targets)[::-1])
    assert fleet._table is not table


def test_fleet_own_targets_keeps_a_column_per_target_so_a_reordered_team_builds_nothing(monkeypatch):
    """The table was keyed by the whole target array: a robot leaving or rejoining (the team
    view appends the silent robot last) rebuilt it inside the tick, 90 ms against the 50 ms
    period. Each target's column depends on that target alone: it is kept, and the answers are
    those of the whole table."""
    from scipy.optimize import linear_sum_assignment

    from sim.geometry import DetourField, Polygon

    observations = obs

    sc = make_scenario("paper-5")
    built = []
    real = observations.own_target_paths
    monkeypatch.setattr(observations, "own_target_paths", lambda p, t, r: built.append(len(t)) or real(p, t, r))
    own = observations.FleetOwnTargets(sc.polygon, sc.robot_radius, sc.arena, sc.targets)
    rng = np.random.default_rng(0)
    whole = DetourField(real(Polygon(torch.as_tensor(sc.polygon)), torch.as_tensor(sc.targets), sc.robot_radius),
                        sc.arena)
    for perm in ([0, 1, 2, 4, 3], [4, 3, 2, 1, 0], [0, 1, 2, 4], [3]):
        pos = rng.uniform(0.05, 0.95, (len(perm), 2))
        sigma = own(pos, sc.targets[perm])
        rows, cols = linear_sum_assignment(whole.lookup_np(pos)[:, perm] ** 2)
        assert sigma.tolist() == cols[np.argsort(rows)].tolist()
    assert built == [5]                          # the scenario's five, at construction only
    own(rng.uniform(0.05, 0.95, (2, 2)), np.vstack([sc.targets[:1], [[0.2, 0.9]]]))
    assert built == [5, 1]                       # a new target: its column alone


@pytest.mark.parametrize("n", [3, 4])
def test_fleet_own_targets_break_ties_as_training_does(n):
    """Robots sharing a spot tie; the stack must tell each the target training would have (scipy
    alone broke 160 of these 400 ties otherwise up to 4 robots, where training enumerates)."""
    from sim.batched_env import BatchedFormationEnv

    sc = make_scenario(f"paper-{n}")
    fleet = obs.FleetOwnTargets(sc.polygon, sc.robot_radius, sc.arena, sc.targets)
    env = BatchedFormationEnv(sc, 1, dtype=torch.float64, own_target=True)
    rng = np.random.default_rng(0)
    spots = rng.uniform(0.05, 0.95, (3, 2))
    for _ in range(200):
        pos = spots[rng.integers(0, 3, n)]
        want = obs.own_assignment(env._own_paths(torch.from_numpy(pos)[None]))[0].numpy()
        assert fleet(pos, sc.targets).tolist() == want.tolist()
