"""bench/generalization.py: the grid's layouts, bad options, and a tiny policy judged on the grid."""

from __future__ import annotations

import json
import subprocess
import sys
import types
from pathlib import Path

import numpy as np
import pytest

ROOT = Path(__file__).resolve().parents[2]
sys.path.insert(0, str(ROOT))

from bench.generalization import LAYOUTS, judge, layout, main, trials  # noqa: E402
from tests.xdist_groups import RAY  # noqa: E402


def test_layouts_are_the_transport_task_mirrored_enlarged_and_hexagonal():
    base, mirrored = layout("transport", 4), layout("mirrored", 4)
    np.testing.assert_array_equal(mirrored.starts, base.targets)
    np.testing.assert_array_equal(mirrored.targets, base.starts)
    large = layout("large-object", 4).polygon
    assert np.ptp(large[:, 0]) == pytest.approx(0.24) and np.ptp(large[:, 1]) == pytest.approx(0.36)
    hexagon = layout("hexagon", 4).polygon
    assert len(hexagon) == 6
    np.testing.assert_allclose(np.linalg.norm(hexagon - 0.5, axis=1), 0.15)
    with pytest.raises(ValueError, match="unknown layout"):
        layout("spiral", 3)


def test_an_unknown_layout_option_exits_2_naming_it():
    proc = subprocess.run([sys.executable, str(ROOT / "bench" / "generalization.py"), "--layouts", "spiral"],
                          capture_output=True, text=True, cwd=ROOT)
    assert proc.returncode == 2 and "spiral" in proc.stderr


def test_a_negative_penalty_curriculum_exits_2_naming_the_flag():
    proc = subprocess.run([sys.executable, str(ROOT / "bench" / "generalization.py"), "--penalty-curriculum", "-1"],
                          capture_output=True, text=True, cwd=ROOT)
    assert proc.returncode == 2 and "--penalty-curriculum" in proc.stderr


def test_the_generalist_alone_trains_with_the_penalty_curriculum(tmp_path):
    args = types.SimpleNamespace(seeds=[0, 1], team_sizes=[3, 4, 5], budget=3200, update_epochs=4,
                                 distribution=None, penalty_curriculum=3.0, config={"actor": {"token_layers": 1}})
    by_group = {(s.group, s.seed): s.fields for s in trials(args, tmp_path)}
    assert {k: f["penalty_curriculum"] for k, f in by_group.items()} == {
        ("generalist", 0): 3.0, ("generalist", 1): 3.0, ("specialist", 0): 0.0, ("specialist", 1): 0.0}
    assert by_group[("generalist", 1)]["team_sizes"] == [3, 4, 5] and by_group[("specialist", 1)]["seed"] == 1
    # --config reaches the generalist alone
    assert {k: f["actor"]["token_layers"] for k, f in by_group.items()} == {
        ("generalist", 0): 1, ("generalist", 1): 1, ("specialist", 0): 0, ("specialist", 1): 0}


def test_a_config_that_is_not_a_json_object_exits_2_naming_the_flag():
    proc = subprocess.run([sys.executable, str(ROOT / "bench" / "generalization.py"), "--config", "[1]"],
                          capture_output=True, text=True, cwd=ROOT)
    assert proc.returncode == 2 and "--config" in proc.stderr and "JSON object" in proc.stderr


def test_a_policy_is_judged_on_every_cell_of_the_grid_in_both_worlds(tmp_path):
    from controllers.mappo import MAPPOConfig, train

    small = {"embed_dim": 16, "num_heads": 2, "hidden_sizes": [32]}
    run = train(MAPPOConfig(num_envs=2, total_episodes=2, eval_episodes=2, progress=False,
                            actor=dict(small), critic=dict(small)), tmp_path / "run")
    args = types.SimpleNamespace(layouts=list(LAYOUTS), robots=[1, 3], eval_episodes=2, pymunk_episodes=1,
                                 capture_radius=[None, 0.06])
    rows = judge(run.checkpoint, args)
    cells = {(r["layout"], r["robots"], r["world"], r.get("capture_radius"), r.get("stall_radius")) for r in rows}
    assert cells == {(lay, n, w, c, st) for lay in LAYOUTS for n in (1, 3)
                     for w, c, st in (("batched", None, None), ("pymunk", 0.06, 0.12), ("pymunk", 0.06, 0.0))}
    for r in rows:
        assert r["success"] in (0.0, 0.5, 1.0) and r["collisions"] in (0.0, 0.5, 1.0)
        assert r["final_distance_mm"] is None or r["final_distance_mm"] > 0


