"""`formation eval`: tiny runs on both worlds write JSON; bad flags give exit code 2 and a clear message."""

from __future__ import annotations

import json

import numpy as np
import pytest
import torch

from controllers.policy import ActorConfig, build_actor
from sim.pymunk_world import ModelError
from stack.cli import main
from stack.commands.latency_args import LinkArgumentError, parse_model_error


def test_parse_model_error_fields():
    me = parse_model_error("gain=0.7,lag_tau=0.05,disturbance=0.1:-0.2,delay_ticks=2")
    assert me == ModelError(gain=0.7, lag_tau=0.05, disturbance=(0.1, -0.2), delay_ticks=2)
    assert parse_model_error(None) == ModelError()
    with pytest.raises(LinkArgumentError, match="FIELD one of"):
        parse_model_error("gian=0.7")
    with pytest.raises(LinkArgumentError, match="gain=.*not a number"):
        parse_model_error("gain=fast")
    with pytest.raises(LinkArgumentError, match="gain must be > 0"):
        parse_model_error("gain=-1")
    link = parse_model_error("delay_ticks=1,delay_jitter_ticks=2,state_drop=0.2,freeze=2:40")
    assert link == ModelError(delay_ticks=1, delay_jitter_ticks=2, state_drop=0.2, freeze=(2, 40))
    with pytest.raises(LinkArgumentError, match="ROBOT:TICK"):
        parse_model_error("freeze=2")
    assert parse_model_error("delay_jitter_ticks=2,adaptive_playout=true").adaptive_playout is True
    with pytest.raises(LinkArgumentError, match="adaptive_playout='yes': write true or false"):
        parse_model_error("adaptive_playout=yes")
    # the same fields as JSON (what fleet-sim took before; the demo passes dataclasses.asdict)
    assert parse_model_error('{"gain": 0.8, "freeze": [1, 5], "playout_ticks": 3}') == \
        ModelError(gain=0.8, freeze=(1, 5), playout_ticks=3)
    with pytest.raises(LinkArgumentError, match=r"unknown fields \['gian'\]"):
        parse_model_error('{"gian": 0.8}')
    with pytest.raises(LinkArgumentError, match="not a JSON object"):
        parse_model_error('{"gain": }')


def test_scripted_pymunk_eval_writes_json(tmp_path, capsys):
    out = tmp_path / "eval.json"
    rc = main(["eval", "--policy", "scripted", "--world", "pymunk", "--episodes", "2", "--episode-ticks", "40",
               "--model-error", "gain=0.8,lag_tau=0.05", "--report", str(out)])
    assert rc == 0
    data = json.loads(out.read_text())
    assert data["world"] == "pymunk" and data["episodes"] == 2 and data["safety"] and data["mec"]
    assert data["model_error"]["gain"] == 0.8
    assert data["collision_rate"] == 0.0
    assert data["tick_p50_ms"] > 0
    assert data["command_delay_ms"] == 150.0                 # safe for 150 ms by default
    assert (data["arrival_rate"], data["arrival_tick"]) == (0.0, None)    # 40 ticks: not there yet
    assert "success_rate" in capsys.readouterr().out


def test_eval_reports_when_the_team_first_stands_on_its_targets(tmp_path):
    """The scripted controller on paper-3, bare, batched world: every episode arrives, at the
    mean of run_episode's arrival ticks for the same seeds."""
    from controllers.scripted import ScriptedController
    from sim.fleet import BatchedFleet
    from sim.scenario import make_scenario
    from stack.pipeline import ControlStack, StackConfig, run_episode

    out = tmp_path / "eval.json"
    assert main(["eval", "--policy", "scripted", "--episodes", "2", "--report", str(out)]) == 0
    data = json.loads(out.read_text())
    sc = make_scenario("paper-3")
    ticks = [run_episode(BatchedFleet(sc), ControlStack(sc, ScriptedController(sc), StackConfig(safety=False, mec=False)),
                         seed).arrival_step for seed in (0, 1)]
    assert data["arrival_rate"] == 1.0 and data["arrival_tick"] == pytest.approx(sum(ticks) / 2)
    assert 1 < data["arrival_tick"] < sc.dynamics.episode_steps


