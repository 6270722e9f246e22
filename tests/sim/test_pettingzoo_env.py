import warnings

import numpy as np
import pytest
import torch
from pettingzoo.test import parallel_api_test, parallel_seed_test

from controllers.mappo.config import TRAINING_REWARD
from sim import observations
from sim.batched_env import BatchedFormationEnv
from sim.metrics import collision_events
from sim.pettingzoo_env import FormationParallelEnv
from sim.pymunk_world import ModelError
from sim.reward import RewardWeights, formation_reward
from sim.scenario import Dynamics, transport_scenario

SHORT = transport_scenario(3, dynamics=Dynamics(episode_steps=25))   # keeps the API runs short


def test_passes_the_pettingzoo_parallel_api_test_without_warnings():
    env = FormationParallelEnv(SHORT, ModelError(gain=0.8, position_noise_std=0.001))
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        parallel_api_test(env, num_cycles=40)      # more cycles than steps: truncation is reached
    pz = [w for w in caught if "pettingzoo" in w.filename]
    assert not pz, [str(w.message) for w in pz]


def test_passes_the_pettingzoo_seed_test():
    parallel_seed_test(lambda: FormationParallelEnv(SHORT, ModelError(disturbance_std=0.1,
                                                                       velocity_noise_std=0.01)),
                       num_cycles=30)


def test_spaces_and_observations_are_the_flattened_tokens_of_the_measured_state():
    env = FormationParallelEnv("paper-4", ModelError(position_noise_std=0.002))
    obs, infos = env.reset(seed=3)
    assert env.agents == ["robot_0", "robot_1", "robot_2", "robot_3"]
    assert env.observation_space("robot_2").shape == (9 * 4,)        # 2N + 1 = 9 tokens of 4
    assert env.action_space("robot_2").low.tolist() == [-1.0, -1.0]
    s = env.world.read_state()
    toks, _ = observations.tokens(torch.from_numpy(s.positions)[None], torch.from_numpy(s.velocities)[None],
                                  torch.from_numpy(s.targets)[None], torch.from_numpy(env.scenario.polygon),
                                  env.scenario.arena)
    for i, agent in enumerate(env.agents):
        assert obs[agent].dtype == np.float32 and env.observation_space(agent).contains(obs[agent])
        assert np.allclose(obs[agent], toks[0, i].reshape(-1).numpy(), atol=1e-6)
        # token 0 = [p - (W/2, H/2), v]: the measured (noisy) position, not the true one
        assert np.allclose(obs[agent][:2], s.positions[i] - 0.5, atol=1e-6)
        assert infos[agent] == {"collision_robot": False, "collision_object": False,
                                "collision_wall": False, "collided": False}
    assert not np.allclose(s.positions, env.world.true_state().positions, atol=1e-5)


def test_reward_equals_the_batched_worlds_on_shared_states_and_truncation_comes_at_episode_steps():
    """Both worlds from one state, one action sequence (straight at the targets across the object,
    then hard into it), the trainer's weights (detour distances, contact onsets, the 1 cm margin,
    the sticky assignment): while their states agree (to 1e-9 m: the 4 steps before the object)
    their rewards agree to 1e-6, and to 1e-3 while pressed on the object (states within 2 mm). The
    former PettingZoo reward (``formation_reward``, none of those terms) differs on every one."""
    weights = RewardWeights(**TRAINING_REWARD)
    env = FormationParallelEnv(SHORT, reward_weights=weights)
    env.reset(seed=0)
    batched = BatchedFormationEnv(SHORT, 1, reward_weights=weights, dtype=torch.float64)
    start = env.world.true_state()
    batched.set_state(torch.from_numpy(start.positions)[None], torch.from_numpy(start.velocities)[None])
    targets = torch.from_numpy(SHORT.targets)[None]
    shared = differs = hits = 0
    for t in range(1, 26):
        pos = env.world.true_state().positions
        toward = np.clip(3.0 * (SHORT.targets - pos), -1, 1) if t < 12 else np.tile([-1.0, 0.0], (3, 1))
        obs, rew, term, trunc, info = env.step({a: toward[i].astype(np.float32) for i, a in enumerate(env.agents)})
        step = batched.step(torch.from_numpy(toward.astype(np.float32)).double()[None])
        true = env.world.true_state().positions
        ours, gap = np.array([rew[a] for a in env.possible_agents]), np.abs(batched.pos[0].numpy() - true).max()
        if gap < 2e-3:      # against the object the worlds differ (pymunk's contact, the batched stop)
            np.testing.assert_allclose(ours, step.reward[0].numpy(), atol=1e-3)
        if gap < 1e-9:
            shared += 1
            np.testing.assert_allclose(ours, step.reward[0].numpy(), atol=1e-6)
            events = collision_events(torch.from_numpy(true)[None], torch.from_numpy(SHORT.polygon),
                                      SHORT.robot_radius, SHORT.arena)
            old = formation_reward(torch.from_numpy(true)[None], targets, events, SHORT.target_tolerance)[0]
            differs += not np.allclose(ours, old.numpy(), atol=1e-3)
        hits += sum(info[a]["collision_object"] for a in env.possible_agents)
        assert not any(term.values())
        assert all(trunc.values()) == (t == 25) and any(trunc.values()) == (t == 25)
    assert shared >= 4 and differs == shared                # the free approach is shared
    assert hits > 0 and info["robot_0"]["collided"]           # the push did reach the object
    assert info["robot_0"]["success"] is False and info["robot_0"]["final_distance"] > 0.05
    assert env.agents == []
    with pytest.raises(RuntimeError, match="reset"):
        env.step({a: np.zeros(2, dtype=np.float32) for a in env.possible_agents})


