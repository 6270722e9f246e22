import json
import subprocess
from pathlib import Path

import pytest
import torch

from controllers.mappo import (
    CheckpointError,
    MAPPOConfig,
    MAPPOTrainer,
    TrainConfigError,
    evaluate,
    load_actor,
    load_checkpoint,
    train,
)
from controllers.mappo.checkpoint import save_checkpoint
from sim.batched_env import BatchedFormationEnv
from sim.distribution import DISTRIBUTIONS
from sim.observations import LAYOUT_VERSION
from sim.scenario import Scenario, make_scenario

SMALL_NET = {"embed_dim": 16, "num_heads": 2, "hidden_sizes": [32]}


def tiny(**changes) -> MAPPOConfig:
    """A run of a few seconds: 4 envs, 32-step rollouts (4 iterations per episode), small nets."""
    base = dict(scenario="paper-3", num_envs=4, rollout_steps=32, update_epochs=2, num_minibatches=2,
                total_episodes=8, eval_interval=4, eval_episodes=4, checkpoint_interval=1,
                stop_at_convergence=False, progress=False, actor=dict(SMALL_NET),
                critic=dict(SMALL_NET))
    base.update(changes)
    return MAPPOConfig(**base)


def rows(path, drop=("wall_time_s",)):
    with open(path) as f:
        return [{k: v for k, v in json.loads(line).items() if k not in drop} for line in f]


def test_a_run_writes_config_logs_checkpoint_and_result(tmp_path):
    result = train(tiny(), tmp_path)
    assert result.episodes == 8 and result.iterations == 8 and result.env_steps == 8 * 32 * 4
    config = json.loads((tmp_path / "config.json").read_text())
    assert MAPPOConfig.from_dict(config) == tiny()
    train_rows = rows(tmp_path / "train.jsonl")
    assert [r["iteration"] for r in train_rows] == list(range(1, 9))
    assert [r["episodes"] for r in train_rows] == [0, 0, 0, 4, 4, 4, 4, 8]
    assert (tmp_path / "train.csv").read_text().splitlines()[0].startswith("iteration,episodes,env_steps")
    assert len((tmp_path / "train.csv").read_text().splitlines()) == 9
    evals = rows(tmp_path / "eval.jsonl")
    assert [e["episodes"] for e in evals] == [0, 4, 8]              # at start, then every batch
    saved = json.loads((tmp_path / "result.json").read_text())
    assert saved["episodes"] == 8 and saved["evaluations"]["episodes"] == [0, 4, 8]
    assert not list(tmp_path.glob(".*.tmp*"))                        # atomic writes left nothing behind
    run = json.loads((tmp_path / "run.json").read_text())             # where the result came from
    head = subprocess.run(["git", "-C", str(Path(__file__).parent), "rev-parse", "HEAD"],
                          capture_output=True, text=True, check=True).stdout.strip()
    assert run["git"]["commit"] == head
    assert run["packages"]["torch"] == torch.__version__ and run["torch_threads"] == torch.get_num_threads()
    assert saved["provenance"] == run

    data = torch.load(tmp_path / "checkpoint.pt", weights_only=True)
    assert data["layout_version"] == LAYOUT_VERSION and data["num_robots"] == 3
    assert data["counters"]["iteration"] == 8 and data["counters"]["episodes"] == 8
    for key in ("config", "actor", "critic", "actor_optimizer", "critic_optimizer", "value_norm", "rng",
                "env_state"):
        assert key in data


def test_on_iteration_sees_every_logged_row_and_an_exception_in_it_stops_the_run_like_ctrl_c(tmp_path):
    seen = []
    train(tiny(), tmp_path / "whole", on_iteration=seen.append)
    assert seen == rows(tmp_path / "whole" / "train.jsonl", drop=())

    def stop_after_the_fifth(row):
        if row["iteration"] == 5:
            raise KeyboardInterrupt
    with pytest.raises(KeyboardInterrupt):
        train(tiny(), tmp_path / "stopped", on_iteration=stop_after_the_fifth)
    assert not (tmp_path / "stopped" / "result.json").exists()
    assert load_checkpoint(tmp_path / "stopped" / "checkpoint.pt")["counters"]["iteration"] == 5