def test_given_policies_are_judged_without_training_and_bad_ones_exit_2(tmp_path):
    from controllers.mappo import MAPPOConfig, train

    small = {"embed_dim": 16, "num_heads": 2, "hidden_sizes": [32]}
    run = train(MAPPOConfig(num_envs=2, total_episodes=2, eval_episodes=2, progress=False,
                            actor=dict(small), critic=dict(small)), tmp_path / "run")
    bench = [sys.executable, str(ROOT / "bench" / "generalization.py")]
    proc = subprocess.run([*bench, "--policies", run.checkpoint, "--layouts", "transport", "--robots", "2",
                           "--eval-episodes", "1", "--pymunk-episodes", "1", "--json", "--out", str(tmp_path / "none")],
                          capture_output=True, text=True, cwd=ROOT)
    assert proc.returncode == 0, proc.stderr
    doc = json.loads(proc.stdout)
    assert doc["train"] == {} and doc["finetune"] is None and not (tmp_path / "none").exists()
    assert [(r["policy"], r["world"], r.get("stall_radius")) for r in doc["grid"]] == [
        (run.checkpoint, "batched", None), (run.checkpoint, "pymunk", 0.12)]
    proc = subprocess.run([*bench, "--policies", str(tmp_path / "missing.pt")], capture_output=True, text=True, cwd=ROOT)
    assert proc.returncode == 2 and "missing.pt" in proc.stderr
    proc = subprocess.run([*bench, "--capture-radius", "0.12,-1"], capture_output=True, text=True, cwd=ROOT)
    assert proc.returncode == 2 and "--capture-radius" in proc.stderr


def test_the_held_out_layout_is_non_convex_and_no_distribution_draws_one():
    from bench.generalization import held_out
    from sim.distribution import DISTRIBUTIONS

    poly = held_out().polygon
    edges = np.roll(poly, -1, 0) - poly
    turns = edges[:, 0] * np.roll(edges[:, 1], -1) - edges[:, 1] * np.roll(edges[:, 0], -1)
    assert (turns < 0).sum() == 1                          # one reflex corner: an L
    for d in DISTRIBUTIONS.values():
        assert set(d.object_shapes) <= {"box", "polygon"}  # both convex by construction


@pytest.mark.slow
@RAY
def test_finetuning_starts_from_the_generalist_and_reports_its_zero_shot_success(tmp_path):
    """A tiny generalist fine-tuned on the held-out layout through Ray: one run per generalist
    seed, its episode-0 evaluation (the generalist as it is) and the episodes it took."""
    import json

    from bench.generalization import finetune, held_out
    from controllers.mappo import MAPPOConfig, train
    from stack.sweep import TrialSpec

    small = {"embed_dim": 16, "num_heads": 2, "hidden_sizes": [32]}
    config = MAPPOConfig(num_envs=2, total_episodes=2, eval_episodes=2, progress=False, team_sizes=[2, 3],
                         actor=dict(small), critic=dict(small), torch_threads=1)
    folder = tmp_path / "generalist" / "seed-0"
    train(config, folder)
    spec = TrialSpec("generalist", 0, config.to_dict(), str(folder))
    args = types.SimpleNamespace(finetune_budget=4, cpus=1)
    try:
        doc = finetune(args, [spec], tmp_path)
    finally:    # the local Ray it started in this process: left up, it runs beside every later test
        import ray

        ray.shutdown()
    assert doc["layout"] == "l-shape-4" and doc["robots"] == 4 and doc["budget"] == 4
    (row,) = doc["runs"]
    run = tmp_path / "finetune" / "seed-0"
    saved = json.loads((run / "config.json").read_text())
    assert saved["init_from"] == str(folder / "checkpoint.pt") and saved["init_keep"] == 1.0
    assert saved["scenario"]["object_vertices"] == [list(p) for p in held_out().object_vertices]
    first = json.loads((run / "eval.jsonl").read_text().splitlines()[0])
    assert first["episodes"] == 0 and row["zero_shot_success"] == first["success_rate"]
    assert row["episodes"] == 4 and not row["converged"]      # a 2-episode generalist does not converge


