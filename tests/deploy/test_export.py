"""TorchScript export: matches the eager actor for N = 1..16, verifies itself, --check catches tampering."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import torch

from controllers.mappo.checkpoint import save_checkpoint
from controllers.mappo.config import MAPPOConfig
from controllers.policy import ActorConfig, build_actor
from deploy.export import (
    ExportError,
    check_export,
    export_policy,
    golden_path,
    load_policy,
    weights_sha256,
)
from sim.observations import LAYOUT_VERSION

ROOT = Path(__file__).resolve().parents[2]
pytestmark = pytest.mark.filterwarnings("ignore:.*torch.jit.*:DeprecationWarning")


def make_actor(seed: int = 0, variant: str = "typed", n: int = 5):
    torch.manual_seed(seed)
    actor = build_actor(ActorConfig(variant=variant, embed_dim=32, velocity_damping=2.0), n)
    with torch.no_grad():  # larger outputs than the tiny initial gain, so differences show
        for p in actor.parameters():
            p.mul_(3.0)
    return actor.eval()


@pytest.fixture(scope="module")
def exported(tmp_path_factory):
    torch.set_num_threads(1)
    out = tmp_path_factory.mktemp("export") / "policy.pt"
    actor = make_actor()
    report = export_policy(actor, out, dt=0.05, trained_robots=5, config={"note": "test"})
    return actor, out, report


def formation(*args: str) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-m", "stack.cli", *args], cwd=ROOT,
                          capture_output=True, text=True, timeout=300)


def test_reloaded_file_matches_eager_for_every_n_and_batch(exported):
    actor, out, report = exported
    module = torch.jit.load(str(out))
    generator = torch.Generator().manual_seed(123)
    worst = 0.0
    for n in range(1, 17):
        for batch in (1, 16):
            obs = torch.randn(batch, n, 2 * n + 1, 4, generator=generator)
            mask = torch.ones(batch, n, 2 * n + 1, dtype=torch.bool)
            with torch.no_grad():
                want = actor(obs, mask)
                got = module(obs, mask)
                one = module.act(obs[:, n - 1], mask[:, n - 1])
            assert got.shape == (batch, n, 2)
            assert float(want.abs().max()) > 1e-3  # the outputs are not trivially zero
            worst = max(worst, float((got - want).abs().max()),
                        float((one - want[:, n - 1]).abs().max()))
    assert worst <= 1e-5
    assert report.max_abs_diff <= 1e-5 and report.cases >= 16 * 2 * 2 * 2


def test_metadata_travels_inside_the_file(exported):
    actor, out, _ = exported
    _, meta = load_policy(out)
    assert meta["layout_version"] == LAYOUT_VERSION
    assert meta["dt"] == 0.05 and meta["accel_limit"] == 1.0
    assert meta["trained_robots"] == 5 and meta["robot_counts"] == "any"
    assert meta["torch_version"] == torch.__version__
    assert meta["weights_sha256"] == weights_sha256(torch.jit.load(str(out)))
    assert meta["golden_file"] == golden_path(out).name == "policy.golden.npz"
    with np.load(golden_path(out)) as golden:
        assert list(golden["counts"]) == [1, 2, 3, 5, 8, 16]
        assert golden["n5_tokens"].shape == (1, 5, 11, 4)


def test_check_passes_on_the_exported_file(exported):
    _, out, _ = exported
    assert check_export(out).max_abs_diff <= 1e-5
    result = formation("export", "--check", str(out))
    assert result.returncode == 0, result.stderr
    assert "OK" in result.stdout


def _copy_export(out: Path, dest: Path) -> Path:
    dest.mkdir()
    (dest / out.name).write_bytes(out.read_bytes())
    golden = golden_path(out)
    (dest / golden.name).write_bytes(golden.read_bytes())
    return dest / out.name


def test_check_catches_a_changed_weight(exported, tmp_path):
    _, out, _ = exported
    copy = _copy_export(out, tmp_path / "tampered")
    extra = {"meta.json": ""}
    module = torch.jit.load(str(copy), _extra_files=extra)
    with torch.no_grad():
        next(module.parameters()).add_(1e-3)
    torch.jit.save(module, str(copy), _extra_files=extra)
    with pytest.raises(ExportError, match="checksum"):
        check_export(copy)
    result = formation("export", "--check", str(copy))
    assert result.returncode == 1 and "checksum" in result.stderr


def test_check_catches_corrupt_bytes_and_a_foreign_golden_file(exported, tmp_path):
    _, out, _ = exported
    corrupt = _copy_export(out, tmp_path / "corrupt")
    data = bytearray(corrupt.read_bytes())
    data[len(data) // 2: len(data) // 2 + 64] = b"\x00" * 64
    corrupt.write_bytes(bytes(data))
    with pytest.raises(ExportError):
        check_export(corrupt)
    foreign = _copy_export(out, tmp_path / "foreign")
    other = make_actor(seed=1)
    other_out = tmp_path / "other" / "policy.pt"
    export_policy(other, other_out, dt=0.05, trained_robots=5)
    golden_path(foreign).write_bytes(golden_path(other_out).read_bytes())
    with pytest.raises(ExportError, match="golden"):
        check_export(foreign)


def test_failed_export_leaves_no_file(tmp_path):
    actor = make_actor()
    with torch.no_grad():
        next(actor.embedding.embed_self.parameters()).view(-1)[0] = float("nan")
    out = tmp_path / "bad.pt"
    with pytest.raises(ExportError, match="differs"):
        export_policy(actor, out, dt=0.05, trained_robots=5)
    assert list(tmp_path.iterdir()) == []


def test_mlp_actor_is_refused_with_a_clear_error(tmp_path):
    with pytest.raises(ExportError, match="typed"):
        export_policy(make_actor(variant="mlp"), tmp_path / "m.pt", dt=0.05, trained_robots=5)


def test_slot_actor_exports_for_its_own_n(tmp_path):
    report = export_policy(make_actor(variant="slot", n=3), tmp_path / "s.pt", dt=0.05,
                           trained_robots=3)
    assert report.meta["robot_counts"] == [3]
    assert check_export(tmp_path / "s.pt").max_abs_diff <= 1e-5


def test_cli_exports_a_checkpoint(tmp_path):
    config = MAPPOConfig()
    actor = build_actor(config.actor, 3)
    save_checkpoint(tmp_path / "ck.pt", {"num_robots": 3, "scenario": config.scenario_name,
                                         "accel_limit": 1.0, "config": config.to_dict(),
                                         "actor": actor.state_dict()})
    result = formation("export", str(tmp_path / "ck.pt"), "--out", str(tmp_path / "p.pt"))
    assert result.returncode == 0, result.stderr
    _, meta = load_policy(tmp_path / "p.pt")
    assert meta["trained_robots"] == 3 and meta["source"].endswith("ck.pt")
    assert json.dumps(meta["config"])  # the training config travels too
    missing = formation("export", str(tmp_path / "nope.pt"), "--out", str(tmp_path / "q.pt"))
    assert missing.returncode == 1 and "does not exist" in missing.stderr
