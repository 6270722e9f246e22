"""Export to TorchScript, torch.export and ONNX: parity with the eager actor for N = 1..21, the
contract inside every file (norm bound, NaN -> brake flag, frozen weights), metadata and digest
checked on every load, clear refusals."""

from __future__ import annotations

import json
import subprocess
import sys
import zipfile
from pathlib import Path

import numpy as np
import pytest
import torch

from controllers.mappo.checkpoint import save_checkpoint
from controllers.mappo.config import MAPPOConfig
from controllers.policy import ActorConfig, build_actor
from deploy.export import (
    DEFAULT_FORMATS,
    ExportError,
    check_export,
    export_policy,
    golden_path,
    load_exported,
    random_fleet_rows,
)
from deploy.export.formats import FORMATS
from sim.fleet import FleetState
from sim.observations import LAYOUT_VERSION
from sim.scenario import MAX_ROBOTS, make_scenario, transport_scenario
from stack.pipeline import ControlStack, StackConfig
from stack.policy_io import StackError, load_policy
from tests.xdist_groups import EXPORT

pytestmark = EXPORT

ROOT = Path(__file__).resolve().parents[2]
SUFFIX = {name: fmt.suffix for name, fmt in FORMATS.items()}


def make_actor(seed: int = 0, variant: str = "typed", n: int = 5):
    torch.manual_seed(seed)
    actor = build_actor(ActorConfig(variant=variant, embed_dim=32, velocity_damping=2.0), n)
    with torch.no_grad():  # outputs up to the limit, as a trained actor gives (the initial gain is
        for p in actor.parameters():        # tiny); x3 grows embeddings to 65, where float32
            p.mul_(1.5)                     # rounding alone is 1e-5

    return actor.eval()


@pytest.fixture(scope="module")
def exported(tmp_path_factory):
    torch.set_num_threads(1)
    stem = tmp_path_factory.mktemp("export") / "policy"
    actor = make_actor()
    reports = export_policy(actor, stem, dt=0.05, trained_robots=5, config={"note": "test"})
    return actor, {r.meta["file_format"]: r.path for r in reports}, reports


def formation(*args: str) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-m", "stack.cli", *args], cwd=ROOT,
                          capture_output=True, text=True, timeout=300)


def formation_here(capsys, *args: str) -> tuple[int, str]:
    """``formation ARGS`` in this process: (exit code, what it wrote to stderr)."""
    from stack.cli import main

    capsys.readouterr()
    try:
        rc = main(list(args))
    except SystemExit as exc:     # argparse's refusals
        rc = exc.code
    return rc, capsys.readouterr().err


def eager_reference(actor, obs, mask):
    """The eager actor's forward (slicing by N), bounded in norm as the contract promises."""
    with torch.no_grad():
        a = actor(obs, mask)
    norm = torch.linalg.vector_norm(a, dim=-1, keepdim=True)
    return a * torch.clamp(actor.accel_limit / norm, max=1.0)


def copy_export(path: Path, dest: Path) -> Path:
    dest.mkdir(exist_ok=True)
    (dest / path.name).write_bytes(path.read_bytes())
    golden = golden_path(path)
    (dest / golden.name).write_bytes(golden.read_bytes())
    return dest / path.name


@pytest.mark.parametrize("name", DEFAULT_FORMATS)
def test_every_format_matches_the_eager_actor_for_every_team_a_scenario_holds(exported, name):
    actor, files, _ = exported
    policy = load_exported(files[name])
    generator = torch.Generator().manual_seed(123)
    scenario = make_scenario("paper-5")
    worst = 0.0
    for n in range(1, MAX_ROBOTS + 1):
        for batch, masked in ((1, False), (16, True)):
            rows, mask = random_fleet_rows(n, batch, generator, scenario, masked)
            obs, obs_mask = rows.view(batch, n, 2 * n + 1, 4), mask.view(batch, n, 2 * n + 1)
            want = eager_reference(actor, obs, obs_mask)       # the training forward, sliced by N
            got, valid = policy.run(rows.numpy(), mask.numpy())
            assert got.shape == (batch * n, 2) and valid.all()
            assert float(want.abs().max()) > 1e-2
            worst = max(worst, float(np.abs(got - want.reshape(-1, 2).numpy()).max()))
    assert worst <= 1e-5


