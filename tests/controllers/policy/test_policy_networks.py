import io
import math

import pytest
import torch

from controllers.policy import (
    ActorConfig,
    CriticConfig,
    PolicyConfigError,
    SlotSDPAActor,
    build_actor,
    build_critic,
    count_parameters,
    gaussian_entropy,
    gaussian_log_prob,
    grow_slot_actor,
    mix_values,
)
from sim.observations import flat, tokens
from sim.scenario import make_scenario


def random_state(n: int, e: int = 3, seed: int = 0):
    """(E, N, 2) positions, velocities and the scenario's targets, plus polygon and arena."""
    sc = make_scenario(f"transport-{n}")
    g = torch.Generator().manual_seed(seed)
    pos = torch.rand(e, n, 2, generator=g) * 0.8 + 0.1
    vel = (torch.rand(e, n, 2, generator=g) - 0.5) * 0.6
    targets = torch.as_tensor(sc.targets, dtype=torch.float32).expand(e, n, 2).clone()
    return pos, vel, targets, torch.as_tensor(sc.polygon, dtype=torch.float32), sc.arena


def obs_of(pos, vel, targets, poly, arena):
    return tokens(pos, vel, targets, poly, arena)


@pytest.mark.parametrize("n", [2, 4, 7])
def test_typed_actor_and_critic_are_permutation_equivariant(n):
    torch.manual_seed(1)
    actor = build_actor(ActorConfig(variant="typed"), n)
    critic = build_critic(CriticConfig(value_mixing=0.7), n)
    pos, vel, targets, poly, arena = random_state(n)
    perm = torch.randperm(n, generator=torch.Generator().manual_seed(n))
    obs, mask = obs_of(pos, vel, targets, poly, arena)
    obs_p, mask_p = obs_of(pos[:, perm], vel[:, perm], targets, poly, arena)
    with torch.no_grad():
        assert torch.allclose(actor(obs_p, mask_p), actor(obs, mask)[:, perm], atol=1e-5)
        assert torch.allclose(critic(obs_p, mask_p), critic(obs, mask)[:, perm], atol=1e-5)
        # relabelling the targets changes nothing at all
        obs_t, mask_t = obs_of(pos, vel, targets[:, perm], poly, arena)
        assert torch.allclose(actor(obs_t, mask_t), actor(obs, mask), atol=1e-5)
        assert torch.allclose(critic(obs_t, mask_t), critic(obs, mask), atol=1e-5)


def test_slot_actor_is_not_permutation_invariant_over_targets():
    # the check above has teeth: per-slot embeddings do see the order of the targets
    torch.manual_seed(2)
    n = 4
    actor = build_actor(ActorConfig(variant="slot"), n)
    pos, vel, targets, poly, arena = random_state(n)
    perm = torch.tensor([2, 0, 3, 1])
    with torch.no_grad():
        a = actor(*obs_of(pos, vel, targets, poly, arena))
        b = actor(*obs_of(pos, vel, targets[:, perm], poly, arena))
    assert not torch.allclose(a, b, atol=1e-5)


@pytest.mark.parametrize("n", range(1, 17))
def test_every_variant_runs_for_one_to_sixteen_robots(n):
    torch.manual_seed(n)
    pos, vel, targets, poly, arena = random_state(n, e=2)
    obs, mask = obs_of(pos, vel, targets, poly, arena)
    typed = build_actor(ActorConfig(variant="typed"), 3)      # built for 3, runs any N
    for actor in (typed, build_actor(ActorConfig(variant="slot"), n)):
        with torch.no_grad():
            out = actor(obs, mask)
            weights = actor.attention(obs, mask)
        assert out.shape == (2, n, 2) and torch.isfinite(out).all()
        assert out.abs().max() < actor.accel_limit
        slots = 2 * n + 1 if actor is typed else 2 * n + 2
        assert weights.shape == (2, n, 4, slots)
        assert torch.allclose(weights.sum(-1), torch.ones(2, n, 4), atol=1e-5)
    values = build_critic(CriticConfig(), 3)(obs, mask)
    assert values.shape == (2, n) and torch.isfinite(values).all()
    flat_obs = flat(pos, vel, targets)
    mlp_actor = build_actor(ActorConfig(variant="mlp"), n)
    mlp_critic = build_critic(CriticConfig(variant="mlp"), n)
    assert mlp_actor(flat_obs).shape == (2, n, 2)
    assert mlp_critic(flat_obs).shape == (2, n)