def test_exported_onnx_batched_eval_and_ignored_flags(tmp_path, capsys):
    from deploy.export import export_policy

    torch.manual_seed(0)
    actor = build_actor(ActorConfig(embed_dim=16, num_heads=2), 3).eval()
    path = export_policy(actor, tmp_path / "policy", dt=0.05, trained_robots=3, formats=("onnx",))[0].path
    out = tmp_path / "b.json"
    rc = main(["eval", str(path), "--episodes", "3", "--no-mec", "--report", str(out)])
    assert rc == 0
    data = json.loads(out.read_text())
    assert data["world"] == "batched" and data["episodes"] == 3 and not data["safety"]
    assert data["notes"] and "--mec ignored" in data["notes"][0]
    assert "--mec ignored" in capsys.readouterr().err
    rc = main(["eval", str(path), "--world", "pymunk", "--episodes", "1", "--episode-ticks", "5", "--no-safety"])
    assert rc == 0
    bare = tmp_path / "bare.pt"                 # TorchScript without the export's metadata: refused
    torch.jit.save(torch.jit.script(actor), str(bare))
    capsys.readouterr()
    assert main(["eval", str(bare), "--episodes", "1"]) == 2
    assert "meta.json" in capsys.readouterr().err


@pytest.mark.parametrize("argv, message", [
    (["eval"], "either a policy file"),
    (["eval", "x.pt", "--policy", "scripted"], "either a policy file"),
    (["eval", "/no/such/file.pt"], "does not exist"),
    (["eval", "--policy", "scripted", "--scenario", "paper-99"], "unknown scenario"),
    (["eval", "--policy", "scripted", "--world", "pymunk", "--model-error", "gain"], "FIELD=VALUE"),
    (["eval", "--policy", "scripted", "--model-error", "garbage"], "--model-error: 'garbage' is not FIELD=VALUE"),
    (["eval", "--policy", "scripted", "--fleet", "lab", "--lockstep", "--connect", "tcp/10.9.9.9:7447",
      "--insecure"], "--fleet, --lockstep, --connect, --insecure apply to --world zenoh"),
    (["eval", "--policy", "scripted", "--world", "pymunk", "--fleet", "lab"], "add --world zenoh"),
    (["eval", "--policy", "scripted", "--world", "pymunk", "--scenario", "paper-4", "--model-error", "freeze=4:20"],
     "paper-4 has 4 robots: pick a row in 0..3"),
    (["eval", "--policy", "scripted", "--intruder", "radius=0.05,x=0.5,y=0.8"], "--intruder and --track-robots need --world pymunk"),
    (["eval", "--policy", "scripted", "--track-robots"], "--intruder and --track-robots need --world pymunk"),
    (["eval", "--policy", "scripted", "--world", "zenoh", "--fleet", "f", "--intruder", "radius=0.05,x=0.5,y=0.8"],
     "fleet-sim --model-error, --intruder"),
])
def test_bad_arguments_exit_2_with_a_message(argv, message, capsys):
    assert main(argv) == 2
    assert message in capsys.readouterr().err


def test_intruders_are_kept_clear_of_in_eval_and_driven_into_without_the_filter(tmp_path):
    """A box on paper-5's top lane, two ticks of command delay: the stack keeps every robot clear
    of it in both episodes (11.8 mm when written); bare, robots drive into it in both."""
    rows = {}
    for flags in ([], ["--no-safety", "--no-mec"]):
        out = tmp_path / f"eval{len(rows)}.json"
        assert main(["eval", "--policy", "scripted", "--world", "pymunk", "--scenario", "paper-5", "--episodes", "2",
                     "--model-error", "delay_ticks=2", "--intruder", "radius=0.05,x=0.5,y=0.8", *flags,
                     "--report", str(out)]) == 0
        rows[bool(flags)] = json.loads(out.read_text())
    assert rows[False]["intruder_drive_in_rate"] == 0.0 and rows[False]["intruder_min_gap_mm"] > 5.0
    assert rows[True]["intruder_drive_in_rate"] == 1.0 and rows[True]["intruder_min_gap_mm"] < -30.0


