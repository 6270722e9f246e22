"""stack.plots and `formation plot`: PNGs that open, trajectories and attention checked by hand."""

import json

import matplotlib.image
import numpy as np
import pytest
import torch
from torch import nn

from controllers.mappo.evaluate import evaluate
from controllers.policy import ActorConfig, build_actor
from sim.scenario import make_scenario
from stack import attention_plot, plots
from stack.cli import main

PNG_SIGNATURE = b"\x89PNG\r\n\x1a\n"
TINY = '{"num_envs": 4, "rollout_steps": 16, "eval_episodes": 4, "eval_interval": 8, "update_epochs": 1, "progress": false}'


def assert_png(path, min_width=300, min_height=200):
    """A real PNG of at least the given size in pixels, not one flat colour."""
    assert path.read_bytes()[:8] == PNG_SIGNATURE
    image = matplotlib.image.imread(path)
    height, width = image.shape[:2]
    assert width >= min_width and height >= min_height, (width, height)
    assert float(image[..., :3].std()) > 0.01
    return width, height


class GoToTarget(nn.Module):
    """Robot i accelerates towards target i: a = gain * (g_i - p), read from token 1 + i."""

    obs_kind = "tokens"

    def __init__(self, gain: float = 2.0):
        super().__init__()
        self.gain = gain

    def forward(self, obs, mask=None):
        n = obs.shape[1]
        return self.gain * obs[:, torch.arange(n), 1 + torch.arange(n), 0:2]


@pytest.fixture(scope="module")
def tiny_run(tmp_path_factory):
    """A real, very short training run of the typed SDPA actor on paper-3."""
    out = tmp_path_factory.mktemp("plot") / "run"
    assert main(["train", "--scenario", "paper-3", "--episodes", "8", "--out", str(out), "--config", TINY]) == 0
    return out


def test_moving_mean_by_hand():
    # window 3, shrinking at the ends: [mean(0,3), mean(0,3,6), mean(3,6,9), mean(6,9)]
    np.testing.assert_allclose(plots.moving_mean(np.array([0.0, 3.0, 6.0, 9.0]), 3), [1.5, 3.0, 6.0, 7.5])
    np.testing.assert_allclose(plots.moving_mean(np.array([1.0, 5.0]), 5), [3.0, 3.0])
    np.testing.assert_allclose(plots.moving_mean(np.array([1.0, 5.0]), 1), [1.0, 5.0])


def test_training_curves_from_rows_and_run(tmp_path, tiny_run):
    rows = [{"episodes": 16 * k, "return_mean": None if k % 2 else -80 + 3 * k,
             "final_distance": None if k % 2 else 0.4 / (1 + k)} for k in range(1, 40)]
    evals = [{"episodes": 100 * k, "success_rate": min(1.0, 0.2 * k), "final_distance": 0.3 / (1 + k),
              "episode_return": -70 + 5 * k} for k in range(7)]
    run = plots.load_run(tiny_run)
    assert len(run.train) >= 2 and len(run.eval) >= 1 and run.target_tolerance == 0.05
    out = plots.plot_training_curves({"transfer": {"train": rows, "eval": evals, "converged_episode": 500},
                                      "rows only": rows, "tiny run": run}, tmp_path / "c" / "curves.png")
    width, height = assert_png(out, 1200, 400)
    assert width > 2 * height


def test_load_run_names_the_missing_file(tmp_path):
    with pytest.raises(plots.PlotError, match="does not exist.*formation train"):
        plots.load_run(tmp_path / "nope")
    with pytest.raises(plots.PlotError, match="train.jsonl.*is missing.*formation train"):
        plots.load_run(tmp_path)


def test_plot_of_an_existing_file_says_it_is_not_a_folder(tmp_path, capsys):
    """Before: "run folder 'afile' does not exist" of a file that exists."""
    (tmp_path / "afile").write_text("x\n")
    assert main(["plot", str(tmp_path / "afile")]) == 2
    err = capsys.readouterr().err
    assert f"'{tmp_path / 'afile'}' is a file, not a run folder" in err and "does not exist" not in err