def test_mask_hides_tokens_and_a_lone_self_token_gives_no_nan():
    torch.manual_seed(3)
    n = 4
    actor = build_actor(ActorConfig(variant="typed"), n)
    pos, vel, targets, poly, arena = random_state(n)
    obs, mask = obs_of(pos, vel, targets, poly, arena)
    mask = mask.clone()
    hidden = 2 * n - 1          # the last other-robot token
    mask[..., hidden] = False
    changed = obs.clone()
    changed[..., hidden, :] += 5.0
    with torch.no_grad():
        base = actor(obs, mask)
        assert torch.equal(actor(changed, mask), base)                  # masked: ignored
        assert not torch.allclose(actor(changed, torch.ones_like(mask)), actor(obs, torch.ones_like(mask)))
        only_self = torch.zeros_like(mask)                               # even the self bit cleared
        for a in (actor, build_actor(ActorConfig(variant="slot"), n)):
            assert torch.isfinite(a(obs, only_self)).all()
        assert torch.isfinite(build_critic(CriticConfig(), n)(obs, only_self)).all()


@pytest.mark.parametrize("bad", [float("nan"), float("inf")])
def test_a_masked_token_holding_nan_or_inf_never_reaches_the_actions(bad):
    """Attention gives a masked key weight 0, but 0 x NaN is NaN: without zeroing the masked
    tokens (layers.zero_masked) every action of every robot became NaN (checked)."""
    torch.manual_seed(4)
    n = 3
    pos, vel, targets, poly, arena = random_state(n)
    obs, mask = obs_of(pos, vel, targets, poly, arena)
    mask, poisoned = mask.clone(), obs.clone()
    mask[..., 3] = False                        # a target token nobody may read
    poisoned[..., 3, :] = bad
    with torch.no_grad():
        for net in (build_actor(ActorConfig(variant="typed"), n), build_actor(ActorConfig(variant="slot"), n),
                    build_critic(CriticConfig(), n)):
            out = net(poisoned, mask)
            assert torch.isfinite(out).all()
            assert torch.equal(out, net(obs, mask))                       # and it changes nothing
            scripted = torch.jit.script(net) if not isinstance(net, SlotSDPAActor) else None
            if scripted is not None:
                assert torch.equal(scripted(poisoned, mask), out)


def test_bad_observation_shapes_name_the_fix():
    actor = build_actor(ActorConfig(variant="typed"), 3)
    with pytest.raises(ValueError, match="2\\*num_robots\\+1"):
        actor(torch.zeros(2, 3, 6, 4))
    slot = build_actor(ActorConfig(variant="slot"), 3)
    with pytest.raises(ValueError, match="grow_slot_actor"):
        slot(torch.zeros(2, 4, 9, 4))
    with pytest.raises(ValueError, match="flat vectors"):
        build_actor(ActorConfig(variant="mlp"), 3)(torch.zeros(2, 3, 7, 4))


def test_grow_slot_actor_keeps_trained_weights_and_adds_fresh_slots():
    torch.manual_seed(4)
    small = build_actor(ActorConfig(variant="slot"), 3)
    assert isinstance(small, SlotSDPAActor)
    with torch.no_grad():
        for p in small.parameters():
            p.add_(0.1)                                           # "trained" weights
    big = grow_slot_actor(small, 5, seed=7)
    s, b = small.state_dict(), big.state_dict()
    assert b["embed_targets.weight"].shape == (5, 4, 64) and b["embed_robots.weight"].shape == (4, 4, 64)
    for name, value in s.items():
        if name.startswith(("embed_targets.", "embed_robots.")):
            k = value.shape[0]
            assert torch.equal(b[name][:k], value)
            assert not torch.allclose(b[name][k:k + 1], value[:1])     # new slots are fresh
            bound = 1 / math.sqrt(4)
            assert b[name][k:].abs().max() <= bound                   # nn.Linear-style init
        else:
            assert torch.equal(b[name], value)
    same = grow_slot_actor(small, 3)
    pos, vel, targets, poly, arena = random_state(3)
    obs, mask = obs_of(pos, vel, targets, poly, arena)
    with torch.no_grad():
        assert torch.equal(same(obs, mask), small(obs, mask))
    assert torch.equal(grow_slot_actor(small, 5, seed=7).state_dict()["embed_targets.weight"],
                       b["embed_targets.weight"])                  # the seed fixes the new slots
    with pytest.raises(TypeError, match="typed actors run any number"):
        grow_slot_actor(build_actor(ActorConfig(variant="typed"), 3), 5)


