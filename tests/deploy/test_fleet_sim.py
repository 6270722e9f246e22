"""deploy.fleet_sim in process over real Zenoh on 127.0.0.1: whom a simulated robot obeys."""

from __future__ import annotations

import threading
import time

import numpy as np
import pytest
import zenoh

from deploy.fleet_sim import FleetSim, FleetSimConfig
from deploy.network import FleetKeys, TransportConfig, free_tcp_port
from deploy.wire import CmdMsg, EstopMsg, encode
from sim.scenario import make_scenario

pytestmark = pytest.mark.realtime   # fleet-sim on Zenoh sessions


def test_a_robot_obeys_no_command_while_no_controller_token_is_seen():
    """A node that publishes well-formed, fresh commands on r0's key but holds no controller
    liveliness token moves no robot: every command is ignored and counted (before the rule the
    robot drove 0.29 m, into the wall)."""
    endpoint = f"tcp/127.0.0.1:{free_tcp_port()}"
    sim = FleetSim(FleetSimConfig(fleet="nc", scenario=make_scenario("paper-3"), rate_hz=20.0, max_ticks=30,
                                  start_timeout_s=0.1, transport=TransportConfig(listen=(endpoint,))))
    runner = threading.Thread(target=sim.run)
    runner.start()
    with zenoh.open(TransportConfig(connect=(endpoint,)).to_zenoh()) as raw:
        publisher = raw.declare_publisher(FleetKeys("nc").cmd("r0"))
        deadline = time.monotonic() + 10.0
        while not publisher.matching_status and time.monotonic() < deadline:
            time.sleep(0.01)
        assert publisher.matching_status, "fleet-sim never subscribed"
        seq = 0
        while runner.is_alive():
            seq += 1
            publisher.put(encode(CmdMsg(0, 4242, seq, time.monotonic_ns(), (1.0, 0.0), 500)))
            time.sleep(0.02)
    runner.join(timeout=10.0)
    report = sim.summary()
    assert report["rejects"] == {}                          # every command was well formed
    assert report["ignored_without_controller"] >= 10
    assert max(report["speeds"]) == 0.0
    assert np.allclose(report["positions"], sim.world.scenario.starts, atol=0.02)


def test_a_run_without_a_tick_or_episode_limit_keeps_a_bounded_trace():
    from deploy.fleet_sim import TRACE_TICKS

    sc = make_scenario("paper-3")
    endless = FleetSim(FleetSimConfig(fleet="tr", scenario=sc, transport=TransportConfig(), rate_hz=20.0))
    for k in range(TRACE_TICKS + 5):
        endless.trace.append({"tick": k})
    assert len(endless.trace) == TRACE_TICKS and endless.trace[0]["tick"] == 5
    lockstep = FleetSim(FleetSimConfig(fleet="tr", scenario=sc, transport=TransportConfig(), rate_hz=None))
    assert lockstep.trace.maxlen == TRACE_TICKS       # lock-step without a limit may run for days too
    for limit in ({"max_ticks": 50}, {"episodes": 2}):  # a run with an end keeps every tick
        kept = FleetSim(FleetSimConfig(fleet="tr", scenario=sc, transport=TransportConfig(), rate_hz=None, **limit))
        assert kept.trace.maxlen is None


def test_fleet_sim_refuses_to_freeze_a_robot_the_team_does_not_have(capsys):
    from stack.cli import main

    assert main(["fleet-sim", "--fleet", "fz", "--scenario", "paper-4", "--model-error", "freeze=4:20"]) == 2
    assert "paper-4 has 4 robots: pick a row in 0..3" in capsys.readouterr().err


def test_a_playout_buffer_takes_the_newest_command_that_is_due_after_the_one_it_took():
    """Hand-worked: commands 5, 6, 7, 8, 9 answer states 10, 11, 12, none (0: a BRAKE or STOP,
    due at once) and 13, in the order they arrived."""
    from deploy.transport import ReceivedCommand

    def cmd(seq: int, state_seq: int) -> ReceivedCommand:
        return ReceivedCommand(CmdMsg(0, 1, seq, 0, (0.0, 0.0), 100, state_seq=state_seq), 0, 0)

    recent = tuple(cmd(seq, s) for seq, s in ((5, 10), (6, 11), (7, 12), (8, 0), (9, 13)))
    due = FleetSim._due_command
    assert due(recent[:3], (1, 4), 11).msg.seq == 6      # 5 overtaken, 7 not due yet
    assert due(recent[:3], (1, 6), 11) is None           # holds 6
    assert due(recent[:3], (1, 6), 12).msg.seq == 7
    assert due(recent, (1, 6), 11).msg.seq == 8          # the one answering no state: at once
    assert due(recent, (1, 8), 12) is None               # 7 came before 8, which overrode it
    assert due(recent, (1, 8), 13).msg.seq == 9
    assert due(recent, (1, 2), 9).msg.seq == 8           # the one taken is no longer kept


