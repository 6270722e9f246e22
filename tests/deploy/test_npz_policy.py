"""The npz format and its compiled kernel (deploy/npz_policy.py): parity with the eager actor for
every actor shape the kernel covers, a copy of the one module running without torch or the
project, tampering refused, clear errors, one compiled signature whatever the caller passes.
(Parity for N = 1..21, NaN rows, `export --check` and flipped bytes run for every format in
test_export.py.)"""

from __future__ import annotations

import json
import shutil
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import torch

from controllers.policy import ActorConfig, build_actor
from deploy.export import ExportError, export_policy, formats_for, load_exported, random_fleet_rows
from deploy.npz_policy import META_MEMBER, NpzPolicyError, npz_bytes, open_npz, typed_rows_forward
from sim.scenario import make_scenario
from tests.deploy.test_export import eager_reference

ROOT = Path(__file__).resolve().parents[2]


def scaled_actor(config: ActorConfig, n: int = 5, seed: int = 0):
    """An untrained actor with outputs up to the limit, as a trained one gives."""
    torch.manual_seed(seed)
    actor = build_actor(config, n)
    with torch.no_grad():
        for p in actor.parameters():
            p.mul_(1.5)
    return actor.eval()


@pytest.fixture(scope="module")
def npz_file(tmp_path_factory):
    torch.set_num_threads(1)
    actor = scaled_actor(ActorConfig(embed_dim=32, velocity_damping=2.0))
    report, = export_policy(actor, tmp_path_factory.mktemp("npz") / "policy", dt=0.05, trained_robots=5,
                            formats=("npz",))
    return actor, report.path


@pytest.mark.parametrize("config", [
    ActorConfig(embed_dim=32),                                   # the default shape (turned frame)
    ActorConfig(embed_dim=32, embed_hidden=0),                   # linear embeddings
    ActorConfig(embed_dim=32, frame="world", velocity_damping=1.5),    # no turn, damping
    ActorConfig(embed_dim=24, num_heads=3, hidden_sizes=(48, 32)),     # more head layers
], ids=["typed", "linear-embedding", "world-frame-damped", "two-hidden-layers"])
def test_the_kernel_matches_the_eager_actor_for_each_actor_shape(config, tmp_path):
    actor = scaled_actor(config)
    report, = export_policy(actor, tmp_path / "p", dt=0.05, trained_robots=5, formats=("npz",))
    assert report.max_abs_diff <= 1e-5 and report.cases == 84       # the export's own comparison
    policy = load_exported(report.path)
    generator = torch.Generator().manual_seed(7)
    for n in (1, 2, 5, 9, 21):
        rows, mask = random_fleet_rows(n, 6, generator, make_scenario("paper-5"), masked=True)
        want = eager_reference(actor, rows.view(6, n, 2 * n + 1, 4), mask.view(6, n, 2 * n + 1))
        got, valid = policy.run(rows.numpy(), mask.numpy())
        assert valid.all() and float(want.abs().max()) > 1e-2
        assert float(np.abs(got - want.reshape(-1, 2).numpy()).max()) <= 1e-5


