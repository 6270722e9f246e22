"""The off-policy loop of the baselines (controllers/baselines/offpolicy.py): exploration schedules
on the run's episodes, the replay buffer's write cursor across a resume, evaluations on the
training reward, a used run folder refused without resume."""

from __future__ import annotations

import json

import pytest
import torch

from controllers.baselines import DDQConfig, MADDPGConfig, train_ddq, train_maddpg
from controllers.baselines.maddpg import MADDPGAgent
from controllers.baselines.offpolicy import OffPolicyTrainer, RunDirError
from controllers.mappo import MAPPOConfig, evaluate
from sim.reward import RewardWeights
from sim.scenario import make_scenario
from sim.torchrl_env import GROUP
from stack.cli import main as cli

# 4 envs x 16 steps: a collection is 1/8 of an episode (episode_steps 128), so 4 episodes end
# together every 8 collections.
FRACTION = dict(scenario="paper-3", total_episodes=8, num_envs=4, steps_per_collection=16, buffer_size=4096,
                batch_size=64, samples_per_update=64, eval_interval=100, eval_episodes=2,
                stop_at_convergence=False)
SMALL = dict(scenario="paper-3", num_envs=8, steps_per_collection=16, batch_size=128, eval_interval=8,
             eval_episodes=2, stop_at_convergence=False)


def _same(a, b) -> bool:
    """Two replay storages hold the same transitions in the same slots (leaf by leaf)."""
    keys = sorted(a.keys(True, True), key=str)
    return keys == sorted(b.keys(True, True), key=str) and all(torch.equal(a.get(k), b.get(k)) for k in keys)


def _rows(path) -> list[dict]:
    return [json.loads(line) for line in path.read_text().splitlines()]


@pytest.mark.parametrize("algo", ["ddq", "maddpg"])
def test_exploration_anneals_over_the_runs_finished_episodes(tmp_path, algo):
    """Annealed over 8 episodes from 1 to 0 (epsilon) or 0.3 a_max to 0 (noise): after every
    collection the value is the schedule's at the episodes finished so far. Counting one episode
    per collection (the defect) reached the end after 4 episodes, at collection 8."""
    if algo == "ddq":
        train_ddq(DDQConfig(**FRACTION, epsilon_start=1.0, epsilon_end=0.0, epsilon_anneal_episodes=8), tmp_path)
        key, start = "epsilon", 1.0
    else:
        train_maddpg(MADDPGConfig(**FRACTION, noise_start=0.3, noise_end=0.0, noise_anneal_episodes=8), tmp_path)
        key, start = "noise_sigma", 0.3 * make_scenario("paper-3").dynamics.accel_limit
    rows = _rows(tmp_path / "train.jsonl")
    assert [r["episodes"] for r in rows] == [0] * 7 + [4] * 8 + [8]      # collections shorter than an episode
    assert [r[key] for r in rows] == pytest.approx([start * (1 - r["episodes"] / 8) for r in rows], abs=1e-6)


def test_a_resumed_replay_buffer_replaces_its_oldest_transitions_first(tmp_path):
    """8 collections of 128 transitions into a 384-slot buffer: it wrapped, its cursor at
    1024 % 384 = 256, slots 256..383 hold the oldest. Resumed, the next 128 transitions go
    there, not to slots 0..127 (the newest); a replay.pt from before the cursor was saved still
    loads, with a warning once it is full."""
    cfg = MADDPGConfig(**SMALL, total_episodes=8, buffer_size=384)
    first = OffPolicyTrainer(cfg, MADDPGAgent, tmp_path)
    first.run()
    assert first.buffer.writer.state_dict()["_cursor"] == 256
    stored = first.buffer.storage[:384].clone()

    resumed = OffPolicyTrainer(MADDPGConfig(**SMALL, total_episodes=16, buffer_size=384), MADDPGAgent, tmp_path,
                               resume=True)
    assert resumed.buffer.writer.state_dict() == first.buffer.writer.state_dict()
    assert _same(resumed.buffer.storage[:384], stored)
    marker = stored[:128].clone().apply(lambda x: torch.full_like(x, -7) if x.is_floating_point() else x)
    resumed.buffer.extend(marker)
    obs = resumed.buffer.storage[:384].get((GROUP, "observation"))
    assert (obs == -7).all(-1).all(-1).nonzero().squeeze(-1).tolist() == list(range(256, 384))
    assert (obs[:256] == stored[:256].get((GROUP, "observation"))).all()

    replay = torch.load(tmp_path / "replay.pt", weights_only=True)
    del replay["writer"]
    torch.save(replay, tmp_path / "replay.pt")
    with pytest.warns(UserWarning, match="age order is unknown"):
        old = OffPolicyTrainer(MADDPGConfig(**SMALL, total_episodes=16, buffer_size=384), MADDPGAgent, tmp_path,
                               resume=True)
    assert len(old.buffer) == 384 and _same(old.buffer.storage[:384], stored)


def test_evaluations_report_the_return_of_the_reward_it_trains_on(tmp_path):
    """eval.jsonl's episode_return is that of the training reward, the one SDPA-MAPPO's
    evaluations report (MAPPOConfig's reward weights), not RewardWeights()'s defaults."""
    cfg = MADDPGConfig(**SMALL, total_episodes=8, buffer_size=4096)
    trainer = OffPolicyTrainer(cfg, MADDPGAgent, tmp_path)
    trainer.run()
    row = _rows(tmp_path / "eval.jsonl")[-1]
    again = dict(episodes=cfg.eval_episodes, seed=row["eval_seed"])
    mappo_reward = MAPPOConfig().build_reward_weights()
    trained_on = evaluate(trainer.agent.actor, trainer.scenario, reward_weights=mappo_reward, **again)
    defaults = evaluate(trainer.agent.actor, trainer.scenario, reward_weights=RewardWeights(), **again)
    assert trained_on.episode_return != pytest.approx(defaults.episode_return)   # the two rewards differ here
    assert row["episode_return"] == pytest.approx(trained_on.episode_return)
    assert row["success_rate"] == pytest.approx(trained_on.success_rate)


def test_a_folder_holding_a_run_is_refused_without_resume(tmp_path, capsys):
    """As MAPPO's trainer: a second run into a used folder stops with "already holds a run"
    (exit 2 from the CLI) and leaves the run's logs and checkpoint as they were."""
    out = tmp_path / "run"
    train_maddpg(MADDPGConfig(**SMALL, total_episodes=8, buffer_size=4096), out)
    kept = {name: (out / name).read_bytes() for name in ("train.jsonl", "eval.jsonl", "checkpoint.pt",
                                                          "replay.pt", "config.json")}
    with pytest.raises(RunDirError, match="already holds a run"):
        train_maddpg(MADDPGConfig(**SMALL, total_episodes=16, buffer_size=4096), out)
    config = tmp_path / "maddpg.json"
    config.write_text(json.dumps({"algo": "maddpg", **SMALL, "buffer_size": 4096}))
    capsys.readouterr()
    assert cli(["train", "--config", str(config), "--episodes", "8", "--out", str(out)]) == 2
    assert "already holds a run" in capsys.readouterr().err
    assert {name: (out / name).read_bytes() for name in kept} == kept
