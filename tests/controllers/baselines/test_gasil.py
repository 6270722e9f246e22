"""GASIL-MADDPG (controllers/baselines/gasil.py): the top-K buffer, the discriminator, the shaped reward."""

from __future__ import annotations

import json

import torch

from controllers.baselines import MADDPGConfig, train_maddpg
from controllers.baselines.gasil import (
    BONUS_CAP,
    Discriminator,
    GoodEpisodes,
    discriminator_step,
    imitation_bonus,
)


def _episodes(returns, steps=4, robots=2, dim=3):
    e = len(returns)
    obs = torch.arange(e, dtype=torch.float32).view(e, 1, 1, 1).expand(e, steps, robots, dim).clone()
    return obs, torch.zeros(e, steps, robots, 2), torch.tensor(returns, dtype=torch.float32)


def test_the_good_buffer_keeps_the_k_best_episodes_by_return():
    good = GoodEpisodes(3)
    good.add(*_episodes([1.0, 5.0, -2.0]))
    assert sorted(good.returns.tolist()) == [-2.0, 1.0, 5.0]
    obs, action, returns = _episodes([3.0, -9.0, 7.0, 0.0])
    obs += 10                                   # tell the second batch's episodes apart
    good.add(obs, action, returns)
    assert good.returns.tolist() == [7.0, 5.0, 3.0]
    assert good.obs[:, 0, 0, 0].tolist() == [12.0, 1.0, 10.0]   # each episode keeps its own steps
    sampled, _ = good.sample(50, torch.Generator().manual_seed(0))
    assert set(sampled[:, 0].tolist()) <= {12.0, 1.0, 10.0}


def test_the_discriminator_learns_to_tell_good_pairs_and_the_bonus_follows():
    """Good pairs act along +x, the policy's along -x: after training, the bonus -log D is large
    on good-looking pairs and near 0 on the policy's, capped at BONUS_CAP."""
    torch.manual_seed(0)
    disc = Discriminator(3, hidden=16)
    opt = torch.optim.Adam(disc.parameters(), lr=1e-2)
    obs = torch.randn(256, 3)
    good = (obs, torch.tensor([[1.0, 0.0]]).expand(256, 2))
    policy = (obs, torch.tensor([[-1.0, 0.0]]).expand(256, 2))
    first = discriminator_step(disc, opt, policy, good)
    for _ in range(200):
        last = discriminator_step(disc, opt, policy, good)
    assert last < 0.1 * first
    assert imitation_bonus(disc, *good).mean() > 3.0
    assert imitation_bonus(disc, *policy).mean() < 0.1
    assert imitation_bonus(disc, *good).max() <= BONUS_CAP


def test_a_gasil_run_fills_its_good_buffer_shapes_rewards_and_resumes(tmp_path):
    small = dict(num_envs=8, steps_per_collection=16, buffer_size=4096, batch_size=128, eval_interval=16,
                 eval_episodes=8, good_episodes=4, self_imitation=True)
    train_maddpg(MADDPGConfig(total_episodes=16, **small), tmp_path)
    assert json.loads((tmp_path / "config.json").read_text())["algo"] == "gasil-maddpg"
    rows = [json.loads(line) for line in (tmp_path / "train.jsonl").read_text().splitlines()]
    assert rows[-1]["good_episodes"] == 4
    shaped = [r for r in rows if r["imitation_bonus"] is not None]
    assert shaped and all(r["imitation_bonus"] > 0 for r in shaped)
    again = train_maddpg(MADDPGConfig(total_episodes=32, **small), tmp_path, resume=True)
    assert again.episodes == 32
