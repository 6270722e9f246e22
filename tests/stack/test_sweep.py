"""formation sweep: the grid, the aggregation by hand, and real Ray Tune runs (reuse, Ctrl-C)."""

from __future__ import annotations

import argparse
import json
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest

from stack.commands.sweep import seeds_arg
from stack.sweep import (
    LOCAL_ONLY_ENV,
    SweepError,
    aggregate,
    check_ray_address,
    grid_trials,
    median_ci,
    parse_grid_option,
    run_trials,
)
from tests.xdist_groups import RAY

ROOT = Path(__file__).resolve().parents[2]
TINY = {"scenario": "paper-3", "num_envs": 8, "eval_interval": 16, "eval_episodes": 8,
        "checkpoint_interval": 8, "update_epochs": 1}   # Ray and the run folders are tested, not learning


def test_grid_options_read_values_as_json_and_keep_other_text():
    assert parse_grid_option("lr=3e-4,1e-3") == ("lr", [3e-4, 1e-3])
    assert parse_grid_option("actor.variant=typed,mlp") == ("actor.variant", ["typed", "mlp"])
    assert parse_grid_option("norm_adv=true,false") == ("norm_adv", [True, False])
    with pytest.raises(SweepError, match="KEY=V1,V2"):
        parse_grid_option("lr")


def test_seeds_are_a_count_a_range_or_a_list():
    assert seeds_arg("3") == [0, 1, 2] and seeds_arg("2-4") == [2, 3, 4] and seeds_arg("0,7") == [0, 7]
    for bad in ("x", "1,1"):
        with pytest.raises(argparse.ArgumentTypeError):
            seeds_arg(bad)
    with pytest.raises(argparse.ArgumentTypeError, match=r"a count of seeds must be >= 1.*--seeds 0,"):
        seeds_arg("0")                        # it said 'seeds must be ... >= 0, got 0'
    assert seeds_arg("0,") == [0]


def test_a_damaged_sweep_file_is_named_not_a_traceback(tmp_path, capsys):
    from stack.cli import main

    (tmp_path / "sweep.json").write_text("{bad")
    for args in (["--resume"], ["--seeds", "1", "--episodes", "4"]):
        assert main(["sweep", *args, "--out", str(tmp_path)]) == 2
        assert f"{tmp_path / 'sweep.json'} is not a sweep's file" in capsys.readouterr().err


def test_the_grid_is_the_cross_product_with_nested_keys_and_checked_fields(tmp_path):
    trials = grid_trials({"scenario": "paper-3", "total_episodes": 64},
                         [("lr", [3e-4, 1e-3]), ("actor.embed_dim", [16, 32])], [0, 5], tmp_path)
    assert len(trials) == 2 * 2 * 2
    assert {(t.fields["lr"], t.fields["actor"]["embed_dim"], t.seed) for t in trials} == {
        (lr, d, s) for lr in (3e-4, 1e-3) for d in (16, 32) for s in (0, 5)}
    assert trials[0].group == 'lr=0.0003,actor.embed_dim=16' and trials[0].budget == 64
    assert trials[1].folder == str(tmp_path.resolve() / "trials" / "000" / "seed-5")
    assert all(t.fields["torch_threads"] == 1 and t.fields["progress"] is False for t in trials)
    with pytest.raises(SweepError, match="lr=-1.*lr"):
        grid_trials({}, [("lr", [-1])], [0], tmp_path)
    with pytest.raises(SweepError, match=r"actor.nope=1: unknown actor field\(s\) \['nope'\]"):
        grid_trials({}, [("actor.nope", [1])], [0], tmp_path)


def test_median_interval_by_hand():
    assert median_ci([700, 700, 700]) == (700.0, 700.0)
    # a resample's median is 5000 when 3+ of its 5 draws are: P = 0.058 > 0.025, and likewise
    # 100; so the 95 % interval spans the whole sample
    assert median_ci([100, 200, 300, 400, 5000]) == (100.0, 5000.0)
    # nine values: an end value is the median only if 5+ of 9 draws are it (P = 0.0015)
    low, high = median_ci([100, 200, 300, 400, 500, 600, 700, 800, 5000])
    assert 100 < low <= 500 <= high < 5000
    assert median_ci([100, 200, 300, 400, 500, 600, 700, 800, 5000]) == (low, high)  # seeded


