import math

import pytest
import torch

from sim.batched_env import BatchedFormationEnv
from sim.scenario import Dynamics, make_scenario, transport_scenario

SC = make_scenario("paper-3")


def _env(sc=SC, e=1, **kw):
    env = BatchedFormationEnv(sc, e, seed=0, dtype=torch.float64, **kw)
    env.reset()
    return env


def _place(env, pos, vel=None):
    pos = torch.as_tensor(pos, dtype=torch.float64).expand(env.num_envs, -1, -1).clone()
    env.set_state(pos, torch.zeros_like(pos) if vel is None else torch.as_tensor(vel).expand_as(pos).clone())


OPEN = [[0.2, 0.15], [0.5, 0.15], [0.8, 0.15]]   # clear of each other, the box and the walls


def test_one_step_by_hand():
    env = _env()
    _place(env, OPEN)
    env.step(torch.tensor([[[1.0, 0.0], [0.0, 0.0], [0.0, 0.0]]]))
    # v = 0.05 * 1 = 0.05 ; p = 0.2 + 0.05 * 0.05 = 0.2025
    assert env.vel[0, 0].tolist() == pytest.approx([0.05, 0.0])
    assert env.pos[0, 0].tolist() == pytest.approx([0.2025, 0.15])
    env.step(torch.zeros(1, 3, 2))
    # damping only: v = 0.05 - 0.05 * 0.5 * 0.05 = 0.04875
    assert env.vel[0, 0, 0].item() == pytest.approx(0.04875)


def test_acceleration_is_clipped_by_norm_keeping_direction():
    env = _env()
    _place(env, OPEN)
    env.step(torch.tensor([[[3.0, 4.0], [0.0, 0.0], [0.0, 0.0]]]))
    # |a| = 5 > 1 -> a = (0.6, 0.8); v = dt * a
    assert env.vel[0, 0].tolist() == pytest.approx([0.03, 0.04])


@pytest.mark.parametrize("accel,damping,expected", [
    (1.0, 0.5, 0.4),     # a / c = 2 m/s > speed limit 0.4: the limit holds
    (0.1, 0.5, 0.2),     # a / c = 0.2 m/s < 0.4: damping sets the terminal speed
])
def test_terminal_speed(accel, damping, expected):
    dyn = Dynamics(damping=damping, episode_steps=10_000)
    sc = transport_scenario(1, dynamics=dyn)
    env = _env(sc)
    _place(env, [[0.05, 0.15]])        # along y = 0.15, clear of the (solid) object
    speeds = []
    for _ in range(300):
        env.step(torch.tensor([[[accel, 0.0]]], dtype=torch.float64))
        if env.pos[0, 0, 0] > 0.9:       # restart before the wall, keep the velocity
            env.set_state(torch.tensor([[[0.05, 0.15]]], dtype=torch.float64), env.vel.clone())
        speeds.append(env.vel[0, 0].norm().item())
    assert max(speeds) <= expected + 1e-12
    assert speeds[-1] == pytest.approx(expected, rel=1e-3)


def test_wall_stops_the_robot_and_counts_one_collision():
    env = _env()
    _place(env, [[0.06, 0.8], [0.5, 0.15], [0.8, 0.15]])
    for _ in range(20):
        r = env.step(torch.tensor([[[-1.0, 0.0], [0.0, 0.0], [0.0, 0.0]]]))
    assert env.pos[0, 0, 0].item() == pytest.approx(0.04)
    assert env.vel[0, 0, 0].item() == 0.0
    assert env.counts[0].tolist() == [0, 0, 1]           # one wall contact onset, nothing else
    assert env.collided[0] and r.reward[0, 0] < r.reward[0, 1]


def test_episode_end_reports_success_and_resets():
    env = _env(e=2)
    tg = env.targets[0]
    _place(env, tg)
    env.t[:] = SC.dynamics.episode_steps - 1
    env._t_max = int(env.t.max())
    r = env.step(torch.zeros(2, 3, 2))
    assert r.done.tolist() == [True, True]
    assert r.finished.env_ids.tolist() == [0, 1]
    assert r.finished.success.tolist() == [True, True]
    assert r.finished.final_distance.tolist() == pytest.approx([0.0, 0.0])
    # reset happened: back on the (jittered) start slots, step counter 0
    assert env.t.tolist() == [0, 0]
    assert (env.pos - torch.as_tensor(SC.starts)).abs().max() <= SC.start_jitter + 1e-12


