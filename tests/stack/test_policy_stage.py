"""The policy stage (stack/policy_stage.py): the tokens a policy is given, the network run with
and without its mask (the module, TorchScript, the compiled kernel), exported files in this
and a fresh process, and policies refused with a clear error."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import torch

from controllers.policy import ActorConfig, build_actor
from controllers.scripted import ScriptedController
from sim.fleet import FleetState
from sim.pymunk_world import PymunkWorld
from sim.scenario import clip_norm, make_scenario, transport_scenario
from stack.pipeline import ControlStack, StackConfig, StackError, load_policy
from tests.stack.test_pipeline import WEAK_ROBOTS, actor

REPO = Path(__file__).resolve().parents[2]


def exportable_actor(seed: int = 0) -> torch.nn.Module:
    """Large outputs from the output layer alone: x20 on every weight drives activations to 1e4,
    where float32 rounding in another runtime (ONNX) differs by 1e-3 and the export refuses."""
    torch.manual_seed(seed)
    net = build_actor(ActorConfig(embed_dim=16, num_heads=2, hidden_sizes=(32,)), 3).eval()
    with torch.no_grad():
        net.head.mlp[-1].weight.mul_(100.0)
    return net


@pytest.mark.parametrize("suffix", [".pt", ".pt2", ".onnx"])
def test_exported_file_gives_the_eager_a_nom_in_this_and_a_fresh_process(tmp_path, suffix):
    from deploy.export import export_policy

    sc = make_scenario("paper-5")
    net = exportable_actor(1)
    name = {".pt": "torchscript", ".pt2": "pt2", ".onnx": "onnx"}[suffix]
    path = export_policy(net, tmp_path / "policy", dt=0.05, trained_robots=5, formats=(name,))[0].path
    state = PymunkWorld(sc, seed=2).reset(seed=2)
    eager = clip_norm(ControlStack(sc, net).tick(state).a_nom, 1.0)   # the file bounds the norm
    exported = ControlStack(sc, str(path)).tick(state).a_nom
    assert np.abs(eager).max() > 0.05
    np.testing.assert_allclose(exported, eager, atol=1e-5)
    code = ("import json, sys; from sim.pymunk_world import PymunkWorld; from sim.scenario import make_scenario;"
            "from stack.pipeline import ControlStack; sc = make_scenario('paper-5');"
            "s = PymunkWorld(sc, seed=2).reset(seed=2);"
            f"print(json.dumps(ControlStack(sc, {str(path)!r}).tick(s).a_nom.tolist()))")
    out = subprocess.run([sys.executable, "-c", code], cwd=REPO, capture_output=True, text=True, check=True)
    np.testing.assert_allclose(np.array(json.loads(out.stdout.strip().splitlines()[-1])), eager, atol=1e-5)


def test_bad_policy_inputs_raise_clear_errors(tmp_path):
    sc = make_scenario("paper-3")
    with pytest.raises(StackError, match="does not exist"):
        load_policy(tmp_path / "missing.pt")
    junk = tmp_path / "junk.pt"
    junk.write_bytes(b"not a model")
    with pytest.raises(StackError, match="neither a training checkpoint nor a policy file") as err:
        ControlStack(sc, junk)
    assert "weights_only" not in str(err.value)
    with pytest.raises(StackError, match="callable"):
        ControlStack(sc, 42)


@pytest.mark.parametrize("n", [1, 2, 3, 5, 8])
def test_numpy_tokens_equal_sim_observations_tokens(n):
    from sim.observations import tokens

    sc = transport_scenario(n)
    stack = ControlStack(sc, actor())
    rng = np.random.default_rng(n)
    for _ in range(5):
        pos = rng.uniform(0.0, 1.0, (n, 2))
        pos[0] = sc.object_center + rng.uniform(-0.05, 0.05, 2)      # one robot inside the object
        vel, targets = rng.normal(0, 0.3, (n, 2)), rng.uniform(0, 1, (n, 2))
        state = FleetState(time=0.0, step=0, positions=pos, velocities=vel, targets=targets,
                           object_pose=np.array([0.5, 0.5, 0.0]))
        got, got_mask = stack.observe(state)
        as_t = lambda x: torch.tensor(x, dtype=torch.float32)[None]  # noqa: E731
        want, want_mask = tokens(as_t(pos), as_t(vel), as_t(targets),
                                 torch.tensor(sc.polygon, dtype=torch.float32), sc.arena)
        assert got.shape == want.shape == (1, n, 2 * n + 1, 4) and got.dtype == torch.float32
        torch.testing.assert_close(got, want, atol=1e-6, rtol=0)
        assert torch.equal(got_mask, want_mask)


# ------------------------------------------------------------------ fast tick path


def _states(sc, count, seed):
    world = PymunkWorld(sc, WEAK_ROBOTS, seed=seed)
    state = world.reset(seed=seed)
    ctl = ScriptedController(sc)
    out = []
    for _ in range(count):
        out.append(state)
        world.send_accelerations(ctl(state))
        state = world.step()
    return out


@pytest.mark.parametrize("runtime", ["kernel", "module", "scripted"])
def test_tick_without_mask_equals_the_network_on_fresh_tokens_and_full_mask(runtime):
    """The tick passes mask=None (all tokens valid) and reuses one token buffer per N: its a_nom
    equals the network on freshly built tokens with the all-true mask, tick after tick, as N
    changes; the eager actor by default through the compiled kernel, which bounds the norm as an
    exported file does (the module bounds each component; the filter clips the norm first)."""
    from sim.observations import tokens

    net = actor(2)
    module = torch.jit.script(net) if runtime == "scripted" else net
    # the measured state goes to the policy as is (by default it reads the estimators' state)
    stack = ControlStack(make_scenario("paper-3"), module, StackConfig(
        estimated_velocity=False, estimated_position=False, policy_kernel=runtime == "kernel"))
    for n in (3, 5, 3):
        sc = transport_scenario(n)
        for state in _states(sc, 4, seed=n):
            got = stack.tick(state).a_nom
            as_t = lambda x: torch.tensor(x, dtype=torch.float32)[None]  # noqa: E731
            obs, mask = tokens(as_t(state.positions), as_t(state.velocities), as_t(state.targets),
                               torch.tensor(sc.polygon, dtype=torch.float32), sc.arena)
            with torch.no_grad():
                want = net(obs, mask)[0].double().numpy()
            assert np.abs(want).max() > 0.05
            if runtime == "kernel":
                want = clip_norm(want, 1.0)
            np.testing.assert_allclose(got, want, atol=1e-6, rtol=0)


def test_exported_policy_runs_in_the_stack_and_foreign_files_are_refused(tmp_path):
    from deploy.export import ExportedPolicy, export_policy
    from deploy.export.contract import PolicyContract
    from deploy.export.formats import FORMATS

    torch.set_num_threads(1)
    net = exportable_actor(3)
    reports = export_policy(net, tmp_path / "policy", dt=0.05, trained_robots=3, formats=("torchscript", "onnx"))
    sc = make_scenario("paper-3")
    state = _states(sc, 1, seed=4)[0]
    want = clip_norm(ControlStack(sc, net).tick(state).a_nom, 1.0)
    for report in reports:
        module = load_policy(report.path)
        assert isinstance(module, ExportedPolicy) and module.file_format == report.meta["file_format"]
        np.testing.assert_allclose(ControlStack(sc, module).tick(state).a_nom, want, atol=1e-5)
    bare = tmp_path / "bare.pt"                      # a TorchScript actor without metadata
    torch.jit.save(torch.jit.script(net), str(bare))
    with pytest.raises(StackError, match="meta.json"):
        ControlStack(sc, bare)
    meta = {k: v for k, v in reports[0].meta.items() if k != "content_sha256"}
    for name, changes, message in (("old_layout", {"layout_version": 99}, "observation layout 99"),
                                   ("other_version", {"format_version": 1}, "v1 file"),
                                   ("wide_tokens", {"token_dim": 7}, "7 features per token")):
        path = tmp_path / f"{name}.pt"
        FORMATS["torchscript"].write(PolicyContract(net), path, meta | changes, None)
        with pytest.raises(StackError, match=message):
            load_policy(path)


def test_fleet_tokens_np_into_a_float32_buffer_for_a_rotated_object():
    """The general polygon path (a rotated box is no longer axis-aligned) against the torch tokens,
    written into a reused float32 buffer that starts dirty."""
    from sim.observations import fleet_tokens_np, tokens

    sc = transport_scenario(4)
    angle = 0.4
    rot = np.array([[np.cos(angle), -np.sin(angle)], [np.sin(angle), np.cos(angle)]])
    polygon = (sc.polygon - 0.5) @ rot.T + 0.5
    rng = np.random.default_rng(9)
    buf = np.full((4, 9, 4), np.nan, dtype=np.float32)
    for _ in range(3):
        pos, vel, targets = rng.uniform(0, 1, (4, 2)), rng.normal(0, 0.3, (4, 2)), rng.uniform(0, 1, (4, 2))
        pos[1] = 0.5 + rng.uniform(-0.05, 0.05, 2)                      # inside the object
        out = fleet_tokens_np(pos, vel, targets, polygon, sc.arena, out=buf)
        assert out is buf
        as_t = lambda x: torch.tensor(x, dtype=torch.float32)[None]  # noqa: E731
        want, _ = tokens(as_t(pos), as_t(vel), as_t(targets), torch.tensor(polygon, dtype=torch.float32),
                         sc.arena)
        torch.testing.assert_close(torch.from_numpy(buf)[None], want, atol=1e-6, rtol=0)
    with pytest.raises(ValueError, match="out must have shape"):
        fleet_tokens_np(pos, vel, targets, polygon, sc.arena, out=np.zeros((4, 8, 4)))