def test_rows_aggregate_each_group_over_its_seeds():
    runs = [{"group": "a", "seed": s, "converged": c, "episodes": e, "wall_s": w, "final_success": f}
            for s, c, e, w, f in ((0, True, 400, 10.0, 0.95), (1, False, 1000, 30.0, 0.5),
                                  (2, True, 600, 20.0, 0.92))]
    runs.append({"group": "b", "seed": 0, "converged": True, "episodes": 50, "wall_s": 1.0,
                 "final_success": 1.0})
    a, b = aggregate(runs)
    assert a["group"] == "a" and a["seeds"] == [0, 1, 2] and a["converged_seeds"] == 2
    assert a["episodes_median"] == 600 and (a["episodes_min"], a["episodes_max"]) == (400, 1000)
    assert a["wall_s_median"] == 20.0 and a["final_success_median"] == 0.92
    assert b["episodes_ci95"] == [50.0, 50.0]


def test_finished_trials_are_summarised_without_starting_ray(tmp_path, monkeypatch):
    trials = grid_trials({"scenario": "paper-3", "total_episodes": 96}, [], [0, 1], tmp_path)
    for t, converged in zip(trials, (48, None), strict=True):
        folder = Path(t.folder)
        folder.mkdir(parents=True)
        (folder / "config.json").write_text(json.dumps(t.fields))
        (folder / "result.json").write_text(json.dumps({"converged_episode": converged, "episodes": 96,
                                                        "env_steps": 12288, "wall_time_s": 30.0}))
        (folder / "eval.jsonl").write_text("".join(json.dumps(
            {"episodes": e, "env_steps": e * 128, "wall_time_s": e / 4, "success_rate": s}) + "\n"
            for e, s in ((48, 0.95), (96, 0.9))))
    monkeypatch.setitem(sys.modules, "ray", None)     # importing Ray would now fail
    rows = run_trials(trials, tmp_path)
    assert [(r["seed"], r["converged"], r["episodes"], r["wall_s"]) for r in rows] == [
        (0, True, 48, 12.0), (1, False, 96, 30.0)]
    Path(trials[1].folder, "result.json").unlink()    # one left to run: that one needs Ray
    with pytest.raises(SweepError, match="Ray Tune, which is not installed"):
        run_trials(trials, tmp_path)


def _sweep(out: Path, *extra: str, config: dict = TINY, cpus: int = 2, **kw) -> subprocess.Popen:
    cmd = [sys.executable, "-m", "stack.cli", "sweep", "--config", json.dumps(config), "--cpus", str(cpus),
           "--out", str(out), *extra]
    return subprocess.Popen(cmd, cwd=ROOT, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, **kw)


@pytest.mark.slow
@RAY
def test_a_ray_sweep_writes_run_folders_and_a_table_and_reuses_finished_trials(tmp_path):
    proc = _sweep(tmp_path, "--episodes", "16", "--seeds", "1", "--grid", "lr=3e-4,1e-3", "--json")
    out, err = proc.communicate(timeout=600)
    assert proc.returncode == 0, err
    doc = json.loads(out)   # stdout is the document alone: Tune reports on stderr
    assert [r["group"] for r in doc["rows"]] == ["lr=0.0003", "lr=0.001"]
    for k, lr in enumerate((3e-4, 1e-3)):
        folder = tmp_path / "trials" / f"{k:03d}" / "seed-0"
        assert json.loads((folder / "config.json").read_text())["lr"] == lr
        result = json.loads((folder / "result.json").read_text())
        assert doc["rows"][k]["episodes"] == [result["episodes"]] == [16]
        assert (folder / "run.json").exists()
    assert json.loads((tmp_path / "sweep.json").read_text())["rows"] == doc["rows"]
    stamp = (tmp_path / "trials" / "000" / "seed-0" / "result.json").stat().st_mtime_ns
    again = _sweep(tmp_path, "--episodes", "16", "--seeds", "1", "--grid", "lr=3e-4,1e-3", "--json")
    out, err = again.communicate(timeout=600)
    assert again.returncode == 0, err
    assert json.loads(out)["rows"] == doc["rows"]
    assert (tmp_path / "trials" / "000" / "seed-0" / "result.json").stat().st_mtime_ns == stamp
    other = _sweep(tmp_path, "--episodes", "16", "--seeds", "2")   # another sweep, same folder
    _, err = other.communicate(timeout=120)
    assert other.returncode == 2 and "--resume" in err


