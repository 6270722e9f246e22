"""deploy.zenoh_fleet: `formation eval --world zenoh` drives a fleet-sim process through the
ControlStack (filter, MEC and docking on) over real Zenoh on 127.0.0.1."""

from __future__ import annotations

import json

import pytest

from deploy.network import free_tcp_port
from stack.cli import main
from tests.deploy.test_fleet_sim_bridge import Proc

pytestmark = pytest.mark.realtime   # a fleet over Zenoh


@pytest.mark.slow
def test_eval_drives_the_fleets_own_episodes_and_agrees_with_its_report(tmp_path, capsys):
    endpoint = f"tcp/127.0.0.1:{free_tcp_port()}"
    sim = Proc("fleet-sim", "--fleet", "ez", "--scenario", "paper-5", "--lockstep", "--episodes", "2",
               "--listen", endpoint, "--report", str(tmp_path / "sim.json"))
    try:
        code = main(["eval", "--policy", "scripted", "--world", "zenoh", "--fleet", "ez", "--lockstep",
                     "--episodes", "2", "--scenario", "paper-5", "--connect", endpoint,
                     "--report", str(tmp_path / "eval.json"), "--record", str(tmp_path / "trace")])
        assert code == 0
        assert sim.finish() == 0, "".join(sim.stderr)
    finally:
        if sim.proc.poll() is None:
            sim.proc.kill()
    ours = json.loads((tmp_path / "eval.json").read_text())
    theirs = json.loads((tmp_path / "sim.json").read_text())["episodes"]
    assert ours["world"] == "zenoh" and ours["episodes"] == 2 and ours["safety"] and ours["mec"]
    assert ours["success_rate"] == 1.0 and ours["collision_rate"] == 0.0
    assert [e["success"] for e in theirs] == [True, True]
    # judged one tick before the fleet's own report (module docstring), both within a millimetre
    assert ours["final_distance"] < 1e-3
    assert max(e["final_distance"] for e in theirs) < 1e-3
    # the recorder keeps what the fleet reported over the wire, tick by tick
    from stack.episode_plot import assigned_distances
    from stack.recorder import load_record

    for seed in (0, 1):
        record = load_record(tmp_path / "trace" / f"episode_{seed}.npz")
        assert (record.steps, record.num_robots) == (127, 5) and record.present.all()
        assert not record.contacts.any() and record.meta["world"] == "zenoh"
        dist, _ = assigned_distances(record)
        assert dist[-1].mean() == pytest.approx(record.meta["metrics"]["final_distance"], abs=1e-12)
        assert (tmp_path / "trace" / f"episode_{seed}.png").stat().st_size > 50_000


def test_eval_over_zenoh_names_what_is_missing(capsys):
    assert main(["eval", "--policy", "scripted", "--world", "zenoh", "--scenario", "paper-3"]) == 2
    assert "--fleet" in capsys.readouterr().err
    assert main(["eval", "--policy", "scripted", "--world", "zenoh", "--fleet", "x", "--episode-ticks", "500",
                 "--connect", "tcp/127.0.0.1:1"]) == 2
    assert "at most 127" in capsys.readouterr().err


def test_eval_over_zenoh_without_a_fleet_there_exits_2_without_a_traceback(monkeypatch, capsys):
    """Before, FleetTimeout escaped `formation eval` as a traceback (here after 1 s, not 30)."""
    from deploy.zenoh_fleet import ZenohFleet

    config, _, answer = ZenohFleet.__init__.__defaults__
    monkeypatch.setattr(ZenohFleet.__init__, "__defaults__", (config, 1.0, answer))
    assert main(["eval", "--policy", "scripted", "--world", "zenoh", "--fleet", "nobody", "--episodes", "1",
                 "--scenario", "paper-5", "--connect", f"tcp/127.0.0.1:{free_tcp_port()}"]) == 2
    assert "error: --world zenoh: no state from fleet 'nobody' within 1.0 s" in capsys.readouterr().err


def test_eval_refuses_a_fleet_whose_robots_are_not_the_scenarios(capsys):
    """Before, `eval --world zenoh` with the default --scenario paper-3 drove three robots of a
    5-robot fleet, left the other two unanswered (UNKNOWN_ROBOT, lock-step timeouts, collisions
    in the fleet) and exited 0 with a result. Both ways round it now exits 2 naming --scenario."""
    endpoints = {n: f"tcp/127.0.0.1:{free_tcp_port()}" for n in (3, 5)}
    sims = {n: Proc("fleet-sim", "--fleet", f"m{n}", "--scenario", f"paper-{n}", "--lockstep", "--episodes", "1",
                    "--listen", endpoints[n]) for n in (3, 5)}
    try:
        for ours, theirs in ((3, 5), (5, 3)):
            code = main(["eval", "--policy", "scripted", "--world", "zenoh", "--fleet", f"m{theirs}", "--lockstep",
                         "--episodes", "1", "--scenario", f"paper-{ours}", "--connect", endpoints[theirs]])
            err = capsys.readouterr().err
            assert code == 2, err[-800:]
            assert (f"--scenario paper-{ours} has robots r0..r{ours - 1}, but fleet 'm{theirs}' runs "
                    f"r0..r{theirs - 1}: give --scenario the scenario the fleet runs (e.g. --scenario "
                    f"paper-{theirs})") in err
            assert "Traceback" not in err
    finally:
        for sim in sims.values():
            sim.proc.kill()
            sim.proc.wait()