@pytest.mark.parametrize("variant", ["typed", "slot", "mlp"])
def test_torchscript_matches_eager_after_save_and_load(variant):
    torch.manual_seed(5)
    n = 3
    actor = build_actor(ActorConfig(variant=variant), n)
    pos, vel, targets, poly, arena = random_state(n)
    if variant == "mlp":
        obs, mask = flat(pos, vel, targets), None
    else:
        obs, mask = obs_of(pos, vel, targets, poly, arena)
    buffer = io.BytesIO()
    torch.jit.save(torch.jit.script(actor), buffer)
    buffer.seek(0)
    loaded = torch.jit.load(buffer)
    with torch.no_grad():
        assert torch.allclose(loaded(obs, mask), actor(obs, mask), atol=1e-6)
        if variant != "mlp":
            assert torch.allclose(loaded.attention(obs, mask), actor.attention(obs, mask), atol=1e-6)
    critic = build_critic(CriticConfig(variant="mlp" if variant == "mlp" else "attention"), n)
    with torch.no_grad():
        assert torch.allclose(torch.jit.script(critic)(obs, mask), critic(obs, mask), atol=1e-6)


def test_value_mixing_by_hand():
    values = torch.tensor([[1.0, 2.0, 6.0]])
    # mean = 3; eps = 0.5: 0.5 * [1, 2, 6] + 0.5 * 3 = [2, 2.5, 4.5]
    assert mix_values(values, 0.5).tolist() == [[2.0, 2.5, 4.5]]
    assert mix_values(values, 1.0).tolist() == [[1.0, 2.0, 6.0]]
    assert mix_values(values, 0.0).tolist() == [[3.0, 3.0, 3.0]]


def test_gaussian_helpers_match_torch_distributions():
    g = torch.Generator().manual_seed(6)
    mean = torch.randn(5, 3, 2, generator=g)
    log_std = torch.tensor([-0.3, 0.4])
    actions = mean + torch.randn(5, 3, 2, generator=g)
    normal = torch.distributions.Normal(mean, log_std.exp())
    assert torch.allclose(gaussian_log_prob(actions, mean, log_std), normal.log_prob(actions).sum(-1), atol=1e-6)
    assert torch.allclose(gaussian_entropy(log_std), normal.entropy()[0, 0].sum(), atol=1e-6)


def test_config_errors_name_the_field():
    with pytest.raises(PolicyConfigError, match="actor.variant"):
        ActorConfig(variant="transformer")
    with pytest.raises(PolicyConfigError, match="num_heads"):
        ActorConfig(embed_dim=30, num_heads=4)
    with pytest.raises(PolicyConfigError, match="critic.value_mixing"):
        CriticConfig(value_mixing=1.5)
    with pytest.raises(PolicyConfigError, match="unknown actor field"):
        ActorConfig.from_dict({"variant": "typed", "depth": 3})
    assert ActorConfig.from_dict(ActorConfig(hidden_sizes=[64, 64]).to_dict()) == ActorConfig(hidden_sizes=(64, 64))


def test_embedding_hidden_layer_defaults_per_variant_and_is_checked():
    assert ActorConfig().embed_hidden == 32 and ActorConfig(variant="slot").embed_hidden == 0
    assert ActorConfig(variant="mlp").embed_hidden == 0 and ActorConfig(embed_hidden=0).embed_hidden == 0
    with pytest.raises(PolicyConfigError, match="actor.embed_hidden"):
        ActorConfig(variant="slot", embed_hidden=16)
    with pytest.raises(PolicyConfigError, match="critic.embed_hidden"):
        CriticConfig(variant="mlp", embed_hidden=16)
    with pytest.raises(PolicyConfigError, match="actor.embed_hidden"):
        ActorConfig(embed_hidden=-1)
    obs = torch.randn(2, 4, 9, 4)
    linear, hidden = build_actor(ActorConfig(embed_hidden=0), 4), build_actor(ActorConfig(embed_hidden=8), 4)
    assert linear(obs).shape == hidden(obs).shape == (2, 4, 2)
    assert count_parameters(hidden) != count_parameters(linear)