def test_recorder_starts_on_the_slots_and_follows_the_dynamics():
    scenario = make_scenario("paper-3")
    dyn = scenario.dynamics
    traj = plots.record_trajectories(GoToTarget(), scenario, episodes=3, seed=4, steps=40)
    pos = traj.positions
    assert pos.shape == (3, 41, 3, 2) and traj.contacts.shape == (3, 40, 3, 3)
    # starts: the slots moved by at most the jitter per axis (float32 state)
    assert np.abs(pos[:, 0] - scenario.starts).max() <= scenario.start_jitter + 1e-6
    # first step from rest: v1 = dt * a0 (a0 = clip_norm(2 (g - p0), 1)), p1 = p0 + dt * v1
    a0 = 2.0 * (scenario.targets - pos[:, 0])
    a0 *= np.minimum(1.0, dyn.accel_limit / np.linalg.norm(a0, axis=-1, keepdims=True))
    np.testing.assert_allclose(pos[:, 1], pos[:, 0] + dyn.dt * dyn.dt * a0, atol=1e-6)
    # no reset inside the record: no step is longer than dt * speed_limit
    assert np.linalg.norm(np.diff(pos, axis=1), axis=-1).max() <= dyn.dt * dyn.speed_limit + 1e-6
    # the straight path to the left crosses the box (x 0.4..0.6, y 0.35..0.65): object contact
    assert traj.contacts[..., 1].any(1).all() and not traj.contacts[..., 0].any()
    assert not traj.success.any()
    again = plots.record_trajectories(GoToTarget(), scenario, episodes=3, seed=4, steps=40)
    np.testing.assert_array_equal(again.positions, pos)
    other = plots.record_trajectories(GoToTarget(), scenario, episodes=3, seed=5, steps=40)
    assert not np.allclose(other.positions[:, 0], pos[:, 0])


def test_recorder_agrees_with_evaluate():
    """Full episodes: success and mean final distance equal those of the evaluation code path."""
    scenario = make_scenario("paper-3")
    policy = GoToTarget(gain=1.5)
    traj = plots.record_trajectories(policy, scenario, episodes=4, seed=11)
    assert traj.positions.shape == (4, scenario.dynamics.episode_steps + 1, 3, 2)
    result = evaluate(policy, scenario, episodes=4, seed=11)
    assert traj.final_distance.mean() == pytest.approx(result.final_distance, abs=1e-6)
    assert traj.success.mean() == pytest.approx(result.success_rate)


def test_by_entity_puts_each_robot_in_its_own_column():
    n = 3
    w = np.arange(n * 7, dtype=float).reshape(n, 1, 7)    # typed: self, G1..G3, two others, O
    out, labels = attention_plot.by_entity(w)
    assert labels == ["self", "G1", "G2", "G3", "R1", "R2", "R3", "O"]
    r = {f"R{j + 1}": 4 + j for j in range(n)}
    # robot 1 (row 0) sees robots 2, 3 in tokens 4, 5; robot 2 sees 1, 3; robot 3 sees 1, 2
    assert np.isnan(out[0, 0, r["R1"]]) and out[0, 0, r["R2"]] == w[0, 0, 4] and out[0, 0, r["R3"]] == w[0, 0, 5]
    assert out[1, 0, r["R1"]] == w[1, 0, 4] and np.isnan(out[1, 0, r["R2"]]) and out[1, 0, r["R3"]] == w[1, 0, 5]
    assert out[2, 0, r["R1"]] == w[2, 0, 4] and out[2, 0, r["R2"]] == w[2, 0, 5] and np.isnan(out[2, 0, r["R3"]])
    np.testing.assert_array_equal(out[:, 0, :4], w[:, 0, :4])
    np.testing.assert_array_equal(out[:, 0, -1], w[:, 0, -1])
    slot, slot_labels = attention_plot.by_entity(np.ones((n, 2, 8)))
    assert slot.shape == (n, 2, 9) and slot_labels[:2] == ["P", "V"]
    with pytest.raises(plots.PlotError, match="2N\\+1"):
        attention_plot.by_entity(np.ones((n, 1, 5)))


def test_attention_sums_to_one_over_valid_tokens(tmp_path):
    torch.manual_seed(0)
    scenario = make_scenario("paper-4")
    actor = build_actor(ActorConfig(), 4).eval()
    from sim.batched_env import BatchedFormationEnv

    obs, mask = BatchedFormationEnv(scenario, 1, seed=0).reset()
    mask = mask.clone()
    mask[0, :, 5] = False                    # every robot loses its first other-robot token
    w = attention_plot.attention_weights(actor, obs[0], mask[0])
    assert w.shape == (4, 4, 9)              # (N, H, 2N + 1)
    np.testing.assert_allclose(w.sum(-1), 1.0, atol=1e-6)
    assert np.all(w[:, :, 5] == 0) and np.all(w[:, :, [0, 1, 4, 6, 8]] > 0)
    weights, labels = attention_plot.attention_snapshot(actor, scenario, seed=0, step=3)
    assert weights.shape == (4, 4, 10) and len(labels) == 10
    np.testing.assert_allclose(np.nansum(weights, -1), 1.0, atol=1e-6)
    assert np.isnan(weights[np.arange(4), :, 5 + np.arange(4)]).all()    # (i, R_i) is empty
    out = attention_plot.plot_attention(weights, labels, tmp_path / "attention.png")
    assert_png(out, 600, 200)
    with pytest.raises(plots.PlotError, match="no attention"):
        attention_plot.attention_weights(GoToTarget(), obs[0], mask[0])