@pytest.mark.parametrize("ema", [0.0, 0.5])
def test_resume_continues_the_same_curve(tmp_path, ema):
    whole = tmp_path / "whole"
    train(tiny(policy_ema=ema), whole)
    parts = tmp_path / "parts"
    first = train(tiny(total_episodes=4, policy_ema=ema), parts)
    assert first.iterations == 4
    started = json.loads((parts / "run.json").read_text())
    # a crash after the checkpoint leaves rows the checkpoint does not cover: resume drops them
    with open(parts / "train.jsonl", "a") as f:
        f.write(json.dumps(rows(parts / "train.jsonl")[-1] | {"iteration": 5}) + "\n")
    second = train(tiny(total_episodes=8, policy_ema=ema), parts, resume=True)
    assert second.iterations == 8 and second.episodes == 8
    assert json.loads((parts / "run.json").read_text())["before_resume"] == started   # kept, not overwritten
    assert rows(parts / "train.jsonl") == rows(whole / "train.jsonl")
    assert rows(parts / "eval.jsonl") == rows(whole / "eval.jsonl")
    assert len((parts / "train.csv").read_text().splitlines()) == 9
    a = load_checkpoint(whole / "checkpoint.pt")
    b = load_checkpoint(parts / "checkpoint.pt")
    for key in ("actor", "policy"):
        for name in a[key]:
            assert torch.equal(a[key][name], b[key][name]), (key, name)
    assert torch.equal(a["rng"]["sampler"], b["rng"]["sampler"])


def test_policy_average_is_evaluated_saved_and_loaded(tmp_path):
    trainer = MAPPOTrainer(tiny(policy_ema=0.75), tmp_path)
    before = {k: v.clone() for k, v in trainer.policy.state_dict().items()}
    assert all(torch.equal(before[k], v) for k, v in trainer.actor.state_dict().items())
    trainer._iteration()
    after, actor = trainer.policy.state_dict(), trainer.actor.state_dict()
    for name, old in before.items():      # w_avg <- 0.75 w_avg + 0.25 w
        assert torch.allclose(after[name], 0.75 * old + 0.25 * actor[name]), name
    changed = [k for k in actor if not torch.equal(actor[k], before[k])]
    assert changed and all(not torch.equal(after[k], actor[k]) for k in changed)
    trainer.save()
    data = load_checkpoint(tmp_path / "checkpoint.pt")
    loaded = load_actor(tmp_path / "checkpoint.pt").state_dict()
    assert all(torch.equal(loaded[k], after[k]) for k in after)              # the policy is the average
    assert all(torch.equal(data["actor"][k], actor[k]) for k in actor)       # training resumes from w
    with pytest.raises(TrainConfigError, match="policy_ema"):
        tiny(policy_ema=1.0)


def test_penalty_curriculum_follows_the_arrival_rate(tmp_path):
    trainer = MAPPOTrainer(tiny(penalty_curriculum=4.0), tmp_path)
    assert trainer.groups[0].env.penalty_scale == 1.0
    arrived = []
    for _ in range(8):                     # 32-step rollouts: 4 envs finish every 4th iteration
        row = trainer._iteration()
        if row["episodes_finished"]:
            arrived.append(trainer.arrival_rate)
    rate = 0.0
    for _ in arrived:                      # the untrained robots never arrive: the rate stays 0
        rate += 0.25 * (0.0 - rate)
    assert len(arrived) == 2 and trainer.arrival_rate == rate == 0.0
    trainer.arrival_rate = 0.5             # as if half the recent episodes had ended on target
    trainer.groups[0].env.penalty_scale = 1.0
    trainer._iteration(), trainer._iteration(), trainer._iteration()
    row = trainer._iteration()             # a batch finishes: 0.5 + 0.25 * (0 - 0.5) = 0.375
    assert trainer.arrival_rate == pytest.approx(0.375)
    assert row["penalty_scale"] == pytest.approx(1.0 + 4.0 * 0.375) == trainer.groups[0].env.penalty_scale


