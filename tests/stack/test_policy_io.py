"""stack.policy_io.ModuleKernel: a typed actor in memory run by the npz kernel, its current weights."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from controllers.policy import ActorConfig, build_actor
from controllers.policy.actor import TypedSDPAActor
from deploy.export import random_fleet_rows
from sim.pymunk_world import ModelError, PymunkWorld
from sim.scenario import clip_norm, make_scenario, transport_scenario
from stack.pipeline import ControlStack, StackConfig
from stack.policy_io import ModuleKernel

SMALL = ActorConfig(embed_dim=16, num_heads=2, hidden_sizes=(32,))


def typed_actor(seed: int, config: ActorConfig = SMALL) -> torch.nn.Module:
    torch.manual_seed(seed)
    net = build_actor(config, 3).eval()
    with torch.no_grad():      # outputs of order 0.1-1 m/s^2, so that rows differ visibly
        net.head.mlp[-1].weight.mul_(60.0)
    return net


def random_rows(n: int, batch: int, seed: int) -> tuple[torch.Tensor, torch.Tensor]:
    """Rows of ``batch`` random fleets of ``n`` robots, 30 % of their tokens masked."""
    return random_fleet_rows(n, batch, torch.Generator().manual_seed(seed), transport_scenario(n), masked=True)


def module_rows(net: torch.nn.Module, tokens: torch.Tensor, mask: torch.Tensor) -> np.ndarray:
    """What the module computes for the rows, with the norm bound of the export contract."""
    with torch.no_grad():
        return clip_norm(net.rows(tokens, mask).double().numpy(), net.accel_limit)


OTHER = ActorConfig(embed_dim=16, num_heads=4, embed_hidden=0, hidden_sizes=(32, 16), frame="world",
                    velocity_damping=1.0, own_target=True)


@pytest.mark.parametrize("n, config", [(1, SMALL), (3, SMALL), (6, SMALL), (4, OTHER)])
def test_the_kernel_computes_the_actors_rows(n, config):
    net = typed_actor(0, config)
    tokens, mask = random_rows(n, 40, seed=n)
    accel, valid = ModuleKernel.of(net)(tokens.numpy(), mask.numpy())
    want = module_rows(net, tokens, mask)
    assert valid.all() and np.abs(want).max() > 0.3
    np.testing.assert_allclose(accel, want, atol=1e-5, rtol=0)


def test_the_kernel_follows_the_weights_of_an_actor_still_in_training():
    """An optimiser step and a load_state_dict change the weights in place; the kernel built
    before either runs the new weights (without the version check it runs the first ones)."""
    net = typed_actor(1)
    first = {k: v.clone() for k, v in net.state_dict().items()}
    kernel = ModuleKernel.of(net)
    tokens, mask = random_rows(3, 40, seed=7)
    before, _ = kernel(tokens.numpy(), mask.numpy())
    optimiser = torch.optim.Adam(net.parameters(), lr=0.05)
    net.rows(tokens, mask).square().sum().backward()
    optimiser.step()
    after, _ = kernel(tokens.numpy(), mask.numpy())
    assert np.abs(after - before).max() > 1e-2
    np.testing.assert_allclose(after, module_rows(net, tokens, mask), atol=1e-5, rtol=0)
    net.load_state_dict(first)
    restored, _ = kernel(tokens.numpy(), mask.numpy())
    np.testing.assert_allclose(restored, before, atol=1e-7, rtol=0)


class Braking(TypedSDPAActor):
    """A typed actor whose forward differs from its weights' rows: the kernel must not run it."""

    def forward(self, obs, mask=None):
        return torch.zeros(obs.shape[0], obs.shape[1], 2)


def test_modules_the_kernel_does_not_cover_are_named_and_run_as_given():
    state = PymunkWorld(make_scenario("paper-3")).reset(seed=3)
    sc = make_scenario("paper-3")
    for config, kind in ((ActorConfig(variant="slot", embed_dim=16, num_heads=2), "SlotSDPAActor"),
                         (ActorConfig(variant="mlp"), "MLPActor")):
        assert kind in ModuleKernel.refusal(build_actor(config, 3))
    assert "token_layers" in ModuleKernel.refusal(build_actor(ActorConfig(token_layers=1), 3))
    assert ModuleKernel.refusal(torch.jit.script(typed_actor(0))) is not None
    subclass = Braking(SMALL)
    assert "Braking" in ModuleKernel.refusal(subclass)
    stack = ControlStack(sc, subclass, StackConfig(safety=False, mec=False))
    assert stack.policy_runtime == "torch"
    np.testing.assert_array_equal(stack.tick(state).a_nom, 0.0)
    assert "CPU" in ModuleKernel.refusal(typed_actor(0).to("meta"))
    with torch.inference_mode():
        made_in_inference_mode = typed_actor(0)
    assert "inference_mode" in ModuleKernel.refusal(made_in_inference_mode)
    assert ControlStack(sc, made_in_inference_mode).policy_runtime == "torch"
    assert ModuleKernel.refusal(typed_actor(0)) is None


def test_a_stack_runs_the_kernel_and_commands_what_the_module_would():
    """paper-5 in pymunk with model error, filter + MEC on: the default stack (kernel) and one
    running the module, given the same states, send the same commands to 1e-5."""
    sc = make_scenario("paper-5")
    net = typed_actor(2)
    stacks = [ControlStack(sc, net), ControlStack(sc, net, StackConfig(policy_kernel=False))]
    assert [stack.policy_runtime for stack in stacks] == ["kernel", "torch"]
    world = PymunkWorld(sc, ModelError(gain=0.85, lag_tau=0.05, delay_ticks=1), seed=4)
    state, moved, gap = world.reset(seed=4), 0.0, 0.0
    for _ in range(60):
        ticks = [stack.tick(state) for stack in stacks]
        gap = max(gap, float(np.abs(ticks[0].a_cmd - ticks[1].a_cmd).max()))
        moved = max(moved, float(np.abs(ticks[1].a_cmd).max()))
        world.send_accelerations(ticks[1].a_cmd)
        state = world.step()
    assert moved > 0.1 and gap <= 1e-5
