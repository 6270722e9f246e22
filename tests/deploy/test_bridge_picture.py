"""The bridge's picture over real Zenoh, in this process (deploy/bridge_picture.py): stale,
silent, leaving and rejoining robots, state ages, the fleet e-stop raised and an operator's
requests, the stall rule, the commands in flight of a robot that left."""

from __future__ import annotations

import json
import threading
import time

import numpy as np
import pytest

from controllers.scripted import ScriptedController
from deploy.bridge import ESTOP_STALE_PICTURE, Bridge, BridgeConfig
from deploy.fleet_sim import FleetSim, FleetSimConfig, robot_names
from deploy.network import TransportConfig, free_tcp_port
from deploy.robot_link import RobotLink
from deploy.wire import CmdFlags, RobotRegistry, StateMsg, encode
from sim.scenario import make_scenario
from tests.deploy.bridge_fleet import REGISTRY, ROBOTS, TARGETS, last_flags, tick

pytestmark = pytest.mark.realtime   # bridges and robot links on Zenoh sessions, e-stop timing


def test_a_stale_robot_stays_in_the_picture_is_braked_and_alone_raises_the_estop(fleet):
    bridge, links, seen = fleet
    record = tick(bridge, links, links)
    assert record.robots == ROBOTS and record.stale == ()
    assert seen[-1].num_robots == 2 and np.allclose(seen[-1].targets, [[0.2, 0.2], [0.8, 0.8]])
    assert not last_flags(links[1]) & CmdFlags.BRAKE
    silent_from = time.monotonic()
    while time.monotonic() - silent_from < 0.3:  # r1 falls silent; r0 keeps publishing
        record = tick(bridge, links, links[:1])
        time.sleep(0.02)
    assert record.robots == ROBOTS and record.stale == ("r1",)   # kept, not dropped
    assert seen[-1].robot_ids == ROBOTS
    ages = seen[-1].state_age_s
    assert ages[1] > 0.2 and ages[0] < 0.1
    assert record.flags[1] == CmdFlags.BRAKE and not record.flags[0] & CmdFlags.BRAKE
    assert last_flags(links[1]) == CmdFlags.BRAKE    # what r1 actually received
    assert not last_flags(links[0]) & CmdFlags.BRAKE
    assert not bridge.link.estop_engaged
    while not bridge.link.estop_engaged and time.monotonic() - silent_from < 5.0:
        tick(bridge, links, links[:1])   # r0 stays fresh: only r1's silence can raise it
        time.sleep(0.02)
    assert bridge.link.estop_engaged and bridge.stats.estops == 1
    assert time.monotonic() - silent_from > 0.6
    assert bridge.summary()["estop_robot"] == "r1"
    for link in links:
        assert link.wait_for(lambda lk=link: lk.estopped, 5.0)
        assert link.estop_reason == ESTOP_STALE_PICTURE


def test_a_robot_that_leaves_stays_a_silent_obstacle_until_it_rejoins(fleet):
    bridge, links, seen = fleet
    links[1].publish_state((0.7, 0.6), (0.05, 0.0))
    tick(bridge, links, links[:1])
    links[1].close()   # r1 leaves the link: its liveliness token goes at once
    assert bridge.link.wait_for(lambda: "r1" not in bridge.link.alive_robots, 5.0)
    start = time.monotonic()
    while time.monotonic() - start < 0.8:   # longer than estop_after_s
        record = tick(bridge, links, links[:1])
        time.sleep(0.02)
    assert record.robots == ("r0",) and record.silent == ("r1",)
    silent = seen[-1].silent
    assert silent.ids == ("r1",) and np.allclose(silent.positions, [[0.7, 0.6]])
    assert np.allclose(silent.velocities, [[0.05, 0.0]]) and silent.age_s[0] > 0.7
    assert np.allclose(silent.targets, [TARGETS["r1"]])    # the policy and docking see it too
    assert not bridge.link.estop_engaged   # a robot that left is not a silent live robot
    rejoined = RobotLink("bf", "r1", REGISTRY, links[0].session)   # r1 back, on r0's session
    links.insert(0, rejoined)   # closed before the session it borrows
    assert bridge.link.wait_for(lambda: "r1" in bridge.link.alive_robots, 5.0)
    record = tick(bridge, links, links[1:2])     # live again, but no state since: still silent
    assert record.robots == ("r0",) and record.silent == ("r1",)
    assert last_flags(rejoined) == CmdFlags.BRAKE and rejoined.latest_command.msg.state_seq == 0
    sent = rejoined.publish_state((0.71, 0.6), (0.0, 0.0))
    assert bridge.link.wait_for(lambda: bridge.link.state_of("r1").msg.epoch == sent.epoch, 5.0)
    record = tick(bridge, links, links[1:2])
    assert record.robots == ROBOTS and record.silent == ()
    assert np.allclose(seen[-1].positions[1], [0.71, 0.6])