def test_an_answer_past_its_deadline_is_dropped_and_the_stack_told_of_the_brake():
    """A lock-stepped fleet-sim driven tick by tick through ZenohFleet; the answer to the fourth
    picture comes 0.8 s late (``answer_timeout_s`` 0.3). The bridge brakes every robot on that
    tick and the next (whose picture the stack answers late in turn), and every other tick's
    command is the answer to that tick's own picture: a late answer is not taken for the next
    (before, every later command was one picture old). The stack hears of both brakes (its
    command history's newest entry is braking on every row). Once the fleet has gone quiet, an
    answer nobody reads does not block the next."""
    import threading
    import time

    import numpy as np

    from deploy.bridge import BridgeConfig
    from deploy.network import TransportConfig
    from deploy.zenoh_fleet import ZenohFleet
    from sim.scenario import make_scenario
    from stack.pipeline import ControlStack, StackConfig

    endpoint = f"tcp/127.0.0.1:{free_tcp_port()}"
    sim = Proc("fleet-sim", "--fleet", "late", "--scenario", "paper-3", "--lockstep", "--episodes", "1",
               "--lockstep-timeout", "0.25", "--listen", endpoint)
    scenario = make_scenario("paper-3")
    answers, sent = [], []
    stack = ControlStack(scenario, lambda s: np.tile([0.1 * len(answers) + 0.05, 0.0], (s.num_robots, 1)),
                         StackConfig(mec=False))
    try:
        with ZenohFleet(scenario, "late", TransportConfig(connect=(endpoint,)),
                        BridgeConfig(lockstep=True, period_s=scenario.dynamics.dt),
                        answer_timeout_s=0.3) as fleet:
            send = fleet.bridge.link.send_command

            def spy(robot, acceleration, *args, **kwargs):
                if robot == "r0":
                    sent.append(acceleration[0])
                return send(robot, acceleration, *args, **kwargs)

            fleet.bridge.link.send_command = spy
            state = fleet.reset()
            braked = []
            for k in range(8):
                command = stack.tick(state).a_cmd
                answers.append(command[0, 0])
                if k == 3:
                    time.sleep(0.8)
                fleet.send_accelerations(command)
                given, state = state, fleet.step()
                braked.append(fleet.braked_in_place(given))
                if braked[-1] is not None:
                    stack.sent_braking(given, braked[-1])
                    assert stack.predictor._braked[-1].all()
            sim.proc.kill()                     # the fleet goes quiet: answers pile up unread
            sim.proc.wait()
            answered = threading.Event()

            def answer_thrice():       # the bridge takes the first, the second waits unread
                for _ in range(3):
                    fleet.send_accelerations(command)
                answered.set()

            threading.Thread(target=answer_thrice, daemon=True).start()
            assert answered.wait(5.0), "an answer nobody reads blocked the caller"
    finally:
        sim.proc.kill()
        sim.proc.wait()
    assert [b is not None and b.all() for b in braked] == [False] * 3 + [True] * 2 + [False] * 3, braked
    assert np.allclose(sent[:8], answers[:3] + [0.0, 0.0] + answers[5:]), (sent, answers)


def test_run_episode_over_zenoh_records_the_ticks_the_bridge_braked_for_a_late_answer():
    """`formation eval --world zenoh --record`'s path: run_episode drives a lock-stepped
    fleet-sim through ZenohFleet with a policy that takes 0.5 s over tick 10
    (``answer_timeout_s`` 0.3). The record flags every row of that tick (and of the next, whose
    picture waited behind it) as braked by the link, with the braking law as the command sent,
    and no other tick."""
    import time

    import numpy as np

    from controllers.scripted import ScriptedController
    from deploy.bridge import BridgeConfig
    from deploy.network import TransportConfig
    from deploy.zenoh_fleet import ZenohFleet
    from sim.scenario import make_scenario
    from stack.episodes import run_episode
    from stack.pipeline import ControlStack, StackConfig
    from stack.recorder import EpisodeRecorder

    scenario = make_scenario("paper-3")
    scripted = ScriptedController(scenario)

    def slow_on_tick_10(state):
        if state.step == 10:
            time.sleep(0.5)
        return scripted(state)

    endpoint = f"tcp/127.0.0.1:{free_tcp_port()}"
    sim = Proc("fleet-sim", "--fleet", "slow", "--scenario", "paper-3", "--lockstep", "--episodes", "1",
               "--lockstep-timeout", "0.25", "--listen", endpoint)
    recorder = EpisodeRecorder()
    try:
        with ZenohFleet(scenario, "slow", TransportConfig(connect=(endpoint,)),
                        BridgeConfig(lockstep=True, period_s=scenario.dynamics.dt), answer_timeout_s=0.3) as fleet:
            stack = ControlStack(scenario, slow_on_tick_10, StackConfig())
            run_episode(fleet, stack, 0, 20, recorder=recorder)
    finally:
        sim.proc.kill()
        sim.proc.wait()
    record = recorder.finish()
    braked_ticks = np.flatnonzero(record.link_braked.any(axis=1)).tolist()
    assert braked_ticks[0] == 10 and braked_ticks == list(range(10, 10 + len(braked_ticks)))
    assert len(braked_ticks) <= 2 and record.link_braked[braked_ticks].all()
    assert np.abs(record.a_cmd[braked_ticks] - record.a_safe[braked_ticks]).max() > 0.01