def test_plot_trajectories_png(tmp_path):
    scenario = make_scenario("paper-3")
    traj = plots.record_trajectories(GoToTarget(), scenario, episodes=3, seed=0, steps=30)
    width, height = assert_png(plots.plot_trajectories(traj, scenario, tmp_path / "t.png"), 900, 400)
    assert width > height
    with pytest.raises(plots.PlotError, match="positions must have shape"):
        plots.plot_trajectories(traj, make_scenario("paper-4"), tmp_path / "bad.png")


def test_cli_writes_three_pngs(tmp_path, tiny_run, capsys):
    out = tmp_path / "figs"
    assert main(["plot", str(tiny_run), "--episodes", "2", "--out", str(out), "--scenario", "paper-4"]) == 0
    printed = capsys.readouterr().out.split()
    for name in ("curves.png", "trajectories.png", "attention.png"):
        assert str(out / name) in printed
        assert_png(out / name)
    assert json.loads((tiny_run / "config.json").read_text())["scenario"] == "paper-3"


def test_cli_errors(tmp_path, tiny_run, capsys):
    missing = tmp_path / "no-such-run"
    assert main(["plot", str(missing)]) == 2
    err = capsys.readouterr().err
    assert str(missing) in err and "formation train" in err
    (tmp_path / "empty").mkdir()
    assert main(["plot", str(tmp_path / "empty")]) == 2
    assert "train.jsonl" in capsys.readouterr().err
    assert main(["plot", str(tiny_run), str(tiny_run), "--labels", "a"]) == 2
    assert "--labels has 1 labels for 2" in capsys.readouterr().err
    assert main(["plot", str(tiny_run), "--scenario", "paper-99x", "--out", str(tmp_path / "x")]) == 2
    assert "unknown scenario" in capsys.readouterr().err and not (tmp_path / "x").exists()


ROW = '{"episodes": 16, "return_mean": -3.0, "final_distance": 0.3}\n'


def _run_folder(tmp_path, train_text: str, **files: str):
    folder = tmp_path / "run"
    folder.mkdir()
    (folder / "train.jsonl").write_text(train_text)
    for name, text in files.items():
        (folder / name.replace("_", ".")).write_text(text)
    return folder


def test_a_torn_last_log_line_is_skipped_and_a_damaged_one_before_it_is_named(tmp_path):
    """A crash in the middle of an append leaves a cut last line: the rows before it are the log.
    A bad line before the last is damage: named with its file and line."""
    torn = _run_folder(tmp_path, ROW + ROW.replace("16", "32") + '{"episodes": 48, "ret')
    assert [r["episodes"] for r in plots.load_run(torn).train] == [16, 32]
    (torn / "train.jsonl").write_text(ROW + '{"episodes": 32, "ret\n' + ROW)
    with pytest.raises(plots.PlotError, match=r"train\.jsonl, line 2: not valid JSON"):
        plots.load_run(torn)
    (torn / "train.jsonl").write_text(ROW + "[1, 2]\n" + ROW)
    with pytest.raises(plots.PlotError, match=r"train\.jsonl, line 2: expected a JSON object, got list"):
        plots.load_run(torn)
    (torn / "train.jsonl").write_text(ROW)
    (torn / "eval.jsonl").write_text('{"episodes": 16}\n\xff\n{"episodes": 32}\n')
    with pytest.raises(plots.PlotError, match=r"eval\.jsonl, line 2"):
        plots.load_run(torn)


@pytest.mark.parametrize(("name", "text", "message"), [
    ("result.json", "", "is not valid JSON"),
    ("config.json", "[]\n", "expected a mapping of fields, got list"),
    ("config.json", '{"success_threshold": "high"}', "success_threshold 'high' is not a number"),
])
def test_a_damaged_result_or_config_file_is_named_exit_2(tmp_path, capsys, name, text, message):
    folder = _run_folder(tmp_path, ROW)
    (folder / name).write_text(text)
    assert main(["plot", str(folder), "--curves-only", "--out", str(tmp_path / "figs")]) == 2
    err = capsys.readouterr().err
    assert err.startswith(f"error: {folder / name}") and message in err and "Traceback" not in err
    assert not (tmp_path / "figs").exists()


