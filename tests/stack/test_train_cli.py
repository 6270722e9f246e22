import json

import pytest

from stack.cli import main

TINY = '{"num_envs": 4, "rollout_steps": 16, "eval_episodes": 4, "eval_interval": 8, "update_epochs": 1, "progress": false}'


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


def test_resume_takes_the_runs_own_config_and_refuses_a_changed_one_by_name(tmp_path, capsys):
    """``--resume --out RUN`` alone continues the run as it was configured (its seed, scenario
    and nested actor fields: not the defaults); a change outside the resumable fields is an
    error naming the field, not a traceback."""
    out = tmp_path / "run"
    tiny = json.loads(TINY) | {"seed": 5, "actor": {"embed_dim": 16}}
    assert main(["train", "--scenario", "line-1", "--episodes", "8", "--out", str(out),
                 "--config", json.dumps(tiny)]) == 0
    assert main(["train", "--resume", "--out", str(out), "--episodes", "16", "--no-stop"]) == 0
    config = json.loads((out / "config.json").read_text())
    assert (config["seed"], config["scenario"], config["actor"]["embed_dim"]) == (5, "line-1", 16)
    assert config["stop_at_convergence"] is False
    assert json.loads((out / "result.json").read_text())["episodes"] >= 16
    capsys.readouterr()
    assert main(["train", "--resume", "--out", str(out), "--config", '{"lr": 1e-3}']) == 2
    err = capsys.readouterr().err
    assert err.startswith("error: cannot resume: config field 'lr'") and "Traceback" not in err


def test_train_rejects_unknown_fields_and_resume_without_out(tmp_path, capsys):
    assert main(["train", "--config", '{"lrr": 1}', "--out", str(tmp_path / "x")]) == 2
    assert "unknown config field(s) ['lrr']" in capsys.readouterr().err
    assert main(["train", "--resume"]) == 2
    assert "--resume needs --out" in capsys.readouterr().err
    assert not (tmp_path / "x").exists()


def test_train_mlp_baseline(tmp_path):
    out = tmp_path / "mlp"
    assert main(["train", "--scenario", "paper-3", "--variant", "mlp", "--episodes", "4",
                 "--out", str(out), "--config", TINY]) == 0
    assert json.loads((out / "config.json").read_text())["actor"]["variant"] == "mlp"


def test_a_toml_file_flags_and_print_config_resolve_in_order(tmp_path, capsys):
    """Defaults < --config file < flags given; the printed configuration is itself a config file."""
    config = tmp_path / "run.toml"
    config.write_text('scenario = "paper-4"\nseed = 7\nlr = 5e-4\n[actor]\nembed_dim = 32\n'
                      "[reward_weights]\nw_arrive = 2.0\n")
    assert main(["train", "--config", str(config), "--seed", "3", "--print-config"]) == 0
    printed = capsys.readouterr().out
    resolved = json.loads(printed)
    assert (resolved["scenario"], resolved["seed"], resolved["lr"]) == ("paper-4", 3, 5e-4)
    assert resolved["actor"]["embed_dim"] == 32 and resolved["actor"]["num_heads"] == 4
    assert resolved["reward_weights"]["w_arrive"] == 2.0
    assert resolved["reward_weights"]["assignment_power"] == 2.0   # the training reward's, kept
    again = tmp_path / "resolved.json"
    again.write_text(printed)
    assert main(["train", "--config", str(again), "--print-config"]) == 0
    assert json.loads(capsys.readouterr().out) == resolved


@pytest.mark.parametrize("text, message", [
    ("lr = [", "not valid TOML"),
    ("[actor]\nembed_dimm = 3\n", "embed_dimm"),
    ("[reward_weights]\nw_team = 1.0\n", "w_team"),
])
def test_a_bad_config_file_names_the_problem(tmp_path, capsys, text, message):
    config = tmp_path / "bad.toml"
    config.write_text(text)
    assert main(["train", "--config", str(config), "--print-config"]) == 2
    err = capsys.readouterr().err
    assert message in err and err.startswith("error:")


def test_config_that_is_neither_file_nor_json_is_refused(capsys):
    assert main(["train", "--config", "no/such/file.toml", "--print-config"]) == 2
    assert "--config: no file 'no/such/file.toml' (looked in " in capsys.readouterr().err
    assert main(["train", "--config", "lr=1e-3", "--print-config"]) == 2
    assert "neither a file nor inline JSON" in capsys.readouterr().err
    assert main(["train", "--scenario", "no/such/layout.json", "--print-config"]) == 2
    assert "no file 'no/such/layout.json'" in capsys.readouterr().err


def test_inline_json_longer_than_a_file_name_is_read(capsys):
    """A whole printed configuration given inline (well over the 255 bytes a file name may have)
    is read as JSON, not stat'ed as a path (that raised OSError: File name too long)."""
    assert main(["train", "--scenario", "paper-4", "--print-config"]) == 0
    printed = capsys.readouterr().out
    assert len(printed) > 1000
    assert main(["train", "--config", printed, "--print-config"]) == 0
    assert json.loads(capsys.readouterr().out) == json.loads(printed)
    assert main(["train", "--config", "x" * 300, "--print-config"]) == 2
    assert "neither a file nor inline JSON" in capsys.readouterr().err