def test_a_tracker_that_sees_the_robots_changes_nothing_while_they_all_report(tmp_path):
    """--track-robots on paper-4 with a tick of delay: each robot's own sighting never holds it,
    so the episodes are the ones without a tracker, to the last digit."""
    rows = []
    for flags in ([], ["--track-robots"]):
        out = tmp_path / f"eval{len(rows)}.json"
        assert main(["eval", "--policy", "scripted", "--world", "pymunk", "--scenario", "paper-4", "--episodes", "2",
                     "--model-error", "delay_ticks=1", *flags, "--report", str(out)]) == 0
        rows.append(json.loads(out.read_text()))
    keys = ("success_rate", "final_distance", "arrival_tick", "interventions_per_episode")
    assert [rows[0][k] for k in keys] == [rows[1][k] for k in keys]
    assert rows[0]["success_rate"] == 1.0 and "intruder_min_gap_mm" not in rows[1]


def test_a_negative_seed_is_refused_by_argparse(capsys):
    with pytest.raises(SystemExit) as exit_info:
        main(["eval", "--policy", "scripted", "--world", "pymunk", "--seed", "-1"])
    assert exit_info.value.code == 2
    assert "--seed: a seed must be in 0 .. 2**32 - 1, got -1" in capsys.readouterr().err


def test_not_a_policy_file(tmp_path, capsys):
    junk = tmp_path / "junk.pt"
    junk.write_text("hello")
    assert main(["eval", str(junk), "--world", "pymunk", "--episodes", "1"]) == 2
    assert "neither a training checkpoint nor a policy file" in capsys.readouterr().err


@pytest.mark.slow
def test_trained_checkpoint_runs_in_both_worlds(tmp_path):
    """A few seconds of real training, then the checkpoint through both worlds of `formation eval`."""
    from controllers.mappo import MAPPOConfig, train

    small = {"embed_dim": 16, "num_heads": 2, "hidden_sizes": [32]}
    train(MAPPOConfig(scenario="paper-3", num_envs=4, rollout_steps=32, update_epochs=1, num_minibatches=2,
                      total_episodes=4, eval_interval=4, eval_episodes=2, checkpoint_interval=1,
                      stop_at_convergence=False, progress=False, actor=dict(small), critic=dict(small)),
          tmp_path)
    checkpoints = sorted(tmp_path.rglob("*.pt"))
    assert checkpoints, "training wrote no checkpoint"
    for world in ("batched", "pymunk"):
        out = tmp_path / f"{world}.json"
        assert main(["eval", str(checkpoints[-1]), "--world", world, "--episodes", "2",
                     *(["--episode-ticks", "10"] if world == "pymunk" else []), "--report", str(out)]) == 0
        assert json.loads(out.read_text())["episodes"] == 2
    # --policy FILE, as bridge takes it, is the positional file; the stack runs the actor by the kernel
    flagged = tmp_path / "flagged.json"
    assert main(["eval", "--policy", str(checkpoints[-1]), "--world", "pymunk", "--episodes", "2",
                 "--episode-ticks", "10", "--report", str(flagged)]) == 0
    doc, positional = json.loads(flagged.read_text()), json.loads((tmp_path / "pymunk.json").read_text())
    assert doc["policy_runtime"] == "kernel" and doc["policy"] == str(checkpoints[-1])
    assert doc["final_distance"] == positional["final_distance"]


def test_a_scenario_file_runs_where_a_preset_does(tmp_path, capsys):
    """What `formation scenarios --show` prints is a scenario file for eval and train."""
    assert main(["scenarios", "--show", "paper-4"]) == 0
    layout = json.loads(capsys.readouterr().out) | {"name": "my-layout"}
    path = tmp_path / "layout.json"
    path.write_text(json.dumps(layout))
    out = tmp_path / "e.json"
    assert main(["eval", "--policy", "scripted", "--scenario", str(path), "--episodes", "2", "--report", str(out)]) == 0
    doc = json.loads(out.read_text())
    assert doc["scenario"] == "my-layout" and doc["num_robots"] == 4
    capsys.readouterr()
    assert main(["train", "--scenario", str(path), "--print-config"]) == 0
    assert json.loads(capsys.readouterr().out)["scenario"]["name"] == "my-layout"   # content, not path


