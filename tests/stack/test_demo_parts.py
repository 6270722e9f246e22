"""Parts of `formation demo` on hand-worked cases: the bridge's per-episode recorder, the
tracking-error noise floor, training-stage resume, settings on --resume, the generalist's
background training and its printed table."""

from __future__ import annotations

import json
import math
import subprocess
import sys

import numpy as np
import pytest

from controllers.mappo import train
from sim.fleet import FleetState
from sim.scenario import make_scenario
from stack.cli import main
from stack.commands.bridge import EpisodeCounters
from stack.commands.demo import print_zero_shot_table, run_stage
from stack.demo.fleet import tracking_noise_floor
from stack.demo.stages import GENERALIST_LOG, generalist_stage, train_config, train_stage
from stack.demo.state import Children, DemoError, DemoSettings, StageBook
from stack.pipeline import ControlStack, StackConfig


def test_recorder_tracking_error_is_the_hand_worked_gain_error():
    """A robot reaching half the commanded acceleration a drifts from the nominal model by
    dt^2 (1 - g) |a| per tick: 0.05^2 * 0.5 * 0.5 = 0.625 mm (the damping terms cancel)."""
    sc = make_scenario("paper-3")
    dyn = sc.dynamics
    a = np.tile([0.3, 0.4], (3, 1))   # |a| = 0.5 m/s^2, below accel_limit
    stack = ControlStack(sc, lambda state: a.copy(), StackConfig(safety=False, mec=False))
    recorder = EpisodeCounters(stack)
    for episode in (4, 5):
        recorder.start_episode(episode)
        pos, vel = sc.starts.copy(), np.zeros((3, 2))
        for k in range(5):
            state = FleetState(k * dyn.dt, k, pos, vel, sc.targets, np.array([*sc.object_center, 0.0]))
            cmd = recorder(state)
            np.testing.assert_array_equal(cmd, a)
            pos, vel = dyn.step_np(pos, vel, 0.5 * cmd)
    episodes = recorder.summary()
    assert [e["episode"] for e in episodes] == [4, 5]
    for e in episodes:
        assert e["ticks"] == 5 and e["interventions"] == 0 and e["braking"] == 0
        assert e["tracking_error"] == pytest.approx(dyn.dt ** 2 * 0.5 * 0.5, rel=1e-9)
        assert 0 < e["tick_ms"]["p50"] <= e["tick_ms"]["p99"] <= e["tick_ms"]["max"]


def test_recorder_tracking_error_is_zero_for_a_nominal_robot():
    sc = make_scenario("paper-3")
    dyn = sc.dynamics
    stack = ControlStack(sc, lambda state: np.tile([0.3, -0.2], (3, 1)), StackConfig(safety=False, mec=False))
    recorder = EpisodeCounters(stack)
    pos, vel = sc.starts.copy(), np.zeros((3, 2))
    for k in range(4):
        cmd = recorder(FleetState(k * dyn.dt, k, pos, vel, sc.targets, np.zeros(3)))
        pos, vel = dyn.step_np(pos, vel, cmd)
    [episode] = recorder.summary()
    assert episode["episode"] == 0 and episode["tracking_error"] == pytest.approx(0.0, abs=1e-15)


def test_noise_floor_matches_a_sampled_estimate():
    """The closed form against the error of exact nominal motion measured with noise."""
    me = {"position_noise_std": 0.001, "velocity_noise_std": 0.005}
    dt, c = 0.05, 0.5
    rng = np.random.default_rng(0)
    m = 200_000
    n_p0, n_p1 = rng.normal(0, 0.001, (2, m, 2))
    n_v = rng.normal(0, 0.005, (m, 2))
    err = n_p1 - n_p0 - dt * (1 - c * dt) * n_v
    sampled = np.linalg.norm(err, axis=1).mean()
    assert tracking_noise_floor(me, dt, c) == pytest.approx(sampled, rel=0.01)
    assert tracking_noise_floor(me, dt, c) == pytest.approx(
        math.sqrt(2e-6 + (0.04875 * 0.005) ** 2) * math.sqrt(math.pi / 2))