def test_the_final_observation_is_the_state_the_episode_ended_in():
    """A time-limit bootstrap needs V(o_{t+1}) of the ended episode: the step reports those
    tokens before the reset (a robot sitting on its target: its own target token is zero)."""
    env = _env(e=2)
    _place(env, env.targets[0])
    env.t[:] = SC.dynamics.episode_steps - 2
    env._t_max = int(env.t.max())
    early = env.step(torch.zeros(2, 3, 2))
    assert early.final_obs is None and early.final_mask is None      # nobody finished
    ended_at = env.pos.clone()
    last = env.step(torch.zeros(2, 3, 2))
    assert last.done.tolist() == [True, True]
    from sim.observations import tokens

    want, want_mask = tokens(ended_at, torch.zeros_like(ended_at), env.targets, env.polygon, env.arena)
    torch.testing.assert_close(last.final_obs, want.to(last.final_obs.dtype))
    assert torch.equal(last.final_mask, want_mask)
    assert float(last.final_obs[:, :, 1:4, :2].abs().min()) == 0.0   # on a target at the end
    assert float((last.obs - last.final_obs).abs().max()) > 0.05      # obs: the new episode


def test_collision_during_the_episode_fails_it():
    env = _env()
    tg = env.targets[0]
    _place(env, tg)
    env.collided[0] = True
    env.t[:] = SC.dynamics.episode_steps - 1
    env._t_max = int(env.t.max())
    r = env.step(torch.zeros(1, 3, 2))
    assert r.finished.success.tolist() == [False]


def test_full_episode_length_and_auto_reset():
    env = _env(e=4)
    ends = 0
    for step in range(2 * SC.dynamics.episode_steps):
        r = env.step(torch.zeros(4, 3, 2))
        if r.done.any():
            ends += 1
            assert len(r.finished) == 4 and r.finished.length.tolist() == [128] * 4
            assert step + 1 in (128, 256)
    assert ends == 2


def test_seed_repeats_and_different_seeds_differ():
    def run(seed):
        env = BatchedFormationEnv(SC, 8, seed=seed)
        env.reset()
        g = torch.Generator().manual_seed(123)
        for _ in range(200):
            r = env.step(torch.rand(8, 3, 2, generator=g) * 2 - 1)
        return env.pos.clone(), r.obs.clone()

    a, b, c = run(1), run(1), run(2)
    assert torch.equal(a[0], b[0]) and torch.equal(a[1], b[1])
    assert not torch.equal(a[0], c[0])


def test_bad_actions_raise_clear_errors():
    env = _env()
    with pytest.raises(ValueError, match=r"actions must have shape \(num_envs, num_robots, 2\) = \(1, 3, 2\)"):
        env.step(torch.zeros(1, 4, 2))
    with pytest.raises(ValueError, match="NaN or inf"):
        env.step(torch.full((1, 3, 2), float("nan")))


def test_flat_observations():
    env = BatchedFormationEnv(SC, 2, seed=0, obs="flat")
    obs, mask = env.reset()
    assert obs.shape == (2, 3, 14) and mask is None
    r = env.step(torch.zeros(2, 3, 2))
    assert r.obs.shape == (2, 3, 14)


@pytest.mark.parametrize("n", [1, 2, 8, 16])
def test_runs_for_many_robot_counts(n):
    env = BatchedFormationEnv(transport_scenario(n), 3, seed=0)
    obs, _ = env.reset()
    assert obs.shape == (3, n, 2 * n + 1, 4)
    for _ in range(130):
        r = env.step(torch.rand(3, n, 2) * 2 - 1)
        assert torch.isfinite(r.obs).all() and torch.isfinite(r.reward).all()


def test_tokens_after_a_step_equal_a_fresh_observation():
    env = _env(e=3)
    env.step(torch.rand(3, 3, 2, dtype=torch.float64))
    r = env.step(torch.rand(3, 3, 2, dtype=torch.float64))
    env._frame = None
    fresh, _ = env.observe()
    assert torch.equal(r.obs, fresh)


def test_object_is_solid_and_a_robot_touching_it_stops():
    # box x in [0.4, 0.6]; robot 0 moves left into the right face while drifting up at 0.1 m/s
    env = _env()
    _place(env, [[0.65, 0.5], [0.2, 0.15], [0.8, 0.15]], [[-0.3, 0.1], [0.0, 0.0], [0.0, 0.0]])
    for _ in range(10):
        env.step(torch.tensor([[[-1.0, 0.0], [0.0, 0.0], [0.0, 0.0]]]))
    assert env.pos[0, 0, 0].item() == pytest.approx(0.64)          # centre at r = 0.04 from the face
    assert env.vel[0, 0].tolist() == [0.0, 0.0]                    # stopped, no sliding along it
    assert env.counts[0].tolist() == [0, 1, 0] and env.collided[0]