def test_actions_are_bounded_in_norm_inside_the_file(exported):
    actor, files, _ = exported
    obs = torch.randn(64, 5, 11, 4) * 2.0
    mask = torch.ones(64, 5, 11, dtype=torch.bool)
    with torch.no_grad():
        raw = torch.linalg.vector_norm(actor(obs, mask), dim=-1)
    assert float(raw.max()) > 1.1                      # per-component bound alone: corners > 1
    for name, path in files.items():
        accel, _ = load_exported(path).run(obs.reshape(-1, 11, 4).numpy(), mask.reshape(-1, 11).numpy())
        assert np.linalg.norm(accel, axis=1).max() <= 1.0 + 1e-6, name


def test_the_onnx_runner_answers_buffers_refilled_in_place_swapped_and_resized(exported):
    """The runner binds each input buffer once (a control loop passes the same arrays every
    tick): refilling them in place, passing other arrays of the same shape and another team
    size each give what a fresh session gives for those values."""
    from deploy.robot import open_onnx

    _, files, _ = exported
    policy, (session, _) = load_exported(files["onnx"]), open_onnx(files["onnx"])
    rng = np.random.default_rng(1)

    def fresh(toks, mask):
        return session.run(None, {"tokens": toks, "mask": mask})[0]

    toks, mask = rng.normal(0, 0.3, (5, 11, 4)).astype(np.float32), np.ones((5, 11), dtype=bool)
    first, _ = policy.run(toks, mask)
    toks[:] = rng.normal(0, 0.3, toks.shape)          # refilled in place: same object
    mask[2, 5] = False
    second, _ = policy.run(toks, mask)
    assert np.abs(second - first).max() > 1e-3
    assert np.array_equal(second, fresh(toks, mask))
    other = rng.normal(0, 0.3, (5, 11, 4)).astype(np.float32)
    assert np.array_equal(policy.run(other, np.ones((5, 11), dtype=bool))[0], fresh(other, np.ones((5, 11), dtype=bool)))
    small = rng.normal(0, 0.3, (3, 7, 4)).astype(np.float32)
    assert np.array_equal(policy.run(small, np.ones((3, 7), dtype=bool))[0], fresh(small, np.ones((3, 7), dtype=bool)))
    assert np.array_equal(policy.run(toks, mask)[0], second)     # back to the first buffers


@pytest.mark.parametrize("name", DEFAULT_FORMATS)
def test_non_finite_rows_are_flagged_with_zero_acceleration(exported, name):
    _, files, _ = exported
    policy = load_exported(files[name])
    rng = np.random.default_rng(0)
    toks = rng.normal(0, 0.3, (4, 11, 4)).astype(np.float32)
    mask = np.ones((4, 11), dtype=bool)
    clean, _ = policy.run(toks, mask)
    toks[1, 0, 2] = np.nan          # own velocity
    toks[2, 4, 0] = np.inf          # a read target token
    toks[3, 7, 1] = np.nan          # a masked robot token: ignored
    mask[3, 7] = False
    accel, valid = policy.run(toks, mask)
    assert valid.tolist() == [True, False, False, True]
    assert np.isfinite(accel).all()
    assert (accel[1:3] == 0).all()
    assert np.abs(accel[0] - clean[0]).max() == 0 and np.abs(accel[0]).max() > 1e-3
    masked_zero = toks[3:4].copy()
    masked_zero[0, 7] = 0.0
    want, _ = policy.run(masked_zero, mask[3:4])
    assert np.abs(accel[3] - want[0]).max() <= 1e-6


