"""Smoke test of bench/safety.py: a tiny run prints one JSON document of the promised shape."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[2]
sys.path.insert(0, str(REPO / "bench"))
import _safety_clutter  # noqa: E402


@pytest.mark.slow
def test_safety_bench_json_shape():
    out = subprocess.run(
        [sys.executable, str(REPO / "bench" / "safety.py"), "--json", "--episodes", "4", "--episode-ticks", "15",
         "--cpus", "1", "--mec-episodes", "1", "--robots", "3,5", "--ticks", "20", "--warmup", "5",
         "--conditions", "delay2,frozen_robot", "--condition-episodes", "2", "--task-episodes", "1",
         "--intruder-conditions", "clean", "--intruder-episodes", "1", "--clutter-discs", "0,10",
         "--clutter-episodes", "1"],
        cwd=REPO, capture_output=True, text=True, check=True, timeout=300)
    doc = json.loads(out.stdout)   # stdout holds the document alone; progress is on stderr
    clutter = doc["clutter"]
    assert set(clutter) == {"0", "10"} and clutter["0"]["max_discs_in_qp"] == 0
    for row in clutter.values():
        assert row["ticks"] == 128 and 0 < row["p50_ms"] <= row["p99_ms"] and 0 < row["p50_ms_all"]
        assert row["compared_ticks"] >= 1 and row["max_command_diff"] <= 1e-5
    assert clutter["10"]["max_discs_in_qp"] <= 10
    assert list(doc["intruders"]) == ["clean"] and doc["intruders"]["clean"]["scripted"]["episodes"] == 1
    inv = doc["invariance"]
    assert inv["episodes"] == 4 and inv["steps"] == 15     # the key other tools read, as before
    assert inv["collisions_filter_on"] <= inv["collisions_filter_off"] <= 4
    mec = doc["mec"]
    assert mec["tracking_error_without"] > 0 and mec["tracking_error_with"] >= 0
    assert set(doc["latency_ms"]) == {"3", "5"}
    cond = doc["conditions"]
    assert set(cond) == {"delay2", "frozen_robot"}
    for entry in cond.values():          # the keys other tools read
        assert entry["episodes"] == 2 and entry["scripted_episodes"] == 1
        assert entry["collisions_filter_on"] <= entry["collisions_filter_off"] <= 2
        assert set(entry["tracking_error_mm"]) == {"mec", "no_mec"}
    assert cond["delay2"]["collisions_filter_off"] == 2     # bare robots at full thrust collide
    for entry in cond.values():          # the scripted controller arrives within its 128 ticks
        arrival = entry["arrival_scripted"]
        if arrival["paired_episodes"]:
            assert 1 <= arrival["mean_step"] <= 128 and 1 <= arrival["mean_step_bare"] <= 128
    assert cond["delay2"]["arrival_scripted"]["paired_episodes"] == 1
    for entry in cond.values():          # the split agrees with the two success rates
        pairs = entry["success_scripted_pairs"]
        gap = (entry["success_scripted"] - entry["success_scripted_bare"]) * entry["scripted_episodes"]
        assert round(gap) == pairs["stack_only"] - pairs["bare_only"]
    frozen = cond["frozen_robot"]         # judged on the commanded robots too, only with a freeze
    assert "success_scripted_commanded" not in cond["delay2"]
    assert frozen["success_scripted_commanded"] >= frozen["success_scripted"]
    assert frozen["success_scripted_commanded_bare"] >= frozen["success_scripted_bare"]
    assert set(frozen["success_scripted_commanded_pairs"]) == {"stack_only", "bare_only", "sign_test_p"}
    assert {"frozen_home_scripted", "frozen_home_scripted_bare"} <= set(frozen)   # counted with a freeze
    assert "frozen_home_scripted" not in cond["delay2"]                            # and only then
    assert doc["stack_config"]["latency"]["command_delay_s"] == 0.15    # what "filter + MEC" ran
    assert doc["stack_config"]["safety"] and doc["stack_config"]["mec"]
    assert len(doc["provenance"]["git"]["commit"]) == 40 and doc["provenance"]["packages"]["torch"]
    for row in doc["latency_ms"].values():
        assert 0 < row["p50"] <= row["p99"]
        assert 0 < row["policy_p50"] and 0 < row["safety_p50"]
    assert set(doc["latency_ms_torchscript_module"]) == {"3", "5"}
    by_format = doc["latency_ms_by_format"]            # the key other tools read
    assert set(by_format) == {"torchscript", "pt2", "onnx", "npz"}
    for rows in by_format.values():
        assert set(rows) == {"3", "5"}
        for row in rows.values():
            assert row["ticks"] == 20 and 0 < row["policy_stage_p50"] <= row["policy_stage_p99"]


def test_safety_bench_rejects_an_unknown_condition():
    out = subprocess.run([sys.executable, str(REPO / "bench" / "safety.py"), "--conditions", "delay9"],
                         cwd=REPO, capture_output=True, text=True, timeout=120)
    assert out.returncode == 2 and "unknown condition" in out.stderr and "delay_jitter" in out.stderr


def test_safety_bench_narrows_the_latency_bound_of_the_stack_columns_as_asked():
    out = subprocess.run(
        [sys.executable, str(REPO / "bench" / "safety.py"), "--json", "--only", "conditions", "--conditions", "clean",
         "--condition-episodes", "1", "--task-episodes", "1", "--mec-episodes", "1", "--episode-ticks", "5",
         "--cpus", "1", "--command-delay-ms", "50"],
        cwd=REPO, capture_output=True, text=True, check=True, timeout=300)
    doc = json.loads(out.stdout)
    assert doc["stack_config"]["latency"]["command_delay_s"] == 0.05
    assert doc["conditions"]["clean"]["episodes"] == 1
    bad = subprocess.run([sys.executable, str(REPO / "bench" / "safety.py"), "--command-delay-ms", "-5"],
                         cwd=REPO, capture_output=True, text=True, timeout=120)
    assert bad.returncode == 2 and "--command-delay-ms" in bad.stderr


def test_safety_bench_intruders_part_runs_both_stacks_on_the_same_intruders():
    """Three seeds (paper-3, -4, -5) of the delay2 condition: the document's shape, and the
    stack keeping clear of what the bare run drives into on the same seeds."""
    out = subprocess.run(
        [sys.executable, str(REPO / "bench" / "safety.py"), "--json", "--only", "intruders",
         "--intruder-conditions", "delay2", "--intruder-episodes", "3", "--cpus", "1", "--seed", "3"],
        cwd=REPO, capture_output=True, text=True, check=True, timeout=300)
    doc = json.loads(out.stdout)
    row = doc["intruders"]["delay2"]["scripted"]
    assert row["episodes"] == 3 and row["sighting_delay_ticks"] == 2
    assert row["drive_in_episodes"] == 0 and row["contact_episodes"] == 0
    assert row["drive_in_episodes_bare"] >= 1 and row["min_gap_mm_bare"] < 0 < row["min_gap_mm"]


def test_random_intruders_cross_the_arena_or_stand_clear_of_every_slot():
    sys.path.insert(0, str(REPO / "bench"))
    import numpy as np
    from _safety_intruders import random_intruders

    from sim.scenario import make_scenario

    sc = make_scenario("paper-5")
    drawn = [x for seed in range(40) for x in random_intruders(np.random.default_rng(seed), sc)]
    walkers = [x for x in drawn if x.speed > 0]
    boxes = [x for x in drawn if x.speed == 0]
    assert walkers and boxes and all(0.03 <= x.radius <= 0.08 for x in drawn)
    for x in walkers:       # it enters from outside and is outside again when it leaves
        inside = [bool(((c > 0) & (c < 1)).all()) for c in (x.centre(x.enter_tick, sc.dynamics.dt),
                                                           x.centre(x.leave_tick, sc.dynamics.dt))]
        assert inside == [False, False], x
    slots = np.concatenate([sc.starts, sc.targets])
    for x in boxes:
        assert np.linalg.norm(slots - x.start, axis=1).min() > x.radius + sc.robot_radius + 0.02


def test_safety_bench_rejects_a_missing_policy():
    out = subprocess.run([sys.executable, str(REPO / "bench" / "safety.py"), "--policy", "/no/such.pt"],
                         cwd=REPO, capture_output=True, text=True, timeout=120)
    assert out.returncode == 2 and "does not exist" in out.stderr


def test_success_pairs_count_the_split_episodes_and_its_sign_test():
    sys.path.insert(0, str(REPO / "bench"))
    from _safety_conditions import success_pairs

    def rows(stack_only: int, bare_only: int, both: int) -> list[dict]:
        return ([{"success_on": True, "success_off": False}] * stack_only
                + [{"success_on": False, "success_off": True}] * bare_only
                + [{"success_on": True, "success_off": True}] * both)

    # 1 against 13: p = 2 (C(14, 0) + C(14, 1)) / 2^14 = 30 / 16384
    assert success_pairs(rows(1, 13, 5)) == {"stack_only": 1, "bare_only": 13, "sign_test_p": 0.0018}
    assert success_pairs(rows(0, 5, 0))["sign_test_p"] == 0.0625          # 2 / 2^5
    assert success_pairs(rows(3, 3, 2))["sign_test_p"] == 1.0
    assert success_pairs(rows(0, 0, 4)) == {"stack_only": 0, "bare_only": 0, "sign_test_p": 1.0}


def test_commanded_success_leaves_out_only_the_frozen_robot():
    """Robot 0 of paper-3 freezes at tick 0 on its start slot, 0.34 m from any target: the episode
    fails, but the two robots the scripted stack still commands end on their targets without
    contact, which is what commanded_success judges; a third robot off its target fails it too."""
    sys.path.insert(0, str(REPO / "bench"))
    from _safety_conditions import commanded_success

    from controllers.scripted import ScriptedController
    from sim.pymunk_world import ModelError, PymunkWorld
    from sim.scenario import make_scenario
    from stack.pipeline import ControlStack, run_episode

    sc = make_scenario("paper-3")
    world = PymunkWorld(sc, ModelError(freeze=(0, 0)))
    m = run_episode(world, ControlStack(sc, ScriptedController(sc)), 3)
    assert not m.success and not m.collided
    assert commanded_success(world, m.collided)
    assert not commanded_success(world, True)                      # a contact fails it as before
    world.model_error = ModelError(freeze=(1, 0))                     # judged as if robot 1 froze:
    assert not commanded_success(world, m.collided)                 # robot 0, off its target, counts


def test_frozen_home_asks_only_where_the_frozen_robot_stopped():
    """Robot 0 of paper-3 frozen at tick 0 stands on its start slot, 0.34 m from any target: not
    home. Frozen at tick 120, after the scripted stack brought the team in (tick ~84), it is."""
    sys.path.insert(0, str(REPO / "bench"))
    from _safety_conditions import frozen_home

    from controllers.scripted import ScriptedController
    from sim.pymunk_world import ModelError, PymunkWorld
    from sim.scenario import make_scenario
    from stack.pipeline import ControlStack, run_episode

    sc = make_scenario("paper-3")
    for tick, home in ((0, False), (120, True)):
        world = PymunkWorld(sc, ModelError(freeze=(0, tick)))
        run_episode(world, ControlStack(sc, ScriptedController(sc)), 3)
        assert frozen_home(world) == home


def test_clutter_stacks_take_turns_to_go_first(monkeypatch):
    """Going first costs a stack 10-15 %: over 4 ticks of one episode the peer (every disc) and the
    pruned stack alternate in going first, so each goes first on 2 ticks."""
    calls: list[str] = []

    class Recording(_safety_clutter.ControlStack):
        def tick(self, state):
            calls.append("all" if self.config.all_tracker_discs else "pruned")
            return super().tick(state)

    monkeypatch.setattr(_safety_clutter, "ControlStack", Recording)
    rows = _safety_clutter.run_clutter([0], episodes=1, ticks=4, seed=0)
    assert rows["0"]["ticks"] == 4
    assert calls == ["all", "pruned", "pruned", "all", "all", "pruned", "pruned", "all"]


def _parse(argv):
    import safety

    return safety._parser().parse_args(argv)


def test_ticks_per_episode_and_processes_are_episode_ticks_and_cpus(capsys):
    """One name per concept across the commands: --episode-ticks (ticks in one episode, as the
    bridge's) and --cpus (as sweep's and the other benches')."""
    args = _parse(["--episode-ticks", "5", "--cpus", "3"])
    assert (args.episode_ticks, args.cpus) == (5, 3) and capsys.readouterr().err == ""
    defaults = _parse([])
    assert (defaults.episode_ticks, defaults.cpus) == (60, 2)


@pytest.mark.parametrize("old, new", [(["--steps", "5"], ["--episode-ticks", "5"]),
                                      (["--workers", "3"], ["--cpus", "3"])])
def test_the_old_spellings_still_work_and_warn(old, new, capsys):
    assert _parse(old) == _parse(new)
    assert capsys.readouterr().err == f"warning: {old[0]} is deprecated; use {new[0]}\n"


def test_the_l_object_conditions_put_the_l_in_every_scenario_and_nothing_else():
    import numpy as np
    from _common import L_OBJECT
    from _safety_conditions import model_error, with_object

    from sim.scenario import make_scenario
    paper = make_scenario("paper-4")
    for name in ("l_object", "l_object_link"):
        assert with_object(name, paper).object_vertices == L_OBJECT
        assert with_object(name, paper).target_slots == paper.target_slots
    assert with_object("delay2", paper) is paper
    link = model_error("l_object_link", np.random.default_rng(0), 4, 128)
    assert (link.delay_ticks, link.delay_jitter_ticks, link.state_drop) == (1, 2, 0.2)
    assert model_error("l_object", np.random.default_rng(0), 4, 128).delay_ticks == 0
