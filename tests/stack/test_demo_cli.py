import json

from stack.cli import main


def test_demo_runs_end_to_end_and_writes_metrics(tmp_path):
    assert main(["demo", "--out", str(tmp_path), "--episodes", "1"]) == 0
    data = json.loads((tmp_path / "metrics.json").read_text())
    assert data["world"] == "pymunk" and data["model_error"]["gain"] == 0.8
    for name in ("paper-3", "paper-4", "paper-5"):
        r = data["results"][name]
        assert r["episodes"] == 1
        assert r["success_rate"] == 1.0 and r["collision_episodes"] == 0
        assert r["final_distance"] < 0.05