@pytest.mark.parametrize("name", DEFAULT_FORMATS)
def test_a_file_refuses_input_of_the_wrong_shape_by_name(exported, name):
    """Before, .pt and .onnx broadcast a (1, T) mask over every row and answered T = 6 or T = 1
    with valid actions; T = 2N + 1 for N = 1..21, a mask of the tokens' (B, T), 4 features."""
    policy = load_exported(exported[1][name])
    toks, mask = np.zeros((3, 7, 4), np.float32), np.ones((3, 7), dtype=bool)
    for bad_toks, bad_mask, message in ((toks, mask[:1], r"mask must be \(B, T\) = \(3, 7\)"),
                                        (toks[:, :6], mask[:, :6], "T = 6 tokens a row is not 2N \\+ 1"),
                                        (toks[:, :1], mask[:, :1], "T = 1 tokens"),
                                        (np.zeros((2, 45, 4), np.float32), np.ones((2, 45), bool), "T = 45"),
                                        (np.zeros((3, 7, 5), np.float32), mask, r"tokens must be \(B, T, 4\)")):
        with pytest.raises(ValueError, match=message):
            policy.run(bad_toks, bad_mask)


def test_torch_files_run_in_any_grad_mode(exported):
    """The stack calls under inference_mode; a user may call with gradients on first."""
    _, files, _ = exported
    toks, mask = torch.randn(5, 11, 4), torch.ones(5, 11, dtype=torch.bool)
    module = torch.jit.load(str(files["torchscript"]))
    assert all(not p.requires_grad for p in module.parameters())
    first, _ = module(toks, mask)
    with torch.inference_mode():
        second, _ = module(toks, mask)
    program = torch.export.load(str(files["pt2"])).module()
    third, _ = program(toks, mask)
    with torch.inference_mode():
        fourth, _ = program(toks, mask)
    assert torch.equal(first, second) and torch.allclose(third, fourth)


def test_metadata_travels_inside_every_file(exported):
    _, files, reports = exported
    for name, path in files.items():
        meta = load_exported(path).meta
        assert meta["file_format"] == name and meta["format_version"] == 2
        assert meta["layout_version"] == LAYOUT_VERSION and meta["token_dim"] == 4
        assert meta["dt"] == 0.05 and meta["accel_limit"] == 1.0
        assert meta["trained_robots"] == 5 and meta["robot_counts"] == list(range(1, 22))
        assert meta["scenario"]["name"] == "paper-5"
        assert meta["io"]["inputs"]["tokens"]["dtype"] == "float32"
        assert meta["io"]["inputs"]["mask"]["required"] is True
        assert [k["kind"] for k in meta["token_features"]["kinds"]] == [
            "self", "target k", "other robot j", "object"]
        assert all("[m" in f for f in meta["token_features"]["kinds"][0]["features"])
        assert len(meta["content_sha256"]) == 64
        assert meta["golden_file"] == golden_path(path).name == "policy.golden.npz"
    with np.load(golden_path(files["onnx"])) as golden:
        assert list(golden["counts"]) == [1, 2, 3, 5, 8, 16]
        assert golden["n5_tokens"].shape == (1, 5, 11, 4)
    assert reports[0].cases >= 21 * 2 * 2


@pytest.mark.parametrize("name", DEFAULT_FORMATS)
def test_check_passes_on_each_exported_file(exported, name):
    _, files, _ = exported
    assert check_export(files[name]).max_abs_diff <= 1e-5
    result = formation("export", "--check", str(files[name]))
    assert result.returncode == 0, result.stderr
    assert "OK" in result.stdout and name in result.stdout


