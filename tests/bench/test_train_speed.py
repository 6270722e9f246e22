"""bench/train_speed.py: a tiny run prints the JSON shape other tools read."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import pytest

from bench import train_speed

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
    sdpa, mlp = rows
    # The MLP-MAPPO update, worked by hand: 10 epochs x 4 minibatches of 128 teams x 3 robots
    # (384 rows); actor 14 -> 128 -> 2 (the flat vector of 3 robots: 4 * 3 + 2 numbers), critic
    # 56 -> 128 -> 1 (its own vector and the team's). A layer's forward is 2 * rows * in * out;
    # its backward adds the weight gradient (1x) and, above the first layer, the input gradient (1x)
    def layers(*shapes):
        first, *rest = shapes
        return 2 * 384 * (2 * first[0] * first[1] + sum(3 * i * o for i, o in rest))
    minibatch = layers((14, 128), (128, 2)) + layers((56, 128), (128, 1))
    assert mlp["update_gflop_per_episode"] == pytest.approx(10 * 4 * minibatch / 4 / 1e9)  # 4 episodes an update
    assert sdpa["update_gflop_per_episode"] > 10 * mlp["update_gflop_per_episode"]
    rate = json.loads(out.stdout)["matmul_gflop_s"] * 1e9
    for r in rows:
        # the floor is the arithmetic at the best matmul rate, so the update measured cannot beat it
        assert r["update_floor_s_per_episode"] == pytest.approx(r["update_gflop_per_episode"] * 1e9 / rate)
        assert r["update_floor_s_per_episode"] < r["update_share"] * r["s_per_episode"]
    assert sdpa["floor_vs_mlp"] == pytest.approx(sdpa["update_floor_s_per_episode"] / mlp["s_per_episode"])


def test_train_speed_rejects_an_unknown_setting():
    out = subprocess.run([sys.executable, str(REPO / "bench" / "train_speed.py"), "--settings", "paper-9"],
                         cwd=REPO, capture_output=True, text=True, timeout=120)
    assert out.returncode == 2 and "paper-9" in out.stderr and "transfer-3to5" in out.stderr


def _fake_timings(monkeypatch) -> list[tuple]:
    """No training: a typed run takes 4 s, an MLP run 1 s, each 16 episodes of 128 steps; the
    calls made (scenario, actor, init_from) are returned."""
    calls: list[tuple] = []

    def timed_run(scenario, actor, episodes, seed, init_from):
        calls.append((scenario, actor, init_from))
        return {"episodes": 16, "env_steps": 16 * 128, "wall_s": {"typed": 4.0, "mlp": 1.0}[actor], "update_s": 0.5}

    monkeypatch.setattr(train_speed, "timed_run", timed_run)
    monkeypatch.setattr(train_speed, "matmul_rate", lambda: 1e9)
    monkeypatch.setattr(train_speed, "source_checkpoint", lambda folder, seed: "source.pt")
    monkeypatch.setattr(train_speed, "update_flops", lambda config: (10**9, 16 * 128))
    return calls


def test_transfer_alone_times_its_mlp_peer_on_paper_5(monkeypatch):
    """--settings transfer-3to5: the peer, MLP-MAPPO from scratch on paper-5, is timed in the same
    run; the transfer's vs_mlp = (4 s / 16) / (1 s / 16) = 4."""
    calls = _fake_timings(monkeypatch)
    rows, _ = train_speed.measure(["transfer-3to5"], episodes=16, repeats=1, seed=0)
    assert calls == [("paper-5", "mlp", None), ("paper-5", "typed", "source.pt")]
    assert [(r["setting"], r["variant"]) for r in rows] == [
        ("paper-5", "mlp"), ("transfer-3to5", "sdpa"), ("transfer-3to5", "mlp")]
    peer, transfer, no_mlp = rows
    assert peer["s_per_episode"] == 1.0 / 16 and peer["vs_mlp"] == 1.0
    assert transfer["s_per_episode"] == 4.0 / 16 and transfer["vs_mlp"] == 4.0
    assert no_mlp["s_per_episode"] is None and no_mlp["vs_mlp"] is None and "another N" in no_mlp["note"]
    # floor: 1 GFLOP an update learning from 2048 steps, 1/16 GFLOP an episode of 128 steps, 1/16 s
    # at 1 GFLOP/s: as long as the peer's whole episode
    assert transfer["update_floor_s_per_episode"] == 1.0 / 16 and transfer["floor_vs_mlp"] == 1.0


def test_transfer_beside_paper_5_times_the_peer_once(monkeypatch):
    calls = _fake_timings(monkeypatch)
    rows, _ = train_speed.measure(["paper-5", "transfer-3to5"], episodes=16, repeats=1, seed=0)
    assert calls.count(("paper-5", "mlp", None)) == 1
    assert [(r["setting"], r["variant"]) for r in rows] == [
        ("paper-5", "sdpa"), ("paper-5", "mlp"), ("transfer-3to5", "sdpa"), ("transfer-3to5", "mlp")]
    assert rows[2]["vs_mlp"] == 4.0