def test_a_copy_of_the_module_runs_the_golden_file_without_torch_or_the_project(npz_file, tmp_path):
    """npz_policy.py and robot.py copied alone, torch, onnxruntime and the project refused."""
    _, path = npz_file
    for source in (path, path.with_name("policy.golden.npz"), ROOT / "deploy" / "npz_policy.py",
                   ROOT / "deploy" / "robot.py"):
        shutil.copy(source, tmp_path / source.name)
    driver = """
import importlib.abc, json, sys
class Refuse(importlib.abc.MetaPathFinder):
    def find_spec(self, name, path, target=None):
        if name.split(".")[0] in ("torch", "onnxruntime", "sim", "controllers", "stack", "deploy"):
            raise ImportError(f"{name} is not on this robot")
sys.meta_path.insert(0, Refuse())
sys.path.insert(0, ".")
import numpy as np
import npz_policy
runner, meta = npz_policy.open_npz("policy.npz")
worst = 0.0
with np.load("policy.golden.npz") as golden:
    polygon, arena = golden["polygon"], golden["arena"]
    for n in golden["counts"]:
        toks = golden[f"n{n}_tokens"][0]
        accel, valid = runner(toks, np.ones(toks.shape[:2], dtype=bool))
        worst = max(worst, float(np.abs(accel - golden[f"n{n}_actions"][0]).max()) if valid.all() else 1e9)
import robot
policy = robot.RobotPolicy("policy.npz")          # golden file replayed through robot_tokens
act = policy.act([0.5, 0.5], [0.1, 0.0], [[0.2, 0.2], [0.8, 0.8]], [[0.3, 0.7]], [[0.0, 0.0]],
                 polygon, arena)
nan = policy.act([0.5, float("nan")], [0.0, 0.0], [[0.2, 0.2]], np.zeros((0, 2)), np.zeros((0, 2)),
                 polygon, arena)
print(json.dumps({"worst": worst, "limit": meta["accel_limit"], "golden_diff": policy.golden_diff,
                  "act": [float(np.linalg.norm(act.accel)), act.valid], "nan": [nan.accel.tolist(), nan.valid],
                  "loaded": sorted(m for m in ("torch", "onnxruntime") if m in sys.modules)}))
"""
    (tmp_path / "driver.py").write_text(driver)
    result = subprocess.run([sys.executable, "-I", "driver.py"], cwd=tmp_path, capture_output=True,
                            text=True, timeout=300)
    assert result.returncode == 0, result.stderr[-3000:]
    out = json.loads(result.stdout.strip().splitlines()[-1])
    assert out["worst"] <= 1e-5 and out["limit"] == 1.0 and out["loaded"] == []
    assert out["golden_diff"] <= 1e-5 and 1e-3 < out["act"][0] <= 1.0 + 1e-6 and out["act"][1] is True
    assert out["nan"] == [[0.0, 0.0], False]


def _rewrite(path: Path, dest: Path, *, meta_changes=None, array_changes=None, keep_digest=True) -> Path:
    with np.load(path) as data:
        arrays = {name: data[name] for name in data.files}
    meta = json.loads(str(arrays.pop(META_MEMBER)))
    digest = meta.pop("content_sha256")
    meta |= meta_changes or {}
    arrays |= array_changes or {}
    arrays = {k: v for k, v in arrays.items() if v is not None}
    if keep_digest:
        arrays[META_MEMBER] = np.array(json.dumps(meta | {"content_sha256": digest}))
        np.savez(dest, **arrays)
    else:
        dest.write_bytes(npz_bytes(arrays, meta))
    return dest


def test_changed_metadata_weights_or_arrays_are_refused(npz_file, tmp_path):
    _, path = npz_file
    assert open_npz(path)[1]["file_format"] == "npz"
    with pytest.raises(ExportError, match="content_sha256"):
        load_exported(_rewrite(path, tmp_path / "limit.npz", meta_changes={"accel_limit": 5.0}))
    with np.load(path) as data:
        head = data["head_in"].copy()
    head[3, 4] += 1e-3
    with pytest.raises(ExportError, match="content_sha256"):
        load_exported(_rewrite(path, tmp_path / "w.npz", array_changes={"head_in": head}))
    unsigned = _rewrite(path, tmp_path / "missing.npz", array_changes={"scores": None}, keep_digest=False)
    with pytest.raises(ExportError, match="scores"):     # signed anew, but the kernel's array is gone
        load_exported(unsigned)
    (tmp_path / "junk.npz").write_bytes(np.random.default_rng(0).bytes(2000))
    with pytest.raises(ExportError, match="not an npz policy"):
        load_exported(tmp_path / "junk.npz")


def test_actors_the_kernel_does_not_cover_are_refused_clearly_and_left_out_by_default(tmp_path):
    slot = scaled_actor(ActorConfig(variant="slot", embed_dim=32), n=3)
    mixed = scaled_actor(ActorConfig(embed_dim=32, token_layers=1))
    for actor in (slot, mixed):
        with pytest.raises(ExportError, match="--format onnx"):
            export_policy(actor, tmp_path / "x", dt=0.05, trained_robots=3, formats=("npz",))
        assert formats_for(actor) == ("torchscript", "pt2", "onnx")
    assert list(tmp_path.iterdir()) == []
    assert formats_for(scaled_actor(ActorConfig(embed_dim=32))) == ("torchscript", "pt2", "onnx", "npz")