@pytest.mark.parametrize("value", [-1, 1.5, True])
def test_a_playout_that_cannot_work_is_refused_by_name(value):
    with pytest.raises(ValueError, match="playout_ticks must be an integer >= 0"):
        FleetSimConfig(fleet="f", scenario=make_scenario("paper-3"), transport=TransportConfig(),
                       playout_ticks=value)


def test_a_robot_brakes_until_it_knows_whether_the_controller_has_an_estop_latched():
    """A controller (its token, its e-stop queryable) that answers the robots' query for its latched
    e-stop only after 0.6 s, with an ENGAGED one, and meanwhile sends full-thrust commands: no robot
    moves, neither before the answer (it cannot know yet) nor after (it is latched). Before the
    rule r0 drove off in the 0.6 s before the answer."""
    endpoint = f"tcp/127.0.0.1:{free_tcp_port()}"
    keys = FleetKeys("es")
    sim = FleetSim(FleetSimConfig(fleet="es", scenario=make_scenario("paper-3"), rate_hz=20.0, max_ticks=30,
                                  start_timeout_s=5.0, transport=TransportConfig(listen=(endpoint,))))
    runner = threading.Thread(target=sim.run)
    runner.start()
    engaged = encode(EstopMsg(99, 1, time.monotonic_ns(), True, 2))
    with zenoh.open(TransportConfig(connect=(endpoint,)).to_zenoh()) as raw:
        queries = raw.declare_queryable(keys.estop, zenoh.handlers.FifoChannel(16))
        publisher = raw.declare_publisher(keys.cmd("r0"))
        token = raw.liveliness().declare_token(keys.ctrl_alive)
        first_query_ns, pending, seq = None, [], 0
        while runner.is_alive():
            query = queries.try_recv()
            if query is not None:
                first_query_ns = first_query_ns or time.monotonic_ns()
                pending.append(query)
            if first_query_ns and time.monotonic_ns() - first_query_ns >= 600_000_000:
                for late in pending:                           # every robot's query, answered late
                    late.reply(keys.estop, engaged)
                    late.drop()
                pending.clear()
            seq += 1
            publisher.put(encode(CmdMsg(0, 4242, seq, time.monotonic_ns(), (1.0, 0.0), 500)))
            time.sleep(0.02)
        token.undeclare()
    runner.join(timeout=10.0)
    report = sim.summary()
    assert first_query_ns is not None, "no robot asked for the latched e-stop"
    assert max(report["speeds"]) == 0.0
    assert np.allclose(report["positions"], sim.world.scenario.starts, atol=0.02)


@pytest.mark.parametrize("change, message", [
    ({"rate_hz": float("inf")}, "rate_hz must be a finite number"),
    ({"lockstep_timeout_s": float("nan")}, "lockstep_timeout_s must be a finite number"),
    ({"lockstep_timeout_s": -1.0}, "lockstep_timeout_s must be a finite number"),
    ({"start_timeout_s": float("nan")}, "start_timeout_s must be a finite number"),
    ({"max_ticks": -3}, "max_ticks must be an integer >= 0"),
])
def test_settings_that_disable_the_watchdog_or_spin_the_start_are_refused(change, message):
    """rate_hz inf made the period 0, so a robot's command never aged and its watchdog never
    latched; stop_after_s inf did the same; a NaN start timeout waited for ever on a full core."""
    from deploy.fleet_sim_config import WatchdogConfig

    transport = TransportConfig(listen=("tcp/127.0.0.1:7447",))
    with pytest.raises(ValueError, match=message):
        FleetSimConfig("f", make_scenario("paper-3"), transport, **change)
    with pytest.raises(ValueError, match="stop_after_s must be a finite number"):
        WatchdogConfig(stop_after_s=float("inf"))


def test_a_robot_restarted_at_a_tick_is_online_before_it():
    """--leave r4@2 --join r4@2 (a restart) started r4 offline: its first event was read from
    the events sorted by name, where 'join' comes before 'leave'."""
    cfg = FleetSimConfig("sametick", make_scenario("paper-5"),
                         TransportConfig(listen=(f"tcp/127.0.0.1:{free_tcp_port()}",)), rate_hz=20.0,
                         max_ticks=4, start_timeout_s=0.2, events=((2, "r4", "leave"), (2, "r4", "join")))
    modes = [entry["modes"][4] for entry in FleetSim(cfg).run()["trace"]]
    assert modes[0] != "offline" and modes[1] != "offline", modes