def test_the_docking_switch_reaches_the_stack():
    import argparse

    from sim.scenario import make_scenario
    from stack.commands import argtypes
    from stack.commands.bridge import build_stack

    parser = argparse.ArgumentParser()
    argtypes.add_stage_flags(parser, None)
    assert parser.parse_args([]).docking is None
    assert parser.parse_args(["--no-docking"]).docking is False
    assert build_stack(make_scenario("paper-3"), "scripted", True, True, docking=False).docking is None
    assert build_stack(make_scenario("paper-3"), "scripted", True, True).docking is not None


def test_eval_record_records_and_draws_every_stack_episode(tmp_path, capsys):
    from stack.recorder import load_record

    folder = tmp_path / "trace"
    rc = main(["eval", "--policy", "scripted", "--world", "pymunk", "--scenario", "paper-4", "--episodes", "2",
               "--seed", "5", "--episode-ticks", "15", "--model-error", "freeze=0:5", "--record", str(folder)])
    assert rc == 0
    assert sorted(p.name for p in folder.iterdir()) == ["episode_5.npz", "episode_5.png", "episode_6.npz",
                                                        "episode_6.png"]
    record = load_record(folder / "episode_6.npz")
    assert (record.steps, record.num_robots, record.meta["seed"]) == (15, 4, 6)
    assert record.meta["scenario"]["name"] == "paper-4" and record.meta["safety"] and record.meta["mec"]
    assert record.frozen[14, 0] and not record.frozen[3, 0]
    capsys.readouterr()
    assert main(["eval", "--policy", "scripted", "--episodes", "1", "--record", str(folder)]) == 2
    assert "--record records the ControlStack's episodes: use --world pymunk" in capsys.readouterr().err
    (tmp_path / "file").write_text("x")
    with pytest.raises(SystemExit) as done:          # refused while the flags are read
        main(["eval", "--policy", "scripted", "--world", "pymunk", "--episodes", "1", "--record",
              str(tmp_path / "file")])
    assert done.value.code == 2
    assert "argument --record: " in capsys.readouterr().err


def test_the_intruder_of_the_help_text_is_traced_and_the_run_survives_it(tmp_path):
    """`--help`'s own --intruder example walks down through paper-5's object, where a robot's
    swept disc came to touch the object exactly: FCL aborted the process there (SIGABRT, a C++
    error python-fcl does not catch). Run as a user would, in a child process: exit 0, and the
    trace holds the intruder where the tracker saw it, from tick 20 down at 0.01 m a tick."""
    import subprocess
    import sys
    from pathlib import Path

    from stack.commands.argtypes import INTRUDER_HELP
    from stack.recorder import load_record

    example = "radius=0.06,x=0.5,y=1.1,vy=-0.2,enter=20"
    assert example in INTRUDER_HELP
    run = subprocess.run([sys.executable, "-m", "stack.cli", "eval", "--policy", "scripted", "--world", "pymunk",
                          "--scenario", "paper-5", "--episodes", "1", "--seed", "1", "--intruder", example,
                          "--record", str(tmp_path)], cwd=Path(__file__).resolve().parents[2], capture_output=True,
                         text=True, timeout=300)
    assert run.returncode == 0, run.stderr[-600:]
    record = load_record(tmp_path / "episode_1.npz")
    seen = record.obstacles[:, 0]
    assert record.obstacle_ids.tolist() == ["#0"] and np.isnan(seen[:20]).all()
    np.testing.assert_allclose(seen[20:25], [[0.5, 1.1 - 0.01 * k, 0.06, 0.0] for k in range(5)], atol=1e-9)


KEYS_BEFORE = {"scenario", "num_robots", "world", "policy", "episodes", "seed", "success_rate", "final_distance",
               "arrival_rate", "arrival_tick", "collision_rate", "robot_collisions", "object_collisions",
               "wall_collisions", "interventions_per_episode", "infeasible_per_episode", "fallbacks_per_episode",
               "braking_per_episode", "tracking_error_m", "tick_p50_ms", "tick_p99_ms", "safety", "mec",
               "model_error", "command_delay_ms", "policy_runtime", "notes"}


