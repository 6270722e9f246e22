import json

from stack.cli import main

TINY = '{"num_envs": 4, "rollout_steps": 16, "eval_episodes": 4, "eval_interval": 8, "progress": false}'


def test_train_writes_a_resumable_run(tmp_path):
    out = tmp_path / "run"
    assert main(["train", "--scenario", "line-1", "--episodes", "8", "--out", str(out), "--config", TINY]) == 0
    for name in ("config.json", "checkpoint.pt", "train.csv", "eval.csv", "result.json"):
        assert (out / name).is_file(), name
    config = json.loads((out / "config.json").read_text())
    assert config["scenario"] == "line-1" and config["num_envs"] == 4
    first = json.loads((out / "result.json").read_text())["episodes"]
    assert first >= 8
    assert main(["train", "--scenario", "line-1", "--episodes", "16", "--out", str(out),
                 "--config", TINY, "--resume"]) == 0
    assert json.loads((out / "result.json").read_text())["episodes"] >= 16 > first


def test_train_rejects_unknown_fields_and_resume_without_out(tmp_path, capsys):
    assert main(["train", "--config", '{"lrr": 1}', "--out", str(tmp_path / "x")]) == 2
    assert "unknown config field(s) ['lrr']" in capsys.readouterr().out
    assert main(["train", "--resume"]) == 2
    assert "--resume needs --out" in capsys.readouterr().out


def test_train_mlp_baseline(tmp_path):
    out = tmp_path / "mlp"
    assert main(["train", "--scenario", "paper-3", "--variant", "mlp", "--episodes", "4",
                 "--out", str(out), "--config", TINY]) == 0
    assert json.loads((out / "config.json").read_text())["actor"]["variant"] == "mlp"
