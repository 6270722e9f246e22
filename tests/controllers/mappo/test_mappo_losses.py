import math

import pytest
import torch

from controllers.mappo.losses import (
    ValueNormalizer,
    clipped_surrogate_loss,
    compute_gae,
    explained_variance,
    value_loss,
)


def _col(values):                  # (S,) -> (S, E=1, N=1)
    return torch.tensor(values, dtype=torch.float64).view(-1, 1, 1)


def test_gae_by_hand_with_an_episode_end():
    # gamma = 0.9, lambda = 0.5, three steps, the episode ends with step 1 (terminal).
    r, v = _col([1.0, 2.0, 3.0]), _col([0.5, 1.0, 1.5])
    dones = torch.tensor([[False], [True], [False]])
    next_v = torch.tensor([[2.0]], dtype=torch.float64)
    adv, ret = compute_gae(r, v, dones, next_v, gamma=0.9, gae_lambda=0.5)
    # t=2: delta = 3 + 0.9*2.0 - 1.5 = 3.3                          A2 = 3.3
    # t=1: done, delta = 2 + 0 - 1.0 = 1.0                          A1 = 1.0 (chain cut)
    # t=0: delta = 1 + 0.9*1.0 - 0.5 = 1.4 ; A0 = 1.4 + 0.9*0.5*1.0 = 1.85
    assert adv.flatten().tolist() == pytest.approx([1.85, 1.0, 3.3])
    assert ret.flatten().tolist() == pytest.approx([2.35, 2.0, 4.8])


def test_gae_time_limit_bootstraps_from_the_given_value():
    r, v = _col([1.0, 2.0, 3.0]), _col([0.5, 1.0, 1.5])
    dones = torch.tensor([[False], [True], [False]])
    next_v = torch.tensor([[2.0]], dtype=torch.float64)
    adv, _ = compute_gae(r, v, dones, next_v, gamma=0.9, gae_lambda=0.5, truncation_values=_col([0.0, 4.0, 0.0]))
    # t=2: A2 = 3.3 as before
    # t=1: truncated, delta = 2 + 0.9*4.0 - 1.0 = 4.6 ; the chain is still cut: A1 = 4.6
    # t=0: delta = 1 + 0.9*1.0 - 0.5 = 1.4 ; A0 = 1.4 + 0.45*4.6 = 3.47
    assert adv.flatten().tolist() == pytest.approx([3.47, 4.6, 3.3])


def test_gae_with_lambda_one_is_the_discounted_return_minus_value():
    g = torch.Generator().manual_seed(0)
    r = torch.randn(6, 2, 3, generator=g, dtype=torch.float64)
    v = torch.randn(6, 2, 3, generator=g, dtype=torch.float64)
    nv = torch.randn(2, 3, generator=g, dtype=torch.float64)
    adv, ret = compute_gae(r, v, torch.zeros(6, 2, dtype=torch.bool), nv, gamma=0.8, gae_lambda=1.0)
    expected = nv.clone()
    for t in reversed(range(6)):
        expected = r[t] + 0.8 * expected
        assert torch.allclose(ret[t], expected)


def test_gae_rejects_wrong_shapes():
    with pytest.raises(ValueError, match="dones must be"):
        compute_gae(torch.zeros(3, 2, 1), torch.zeros(3, 2, 1), torch.zeros(3, 1, dtype=torch.bool),
                    torch.zeros(2, 1), 0.9, 0.9)


def test_clipped_surrogate_by_hand():
    # ratios exp(log 1.5) = 1.5 and exp(log 0.5) = 0.5, clip 0.2
    new = torch.log(torch.tensor([1.5, 1.5, 0.5, 0.5]))
    old = torch.zeros(4)
    adv = torch.tensor([2.0, -2.0, 2.0, -2.0])
    # a=+2, r=1.5: min(3.0, 1.2*2 = 2.4)            = 2.4
    # a=-2, r=1.5: min(-3.0, 1.2*-2 = -2.4)         = -3.0
    # a=+2, r=0.5: min(1.0, 0.8*2 = 1.6)            = 1.0
    # a=-2, r=0.5: min(-1.0, 0.8*-2 = -1.6)         = -1.6
    # loss = -mean(2.4, -3.0, 1.0, -1.6) = -(-1.2 / 4) = 0.3
    assert clipped_surrogate_loss(new, old, adv, 0.2).item() == pytest.approx(0.3)


def test_clipped_surrogate_gradient_vanishes_outside_the_clip():
    new = torch.log(torch.tensor([1.5])).requires_grad_()
    clipped_surrogate_loss(new, torch.zeros(1), torch.tensor([2.0]), 0.2).backward()
    assert new.grad.item() == 0.0                   # r = 1.5 > 1.2 with A > 0: no push further
    inside = torch.log(torch.tensor([1.1])).requires_grad_()
    clipped_surrogate_loss(inside, torch.zeros(1), torch.tensor([2.0]), 0.2).backward()
    assert inside.grad.item() == pytest.approx(-2.0 * 1.1)   # d(-r A)/d log r = -r A


def test_value_loss_plain_and_clipped_by_hand():
    v, old, target = torch.tensor([1.0, 3.0]), torch.tensor([0.5, 0.5]), torch.tensor([2.0, 0.0])
    # plain: 0.5 * mean(1^2, 3^2) = 2.5
    assert value_loss(v, old, target, None).item() == pytest.approx(2.5)
    # clip 0.2: V_clip = [0.7, 0.7]; max((1-2)^2, (0.7-2)^2) = 1.69 ; max(9, 0.49) = 9
    # 0.5 * mean(1.69, 9) = 0.5 * 5.345 = 2.6725
    assert value_loss(v, old, target, 0.2).item() == pytest.approx(2.6725)


def test_value_normalizer_tracks_mean_and_variance_of_all_batches():
    g = torch.Generator().manual_seed(1)
    batches = [torch.randn(50, generator=g, dtype=torch.float64) * 3 + 7 for _ in range(4)]
    vn = ValueNormalizer()
    for b in batches:
        vn.update(b)
    every = torch.cat(batches)
    assert vn.mean.item() == pytest.approx(every.mean().item())
    assert vn.var.item() == pytest.approx(every.var(unbiased=False).item())
    x = torch.tensor([1.0, 10.0])
    assert torch.allclose(vn.denormalize(vn.normalize(x)), x, atol=1e-6)
    assert vn.normalize(torch.tensor([every.mean().item()])).abs().item() < 1e-6
    off = ValueNormalizer(enabled=False)
    off.update(every)
    assert torch.equal(off.normalize(x), x)


def test_explained_variance():
    t = torch.tensor([1.0, 2.0, 3.0, 4.0])
    assert explained_variance(t, t) == pytest.approx(1.0)
    assert explained_variance(torch.full((4,), 2.5), t) == pytest.approx(0.0)
    assert math.isnan(explained_variance(t, torch.ones(4)))