def test_a_log_holding_only_a_torn_line_starts_anew_on_the_first_append(tmp_path):
    """The trainer appends to a log whose only line a crash cut: the row is read back alone (not
    glued to the torn text, which would damage the log's first line)."""
    from controllers.mappo.logs import MetricsLog

    (tmp_path / "train.jsonl").write_text('{"iteration": 1, "epi')
    log = MetricsLog(tmp_path, "train")
    assert log.read() == []
    log.append({"iteration": 1, "episodes": 16})
    assert MetricsLog(tmp_path, "train").read() == [{"iteration": 1, "episodes": 16}]


def _bridge_record(scenario, ticks: int, nan_robot: int | None):
    """A record as `formation bridge --record` writes it (no fleet: positions are the measured
    ones), ``ticks`` ticks; robot ``nan_robot`` reports a NaN position on every one."""
    from sim.fleet import FleetState
    from stack.recorder import EpisodeRecorder
    from stack.tick_types import PolicyStatus, TickResult

    n = scenario.num_robots
    recorder = EpisodeRecorder(scenario)
    states = []
    for k in range(max(ticks, 1)):
        pos = np.array(scenario.starts, dtype=float) + [0.01 * k, 0.0]
        if nan_robot is not None:
            pos[nan_robot] = np.nan
        states.append(FleetState(time=0.05 * k, step=k, positions=pos, velocities=np.zeros((n, 2)),
                                 targets=np.array(scenario.targets, dtype=float),
                                 object_pose=np.array([*scenario.object_center, 0.0]),
                                 robot_ids=tuple(f"r{i}" for i in range(n))))
    recorder.start(None, states[0])
    for state in states[:ticks]:
        a = np.zeros((n, 2))
        stale = np.zeros(n, bool) if nan_robot is None else np.arange(n) == nan_robot
        recorder.tick(state, TickResult(a_nom=a, a_safe=a, a_cmd=a, policy_status=PolicyStatus.OK,
                                        safety_status=None, mec_status=None, stale=stale,
                                        docking=np.zeros(n, bool), detour=np.zeros(n, bool)))
    return recorder.finish({"seed": 0})


def test_a_robot_without_any_position_is_left_out_of_the_paths_and_named_absent(tmp_path, monkeypatch, capsys):
    """A robot that reported NaN on every tick (the stack braked it; the record keeps NaN as
    received) has no path: the figure draws the others and names it absent in the path panel;
    `formation plot` draws it (exit 0)."""
    from stack import episode_plot

    scenario = make_scenario("paper-3")
    record = _bridge_record(scenario, 5, nan_robot=1)
    assert np.isnan(record.positions[:, 1]).all() and np.isfinite(record.positions[:, [0, 2]]).all()
    drawn = []
    real_save = episode_plot.save_figure
    monkeypatch.setattr(episode_plot, "save_figure", lambda fig, out: drawn.append(fig) or real_save(fig, out))
    assert_png(episode_plot.plot_episode(record, scenario, tmp_path / "nan.png"))
    texts = [t.get_text() for t in drawn[0].axes[0].texts]
    assert "r0" in texts and "r2" in texts and "r1" not in texts          # robot labels at their ends
    assert [t for t in texts if "absent" in t] == ["absent (no position in the record): r1"]
    path = record.save(tmp_path / "record_00000.npz")
    assert main(["plot", str(path), "--out", str(tmp_path / "figs")]) == 0
    assert_png(tmp_path / "figs" / "record_00000.png")


def test_a_record_without_ticks_is_a_plot_error_and_plot_exits_2(tmp_path, capsys):
    """EpisodeRecorder.start then finish, no tick (an episode that stopped at once): a
    PlotError "the record has no ticks", and `formation plot` exits 2 with it, drawing nothing."""
    from stack.episode_plot import assigned_distances, plot_episode

    scenario = make_scenario("paper-3")
    record = _bridge_record(scenario, 0, nan_robot=None)
    assert record.steps == 0 and record.positions.shape == (1, 3, 2)
    with pytest.raises(plots.PlotError, match="cannot draw zero.png: the record has no ticks"):
        plot_episode(record, scenario, tmp_path / "zero.png")
    with pytest.raises(plots.PlotError, match="the record has no ticks"):
        assigned_distances(record)
    path = record.save(tmp_path / "zero.npz")
    assert main(["plot", str(path), "--out", str(tmp_path / "figs")]) == 2
    err = capsys.readouterr().err
    assert err.startswith("error: cannot draw zero.png: the record has no ticks") and "Traceback" not in err
    assert not (tmp_path / "zero.png").exists() and not (tmp_path / "figs" / "zero.png").exists()