def test_a_robot_that_restarts_between_two_ticks_is_not_commanded_from_its_old_state(fleet):
    """r1 leaves and rejoins (a new link, a new epoch) while the bridge is between two looks, so no
    tick ever saw it gone: its state from before the restart must not stay a row (it did: the
    new link was commanded from the old link's state), but a silent obstacle until it reports."""
    bridge, links, seen = fleet
    record = tick(bridge, links, links)
    assert record.robots == ROBOTS
    links[1].close()
    assert bridge.link.wait_for(lambda: "r1" not in bridge.link.alive_robots, 5.0)
    restarted = RobotLink("bf", "r1", REGISTRY, links[0].session)
    links.insert(0, restarted)   # closed before the session it borrows
    assert bridge.link.wait_for(lambda: "r1" in bridge.link.alive_robots, 5.0)
    record = tick(bridge, links, links[1:2])     # r0 reports; r1 has not since its restart
    assert record.robots == ("r0",) and record.silent == ("r1",)
    sent = restarted.publish_state((0.71, 0.6), (0.0, 0.0))
    assert bridge.link.wait_for(lambda: bridge.link.state_of("r1").msg.epoch == sent.epoch, 5.0)
    record = tick(bridge, links, links[1:2])
    assert record.robots == ROBOTS and np.allclose(seen[-1].positions[1], [0.71, 0.6])


def test_a_rejoining_robots_state_that_outruns_its_liveliness_token_is_answered_once_it_comes(fleet):
    """A new link's STATE and its liveliness token travel apart, and the STATE can come first
    (a clean-clone CI run: the lock-stepped fleet then stalled 2 s and re-armed the robot a tick
    late). Here the order is forced: r1 leaves, a STATE of a new epoch arrives without a token,
    then the token. The bridge must answer that STATE as a row, not wait for the robot's next
    one; a late STATE of the old link (its epoch) stays discarded."""
    bridge, links, seen = fleet
    tick(bridge, links, links)
    old = links[1].publish_state((0.7, 0.6), (0.05, 0.0))   # the last STATE r1 sends
    tick(bridge, links, links[:1])
    links[1].close()
    assert bridge.link.wait_for(lambda: "r1" not in bridge.link.alive_robots, 5.0)
    tick(bridge, links, links[:1])
    keys, session, r1 = links[0].keys, links[0].session, REGISTRY.id_of("r1")

    def arrive(msg):
        """``msg`` reaches the bridge before r1's liveliness token; a tick, the token, a tick."""
        session.put(keys.state("r1"), encode(msg))
        assert bridge.link.wait_for(lambda: bridge.link.state_of("r1").msg == msg, 5.0)
        before = tick(bridge, links, links[:1])
        assert before.robots == ("r0",) and before.silent == ("r1",)   # no token: an obstacle
        token = session.liveliness().declare_token(keys.robot_alive("r1"))
        assert bridge.link.wait_for(lambda: "r1" in bridge.link.alive_robots, 5.0)
        return tick(bridge, links, links[:1]), token

    # a late STATE of the old link (its epoch), then a token: nothing to act on
    late = StateMsg(r1, old.epoch, old.seq + 1, time.monotonic_ns(), (0.7, 0.61), (0.0, 0.0))
    record, token = arrive(late)
    assert record.robots == ("r0",)
    token.undeclare()
    assert bridge.link.wait_for(lambda: "r1" not in bridge.link.alive_robots, 5.0)
    tick(bridge, links, links[:1])
    # the rejoined link's first STATE (a new epoch), its token after it: a row at once
    fresh = StateMsg(r1, old.epoch % 1000 + 1, 1, time.monotonic_ns(), (0.72, 0.6), (0.0, 0.0))
    record, token = arrive(fresh)
    try:
        assert record.robots == ROBOTS and record.silent == ()
        assert np.allclose(seen[-1].positions[1], [0.72, 0.6])
    finally:
        token.undeclare()