def test_each_stage_trains_with_its_own_settings(tmp_path):
    """paper-3 and the generalist (what the demo waits on) take four PPO epochs, the transfer to
    paper-5 the default ten; only the transfer starts from the 3-robot checkpoint (the generalist
    trains from scratch beside paper-3); the budgets and the seed are the demo's."""
    settings = DemoSettings(seed=7, budget_3=100, budget_5=200, budget_generalist=300)
    configs = {robots: train_config(settings, robots, tmp_path) for robots in ("3", "5", "generalist")}
    assert {r: c.update_epochs for r, c in configs.items()} == {"3": 4, "5": 10, "generalist": 4}
    assert {r: c.total_episodes for r, c in configs.items()} == {"3": 100, "5": 200, "generalist": 300}
    assert {r: c.seed for r, c in configs.items()} == {"3": 7, "5": 7, "generalist": 7}
    assert configs["3"].init_from is None and configs["generalist"].init_from is None
    assert configs["5"].init_from == str((tmp_path / "train-3" / "checkpoint.pt").resolve())
    assert configs["generalist"].team_sizes == [3, 4, 5] and configs["generalist"].penalty_curriculum == 3.0


def test_the_generalist_starts_with_the_first_training_stage_that_runs(tmp_path):
    """Its child process starts with train-3 (it trains from scratch, so nothing holds it back);
    on a resume after train-3, with train-5; once the generalist stage is done, with neither."""
    settings = DemoSettings(quick=True, budget_3=16, budget_5=16, budget_generalist=16, eval_episodes=4,
                            eval_interval=16, zero_shot_episodes=4, fleet_episodes=1)
    book = StageBook(tmp_path, settings)
    book.save()                                   # what the child reads its settings from
    children = Children()
    try:
        background: dict = {}
        book.finish("train-3", run_stage("train-3", book, children, background), 1.0)
        assert set(background) == {"generalist"} and background["generalist"].poll() in (None, 0)
        children.terminate_all()
        background.clear()                        # a resume after train-3
        run_stage("train-5", book, children, background)
        assert set(background) == {"generalist"}
        children.terminate_all()
        background.clear()
        book.finish("generalist", {}, 1.0)
        run_stage("train-5", book, children, background)    # its checkpoint is at the budget
        assert background == {}
    finally:
        children.terminate_all()


def test_an_interrupted_training_stage_continues_from_its_checkpoint(tmp_path):
    settings = DemoSettings(quick=True, budget_3=32, budget_5=16, eval_episodes=4, eval_interval=16,
                            zero_shot_episodes=4, fleet_episodes=1)
    # The run as it stands after an interruption at 16 of 32 episodes (checkpoint written); one
    # update epoch, which the continued run takes from the run's saved config.json.
    config = train_config(settings, "3", tmp_path).replace(total_episodes=16, update_epochs=1, progress=False)
    first = train(config, tmp_path / "train-3")
    assert first.episodes == 16
    rows_before = (tmp_path / "train-3" / "train.jsonl").read_text().splitlines()
    result = train_stage(settings, "3", tmp_path)
    rows = [json.loads(r) for r in (tmp_path / "train-3" / "train.jsonl").read_text().splitlines()]
    assert result["episodes"] == 32 and result["budget"] == 32
    assert json.loads((tmp_path / "train-3" / "config.json").read_text())["update_epochs"] == 1
    assert [r["iteration"] for r in rows] == list(range(1, len(rows) + 1))
    assert [json.dumps(r) for r in rows[:len(rows_before)]] == [json.dumps(json.loads(r)) for r in rows_before]
    assert rows[-1]["episodes"] == 32


def test_a_run_folder_without_checkpoint_starts_again(tmp_path):
    settings = DemoSettings(quick=True, budget_3=16, budget_5=16, eval_episodes=4, eval_interval=16,
                            zero_shot_episodes=4, fleet_episodes=1)
    (tmp_path / "train-3").mkdir()
    (tmp_path / "train-3" / "train.jsonl").write_text('{"iteration": 99}\n')
    result = train_stage(settings, "3", tmp_path)
    rows = [json.loads(r) for r in (tmp_path / "train-3" / "train.jsonl").read_text().splitlines()]
    assert result["episodes"] == 16 and rows[0]["iteration"] == 1


