import json

import pytest
import torch
from torch import nn

from controllers.mappo import ConvergenceTracker, converged_episode, evaluate, evaluation_due
from sim.batched_env import BatchedFormationEnv
from sim.metrics import CollisionEvents, episode_outcome
from sim.reward import formation_reward
from sim.scenario import make_scenario


class StandStill(nn.Module):
    """Commands zero acceleration: every robot stays on its (jittered) start."""

    obs_kind = "tokens"

    def forward(self, obs, mask=None):
        return torch.zeros(obs.shape[0], obs.shape[1], 2)


def test_converged_episode_needs_two_evaluations_in_a_row():
    assert converged_episode([0, 50, 100, 150], [0.5, 0.95, 0.85, 0.95]) is None
    assert converged_episode([0, 50, 100, 150, 200], [0.5, 0.95, 0.85, 0.92, 0.9]) == 150
    assert converged_episode([0, 48, 96], [0.9, 0.9, 0.1]) == 0
    assert converged_episode([], []) is None
    tracker = ConvergenceTracker(0.9)
    assert tracker.add(48, 0.91) is None
    assert tracker.add(96, 0.93) == 48
    assert ConvergenceTracker.from_state_dict(tracker.state_dict()).converged_episode == 48


def test_evaluation_schedule_never_leaves_more_than_the_interval():
    # episodes finish 16 at a time: evaluate at 48 (64 would be 64 > 50 after the last one)
    assert not evaluation_due(32, 0, 50, 16)
    assert evaluation_due(48, 0, 50, 16)
    assert evaluation_due(50, 0, 50, 50)
    assert evaluation_due(64, 0, 50, 64)                 # batches larger than the interval
    for batch in (1, 7, 16, 25, 32, 50, 64):
        last, episodes, gaps = 0, 0, []
        while episodes < 1000:
            episodes += batch
            if evaluation_due(episodes, last, 50, batch):
                gaps.append(episodes - last)
                last = episodes
        assert max(gaps) <= max(50, batch)


def test_evaluate_a_policy_that_stands_still_by_hand():
    sc = make_scenario("paper-3")
    result = evaluate(StandStill(), sc, episodes=10, seed=3)
    env = BatchedFormationEnv(sc, 10, seed=3)
    env.reset()
    start = env.pos.clone()
    outcome = episode_outcome(start, env.targets, torch.zeros(10, dtype=torch.bool), sc.target_tolerance)
    no_contact = torch.zeros(10, 3, dtype=torch.bool)
    per_step = formation_reward(start, env.targets, CollisionEvents(no_contact, no_contact, no_contact),
                                sc.target_tolerance, detour=env.rewarder.detour).mean(-1)  # (E,)
    assert result.episodes == 10 and result.num_robots == 3
    assert result.success_rate == 0.0 and result.collision_rate == 0.0
    assert result.final_distance == pytest.approx(outcome.final_distance.mean().item(), abs=1e-6)
    assert 0.3 < result.final_distance < 0.4                     # right-hand slots to left-hand slots
    assert result.episode_return == pytest.approx(128 * per_step.mean().item(), rel=1e-4)


def test_evaluate_is_deterministic_and_writes_json(tmp_path):
    sc = make_scenario("paper-3")
    torch.manual_seed(0)
    from controllers.policy import ActorConfig, build_actor

    actor = build_actor(ActorConfig(embed_dim=16, num_heads=2, hidden_sizes=(32,)), 3)
    with torch.no_grad():
        actor.head.mlp[-1].weight.mul_(300)            # make it move, so collisions can happen
    a = evaluate(actor, sc, episodes=12, seed=5, batch_size=5)
    b = evaluate(actor, sc, episodes=12, seed=5, batch_size=5)
    assert a == b
    assert a.final_distance != pytest.approx(evaluate(StandStill(), sc, episodes=12, seed=5).final_distance)
    a.save_json(tmp_path / "eval.json")
    assert json.loads((tmp_path / "eval.json").read_text())["episodes"] == 12
    with pytest.raises(ValueError, match="episodes"):
        evaluate(actor, sc, episodes=0)


class CountsMarks(StandStill):
    """Stands still and counts, per robot and step, the target tokens that carry a mark."""

    def __init__(self, own_target: bool):
        super().__init__()
        self.own_target, self.marks = own_target, []

    def forward(self, obs, mask=None):
        n = obs.shape[1]
        self.marks.append((obs[:, :, 1:n + 1, 2:4].abs().sum(-1) > 0).sum(-1))
        return super().forward(obs, mask)


def test_evaluation_gives_an_own_target_actor_marked_tokens():
    """Every robot of an actor that reads own-target marks sees exactly one marked target at
    every step of evaluation; an actor that does not read them sees none."""
    scenario = make_scenario("paper-3")
    for own in (True, False):
        actor = CountsMarks(own)
        evaluate(actor, scenario, episodes=4)
        marks = torch.stack(actor.marks)
        assert marks.shape == (scenario.dynamics.episode_steps, 4, 3)
        assert bool((marks == int(own)).all())