def test_learning_rate_drops_while_the_last_evaluation_succeeds(tmp_path):
    trainer = MAPPOTrainer(tiny(lr=1e-3, critic_lr=2e-3, lr_after_success=0.25), tmp_path)
    trainer.last_eval = {"success_rate": 0.95}
    assert trainer._iteration()["lr"] == pytest.approx(0.25e-3)
    assert trainer.critic_optimizer.param_groups[0]["lr"] == pytest.approx(0.5e-3)
    trainer.last_eval = {"success_rate": 0.85}          # below the 0.9 threshold: full rate again
    assert trainer._iteration()["lr"] == pytest.approx(1e-3)
    with pytest.raises(TrainConfigError, match="lr_after_success"):
        tiny(lr_after_success=0.0)


def test_resume_rejects_a_changed_config_and_a_fresh_run_refuses_a_used_directory(tmp_path):
    train(tiny(total_episodes=4), tmp_path)
    with pytest.raises(TrainConfigError, match="'lr'"):
        train(tiny(total_episodes=8, lr=1e-2), tmp_path, resume=True)
    with pytest.raises(TrainConfigError, match="already holds a run"):
        train(tiny(), tmp_path)


def test_a_run_stopped_before_its_first_checkpoint_starts_over_in_its_directory(tmp_path):
    """Ctrl-C before the first checkpoint leaves logs and nothing to resume: resuming says so, and
    a fresh start in the same directory starts over (before, both were refused and the user had
    to delete the folder)."""
    early = MAPPOTrainer(tiny(checkpoint_interval=100), tmp_path)
    early._evaluate()
    early._iteration()
    assert early.train_log.read() and not (tmp_path / "checkpoint.pt").exists()
    with pytest.raises(TrainConfigError, match="holds no checkpoint yet"):
        train(tiny(), tmp_path, resume=True)
    result = train(tiny(total_episodes=4), tmp_path)
    assert result.episodes == 4
    assert [r["iteration"] for r in rows(tmp_path / "train.jsonl")] == list(range(1, result.iterations + 1))


@pytest.mark.parametrize("variant", ["typed", "slot"])
def test_three_robot_checkpoint_starts_four_and_five_robot_runs(tmp_path, variant):
    source = MAPPOTrainer(tiny(actor=SMALL_NET | {"variant": variant}), tmp_path / "three")
    with torch.no_grad():                             # stand-in for training: move every weight
        for p in [*source.actor.parameters(), *source.critic.parameters()]:
            p.add_(0.05)
    source.value_norm.update(torch.tensor([-3.0, -1.0]))
    ckpt = source.save()
    for n in (4, 5):
        run = MAPPOTrainer(tiny(scenario=f"paper-{n}", init_from=str(ckpt), init_keep=1.0,
                                actor=SMALL_NET | {"variant": variant}), tmp_path / f"to{n}")
        grown, trained = run.actor.state_dict(), source.actor.state_dict()
        for name, value in trained.items():
            if name.startswith(("embed_targets.", "embed_robots.")):
                assert torch.equal(grown[name][:value.shape[0]], value)
                assert grown[name].shape[0] == value.shape[0] + n - 3
            else:
                assert torch.equal(grown[name], value), name
        for name, value in source.critic.state_dict().items():
            assert torch.equal(run.critic.state_dict()[name], value)
        assert run.value_norm.mean.item() == pytest.approx(-2.0)
        row = run._iteration()                         # and it trains
        assert row["iteration"] == 1 and torch.isfinite(torch.tensor(row["policy_loss"]))

        zero_shot = load_actor(ckpt, num_robots=n)
        result = evaluate(zero_shot, make_scenario(f"paper-{n}"), episodes=4, seed=1)
        assert result.num_robots == n and result.episodes == 4


