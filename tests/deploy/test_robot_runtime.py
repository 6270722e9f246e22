"""deploy/robot.py alone on a "robot": a fresh virtual environment with only numpy and
onnxruntime installed (no torch, no project), running the exported ONNX file."""

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
from deploy.export import export_policy
from sim.observations import tokens
from sim.scenario import make_scenario
from tests.xdist_groups import ROBOT_RUNTIME

ROOT = Path(__file__).resolve().parents[2]
pytestmark = [pytest.mark.filterwarnings("ignore:.*torch.jit.*:DeprecationWarning"), ROBOT_RUNTIME]

DRIVER = """
import importlib.util, json, sys
sys.path.insert(0, {here!r})
import numpy as np
import robot
policy = robot.RobotPolicy("policy.onnx")
cases = np.load("cases.npz")
actions, valid = [], []
for k in range(int(cases["count"])):
    pos, vel = cases[f"pos{{k}}"], cases[f"vel{{k}}"]
    n = len(pos)
    for i in range(n):
        others = [j for j in range(n) if j != i]
        a, ok = policy.act(pos[i], vel[i], cases[f"targets{{k}}"], pos[others], vel[others],
                           cases["polygon"], cases["arena"])
        actions.append(a.tolist())
        valid.append(ok)
bad, ok = policy.act([0.5, float("nan")], [0, 0], cases["targets0"], np.zeros((0, 2)), np.zeros((0, 2)),
                     cases["polygon"], cases["arena"])
print(json.dumps({{"torch": importlib.util.find_spec("torch") is not None,
                  "project": any(importlib.util.find_spec(m) is not None
                                 for m in ("sim", "controllers", "stack")),
                  "golden_diff": policy.golden_diff, "actions": actions, "valid": valid,
                  "nan_case": [bad.tolist(), ok]}}))
"""


@pytest.fixture(scope="module")
def robot_python(tmp_path_factory) -> Path:
    """A virtual environment with numpy and onnxruntime alone (from the package index)."""
    env = tmp_path_factory.mktemp("robot-venv") / "venv"
    subprocess.run([sys.executable, "-m", "venv", str(env)], check=True, timeout=300)
    python = env / "bin" / "python"
    install = subprocess.run([str(python), "-m", "pip", "install", "--quiet", "--disable-pip-version-check",
                              "numpy", "onnxruntime"], capture_output=True, text=True, timeout=600)
    assert install.returncode == 0, install.stderr[-2000:]
    return python


def robot_run(python: Path, folder: Path, script: str) -> subprocess.CompletedProcess:
    (folder / "driver.py").write_text(script.format(here=str(folder)))
    return subprocess.run([str(python), "-I", "driver.py"], cwd=folder, capture_output=True,
                          text=True, timeout=300)


@pytest.fixture(scope="module")
def robot_dir(tmp_path_factory):
    torch.set_num_threads(1)
    torch.manual_seed(3)
    actor = build_actor(ActorConfig(embed_dim=32, velocity_damping=2.0), 5).eval()
    with torch.no_grad():           # outputs up to the limit, as a trained actor gives
        for p in actor.parameters():
            p.mul_(1.5)
    export_dir = tmp_path_factory.mktemp("export")
    export_policy(actor, export_dir / "policy", dt=0.05, trained_robots=5, formats=("onnx",))
    folder = tmp_path_factory.mktemp("robot")
    for name in ("policy.onnx", "policy.golden.npz"):
        shutil.copy(export_dir / name, folder / name)
    shutil.copy(ROOT / "deploy" / "robot.py", folder / "robot.py")
    return actor, folder


@pytest.mark.slow
def test_robot_runtime_matches_eager_with_only_numpy_and_onnxruntime(robot_dir, robot_python):
    actor, folder = robot_dir
    scenario = make_scenario("paper-5")
    rng = np.random.default_rng(7)
    cases, want = {"polygon": scenario.polygon, "arena": np.asarray(scenario.arena)}, []
    counts = (1, 3, 5, 7, 16)
    for k, n in enumerate(counts):
        pos = rng.uniform(0.05, 0.95, (n, 2))
        vel = rng.uniform(-0.4, 0.4, (n, 2))
        targets = rng.uniform(0.05, 0.95, (n, 2))
        cases.update({f"pos{k}": pos, f"vel{k}": vel, f"targets{k}": targets})
        toks, mask = tokens(*(torch.from_numpy(x)[None] for x in (pos, vel, targets)),
                            torch.from_numpy(scenario.polygon), scenario.arena)
        with torch.no_grad():
            a = actor(toks.float(), mask)[0]
        want.append((a * torch.clamp(1.0 / torch.linalg.vector_norm(a, dim=-1, keepdim=True), max=1.0)).numpy())
    cases["count"] = np.array(len(counts))
    np.savez(folder / "cases.npz", **cases)
    result = robot_run(robot_python, folder, DRIVER)
    assert result.returncode == 0, result.stderr
    report = json.loads(result.stdout)
    assert report["torch"] is False and report["project"] is False
    assert report["golden_diff"] <= 1e-5
    got = np.array(report["actions"])
    expected = np.concatenate(want)
    assert got.shape == expected.shape == (sum(counts), 2)
    assert np.abs(expected).max() > 1e-2 and all(report["valid"])
    assert np.abs(got - expected).max() <= 1e-5
    assert np.linalg.norm(got, axis=1).max() <= 1.0 + 1e-6
    assert report["nan_case"] == [[0.0, 0.0], False]      # a NaN state brakes, never NaN


@pytest.mark.slow
@pytest.mark.parametrize("damage", ["golden_missing", "byte_flipped", "golden_foreign"])
def test_robot_runtime_refuses_an_untrustworthy_file(robot_dir, robot_python, tmp_path, damage):
    _, folder = robot_dir
    for name in ("policy.onnx", "robot.py", "policy.golden.npz"):
        shutil.copy(folder / name, tmp_path / name)
    if damage == "golden_missing":
        (tmp_path / "policy.golden.npz").unlink()
    elif damage == "byte_flipped":
        data = bytearray((tmp_path / "policy.onnx").read_bytes())
        data[len(data) // 2] ^= 0x10
        (tmp_path / "policy.onnx").write_bytes(bytes(data))
    else:
        with np.load(folder / "policy.golden.npz") as golden:
            changed = dict(golden)
        changed["n5_actions"] = changed["n5_actions"] + 1e-3
        np.savez(tmp_path / "policy.golden.npz", **changed)
    script = "import sys\nsys.path.insert(0, {here!r})\nimport robot\nrobot.RobotPolicy('policy.onnx')\n"
    result = robot_run(robot_python, tmp_path, script)
    assert result.returncode != 0
    expected = {"golden_missing": "golden file", "byte_flipped": "content_sha256",
                "golden_foreign": "does not belong"}[damage]
    assert "RobotPolicyError" in result.stderr and expected in result.stderr