def test_resume_keeps_the_saved_settings_and_refuses_others(tmp_path, capsys):
    out = tmp_path / "run"
    out.mkdir()
    StageBook(out, DemoSettings(budget_3=8)).save()
    before = (out / "stages.json").read_text()
    assert main(["demo", "--out", str(out), "--resume", "--budget-3", "9"]) == 2
    assert "--budget-3" in capsys.readouterr().err
    assert main(["demo", "--out", str(out), "--resume", "--quick"]) == 2   # saved as a full run
    assert "--quick" in capsys.readouterr().err
    assert main(["demo", "--out", str(out), "--resume", "--fleet-episodes", "9"]) == 2
    assert "(--fleet-episodes differ)" in capsys.readouterr().err
    assert (out / "stages.json").read_text() == before


def test_resume_needs_a_demo_folder(tmp_path, capsys):
    assert main(["demo", "--out", str(tmp_path / "nothing"), "--resume"]) == 2
    assert "stages.json" in capsys.readouterr().err
    assert not (tmp_path / "nothing").exists()


def test_a_failed_background_training_stops_the_generalist_stage_with_its_log(tmp_path):
    """The generalist's child process exits non-zero: the stage raises with its exit code and
    the tail of its log, and trains nothing in its place."""
    settings = DemoSettings(quick=True, budget_generalist=16, eval_episodes=4, eval_interval=16,
                            zero_shot_episodes=4, fleet_episodes=1)
    (tmp_path / GENERALIST_LOG).write_text("first line\nthe reason it stopped\n")
    child = subprocess.Popen([sys.executable, "-c", "import sys; sys.exit(3)"])
    with pytest.raises(DemoError, match=r"exited with code 3(.|\n)*the reason it stopped"):
        generalist_stage(settings, tmp_path, child, Children())
    assert not (tmp_path / "train-generalist").exists()


def test_the_zero_shot_table_prints_one_column_per_team_size(capsys):
    table = [{"robots": n, "trained": n == 3, "success": s, "collision_rate": 1 - s,
              "final_distance": d, "episodes": 100}
             for n, s, d in ((2, 0.5, 0.0123), (3, 1.0, 0.004))]
    print_zero_shot_table(table)
    lines = capsys.readouterr().out.splitlines()
    assert "100 deterministic episodes" in lines[0]
    assert lines[1].split() == ["robots", "2", "3*"]
    assert lines[2].split() == ["success", "0.50", "1.00"]
    assert lines[3].split() == ["collision", "rate", "0.50", "0.00"]
    assert lines[4].split() == ["final", "distance", "[mm]", "12.3", "4.0"]


BOOK_HEAD = '"format": "formation-stack/demo", "version": 1'


@pytest.mark.parametrize(("text", "message"), [
    ("[]", "expected a mapping of fields, got list"),
    ("", "is not valid JSON"),
    ("{" + BOOK_HEAD + ', "stages": {}}', "'settings' is missing"),
    ("{" + BOOK_HEAD + ', "settings": [], "stages": {}}', "'settings' is not a mapping"),
    ("{" + BOOK_HEAD + ', "settings": {}, "stages": []}', "'stages' is not a mapping of stage records"),
    ("{" + BOOK_HEAD + ', "settings": {}, "stages": {"train-3": {"done": true}}}', "'stages' is not a mapping"),
    ("{" + BOOK_HEAD + ', "settings": {}, "stages": {}, "created_unix": "x"}', "'created_unix' is not a number"),
    (None, "is not a file"),
])
def test_a_damaged_or_foreign_stage_book_is_named(tmp_path, text, message):
    """A stages.json of the wrong type (or a folder of that name) is a DemoError naming the file,
    not a KeyError / AttributeError / IsADirectoryError traceback."""
    if text is None:
        (tmp_path / "stages.json").mkdir()
    else:
        (tmp_path / "stages.json").write_text(text)
    with pytest.raises(DemoError, match="stages.json") as raised:
        StageBook.load(tmp_path)
    assert message in str(raised.value) and str(tmp_path / "stages.json") in str(raised.value)


def test_resume_on_a_damaged_stage_book_exits_2_naming_it(tmp_path, capsys):
    (tmp_path / "stages.json").write_text('{"format": "formation-stack/demo", "version": 1, "stages": {}}')
    assert main(["demo", "--out", str(tmp_path), "--resume"]) == 2
    err = capsys.readouterr().err
    assert err.startswith("error: ") and str(tmp_path / "stages.json") in err and "'settings' is missing" in err
