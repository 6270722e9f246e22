"""bench/train_speed.py: a tiny run prints the JSON shape other tools read."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[2]


@pytest.mark.slow
def test_train_speed_json_shape():
    out = subprocess.run([sys.executable, str(REPO / "bench" / "train_speed.py"), "--settings", "paper-3",
                          "--episodes", "16", "--repeats", "1", "--json"],
                         cwd=REPO, capture_output=True, text=True, check=True, timeout=600)
    rows = json.loads(out.stdout)["rows"]
    assert [(r["setting"], r["variant"]) for r in rows] == [("paper-3", "sdpa"), ("paper-3", "mlp")]
    for r in rows:
        assert r["episodes"] == 16
        # one environment step per environment and tick: 128 steps an episode
        assert r["env_steps_per_s"] * r["s_per_episode"] == pytest.approx(128.0)
    assert rows[1]["vs_mlp"] == 1.0
    assert rows[0]["vs_mlp"] == pytest.approx(rows[0]["s_per_episode"] / rows[1]["s_per_episode"])


def test_train_speed_rejects_an_unknown_setting():
    out = subprocess.run([sys.executable, str(REPO / "bench" / "train_speed.py"), "--settings", "paper-9"],
                         cwd=REPO, capture_output=True, text=True, timeout=120)
    assert out.returncode == 2 and "paper-9" in out.stderr and "transfer-3to5" in out.stderr