def test_a_state_that_queued_on_the_uplink_is_aged_and_braked():
    """The robot's clock is 1000 s off ours (another host); one state then reaches the bridge
    0.3 s later than the fastest transfer, as one stuck in a queue would: its age says so."""
    port = free_tcp_port()
    offset = [1000 * 10**9]
    clock = lambda: time.monotonic_ns() + offset[0]  # noqa: E731
    seen = []
    bridge = Bridge("up", RobotRegistry(("r0",)), TransportConfig(listen=(f"tcp/127.0.0.1:{port}",)),
                    lambda s: seen.append(s) or np.zeros((s.num_robots, 2)),
                    targets={"r0": np.zeros(2)}, object_pose=np.zeros(3),
                    config=BridgeConfig(shared_clock=False))   # loopback, but "another host"
    link = None
    try:
        link = RobotLink("up", "r0", RobotRegistry(("r0",)),
                         TransportConfig(connect=(f"tcp/127.0.0.1:{port}",)), clock_ns=clock)
        assert link.wait_for(lambda: link.controller_alive, 20.0)
        assert bridge.link.wait_for(lambda: "r0" in bridge.link.alive_robots, 20.0)
        for _ in range(5):
            link.publish_state((0.5, 0.5), (0.0, 0.0))
            record = bridge.step(timeout_s=1.0)
            assert record is not None and record.stale == ()
        assert seen[-1].state_age_s[0] < 0.05
        offset[0] -= 300_000_000   # this state was sent 0.3 s before it arrives
        link.publish_state((0.5, 0.5), (0.0, 0.0))
        record = bridge.step(timeout_s=1.0)
        # the estimate is 0.3 s plus this transfer less the fastest one seen, less the drift
        # allowance since the last state: tens of us below 0.3 at most on loopback, and above
        # it by however long this delivery was held up on a loaded machine
        assert 0.299 <= seen[-1].state_age_s[0] < 0.35 and record.stale == ("r0",)
        assert record.flags == (CmdFlags.BRAKE,)
    finally:
        if link is not None:
            link.close()
        bridge.close()


def test_a_starved_bridge_discards_its_old_picture_and_rearms_without_an_estop(tmp_path):
    """The bridge loop stops looking for longer than estop_after_s while the fleet runs (lock-step
    fleet-sim in a thread: it times out and its watchdogs latch). The stall rule: no e-stop,
    the states from before are dropped, latched robots come back through FAULT -> STOP."""
    scenario = make_scenario("paper-3")
    port = free_tcp_port()
    names = robot_names(3)
    sim = FleetSim(FleetSimConfig(fleet="st", scenario=scenario, rate_hz=None, max_ticks=80,
                                  lockstep_timeout_s=0.05,
                                  transport=TransportConfig(listen=(f"tcp/127.0.0.1:{port}",))))
    result = {}
    thread = threading.Thread(target=lambda: result.update(sim.run()))
    thread.start()
    stalls = []
    bridge = Bridge("st", RobotRegistry(names), TransportConfig(connect=(f"tcp/127.0.0.1:{port}",)),
                    ScriptedController(scenario), targets=dict(zip(names, scenario.targets, strict=True)),
                    object_pose=np.zeros(3), on_stall=lambda: stalls.append(time.monotonic()))
    try:
        while bridge.stats.ticks < 10:
            bridge.step(timeout_s=1.0)
        time.sleep(1.5)    # starved: longer than estop_after_s (1 s) without a look
        first = None
        while thread.is_alive():
            record = bridge.step(timeout_s=0.1)
            if record is not None and first is None:
                first = record
    finally:
        thread.join(timeout=30)
        bridge.close()
    summary = bridge.summary()
    assert summary["stalls"] == 1 and len(stalls) == 1 and summary["longest_stall_s"] > 1.0
    assert summary["estops"] == 0 and not summary["estop_engaged"]
    assert summary["rearms"] >= 3
    assert summary["rearm_alarms"] == 0 and summary["refusing"] == []   # each re-arm answered
    assert max(summary["rearms_in_a_row"].values()) < summary["rearm_alarm_after"]
    modes = [t["modes"] for t in result["trace"]]
    latched = next(i for i, m in enumerate(modes) if m == ["latched"] * 3)
    assert any(m == ["run"] * 3 for m in modes[latched:])   # driving again after the re-arm