@pytest.mark.parametrize("embed_hidden", [0, 32])
def test_one_query_attention_computes_the_training_numbers(embed_hidden):
    """The attention torch.export traces for a slot actor (one query, the key and value
    projections absorbed) gives the actions of the training forward, for every N and with
    masked tokens."""
    torch.manual_seed(0)
    actor = build_actor(ActorConfig(embed_hidden=embed_hidden, frame="world"), 3).eval()   # the turn: below
    generator = torch.Generator().manual_seed(1)
    for n in (1, 2, 5, 16):
        obs = torch.randn(4, n, 2 * n + 1, 4, generator=generator) * 0.3
        mask = torch.rand(4, n, 2 * n + 1, generator=generator) > 0.3
        with torch.no_grad():
            want = actor(obs, mask).reshape(-1, 2)
            rows, row_mask = obs.reshape(-1, 2 * n + 1, 4), mask.reshape(-1, 2 * n + 1)
            plain = actor.rows(rows, row_mask)
            embed, head = actor.embedding, actor.head
            x = embed(torch.where(torch.cat((torch.ones_like(row_mask[:, :1]), row_mask[:, 1:]), 1)
                                  .unsqueeze(-1), rows, torch.zeros(())) * actor.input_scale, n)
            m = torch.cat((torch.ones_like(row_mask[:, :1]), row_mask[:, 1:]), 1)
            attended = head.attention.one_query(x[:, 0], x, m)
            u = head.mlp(torch.cat((x[:, 0], attended), -1))
            got = actor.accel_limit * torch.tanh((u - actor.velocity_damping * rows[:, 0, 2:4]) / actor.accel_limit)
        assert float((plain - want).abs().max()) <= 1e-6
        assert float((got - want).abs().max()) <= 1e-5 and float(want.abs().max()) > 1e-3


def _mixing_actor(layers: int, n: int) -> torch.nn.Module:
    """A typed actor with ``layers`` token blocks whose zero-initialised outputs are moved, so the
    blocks change the actions."""
    actor = build_actor(ActorConfig(token_layers=layers), n)
    with torch.no_grad():
        for block in actor.mixers:
            block.out.weight.normal_(0.0, 0.2)
            block.feed[2].weight.normal_(0.0, 0.2)
    return actor


@pytest.mark.parametrize("n", [2, 5])
def test_token_blocks_keep_the_typed_actor_equivariant_and_change_its_actions(n):
    torch.manual_seed(7)
    actor = _mixing_actor(2, n)
    pos, vel, targets, poly, arena = random_state(n)
    perm = torch.randperm(n, generator=torch.Generator().manual_seed(n))
    obs, mask = obs_of(pos, vel, targets, poly, arena)
    with torch.no_grad():
        a = actor(obs, mask)
        assert torch.allclose(actor(*obs_of(pos[:, perm], vel[:, perm], targets, poly, arena)), a[:, perm], atol=1e-5)
        assert torch.allclose(actor(*obs_of(pos, vel, targets[:, perm], poly, arena)), a, atol=1e-5)
        plain = build_actor(ActorConfig(), n)
        plain.load_state_dict({k: v for k, v in actor.state_dict().items() if not k.startswith("mixers.")})
        assert float((plain(obs, mask) - a).abs().max()) > 1e-3          # the blocks do something
        rows = actor.rows(obs.reshape(-1, 2 * n + 1, 4), mask.reshape(-1, 2 * n + 1))
        assert torch.allclose(rows, a.reshape(-1, 2), atol=1e-6)
        assert torch.allclose(torch.jit.script(actor)(obs, mask), a, atol=1e-6)


def test_fresh_token_blocks_are_the_identity_and_are_checked():
    torch.manual_seed(8)
    plain, mixed = build_actor(ActorConfig(), 4), build_actor(ActorConfig(token_layers=1), 4)
    mixed.load_state_dict({**mixed.state_dict(), **plain.state_dict()})
    obs = torch.randn(3, 4, 9, 4) * 0.3
    mask = torch.rand(3, 4, 9) > 0.2
    with torch.no_grad():
        assert torch.equal(mixed(obs, mask), plain(obs, mask))
    assert count_parameters(mixed) - count_parameters(plain) == 64 * 64 * 4 + 64 * 4 + 2 * (64 * 128) + 128 + 64
    for bad in (-1, 5, True, 1.0):
        with pytest.raises(PolicyConfigError, match="actor.token_layers"):
            ActorConfig(token_layers=bad)
    with pytest.raises(PolicyConfigError, match="typed actor only"):
        ActorConfig(variant="slot", token_layers=1)