@pytest.mark.slow
@RAY
def test_ctrl_c_stops_a_sweep_that_resume_then_finishes_from_its_checkpoints(tmp_path):
    """One CPU, two seeds: Ctrl-C comes while seed 0 runs and seed 1 has not started (a pending
    trial has no config in Tune's results: reading it crashed the stop). The moment is set by
    seed 0's first checkpoint (after 2 of its 16 iterations), not by the clock, and Tune stops
    the trial at its next iteration's report. Before the trials reported every iteration, Tune
    let a running trial train on for its 10 s grace period, and on a fast machine seed 0
    finished in it; the 10 update epochs keep its remaining iterations longer than the stop
    takes (with TINY's one it finished first beside another test on a 2-core machine)."""
    proc = _sweep(tmp_path, "--episodes", "32", "--seeds", "2",
                  config=TINY | {"checkpoint_interval": 2, "update_epochs": 10}, cpus=1)
    seed0 = tmp_path / "trials" / "000" / "seed-0"
    deadline = time.monotonic() + 300
    while not (seed0 / "checkpoint.pt").exists() and time.monotonic() < deadline and proc.poll() is None:
        time.sleep(0.5)
    assert (seed0 / "checkpoint.pt").exists(), proc.communicate()[1]
    proc.send_signal(signal.SIGINT)
    _, err = proc.communicate(timeout=120)
    assert proc.returncode == 130 and "--resume --out" in err, err
    assert "Traceback" not in err and "Tuner.restore" not in err, err    # one hint: ours
    logged = (seed0 / "train.jsonl").read_text().splitlines()
    assert not (seed0 / "result.json").exists()
    assert not (tmp_path / "trials" / "000" / "seed-1" / "result.json").exists()
    resumed = subprocess.run([sys.executable, "-m", "stack.cli", "sweep", "--resume", "--out",
                              str(tmp_path), "--json"], cwd=ROOT, capture_output=True, text=True,
                             timeout=600)
    assert resumed.returncode == 0, resumed.stderr
    assert json.loads(resumed.stdout)["rows"][0]["episodes"] == [32, 32]
    iterations = [json.loads(line)["iteration"] for line in (seed0 / "train.jsonl").read_text().splitlines()]
    assert iterations == list(range(1, len(iterations) + 1))   # one curve, continued
    assert len(iterations) > len(logged) >= 1


LOCAL_RAY = ("import sys; from stack.sweep import start_ray; start_ray(1, None); print('up', flush=True); "
             "sys.stdin.read(); import ray; ray.shutdown()")


def descendants(pid: int) -> set[int]:
    """``pid`` and every process below it."""
    found, todo = set(), [pid]
    while todo:
        p = todo.pop()
        found.add(p)
        for task in Path(f"/proc/{p}/task").glob("*"):
            try:
                todo += [int(c) for c in (task / "children").read_text().split()]
            except OSError:
                pass
    return found


def ray_listeners(env: dict) -> list[str]:
    """Start a local Ray the way a sweep does, in a fresh process with ``env``: the local
    addresses its processes (driver, GCS, raylet, workers) listen on."""
    driver = subprocess.Popen([sys.executable, "-c", LOCAL_RAY], cwd=ROOT, env=env, text=True,
                              stdin=subprocess.PIPE, stdout=subprocess.PIPE, stderr=subprocess.DEVNULL)
    try:
        assert driver.stdout.readline().strip() == "up"
        tree = descendants(driver.pid)
        listening = subprocess.run(["ss", "-Hltnp"], capture_output=True, text=True, check=True).stdout
        return [line.split()[3] for line in listening.splitlines()
                if any(f"pid={p}," in line for p in tree)]
    finally:
        driver.communicate("", timeout=120)


LOOPBACK = ("127.0.0.1", "[::ffff:127.0.0.1]")


@pytest.mark.slow
@RAY
def test_a_local_sweeps_ray_listens_on_the_loopback_address_only():
    """Ray's servers run whatever work reaches them; a local sweep keeps them off the network."""
    env = {k: v for k, v in os.environ.items() if k != LOCAL_ONLY_ENV}
    local = ray_listeners(env)
    assert len(local) >= 3, local   # the GCS, the raylet, the driver at least
    assert all(a.rsplit(":", 1)[0] in LOOPBACK for a in local), local
    default = ray_listeners(env | {LOCAL_ONLY_ENV: "1"})   # Ray's own default
    assert any(a.rsplit(":", 1)[0] not in LOOPBACK for a in default), default


def test_a_ctrl_c_wrapped_by_a_lazy_import_stops_the_sweep_with_130_and_the_resume_hint(tmp_path, monkeypatch,
                                                                                          capsys):
    """A Ctrl-C inside a class definition reaches the command as a RuntimeError
    (sim.interrupts); the sweep reads it as an interruption. The teeth: with ``except
    KeyboardInterrupt`` alone the RuntimeError escapes run() with a traceback."""
    from stack.cli import main
    from stack.commands import sweep as sweep_command
    from tests.signals import define_a_class_under_sigint

    monkeypatch.setattr(sweep_command, "run_trials", lambda *a, **k: define_a_class_under_sigint())
    assert main(["sweep", "--seeds", "1", "--episodes", "8", "--out", str(tmp_path / "sweep")]) == 130
    err = capsys.readouterr().err
    assert f"formation sweep --resume --out {tmp_path / 'sweep'}" in err
    assert "Traceback" not in err


