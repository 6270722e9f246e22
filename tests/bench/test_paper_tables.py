"""bench/paper_tables.py: the convergence summary by hand, and a tiny real run (shape, reuse)."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[2]
sys.path.insert(0, str(ROOT))

from bench.paper_tables import main, row, zero_shot  # noqa: E402
from stack.sweep import summarize  # noqa: E402
from tests.xdist_groups import RAY  # noqa: E402


def _write_run(folder: Path, converged, evals):
    folder.mkdir(parents=True)
    (folder / "result.json").write_text(json.dumps({"converged_episode": converged, "env_steps": 99_999,
                                                    "wall_time_s": 42.0, "episodes": evals[-1][0]}))
    (folder / "eval.jsonl").write_text("".join(
        json.dumps({"episodes": e, "env_steps": e * 128, "wall_time_s": e / 10, "success_rate": s}) + "\n"
        for e, s in evals))


def test_summary_takes_the_first_of_two_evaluations_and_counts_a_failure_as_the_budget(tmp_path):
    _write_run(tmp_path / "a", 96, [(0, 0.0), (48, 0.5), (96, 0.95), (144, 0.92)])
    _write_run(tmp_path / "b", None, [(0, 0.0), (48, 0.95), (96, 0.2)])
    a, b = summarize(tmp_path / "a", 500), summarize(tmp_path / "b", 500)
    assert a == {"converged": True, "episodes": 96, "env_steps": 96 * 128, "wall_s": 9.6, "final_success": 0.92}
    assert b["converged"] is False and b["episodes"] == 500 and b["env_steps"] == 99_999
    r = row("sdpa-3", 2, [a, b])
    assert r["converged_seeds"] == 1 and r["episodes_median"] == pytest.approx((96 + 500) / 2)
    assert r["paper_episodes"] == 1200


@pytest.mark.slow
@RAY
def test_tiny_run_prints_the_documented_json_and_reuses_finished_runs(tmp_path):
    cmd = [sys.executable, str(ROOT / "bench" / "paper_tables.py"), "--seeds", "1", "--settings",
           "sdpa-3,transfer-3to4,ddq-3", "--budget-scale", "0.0015", "--out", str(tmp_path), "--json",
           "--config", json.dumps({"num_envs": 16, "eval_episodes": 4, "eval_interval": 16, "update_epochs": 1})]
    first = subprocess.run(cmd, cwd=ROOT, capture_output=True, text=True, timeout=600)
    assert first.returncode == 0, first.stderr
    doc = json.loads(first.stdout)
    assert [r["setting"] for r in doc["rows"]] == ["sdpa-3", "transfer-3to4", "ddq-3"]
    # the baseline: its own defaults (not --config's MAPPO fields), the paper's episodes x 0.0015
    config = json.loads((tmp_path / "ddq-3" / "seed-0" / "config.json").read_text())
    assert config["algo"] == "ddq" and config["total_episodes"] == doc["budgets"]["ddq-3"] == 60
    assert config["num_envs"] == 32
    ddq, sdpa = doc["rows"][2], doc["rows"][0]
    assert doc["ratios"] == [{"baseline": "ddq-3", "ratio": round(ddq["episodes_median"] / sdpa["episodes_median"], 2),
                              "lower_bound": ddq["converged_seeds"] < 1, "paper": 33.3}]
    for r in doc["rows"]:
        assert {"setting", "seeds", "converged_seeds", "episodes_median", "env_steps_median",
                "wall_s_median"} <= set(r)
        run = summarize(tmp_path / r["setting"] / "seed-0", doc["budgets"][r["setting"]])
        assert r["seeds"] == 1 and r["converged_seeds"] == int(run["converged"])
        assert r["episodes"] == [run["episodes"]] and r["env_steps_median"] == run["env_steps"]
    assert set(doc["zero_shot"]) == {"3to4", "3to5"}
    assert doc["zero_shot"]["3to5"] == pytest.approx(zero_shot(tmp_path, 0, 5), abs=1e-3)
    # the transfer run started from the 3-robot checkpoint of the same seed
    result = json.loads((tmp_path / "transfer-3to4" / "seed-0" / "result.json").read_text())
    assert result["transferred_from"] is not None
    stamp = (tmp_path / "sdpa-3" / "seed-0" / "checkpoint.pt").stat().st_mtime_ns
    again = subprocess.run(cmd, cwd=ROOT, capture_output=True, text=True, timeout=600)
    assert again.returncode == 0, again.stderr
    assert json.loads(again.stdout)["rows"] == doc["rows"]          # same runs, not retrained
    assert (tmp_path / "sdpa-3" / "seed-0" / "checkpoint.pt").stat().st_mtime_ns == stamp


def test_ratios_divide_the_baselines_median_by_sdpa_3_and_flag_unconverged_ones():
    rows = [{"setting": "sdpa-3", "episodes_median": 800.0, "converged_seeds": 3, "seeds": 3},
            {"setting": "ddq-3", "episodes_median": 40_000.0, "converged_seeds": 0, "seeds": 3},
            {"setting": "maddpg-3", "episodes_median": 4000.0, "converged_seeds": 3, "seeds": 3}]
    from bench.paper_tables import ratios

    assert ratios(rows) == [{"baseline": "maddpg-3", "ratio": 5.0, "lower_bound": False, "paper": None},
                            {"baseline": "ddq-3", "ratio": 50.0, "lower_bound": True, "paper": 33.3}]
    assert ratios(rows[1:]) == []


@pytest.mark.parametrize("scale", ["nan", "inf", "0", "-1"])
def test_budget_scale_must_be_finite_and_positive(scale, tmp_path, capsys):
    with pytest.raises(SystemExit) as info:
        main(["--settings", "sdpa-3", "--seeds", "1", "--budget-scale", scale, "--out", str(tmp_path)])
    assert info.value.code == 2 and "--budget-scale" in capsys.readouterr().err
    assert not any(tmp_path.iterdir())         # no run started


def _fake_training(monkeypatch) -> list[tuple]:
    """``train_all`` replaced by one that records (phase, cpus, [(setting, seed)]) and reports
    every run converged at 100 episodes."""
    import bench.paper_tables as paper_tables

    calls = []

    def train_all(specs, out, cpus, phase):
        calls.append((phase, cpus, [(s.group, s.seed) for s in specs]))
        return {(s.group, s.seed): {"group": s.group, "seed": s.seed, "converged": True, "episodes": 100,
                                    "env_steps": 12_800, "wall_s": 1.0} for s in specs}

    monkeypatch.setattr(paper_tables, "train_all", train_all)
    return calls


@pytest.mark.parametrize("seeds, expected", [("3,7", [3, 7]), ("2-3", [2, 3]), ("2", [0, 1])])
def test_seeds_take_sweeps_syntax_and_cpus_sets_the_trials_at_a_time(seeds, expected, tmp_path, monkeypatch,
                                                                     capsys):
    """--seeds as `formation sweep --seeds` (a count K still means 0..K-1); --cpus as sweep's."""
    calls = _fake_training(monkeypatch)
    assert main(["--seeds", seeds, "--settings", "mlp-3", "--cpus", "3", "--out", str(tmp_path), "--json"]) == 0
    assert calls == [("scratch", 3, [("mlp-3", s) for s in expected])]
    out = capsys.readouterr()
    assert json.loads(out.out)["rows"][0]["seeds"] == len(expected) and "warning" not in out.err