def test_init_keep_mixes_the_transferred_weights_with_the_runs_own_fresh_ones(tmp_path):
    source = MAPPOTrainer(tiny(), tmp_path / "three")
    with torch.no_grad():
        for p in [*source.actor.parameters(), *source.critic.parameters()]:
            p.add_(0.5)
    ckpt = source.save()
    fresh = MAPPOTrainer(tiny(scenario="paper-5", seed=7), tmp_path / "fresh")
    mixed = MAPPOTrainer(tiny(scenario="paper-5", seed=7, init_from=str(ckpt), init_keep=0.25),
                         tmp_path / "mixed")
    for net in ("actor", "critic"):
        want_old = getattr(source, net).state_dict()
        want_new = getattr(fresh, net).state_dict()
        for name, value in getattr(mixed, net).state_dict().items():
            assert torch.allclose(value, 0.25 * want_old[name] + 0.75 * want_new[name], atol=1e-6), name
    # log-std, too: 0.25 * (-0.5 + 0.5) + 0.75 * (-0.5)
    assert torch.allclose(mixed.actor.log_std, torch.full((2,), -0.375))
    with pytest.raises(TrainConfigError, match="init_keep"):
        tiny(init_keep=0.0)
    with pytest.raises(TrainConfigError, match="init_keep"):
        tiny(init_keep=1.5)


def test_a_run_with_token_blocks_starts_from_a_checkpoint_without_them(tmp_path):
    source = MAPPOTrainer(tiny(), tmp_path / "plain")
    with torch.no_grad():
        for p in source.actor.parameters():
            p.add_(0.05)
    ckpt = source.save()
    mixed = MAPPOTrainer(tiny(scenario="paper-4", init_from=str(ckpt), init_keep=1.0,
                              actor=SMALL_NET | {"token_layers": 1}), tmp_path / "mixed")
    obs, mask = BatchedFormationEnv(make_scenario("paper-4"), 2, seed=0).reset()
    with torch.no_grad():                  # the new block starts as the identity
        assert torch.equal(mixed.actor(obs, mask), source.actor(obs, mask))
    assert len(mixed.actor.mixers) == 1
    row = mixed._iteration()
    assert row["iteration"] == 1 and torch.isfinite(torch.tensor(row["policy_loss"]))
    with torch.no_grad():                  # and it trains: the block's output layer moved off zero
        assert float(mixed.actor.mixers[0].out.weight.abs().max()) > 0
    back = mixed.save()
    with pytest.raises(CheckpointError, match="token_layers"):
        MAPPOTrainer(tiny(init_from=str(back)), tmp_path / "drop")


@pytest.mark.parametrize("change", [{"velocity_damping": 3.0}, {"frame": "world"}, {"own_target": True}])
def test_a_transfer_refuses_an_actor_that_would_compute_otherwise_than_its_source(tmp_path, change):
    """The transferred actor is rebuilt from the source's settings, and the checkpoint records this
    run's: a setting the network computes with must agree, or export, eval and resume would load
    another network than the one trained (before, a damping of 3 trained as 0 and was loaded as 3)."""
    ckpt = MAPPOTrainer(tiny(), tmp_path / "three").save()
    key = next(iter(change))
    with pytest.raises(CheckpointError, match=f"actor.{key} is"):
        MAPPOTrainer(tiny(scenario="paper-5", init_from=str(ckpt), actor=SMALL_NET | change), tmp_path / "five")


def test_typed_zero_shot_policy_is_the_trained_one(tmp_path):
    source = MAPPOTrainer(tiny(), tmp_path / "three")
    ckpt = source.save()
    five = load_actor(ckpt, num_robots=5)
    obs, mask = BatchedFormationEnv(make_scenario("paper-5"), 2, seed=0).reset()
    with torch.no_grad():
        assert torch.equal(five(obs, mask), source.actor(obs, mask))


def test_mlp_baseline_trains_on_flat_vectors_and_refuses_transfer(tmp_path):
    mlp = tiny(actor={"variant": "mlp", "hidden_sizes": [32]}, critic={"variant": "mlp", "hidden_sizes": [32]},
               total_episodes=4)
    result = train(mlp, tmp_path / "mlp")
    assert result.iterations == 4
    with pytest.raises(CheckpointError, match="cannot run 4"):
        MAPPOTrainer(mlp.replace(scenario="paper-4", init_from=result.checkpoint), tmp_path / "mlp4")
    with pytest.raises(TrainConfigError, match="critic.variant"):
        tiny(actor={"variant": "mlp"})