def test_the_report_and_the_records_carry_provenance_and_the_resolved_config(tmp_path, capsys):
    """--report and every --record file: git commit and package versions (sim.provenance), and
    the settings the episodes ran with, defaults filled in (the steps, the flags, the
    StackConfig used); every key the result had before is still there."""
    import importlib.metadata

    from sim.scenario import make_scenario
    from stack.recorder import load_record

    out, folder = tmp_path / "eval.json", tmp_path / "trace"
    assert main(["eval", "--policy", "scripted", "--world", "pymunk", "--episodes", "1", "--episode-ticks", "3",
                 "--no-docking", "--command-delay-ms", "100", "--model-error", "gain=0.9", "--report", str(out),
                 "--record", str(folder)]) == 0
    assert "provenance" not in capsys.readouterr().out                  # in the file, not on the screen
    data = json.loads(out.read_text())
    assert KEYS_BEFORE <= set(data)
    meta = load_record(folder / "episode_0.npz").meta
    for doc in (data, meta):
        assert doc["provenance"]["packages"]["numpy"] == importlib.metadata.version("numpy")
        git = doc["provenance"]["git"]                                  # None outside a git checkout
        assert git is None or (len(git["commit"]) == 40 and isinstance(git["dirty"], bool))
        config = doc["config"]
        assert (config["steps"], config["seed"], config["episodes"], config["world"]) == (3, 0, 1, "pymunk")
        assert config["scenario"]["name"] == "paper-3" and config["model_error"]["gain"] == 0.9
        assert (config["intruder"], config["track_robots"], config["command_delay_ms"]) == ([], False, 100.0)
        stack = config["stack"]
        assert (stack["safety"], stack["mec"], stack["docking"]["enabled"]) == (True, True, False)
        assert stack["latency"]["command_delay_s"] == pytest.approx(0.1)
    assert (data["steps"], data["docking"]) == (3, False)
    # the batched world: the scenario's episode length resolved, the scripted stack's stages off
    assert main(["eval", "--policy", "scripted", "--episodes", "1", "--report", str(out)]) == 0
    data = json.loads(out.read_text())
    assert "git" in data["provenance"] and "packages" in data["provenance"]
    assert data["config"]["steps"] == data["steps"] == make_scenario("paper-3").dynamics.episode_steps
    assert (data["config"]["stack"]["safety"], data["config"]["stack"]["mec"], data["config"]["model_error"]) == \
        (False, False, None)


def test_the_batched_world_notes_the_link_flags_it_ignores_and_records_none_for_them(tmp_path, capsys):
    """Before, `eval --command-delay-ms 50` in the batched world ran without a word and wrote 50
    into the result's config, as if a link had been simulated."""
    out = tmp_path / "eval.json"
    assert main(["eval", "--policy", "scripted", "--episodes", "1", "--command-delay-ms", "50",
                 "--model-error", "gain=0.9", "--report", str(out)]) == 0
    assert "--model-error, --command-delay-ms ignored" in capsys.readouterr().err
    data = json.loads(out.read_text())
    assert "--command-delay-ms" in data["notes"][0]
    config = data["config"]
    assert [config[k] for k in ("command_delay_ms", "model_error", "fleet", "lockstep", "intruder",
                                "track_robots")] == [None] * 6


@pytest.mark.parametrize("old, new, value", [("--steps", "--episode-ticks", "3"),
                                             ("--json", "--report", "eval.json"),
                                             ("--trace", "--record", "records")])
def test_the_old_spelling_of_a_renamed_eval_flag_still_works_and_warns(old, new, value, tmp_path, capsys):
    argv = ["eval", "--policy", "scripted", "--world", "pymunk", "--episodes", "1", "--episode-ticks", "3"]
    argv = [*(argv[:-2] if old == "--steps" else argv), old, str(tmp_path / value) if old != "--steps" else value]
    assert main(argv) == 0
    assert f"warning: {old} is deprecated; use {new}" in capsys.readouterr().err
    if old == "--json":
        assert json.loads((tmp_path / value).read_text())["steps"] == 3
    if old == "--trace":
        assert (tmp_path / value / "episode_0.npz").is_file()
