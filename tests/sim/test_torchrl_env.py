"""sim.torchrl_env: TorchRL's own spec check, and the same world and reward as the trainer's."""

from __future__ import annotations

import pytest
import torch

pytest.importorskip("torchrl")   # the dev extra installs it (make test)

from torchrl.envs.utils import check_env_specs  # noqa: E402

from controllers.mappo.config import TRAINING_REWARD  # noqa: E402
from sim.batched_env import BatchedFormationEnv  # noqa: E402
from sim.reward import RewardWeights  # noqa: E402
from sim.scenario import Dynamics, transport_scenario  # noqa: E402
from sim.torchrl_env import FormationTorchRLEnv  # noqa: E402

SHORT = transport_scenario(3, dynamics=Dynamics(episode_steps=20))


def test_passes_torchrls_check_env_specs():
    check_env_specs(FormationTorchRLEnv(SHORT, num_envs=4, seed=0))


def test_a_rollout_is_the_batched_world_step_for_step_and_resets_at_the_time_limit():
    """4 environments, 25 steps of seeded random accelerations: the rewards are the batched
    world's (the trainer's weights, same seed, same actions), every environment is done at step
    20 exactly, with its outcome, and starts afresh at its start slots after TorchRL's reset."""
    env = FormationTorchRLEnv(SHORT, num_envs=4, seed=7)
    ref = BatchedFormationEnv(SHORT, 4, seed=7, reward_weights=RewardWeights(**TRAINING_REWARD))
    ref.reset()
    g = torch.Generator().manual_seed(0)
    actions = [torch.rand(4, 3, 2, generator=g) * 2 - 1 for _ in range(25)]
    calls = iter(actions)
    td = env.rollout(25, policy=lambda td: td.set(("agents", "action"), next(calls)), break_when_any_done=False)
    done = td["next", "done"].squeeze(-1)                                      # (4, 25)
    assert done.nonzero()[:, 1].unique().tolist() == [19] and done[:, 19].all()
    assert not td["next", "terminated"].any()
    for k in range(20):
        out = ref.step(actions[k])
        torch.testing.assert_close(td["next", "agents", "reward"][:, k, :, 0], out.reward, atol=1e-6, rtol=0)
    final = td["next", "agents", "final_distance"][:, 19, 0, 0]
    torch.testing.assert_close(final, out.finished.final_distance.float(), atol=1e-6, rtol=0)
    assert td["next", "agents", "success"][:, 19].tolist() == out.finished.success.view(4, 1, 1).expand(4, 3, 1).tolist()
    after = td["agents", "observation"][:, 20, :, :2]              # the flat layout starts with p
    starts = torch.as_tensor(SHORT.starts, dtype=torch.float32)
    assert (after - starts).abs().max() <= SHORT.start_jitter + 1e-6