@pytest.mark.parametrize("doc", [
    {"options": {}},
    {"options": []},
    {"options": {"base": [], "grid": [], "seeds": [0]}},
    {"options": {"base": {}, "grid": [["lr"]], "seeds": [0]}},
    {"options": {"base": {}, "grid": [], "seeds": [0, 0]}},
    {"options": {"base": {}, "grid": [], "seeds": "0"}},
    [],
])
def test_a_sweep_file_of_the_wrong_shape_is_named_not_a_traceback(tmp_path, capsys, monkeypatch, doc):
    import stack.commands.sweep as sweep_command
    from stack.cli import main

    monkeypatch.setattr(sweep_command, "run_trials", lambda *a, **k: pytest.fail("trials ran"))
    (tmp_path / "sweep.json").write_text(json.dumps(doc))
    assert main(["sweep", "--resume", "--out", str(tmp_path)]) == 2
    err = capsys.readouterr().err
    assert f"{tmp_path / 'sweep.json'} is not a sweep's file" in err and "remove it" in err


def test_a_sweep_json_that_is_a_folder_is_named(tmp_path, capsys):
    from stack.cli import main

    (tmp_path / "sweep.json").mkdir()
    assert main(["sweep", "--resume", "--out", str(tmp_path)]) == 2
    assert f"{tmp_path / 'sweep.json'} is a folder" in capsys.readouterr().err


SAVED = {"base": {"total_episodes": 16, "eval_episodes": 4}, "grid": [["lr", [0.001, 0.0003]]], "seeds": [0, 1]}


@pytest.mark.parametrize(("flags", "named"), [
    (["--seeds", "5"], ["--seeds"]),
    (["--grid", "lr=1e-3"], ["--grid"]),
    (["--episodes", "4000"], ["--episodes"]),
    (["--config", '{"scenario": "paper-5"}'], ["--config"]),
    (["--config", '{"eval_episodes": 4}', "--episodes", "17", "--seeds", "3"], ["--seeds", "--episodes"]),
])
def test_resume_refuses_flags_that_differ_from_the_saved_options(tmp_path, capsys, monkeypatch, flags, named):
    """`sweep --resume` keeps the options of its sweep.json, as `demo --resume` does: a flag given
    with it that says otherwise is refused by name (it was silently ignored), before any trial."""
    import stack.commands.sweep as sweep_command
    from stack.cli import main

    (tmp_path / "sweep.json").write_text(json.dumps({"options": SAVED}))
    before = (tmp_path / "sweep.json").read_text()
    monkeypatch.setattr(sweep_command, "run_trials", lambda *a, **k: pytest.fail("trials ran"))
    assert main(["sweep", "--resume", "--out", str(tmp_path), *flags]) == 2
    err = capsys.readouterr().err
    assert f"{tmp_path} was started with other options than the {', '.join(named)} given now" in err
    assert (tmp_path / "sweep.json").read_text() == before


def test_resume_takes_flags_that_agree_with_the_saved_options(tmp_path):
    from stack.cli import build_parser
    from stack.commands.sweep import _options

    (tmp_path / "sweep.json").write_text(json.dumps({"options": SAVED}))
    for flags in ([], ["--seeds", "2"], ["--seeds", "0,1", "--grid", "lr=1e-3,3e-4", "--episodes", "16"],
                  ["--config", '{"eval_episodes": 4}'],
                  ["--config", '{"eval_episodes": 4, "total_episodes": 99}', "--episodes", "16"]):
        args = build_parser(("sweep",)).parse_args(["sweep", "--resume", "--out", str(tmp_path), *flags])
        assert _options(args) == SAVED, flags


def test_an_address_nobody_answers_is_refused_naming_it_before_sweep_json(tmp_path, monkeypatch, capsys):
    """Before, `sweep --address 127.0.0.1:1` wrote sweep.json and then Ray retried for ever."""
    import stack.commands.sweep as sweep_command
    from deploy.network import free_tcp_port
    from stack.cli import main

    monkeypatch.setattr(sweep_command, "run_trials", lambda *a, **k: pytest.fail("trials ran"))
    address = f"127.0.0.1:{free_tcp_port()}"
    start = time.monotonic()
    assert main(["sweep", "--address", address, "--episodes", "16", "--seeds", "0,",
                 "--out", str(tmp_path / "sw")]) == 2
    assert time.monotonic() - start < 30
    assert f"error: --address {address}: no Ray cluster answered within" in capsys.readouterr().err
    assert not (tmp_path / "sw" / "sweep.json").exists()
    check_ray_address("auto")                               # Ray's own words: not checked
    with pytest.raises(SweepError, match="--address ray://127.0.0.1:x: expected HOST:PORT"):
        check_ray_address("ray://127.0.0.1:x")