def test_bad_actions_raise_naming_the_agent():
    env = FormationParallelEnv(SHORT)
    env.reset(seed=0)
    ok = {a: np.zeros(2, dtype=np.float32) for a in env.agents}
    with pytest.raises(ValueError, match=r"missing \['robot_2'\]"):
        env.step({k: v for k, v in ok.items() if k != "robot_2"})
    with pytest.raises(ValueError, match=r"unknown \['robot_9'\]"):
        env.step(ok | {"robot_9": np.zeros(2)})
    with pytest.raises(ValueError, match=r"robot_1 must have shape \(2,\)"):
        env.step(ok | {"robot_1": np.zeros(3)})
    with pytest.raises(ValueError, match="NaN"):
        env.step(ok | {"robot_0": np.array([np.nan, 0.0])})
    with pytest.raises(ValueError, match="render_mode"):
        FormationParallelEnv(SHORT, render_mode="human")


def test_own_target_observations_and_rewards_equal_the_batched_worlds():
    """With ``own_target`` both worlds mark the same targets and reward by the same assignment on
    shared states (the free approach, before the object): observations to 1e-6, rewards to 1e-6.
    Without the mark the PettingZoo observation would differ from the batched world's."""
    weights = RewardWeights(**TRAINING_REWARD)
    env = FormationParallelEnv(SHORT, reward_weights=weights, own_target=True)
    plain = FormationParallelEnv(SHORT, reward_weights=weights)
    obs, _ = env.reset(seed=0)
    plain_obs, _ = plain.reset(seed=0)
    batched = BatchedFormationEnv(SHORT, 1, reward_weights=weights, dtype=torch.float64, own_target=True)
    start = env.world.true_state()
    batched.set_state(torch.from_numpy(start.positions)[None], torch.from_numpy(start.velocities)[None])
    want, _ = batched.observe()
    for i, agent in enumerate(env.possible_agents):
        assert np.allclose(obs[agent], want[0, i].reshape(-1).numpy(), atol=1e-6)
    assert not all(np.allclose(plain_obs[a], obs[a], atol=1e-6) for a in env.possible_agents)
    for _ in range(4):
        pos = env.world.true_state().positions
        toward = np.clip(3.0 * (SHORT.targets - pos), -1, 1)
        obs, rew, *_ = env.step({a: toward[i].astype(np.float32) for i, a in enumerate(env.agents)})
        step = batched.step(torch.from_numpy(toward.astype(np.float32)).double()[None])
        assert np.abs(batched.pos[0].numpy() - env.world.true_state().positions).max() < 1e-9
        np.testing.assert_allclose([rew[a] for a in env.possible_agents], step.reward[0].numpy(), atol=1e-6)
        for i, agent in enumerate(env.possible_agents):
            assert np.allclose(obs[agent], step.obs[0, i].reshape(-1).numpy(), atol=1e-6)