def test_an_operator_engages_and_releases_the_estop_but_not_while_a_robot_is_silent(fleet, capsys):
    """`formation estop` over Zenoh: a release is refused while r1 is silent past estop_after_s
    (the rule would raise the e-stop again), carried out once r1 is back; an engage latches it
    at once with the operator's reason code. Exit codes: 0 done, 1 refused."""
    from deploy.bridge import ESTOP_OPERATOR
    from stack.cli import main

    bridge, links, _ = fleet

    def operator(request: str) -> tuple[int, dict]:
        code = main(["estop", "--fleet", "bf", f"--{request}", "--connect", bridge.test_endpoint])
        return code, json.loads(capsys.readouterr().out.strip().splitlines()[-1])

    silent_from = time.monotonic()
    while not bridge.link.estop_engaged and time.monotonic() - silent_from < 5.0:
        tick(bridge, links, links[:1])                     # r1 silent: the bridge raises it
        time.sleep(0.02)
    assert bridge.link.estop_engaged
    code, answer = operator("release")
    assert code == 1 and not answer["ok"] and answer["silent_robot"] == "r1"
    assert "silent" in answer["reason"] and bridge.link.estop_engaged
    for _ in range(3):
        tick(bridge, links, links)                         # r1 is back
    code, answer = operator("release")
    assert code == 0 and answer == {"ok": True, "estop": "released", "silent_robot": answer["silent_robot"],
                                    "silence_s": answer["silence_s"]}
    assert answer["silence_s"] < 0.6 and not bridge.link.estop_engaged
    for link in links:
        assert link.wait_for(lambda lk=link: not lk.estopped, 5.0)
    code, answer = operator("engage")
    assert code == 0 and answer["estop"] == "engaged" and bridge.link.estop_engaged
    for link in links:
        assert link.wait_for(lambda lk=link: lk.estopped, 5.0)
        assert link.estop_reason == ESTOP_OPERATOR
    record = None
    for _ in range(20):                                     # latched robots are told to brake
        record = record or tick(bridge, links, links)
    assert record.flags == (CmdFlags.BRAKE, CmdFlags.BRAKE) and not record.commands.any()
    code, answer = operator("status")
    assert code == 0 and answer["estop"] == "engaged"


def test_a_robot_that_leaves_is_passed_on_with_its_commands_in_flight_counted(fleet):
    """``SilentRobots.commands_pending``: the commands sent after the one the robot's last state
    names, plus a tick for each tick since the bridge last sent it one (the controller records a
    braking row for it on each); -1 when the state names no command the bridge sent."""
    bridge, links, seen = fleet
    for _ in range(3):
        before = links[1].latest_command.msg.seq if links[1].latest_command else 0
        tick(bridge, links, links)
        last_flags(links[1], before)
    acted = links[1].latest_command.msg.seq - 1          # one command not acted on yet
    links[0].publish_state((0.3, 0.4), (0.0, 0.1))
    links[1].publish_state((0.7, 0.6), (0.05, 0.0), last_cmd_seq=acted)
    before = links[1].latest_command.msg.seq
    bridge.step(timeout_s=0.1)
    last_flags(links[1], before)                        # answered: two after the acted one
    links[1].close()
    assert bridge.link.wait_for(lambda: "r1" not in bridge.link.alive_robots, 5.0)
    counts = []
    for _ in range(3):
        tick(bridge, links, links[:1])
        counts.append(int(seen[-1].silent.pending()[0]))
    assert seen[-1].silent.ids == ("r1",)
    assert counts == [2, 3, 4]


def test_a_leaving_robot_whose_state_names_no_sent_command_is_passed_on_uncounted(fleet):
    bridge, links, seen = fleet
    tick(bridge, links, links)
    links[1].publish_state((0.7, 0.6), (0.05, 0.0), last_cmd_seq=10_000)
    links[0].publish_state((0.3, 0.4), (0.0, 0.1))
    bridge.step(timeout_s=0.1)
    links[1].close()
    assert bridge.link.wait_for(lambda: "r1" not in bridge.link.alive_robots, 5.0)
    tick(bridge, links, links[:1])
    assert seen[-1].silent.ids == ("r1",) and seen[-1].silent.pending().tolist() == [-1]