@pytest.mark.parametrize("name", DEFAULT_FORMATS)
def test_a_flipped_byte_is_refused_by_every_loader(exported, tmp_path, name):
    _, files, _ = exported
    copy = copy_export(files[name], tmp_path)
    data = bytearray(copy.read_bytes())
    data[len(data) // 2] ^= 0x01
    copy.write_bytes(bytes(data))
    with pytest.raises(ExportError):
        load_exported(copy)
    with pytest.raises(StackError):                 # eval and bridge load through here
        load_policy(copy)
    result = formation("eval", str(copy), "--world", "pymunk", "--episodes", "1")
    assert result.returncode != 0 and "Traceback" not in result.stderr


def _rewrite_torchscript_meta(path: Path, dest: Path, **changes) -> Path:
    extra = {"meta.json": ""}
    module = torch.jit.load(str(path), _extra_files=extra)
    meta = json.loads(extra["meta.json"]) | changes
    torch.jit.save(module, str(dest), _extra_files={"meta.json": json.dumps(meta)})
    return dest


def test_changed_metadata_or_weights_are_refused(exported, tmp_path):
    _, files, _ = exported
    raised = _rewrite_torchscript_meta(files["torchscript"], tmp_path / "limit.pt", accel_limit=5.0)
    with pytest.raises(ExportError, match="content_sha256"):
        load_exported(raised)
    module = torch.jit.load(str(files["torchscript"]))
    with torch.no_grad():
        next(module.parameters()).add_(1e-3)
    extra = {"meta.json": ""}
    torch.jit.load(str(files["torchscript"]), _extra_files=extra)
    torch.jit.save(module, str(tmp_path / "w.pt"), _extra_files=extra)
    with pytest.raises(ExportError, match="content_sha256"):
        load_exported(tmp_path / "w.pt")
    bare = tmp_path / "bare.pt"                            # metadata removed
    torch.jit.save(torch.jit.load(str(files["torchscript"])), str(bare))
    with pytest.raises(StackError, match="meta.json"):
        load_policy(bare)


def test_onnx_metadata_edit_is_refused(exported, tmp_path):
    import onnx

    _, files, _ = exported
    proto = onnx.load(str(files["onnx"]))
    entry = proto.metadata_props[0]
    entry.value = entry.value.replace('"accel_limit": 1.0', '"accel_limit": 5.0')
    onnx.save(proto, str(tmp_path / "edited.onnx"))
    with pytest.raises(ExportError, match="content_sha256"):
        load_exported(tmp_path / "edited.onnx")


def test_unknown_layout_and_format_are_refused(exported, tmp_path):
    actor, files, reports = exported
    meta = dict(reports[0].meta) | {"layout_version": 99}
    meta.pop("content_sha256")
    import onnx

    FORMATS["onnx"].write_signed(onnx.load(str(files["onnx"])), tmp_path / "old.onnx", meta | {"file_format": "onnx"})
    with pytest.raises(ExportError, match="layout"):
        load_exported(tmp_path / "old.onnx")
    junk = tmp_path / "junk.bin"
    junk.write_bytes(np.random.default_rng(0).bytes(4096))
    with pytest.raises(StackError) as err:
        load_policy(junk)
    assert "weights_only" not in str(err.value)        # never advise unpickling a foreign file
    with zipfile.ZipFile(tmp_path / "other.zip", "w") as archive:
        archive.writestr("x/data.txt", "hello")
    with pytest.raises(ExportError, match="not an exported policy"):
        load_exported(tmp_path / "other.zip")


def test_check_catches_a_foreign_golden_file(exported, tmp_path):
    _, files, _ = exported
    foreign = copy_export(files["onnx"], tmp_path / "foreign")
    other = export_policy(make_actor(seed=1), tmp_path / "other" / "policy", dt=0.05, trained_robots=5,
                          formats=("npz",))           # the golden file is the same in every format
    golden_path(foreign).write_bytes(golden_path(other[0].path).read_bytes())
    with pytest.raises(ExportError, match="golden"):
        check_export(foreign)


def test_failed_export_leaves_no_file(tmp_path):
    actor = make_actor()
    with torch.no_grad():
        actor.embedding.embed_self[0].weight.view(-1)[0] = float("nan")
    with pytest.raises(ExportError, match="non-finite"):
        export_policy(actor, tmp_path / "bad", dt=0.05, trained_robots=5)
    assert list(tmp_path.iterdir()) == []


def test_mlp_actor_is_refused_with_a_clear_error(tmp_path):
    with pytest.raises(ExportError, match="typed"):
        export_policy(make_actor(variant="mlp"), tmp_path / "m", dt=0.05, trained_robots=5)


def test_slot_actor_exports_for_its_own_n(tmp_path):
    reports = export_policy(make_actor(variant="slot", n=3), tmp_path / "s", dt=0.05, trained_robots=3)
    for report in reports:
        assert report.meta["robot_counts"] == [3]
        assert check_export(report.path).max_abs_diff <= 1e-5


def test_the_robot_runtime_runs_the_team_sizes_a_file_was_verified_for_and_names_the_others(tmp_path):
    """deploy/robot.py warmed every file up on 5 robots, so a slot file of paper-3 could never
    start on a robot (onnxruntime: 'invalid dimensions'); a typed file met 22 robots deep in
    onnxruntime (a Gather out of bounds) and an npz one ran them unverified."""
    from deploy.robot import RobotPolicy

    scenario = make_scenario("paper-5")
    rng = np.random.default_rng(0)

    def act(policy, n):
        pos, targets = rng.uniform(0.1, 0.9, (n, 2)), rng.uniform(0.1, 0.9, (n, 2))
        return policy.act(pos[0], np.zeros(2), targets, pos[1:], np.zeros((n - 1, 2)), scenario.polygon,
                          scenario.arena)

    export_policy(make_actor(variant="slot", n=3), tmp_path / "s", dt=0.05, trained_robots=3, formats=("onnx",))
    slot = RobotPolicy(tmp_path / "s.onnx", warmup=2)
    assert act(slot, 3).valid
    with pytest.raises(ValueError, match=r"runs teams of 3 robots .* this team has 4 targets"):
        act(slot, 4)
    export_policy(make_actor(), tmp_path / "t", dt=0.05, trained_robots=5, formats=("onnx", "npz"))
    for name in ("t.onnx", "t.npz"):
        typed = RobotPolicy(tmp_path / name, warmup=2)
        assert act(typed, 21).valid
        with pytest.raises(ValueError, match=r"runs teams of 1..21 robots .* this team has 22 targets"):
            act(typed, 22)


def test_an_actor_with_token_blocks_exports_and_matches_for_every_team(tmp_path):
    """Token-mixing blocks (self-attention over T tokens, T free) through every format."""
    torch.manual_seed(3)
    actor = build_actor(ActorConfig(embed_dim=32, token_layers=1), 5)
    with torch.no_grad():                          # move the blocks off the identity
        for block in actor.mixers:
            block.out.weight.normal_(0.0, 0.3)
            block.feed[2].weight.normal_(0.0, 0.3)
    actor.eval()
    reports = export_policy(actor, tmp_path / "mixed", dt=0.05, trained_robots=5)
    generator = torch.Generator().manual_seed(4)
    for report in reports:
        assert check_export(report.path).max_abs_diff <= 1e-5
        policy = load_exported(report.path)
        for n in (1, 6, MAX_ROBOTS):
            rows, mask = random_fleet_rows(n, 8, generator, make_scenario("paper-5"), True)
            want = eager_reference(actor, rows.view(8, n, 2 * n + 1, 4), mask.view(8, n, 2 * n + 1))
            got, valid = policy.run(rows.numpy(), mask.numpy())
            assert valid.all() and float(np.abs(got - want.reshape(-1, 2).numpy()).max()) <= 1e-5


def test_cli_exports_a_checkpoint_in_the_formats_asked(tmp_path, capsys):
    config = MAPPOConfig()
    actor = build_actor(config.actor, 3)
    save_checkpoint(tmp_path / "ck.pt", {"num_robots": 3, "scenario": config.scenario_name,
                                         "accel_limit": 1.0, "config": config.to_dict(),
                                         "actor": actor.state_dict()})
    # the two quickest formats: the CLI is tested here, every format's writer on the fixture
    result = formation("export", str(tmp_path / "ck.pt"), "--out", str(tmp_path / "p"), "--format", "torchscript,npz")
    assert result.returncode == 0, result.stderr
    assert sorted(p.name for p in tmp_path.iterdir()) == ["ck.pt", "p.golden.npz", "p.npz", "p.pt"]
    for name in ("p.pt", "p.npz"):
        meta = load_exported(tmp_path / name).meta
        assert meta["trained_robots"] == 3 and meta["source"].endswith("ck.pt")
        assert meta["scenario"]["name"] == config.scenario_name
        assert meta["config"]["scenario"] == config.scenario_name
    # a stem with dots of its own keeps them (it was cut at its last dot: p.v1.npz)
    rc, _ = formation_here(capsys, "export", str(tmp_path / "ck.pt"), "--out", str(tmp_path / "p.v1.0"),
                           "--format", "npz")
    assert rc == 0 and (tmp_path / "p.v1.0.npz").exists() and (tmp_path / "p.v1.0.golden.npz").exists()
    # the refusals in this process (an exception escaping main would fail the test as it is)
    rc, err = formation_here(capsys, "export", str(tmp_path / "ck.pt"), "--out", str(tmp_path / "q"),
                             "--format", "tflite")
    assert rc == 2 and "tflite" in err
    rc, err = formation_here(capsys, "export", str(tmp_path / "nope.pt"), "--out", str(tmp_path / "q"))
    assert rc == 2 and "no file" in err and "nope.pt" in err       # a bad argument, as --help says
    rc, err = formation_here(capsys, "export", "--check", str(tmp_path / "nope.onnx"))
    assert rc == 2 and "no file" in err and "nope.onnx" in err
    (tmp_path / "random.pt").write_bytes(np.random.default_rng(1).bytes(3000))
    torch.jit.save(torch.jit.script(actor.eval()), str(tmp_path / "script.pt"))
    for wrong in (tmp_path / "p.npz", tmp_path / "p.golden.npz", tmp_path / "random.pt",
                  tmp_path / "script.pt"):       # not a checkpoint: a bad argument (2), no traceback
        rc, err = formation_here(capsys, "export", str(wrong), "--out", str(tmp_path / "r"))
        assert rc == 2 and "checkpoint" in err and "weights_only" not in err and "Traceback" not in err
    assert not list(tmp_path.glob("r.*"))


def test_the_stack_runs_every_team_the_file_runs_and_names_the_file_otherwise(exported, tmp_path):
    """A typed file runs the largest team a scenario holds (torch.export's bound included); a
    slot file meets a team of another size with an error naming the file and its N."""
    _, files, _ = exported
    big = transport_scenario(MAX_ROBOTS)
    state = FleetState(0.0, 0, big.starts.copy(), np.zeros((MAX_ROBOTS, 2)), big.targets,
                       np.array([*big.object_center, 0.0]))
    for path in files.values():
        a_nom = ControlStack(big, load_exported(path), StackConfig(safety=False, mec=False)).tick(state).a_nom
        assert a_nom.shape == (MAX_ROBOTS, 2) and np.linalg.norm(a_nom, axis=1).max() > 1e-3
    slot = export_policy(make_actor(variant="slot", n=3), tmp_path / "s", dt=0.05, trained_robots=3,
                         formats=("onnx",))[0].path
    with pytest.raises(StackError, match=rf"s\.onnx runs \[3\] robots, this fleet has {MAX_ROBOTS}"):
        ControlStack(big, load_exported(slot), StackConfig(safety=False, mec=False)).tick(state)