def test_object_pushes_back_along_the_corner_normal():
    # a robot heading diagonally into the box corner (0.6, 0.65) ends on the circle of radius r around it
    env = _env()
    c = (0.6, 0.65)
    start = (c[0] + 0.045 / math.sqrt(2), c[1] + 0.045 / math.sqrt(2))
    _place(env, [start, [0.2, 0.15], [0.8, 0.15]], [[-0.2, -0.2], [0.0, 0.0], [0.0, 0.0]])
    env.step(torch.zeros(1, 3, 2, dtype=torch.float64))
    d = math.hypot(env.pos[0, 0, 0].item() - c[0], env.pos[0, 0, 1].item() - c[1])
    assert d == pytest.approx(0.04)
    assert env.vel[0, 0].abs().max().item() == pytest.approx(0.0, abs=1e-12)   # head-on: stopped
    assert env.counts[0, 1].item() == 1


def test_sticky_assignment_switches_only_for_a_clear_gain():
    from sim.reward import RewardWeights

    env = BatchedFormationEnv(make_scenario("paper-3"), 1, seed=0,
                              reward_weights=RewardWeights(w_assigned=1.0, assignment_hysteresis=0.05))
    env.reset()
    far = 9.0

    def cost(a, b, c, d):   # robots 0, 1 choose between targets 0, 1; robot 2 keeps target 2
        return torch.tensor([[[a, b, far], [c, d, far], [far, far, 0.0]]])

    assert env.rewarder._sticky_assignment(cost(0.1, 0.2, 0.2, 0.1))[0].tolist() == [0, 1, 2]   # fresh: optimal
    # swapping saves 0.41 - 0.2 = 0.21 > 0.05: switch
    assert env.rewarder._sticky_assignment(cost(0.2, 0.1, 0.1, 0.21))[0].tolist() == [1, 0, 2]
    # the optimum flips back, but saves only 0.24 - 0.21 = 0.03 < 0.05: keep
    assert env.rewarder._sticky_assignment(cost(0.1, 0.12, 0.12, 0.11))[0].tolist() == [1, 0, 2]
    env.reset()                                                                      # a new episode
    assert env.rewarder._sticky_assignment(cost(0.1, 0.12, 0.12, 0.11))[0].tolist() == [0, 1, 2]


def test_sticky_assignment_changes_the_reward_of_a_flipping_optimum():
    from sim.reward import RewardWeights

    sc = make_scenario("paper-3")
    # step 1: robot 1 on the middle target (0.33, 0.5), robot 2 on the top one (0.33, 0.625);
    # step 2: robot 1 at y = 0.57, robot 2 at y = 0.555, so swapping targets is 0.03 m shorter in
    # total (0.055 + 0.055 against 0.07 + 0.07): the plain reward swaps, a 0.05 m hysteresis keeps
    first = torch.tensor([[[0.33, 0.375], [0.33, 0.5], [0.33, 0.625]]], dtype=torch.float64)
    second = torch.tensor([[[0.33, 0.375], [0.33, 0.57], [0.33, 0.555]]], dtype=torch.float64)
    out = {}
    for h in (0.0, 0.05):
        env = BatchedFormationEnv(sc, 1, seed=0, dtype=torch.float64,
                                  reward_weights=RewardWeights(w_dist=0.0, w_arrive=0.0, w_robot=0.0,
                                                               w_assigned=1.0, assignment_hysteresis=h))
        env.reset()
        for pos in (first, second):
            env.set_state(pos, torch.zeros_like(pos))
            reward = env.step(torch.zeros(1, 3, 2, dtype=torch.float64)).reward[0]
        out[h] = reward
    assert out[0.0].tolist() == pytest.approx([0.0, -0.055, -0.055], abs=1e-6)
    assert out[0.05].tolist() == pytest.approx([0.0, -0.07, -0.07], abs=1e-6)