def test_jobs_still_sets_the_cpus_and_warns(tmp_path, monkeypatch, capsys):
    calls = _fake_training(monkeypatch)
    assert main(["--jobs", "3", "--seeds", "1", "--settings", "mlp-3", "--out", str(tmp_path), "--json"]) == 0
    assert calls[0][1] == 3
    assert "warning: --jobs is deprecated; use --cpus\n" in capsys.readouterr().err


def test_a_bad_config_exits_2_naming_the_flag_before_any_run(tmp_path, monkeypatch, capsys):
    calls = _fake_training(monkeypatch)
    with pytest.raises(SystemExit) as info:
        main(["--config", '{"nope": 1}', "--settings", "sdpa-3,transfer-3to4", "--seeds", "1",
              "--out", str(tmp_path)])
    err = capsys.readouterr().err
    assert info.value.code == 2 and "error: --config: unknown config field(s) ['nope']" in err
    assert "the base config" not in err and "Traceback" not in err
    assert calls == [] and not any(tmp_path.iterdir())


@pytest.mark.parametrize("argv, flag", [(["--seeds", "10000000000"], "--seeds"),   # refused, not built
                                        (["--seeds", "4294967296,"], "--seeds"),   # a seed past 2**32 - 1
                                        (["--seeds", "0"], "--seeds"),
                                        (["--out", "FILE"], "--out")])
def test_bad_seeds_or_an_out_that_is_a_file_exit_2_naming_the_flag(argv, flag, tmp_path, monkeypatch, capsys):
    calls = _fake_training(monkeypatch)
    (tmp_path / "FILE").write_text("")
    argv = [str(tmp_path / a) if a == "FILE" else a for a in argv]
    with pytest.raises(SystemExit) as info:
        main(["--settings", "mlp-3", *argv])
    assert info.value.code == 2 and f"argument {flag}" in capsys.readouterr().err and calls == []