def test_bad_shapes_are_named_and_every_call_reuses_one_compiled_kernel(npz_file):
    _, path = npz_file
    runner, _ = open_npz(path)                 # compiles (or loads) this actor's signature
    compiled = len(typed_rows_forward.signatures)
    with pytest.raises(NpzPolicyError, match=r"\(B, T = 2N \+ 1, 4\)"):
        runner(np.zeros((2, 10, 4), np.float32), np.ones((2, 10), bool))
    with pytest.raises(NpzPolicyError, match="mask must have shape"):
        runner(np.zeros((2, 11, 4), np.float32), np.ones((2, 9), bool))
    rng = np.random.default_rng(2)
    toks = rng.normal(0, 0.3, (5, 11, 4))
    want, _ = runner(toks.astype(np.float32), np.ones((5, 11), bool))
    got, _ = runner(toks, np.ones((5, 11), int))                   # float64 and int mask: cast
    strided, _ = runner(np.repeat(toks, 2, axis=0)[::2], np.ones((5, 11), bool))
    assert np.array_equal(got, want) and np.array_equal(strided, want)
    for n in (1, 3, 16):
        runner(rng.normal(0, 0.3, (n, 2 * n + 1, 4)), np.ones((n, 2 * n + 1), bool))
    assert len(typed_rows_forward.signatures) == compiled


def test_the_control_stack_gives_the_npz_file_the_onnx_files_commands(npz_file, tmp_path):
    """The default stack (filter, latency, MEC) on the states of a pymunk episode with model
    error: the npz file's nominal commands are the ONNX file's within the export tolerance."""
    from controllers.scripted import ScriptedController
    from sim.pymunk_world import ModelError, PymunkWorld
    from sim.scenario import transport_scenario
    from stack.pipeline import ControlStack

    actor, _ = npz_file
    reports = export_policy(actor, tmp_path / "p", dt=0.05, trained_robots=5, formats=("onnx", "npz"))
    scenario = transport_scenario(5)
    world = PymunkWorld(scenario, ModelError(gain=0.8, delay_ticks=1))
    state, scripted, states = world.reset(seed=3), ScriptedController(scenario), []
    for _ in range(60):
        states.append(state)
        world.send_accelerations(scripted(state))
        state = world.step()
    stacks = [ControlStack(scenario, load_exported(r.path)) for r in reports]
    nominal = [[stack.tick(s).a_nom for s in states] for stack in stacks]
    differences = np.abs(np.array(nominal[0]) - np.array(nominal[1]))
    assert differences.max() <= 1e-5 and np.abs(np.array(nominal[1])).max() > 0.1


def test_the_robot_runtime_refuses_an_npz_file_of_another_observation_layout(npz_file, tmp_path):
    """Signed anew, so only the layout check can refuse it (ONNX and npz share that check)."""
    from deploy.robot import RobotPolicy, RobotPolicyError

    _, path = npz_file
    shutil.copy(path.with_name("policy.golden.npz"), tmp_path / "policy.golden.npz")
    good = _rewrite(path, tmp_path / "policy.npz", keep_digest=False)
    assert RobotPolicy(good).golden_diff <= 1e-5
    old = _rewrite(path, tmp_path / "old.npz", meta_changes={"layout_version": 99}, keep_digest=False)
    with pytest.raises(RobotPolicyError, match="observation layout 99"):
        RobotPolicy(old)


def test_the_npz_kernel_breaks_a_turn_tie_with_the_actors_number():
    """deploy/npz_policy.py runs without the project, so it holds TURN_TIE itself: the two must
    agree, or a diagonal layout turns one way in the kernel and another in the actor."""
    from controllers.policy.layers import TURN_TIE
    from deploy import npz_policy

    assert npz_policy.TURN_TIE == TURN_TIE