def test_a_negative_pymunk_episode_count_exits_2_naming_the_flag(capsys):
    """At parse time, before any training or judging (the missing --policies file would be the
    next error)."""
    with pytest.raises(SystemExit) as info:
        main(["--pymunk-episodes", "-1", "--policies", str(ROOT / "no-such-checkpoint.pt")])
    assert info.value.code == 2 and "argument --pymunk-episodes" in capsys.readouterr().err


class _Parsed(Exception):
    """Raised by the stand-in for :func:`bench.generalization.trials`: carries the parsed args."""


def _parsed(argv, monkeypatch):
    import bench.generalization as generalization

    def trials(args, out):
        raise _Parsed(args)

    monkeypatch.setattr(generalization, "trials", trials)
    with pytest.raises(_Parsed) as parsed:
        main(argv)
    return parsed.value.args[0]


def test_seeds_and_team_sizes_take_the_syntax_of_sweep_and_train(tmp_path, monkeypatch, capsys):
    """--seeds as `formation sweep --seeds` (a count K still means 0..K-1), --team-sizes as
    `formation train --team-sizes` (a list or a range), --eval-episodes for the grid's episodes."""
    args = _parsed(["--seeds", "2-3", "--team-sizes", "3-5", "--eval-episodes", "7", "--out", str(tmp_path)],
                   monkeypatch)
    assert (args.seeds, args.team_sizes, args.eval_episodes) == ([2, 3], [3, 4, 5], 7)
    assert _parsed(["--seeds", "0,5", "--out", str(tmp_path)], monkeypatch).seeds == [0, 5]
    defaults = _parsed(["--out", str(tmp_path)], monkeypatch)
    assert (defaults.seeds, defaults.team_sizes, defaults.eval_episodes) == ([0, 1, 2], [3, 4, 5], 100)
    assert capsys.readouterr().err == ""
    assert [(s.group, s.seed) for s in trials(args, tmp_path)] == [
        ("generalist", 2), ("specialist", 2), ("generalist", 3), ("specialist", 3)]


def test_episodes_still_sets_the_eval_episodes_and_warns(tmp_path, monkeypatch, capsys):
    assert _parsed(["--episodes", "7", "--out", str(tmp_path)], monkeypatch).eval_episodes == 7
    assert capsys.readouterr().err == "warning: --episodes is deprecated; use --eval-episodes\n"


@pytest.mark.parametrize("argv, message", [
    (["--config", '{"nope": 1}'], "error: --config: unknown config field(s) ['nope']"),
    (["--config", '{"lr": -1}'], "error: --config: lr must be"),
    (["--distribution", "nope"], "error: --distribution: distribution 'nope' is neither"),
    (["--team-sizes", "3,30"], "error: --team-sizes: team_sizes must be"),
])
def test_a_value_the_trainer_refuses_exits_2_naming_its_flag_before_any_run(argv, message, tmp_path, capsys):
    with pytest.raises(SystemExit) as info:
        main([*argv, "--seeds", "1", "--out", str(tmp_path / "runs")])
    err = capsys.readouterr().err
    assert info.value.code == 2 and message in err
    assert "the base config" not in err and "Traceback" not in err and not (tmp_path / "runs").exists()


@pytest.mark.parametrize("argv, flag", [(["--seeds", "1,1"], "--seeds"), (["--team-sizes", "0"], "--team-sizes"),
                                        (["--out", "FILE"], "--out")])
def test_bad_seeds_team_sizes_or_an_out_that_is_a_file_exit_2_naming_the_flag(argv, flag, tmp_path, capsys):
    (tmp_path / "FILE").write_text("")
    argv = [str(tmp_path / a) if a == "FILE" else a for a in argv]
    with pytest.raises(SystemExit) as info:
        main(argv)
    assert info.value.code == 2 and f"argument {flag}" in capsys.readouterr().err
