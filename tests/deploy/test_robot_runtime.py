"""deploy/robot.py alone on a "robot": a fresh interpreter where the project cannot be imported."""

from __future__ import annotations

import json
import shutil
import subprocess
import sys
import sysconfig
from pathlib import Path

import numpy as np
import pytest
import torch

from controllers.policy import ActorConfig, build_actor
from deploy.export import export_policy
from sim.observations import tokens
from sim.scenario import make_scenario

ROOT = Path(__file__).resolve().parents[2]
pytestmark = pytest.mark.filterwarnings("ignore:.*torch.jit.*:DeprecationWarning")

DRIVER = """
import json, sys
sys.path[:0] = [{here!r}, {site!r}]
try:
    import sim  # noqa: F401
    project_importable = True
except ImportError:
    project_importable = False
import numpy as np
import robot
policy = robot.RobotPolicy("policy.pt")
cases = np.load("cases.npz")
actions = []
for k in range(int(cases["count"])):
    pos, vel = cases[f"pos{{k}}"], cases[f"vel{{k}}"]
    n = len(pos)
    for i in range(n):
        others = [j for j in range(n) if j != i]
        a = policy.act(pos[i], vel[i], cases[f"targets{{k}}"], pos[others], vel[others],
                       cases["polygon"], cases["arena"])
        actions.append(a.tolist())
print(json.dumps({{"project_importable": project_importable, "golden_diff": policy.golden_diff,
                  "modules": sorted(m for m in sys.modules if m.split(".")[0] in
                                    ("sim", "controllers", "deploy", "stack")),
                  "actions": actions}}))
"""


def isolated_python(folder: Path, script: str) -> subprocess.CompletedProcess:
    """``python -I -S``: no user site, no site-packages .pth (so no editable project finder),
    no current directory; the driver adds only its own folder and plain site-packages."""
    site = sysconfig.get_paths()["purelib"]
    (folder / "driver.py").write_text(script.format(here=str(folder), site=site))
    return subprocess.run([sys.executable, "-I", "-S", "driver.py"], cwd=folder,
                          capture_output=True, text=True, timeout=300)


@pytest.fixture(scope="module")
def robot_dir(tmp_path_factory):
    torch.set_num_threads(1)
    torch.manual_seed(3)
    actor = build_actor(ActorConfig(embed_dim=32, velocity_damping=2.0), 5).eval()
    with torch.no_grad():
        for p in actor.parameters():
            p.mul_(3.0)
    export_dir = tmp_path_factory.mktemp("export")
    export_policy(actor, export_dir / "policy.pt", dt=0.05, trained_robots=5)
    folder = tmp_path_factory.mktemp("robot")
    for name in ("policy.pt", "policy.golden.npz"):
        shutil.copy(export_dir / name, folder / name)
    shutil.copy(ROOT / "deploy" / "robot.py", folder / "robot.py")
    return actor, folder


def test_robot_runtime_matches_eager_without_the_project(robot_dir):
    actor, folder = robot_dir
    scenario = make_scenario("paper-5")
    rng = np.random.default_rng(7)
    cases, want = {"polygon": scenario.polygon, "arena": np.asarray(scenario.arena)}, []
    counts = (1, 3, 5, 7)
    for k, n in enumerate(counts):
        pos = rng.uniform(0.05, 0.95, (n, 2))
        vel = rng.uniform(-0.4, 0.4, (n, 2))
        targets = rng.uniform(0.05, 0.95, (n, 2))
        cases.update({f"pos{k}": pos, f"vel{k}": vel, f"targets{k}": targets})
        toks, mask = tokens(*(torch.from_numpy(x)[None] for x in (pos, vel, targets)),
                            torch.from_numpy(scenario.polygon), scenario.arena)
        with torch.no_grad():
            want.append(actor(toks.float(), mask)[0].numpy())
    cases["count"] = np.array(len(counts))
    np.savez(folder / "cases.npz", **cases)
    result = isolated_python(folder, DRIVER)
    assert result.returncode == 0, result.stderr
    report = json.loads(result.stdout)
    assert report["project_importable"] is False
    assert report["modules"] == []
    assert report["golden_diff"] <= 1e-5
    got = np.array(report["actions"])
    expected = np.concatenate(want)
    assert got.shape == expected.shape == (sum(counts), 2)
    assert np.abs(expected).max() > 1e-3
    assert np.abs(got - expected).max() <= 1e-5


def test_robot_runtime_refuses_a_file_without_its_golden_file(robot_dir, tmp_path):
    _, folder = robot_dir
    for name in ("policy.pt", "robot.py"):
        shutil.copy(folder / name, tmp_path / name)
    script = ("import sys\nsys.path[:0] = [{here!r}, {site!r}]\nimport robot\n"
              "robot.RobotPolicy('policy.pt')\n")
    result = isolated_python(tmp_path, script)
    assert result.returncode != 0
    assert "RobotPolicyError" in result.stderr and "golden file" in result.stderr


def test_robot_tokens_reject_non_finite_input():
    from deploy import robot

    scenario = make_scenario("paper-3")
    with pytest.raises(ValueError, match="own_vel"):
        robot.robot_tokens([0.5, 0.2], [np.nan, 0.0], scenario.targets, np.zeros((2, 2)),
                           np.zeros((2, 2)), scenario.polygon, scenario.arena)