def test_checkpoint_errors_name_the_problem(tmp_path):
    with pytest.raises(CheckpointError, match="does not exist"):
        load_checkpoint(tmp_path / "missing.pt")
    save_checkpoint(tmp_path / "old.pt", {"config": {}})
    data = torch.load(tmp_path / "old.pt", weights_only=True)
    data["layout_version"] = LAYOUT_VERSION + 1
    torch.save(data, tmp_path / "old.pt")
    with pytest.raises(CheckpointError, match="observation layout version"):
        load_checkpoint(tmp_path / "old.pt")
    torch.save({"weights": torch.zeros(2)}, tmp_path / "other.pt")
    with pytest.raises(CheckpointError, match="not a formation-stack/mappo checkpoint"):
        load_checkpoint(tmp_path / "other.pt")


def test_config_round_trip_and_errors():
    cfg = tiny(scenario=make_scenario("line-1").to_dict())
    assert MAPPOConfig.from_dict(json.loads(json.dumps(cfg.to_dict()))) == cfg
    with pytest.raises(TrainConfigError, match="unknown config field"):
        MAPPOConfig.from_dict({"num_env": 4})
    with pytest.raises(TrainConfigError, match="num_envs"):
        MAPPOConfig(num_envs=0)
    with pytest.raises(TrainConfigError, match=r"^unknown scenario 'paper-99'; choose one of"):
        MAPPOConfig(scenario="paper-99")            # the message names the scenario: no prefix
    with pytest.raises(TrainConfigError, match=r"^scenario: target_tolerance must be > 0"):
        MAPPOConfig(scenario={**make_scenario("line-1").to_dict(), "target_tolerance": 0.0})
    with pytest.raises(TrainConfigError, match="gamma"):
        MAPPOConfig(gamma=1.5)
    with pytest.raises(TrainConfigError, match="unknown reward_weights field"):
        MAPPOConfig(reward_weights={"w_collision": 1.0})
    assert MAPPOConfig(reward_weights={"w_object": 2.0}).build_reward_weights().w_object == 2.0


# One robot beside the object (the way is clear): a few dozen updates teach it to drive onto its
# target and stop there.
CLEAR_LANE = Scenario(name="clear-lane-1", num_robots=1, start_slots=((0.62, 0.15),),
                      target_slots=((0.38, 0.15),)).to_dict()


@pytest.mark.slow
def test_short_training_run_beats_the_untrained_policy(tmp_path):
    cfg = tiny(scenario=CLEAR_LANE, num_envs=8, total_episodes=120, eval_interval=40, eval_episodes=50,
               update_epochs=5, num_minibatches=4, checkpoint_interval=100, lr=1e-3)
    result = train(cfg, tmp_path)
    evals = rows(tmp_path / "eval.jsonl")
    assert evals[0]["episodes"] == 0 and evals[0]["success_rate"] == 0.0      # untrained: stays put
    assert result.last_eval["success_rate"] >= 0.8
    assert result.last_eval["final_distance"] < 0.05 < evals[0]["final_distance"]   # within tolerance


def test_reward_weight_overrides_reach_the_training_world(tmp_path):
    zero = dict.fromkeys(("w_dist", "w_arrive", "w_robot", "w_object", "w_wall"), 0.0)
    silent = MAPPOTrainer(tiny(reward_weights=zero), tmp_path / "silent")
    assert silent._iteration()["reward_mean"] == 0.0         # every term weighted by zero
    plain = MAPPOTrainer(tiny(), tmp_path / "plain")
    assert plain._iteration()["reward_mean"] < -0.1           # the robots start ~0.34 m from the targets


def test_tensorboard_scalars_hold_the_logged_rows(tmp_path):
    from tensorboard.backend.event_processing.event_accumulator import EventAccumulator

    train(tiny(tensorboard=True), tmp_path)
    events = EventAccumulator(str(tmp_path / "tensorboard"))
    events.Reload()
    evals = rows(tmp_path / "eval.jsonl")
    logged = [(e.step, e.value) for e in events.Scalars("eval/success_rate")]
    assert logged == [(e["episodes"], pytest.approx(e["success_rate"])) for e in evals]
    train_rows = rows(tmp_path / "train.jsonl")
    rewards = [e.value for e in events.Scalars("train/reward_mean")]
    assert rewards == pytest.approx([r["reward_mean"] for r in train_rows], rel=1e-6)
    assert "train/return_mean" in events.Tags()["scalars"]       # None rows are skipped, others kept