def test_own_target_tokens_and_the_reward_name_the_same_target():
    """With ``own_target`` each robot's token of the target :func:`own_assignment` gives it is
    marked, and the reward's assigned term judges it by that target. The state is one where the
    reward's own choice differs (least *linear* detour sum, ``assignment_power`` 1): robots 0 and
    2 are told targets 0 and 1 (least squared detour sum) but would be charged for 2 and 0."""
    from sim.observations import mark_own_targets, own_assignment
    from sim.reward import RewardWeights

    weights = RewardWeights(w_dist=0.0, w_arrive=0.0, w_robot=0.0, w_object=0.0, w_wall=0.0,
                            w_assigned=1.0, assignment_power=1.0, detour_clearance=0.03)
    pos = [[0.67, 0.41], [0.17, 0.19], [0.61, 0.26]]
    rewards, tokens = {}, {}
    for own in (False, True):
        env = _env(reward_weights=weights, own_target=own)
        _place(env, pos)
        result = env.step(torch.zeros(1, 3, 2))
        rewards[own], tokens[own] = result.reward[0], result.obs
    detour = env.rewarder.detour(torch.tensor([pos], dtype=torch.float64))
    told = own_assignment(detour)
    assert told[0].tolist() == [0, 2, 1]
    assert torch.allclose(rewards[True], -detour[0, torch.arange(3), told[0]])
    assert not torch.allclose(rewards[False], rewards[True])          # the reward's own choice differs
    assert torch.equal(tokens[True], mark_own_targets(tokens[False], told))
    with pytest.raises(ValueError, match="needs obs='tokens'"):
        BatchedFormationEnv(SC, 1, obs="flat", own_target=True)


def test_own_target_paths_measure_the_contracts_detour_whatever_the_rewards():
    """The marks follow the detour round the object grown by r + OWN_TARGET_CLEARANCE, also in a
    world whose reward measures another (evaluation's default clearance)."""
    from sim.geometry import DetourDistance
    from sim.observations import OWN_TARGET_CLEARANCE
    from sim.reward import RewardWeights

    pos = torch.rand(1, 3, 2, generator=torch.Generator().manual_seed(0), dtype=torch.float64) * 0.8 + 0.1
    for clearance in (0.01, OWN_TARGET_CLEARANCE):
        env = _env(reward_weights=RewardWeights(detour_clearance=clearance), own_target=True)
        exact = DetourDistance(env.polygon, env.targets[0], SC.robot_radius + OWN_TARGET_CLEARANCE)(pos)
        assert (env._own_paths(pos) - exact).abs().max() <= 0.005 / 2 ** 0.5 + 1e-9
        assert (env._own_paths is env.rewarder.detour) == (clearance == OWN_TARGET_CLEARANCE)


def _step_disp(v: float) -> float:
    """How far one step with no command carries a robot moving at v [m/s] (damping 0.5)."""
    return SC.dynamics.dt * v * (1 - SC.dynamics.dt * SC.dynamics.damping)


def test_two_robots_passing_within_one_step_collide():
    # they pass 78 mm apart (< 2 r = 80 mm) in mid-step, 80.4 mm apart at both ends of it
    half = _step_disp(0.4) / 2
    env = _env()
    _place(env, [[0.2 - half, 0.3], [0.2 + half, 0.378], [0.8, 0.15]],
           [[0.4, 0.0], [-0.4, 0.0], [0.0, 0.0]])
    env.step(torch.zeros(1, 3, 2, dtype=torch.float64))
    ends = (env.pos[0, 0] - env.pos[0, 1]).norm().item()
    assert ends == pytest.approx(math.hypot(0.078, 2 * half)) and ends > 0.08
    assert env.counts[0].tolist() == [2, 0, 0] and env.collided[0]


def test_a_robot_cutting_round_a_corner_within_one_step_touches_the_object_and_stops():
    # tangent to a circle of 39 mm (< r = 40 mm) round the box corner (0.6, 0.65); both ends of
    # the step lie 40.2 mm from the corner, outside the box's faces
    c, u = torch.tensor([0.6, 0.65]), torch.tensor([1.0, -1.0]) / math.sqrt(2)
    mid = c + 0.039 * torch.tensor([1.0, 1.0]) / math.sqrt(2)
    start = mid - u * _step_disp(0.4) / 2
    env = _env()
    _place(env, [start.tolist(), [0.2, 0.15], [0.8, 0.15]], [(0.4 * u).tolist(), [0.0, 0.0], [0.0, 0.0]])
    env.step(torch.zeros(1, 3, 2, dtype=torch.float64))
    assert (env.pos[0, 0] - c.double()).norm().item() == pytest.approx(math.hypot(0.039, _step_disp(0.4) / 2))
    assert env.counts[0].tolist() == [0, 1, 0] and env.collided[0]
    assert env.vel[0, 0].tolist() == [0.0, 0.0]