def test_several_team_sizes_train_side_by_side_and_resume_on_the_same_curve(tmp_path):
    config = tiny(team_sizes=[2, 3], total_episodes=16, eval_interval=8)
    whole = train(config, tmp_path / "whole")
    # every iteration steps both groups: 4 envs x 32 steps each; 8 episodes finish per episode length
    assert whole.env_steps == whole.iterations * 32 * 4 * 2 and whole.episodes == 16
    evals = rows(tmp_path / "whole" / "eval.jsonl")
    assert [e["episodes"] for e in evals] == [0, 8, 16]
    for e in evals:                       # the run's success is its worst size's
        assert e["success_rate"] == min(e["success_rate_n2"], e["success_rate_n3"])
    ckpt = load_checkpoint(tmp_path / "whole" / "checkpoint.pt")
    assert [s["pos"].shape[1] for s in ckpt["env_state"]] == [2, 3]
    train(config.replace(total_episodes=8), tmp_path / "parts")
    train(config, tmp_path / "parts", resume=True)
    assert rows(tmp_path / "parts" / "train.jsonl") == rows(tmp_path / "whole" / "train.jsonl")
    assert rows(tmp_path / "parts" / "eval.jsonl") == evals
    with pytest.raises(TrainConfigError, match="team_sizes"):
        train(tiny(total_episodes=16, eval_interval=8, team_sizes=[2, 3, 4]), tmp_path / "parts", resume=True)


def test_a_distribution_draws_layouts_and_actuators_and_resumes_on_the_same_curve(tmp_path):
    """Training on the broad distribution: each group's layout changes between episodes, the
    actuators differ per environment, the config stores the ranges, and a resume is exact."""
    config = tiny(team_sizes=[2, 3], total_episodes=24, eval_interval=8, distribution="broad")
    assert config.distribution == DISTRIBUTIONS["broad"].to_dict()
    whole = MAPPOTrainer(config, tmp_path / "whole")
    seen = set()
    while whole.episodes < 24:
        whole._iteration()
        seen |= {g.env.scenario.name for g in whole.groups}
    assert len(seen) >= 4                                  # new layouts as episodes end
    assert float(whole.groups[0].env.actuators.gain.std()) > 0.05
    whole.save()
    state = load_checkpoint(tmp_path / "whole" / "checkpoint.pt")["env_state"]
    assert [s["layout"]["name"] for s in state] == [g.env.scenario.name for g in whole.groups]
    shorter = config.replace(total_episodes=16)
    train(config.replace(total_episodes=8), tmp_path / "a")     # stops where a layout was just drawn
    train(shorter, tmp_path / "a", resume=True)                  # ... and draws another
    train(shorter, tmp_path / "b")
    assert rows(tmp_path / "a" / "train.jsonl") == rows(tmp_path / "b" / "train.jsonl")


def test_the_update_draws_minibatches_of_every_team_size(tmp_path):
    trainer = MAPPOTrainer(tiny(team_sizes=[2, 4]), tmp_path / "run")
    seen = []
    forward = trainer.actor.forward

    def spy(obs, mask=None):
        if torch.is_grad_enabled():
            seen.append(obs.shape[1])
        return forward(obs, mask)

    trainer.actor.forward = spy
    trainer._iteration()
    # 2 epochs x 2 minibatches x 2 sizes, in a shuffled order that mixes the sizes
    assert sorted(seen) == [2] * 4 + [4] * 4 and seen != sorted(seen)


@pytest.mark.parametrize(("changes", "field"), [
    ({"team_sizes": [3, 3]}, "twice"),
    ({"team_sizes": [0, 3]}, "1..21"),
    ({"team_sizes": "3,4"}, "team_sizes must be a list"),
    ({"team_sizes": [3, 4], "actor": {"variant": "slot"}}, "actor.variant 'slot'"),
])
def test_team_sizes_errors_name_the_field(changes, field):
    with pytest.raises(TrainConfigError, match=field):
        tiny(**changes)
