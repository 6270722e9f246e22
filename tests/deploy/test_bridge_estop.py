"""Bridge and fleet-sim in this process over real Zenoh: a row's command and bad controllers, the
fleet-sim under the e-stop, measured command delay and the commands in flight, lock-step, how a
tick gathers its burst. Stale, silent and rejoining robots, the e-stop rule and the stall rule:
test_bridge_picture.py."""

from __future__ import annotations

import math
import threading
import time

import numpy as np
import pytest

from controllers.scripted import ScriptedController
from deploy.bridge import Bridge, BridgeConfig, row_flags
from deploy.fleet_sim import FleetSim, FleetSimConfig, robot_names
from deploy.network import TransportConfig, free_tcp_port
from deploy.robot_link import RobotLink
from deploy.wire import CmdFlags, RobotRegistry, StateStatus
from sim.pymunk_world import ModelError
from sim.scenario import make_scenario
from tests.deploy.bridge_fleet import REGISTRY, ROBOTS, TARGETS, last_flags, linked_fleet, tick

pytestmark = pytest.mark.realtime   # bridges and robot links on Zenoh sessions, e-stop timing


def test_a_failing_controller_brakes_every_robot_and_is_counted(fleet):
    """... and the controller is told (``on_sent``) which rows got BRAKE in its place: none on
    a good tick, every row on a failed one."""
    bridge, links, seen = fleet
    told = []
    bridge.on_sent = lambda state, braked: told.append((state, braked.tolist()))
    tick(bridge, links, links)
    assert told == []
    bridge.controller = lambda state: np.full((state.num_robots, 2), np.nan)
    tick(bridge, links, links)
    for link in links:
        assert last_flags(link, after_seq=1) & CmdFlags.BRAKE
    bridge.controller = lambda state: np.zeros((state.num_robots + 1, 2))  # wrong shape
    tick(bridge, links, links)
    assert bridge.stats.controller_faults == 2
    assert [braked for _, braked in told] == [[True, True], [True, True]]
    assert told[0][0].robot_ids == ROBOTS and told[0][0] is not seen[-1]


def test_a_controller_that_asks_for_a_brake_gets_it_in_one_log_line_without_a_fault(fleet, caplog):
    """ZenohFleet brakes between episodes on purpose; before, the bridge logged that as a failed
    controller, with a traceback on stderr in every `formation eval --world zenoh` run."""
    import logging

    from deploy.bridge import BrakeThisTick

    bridge, links, _ = fleet
    told = []
    bridge.on_sent = lambda state, braked: told.append(braked.tolist())

    def between_episodes(state):
        raise BrakeThisTick("between episodes")

    bridge.controller = between_episodes
    with caplog.at_level(logging.INFO, logger="deploy.bridge"):
        tick(bridge, links, links)
    for link in links:
        assert last_flags(link, after_seq=0) & CmdFlags.BRAKE
    assert bridge.stats.controller_faults == 0 and told == [[True, True]]
    records = [r for r in caplog.records if r.name == "deploy.bridge"]
    assert [r.getMessage() for r in records] == ["controller: braking every robot this tick (between episodes)"]
    assert records[0].exc_info is None and "Traceback" not in caplog.text


def test_a_row_braked_for_its_age_is_reported_to_the_controller_and_a_failing_report_is_logged(fleet, caplog):
    bridge, links, seen = fleet
    told = []
    bridge.on_sent = lambda state, braked: told.append((state, braked.tolist()))
    tick(bridge, links, links)
    time.sleep(0.25)                                  # r1 falls silent past stale_after_s 0.2
    record = tick(bridge, links, links[:1])
    assert record.stale == ("r1",)
    assert len(told) == 1 and told[0][0] is seen[-1] and told[0][1] == [False, True]
    bridge.on_sent = lambda state, braked: 1 / 0
    time.sleep(0.02)
    assert tick(bridge, links, links[:1]) is not None   # the tick completes
    assert "on_sent failed" in caplog.text


def test_fleet_sim_obeys_the_estop(tmp_path):
    scenario = make_scenario("paper-3")
    port = free_tcp_port()
    names = robot_names(3)
    sim = FleetSim(FleetSimConfig(fleet="es", scenario=scenario, rate_hz=None, max_ticks=40,
                                  transport=TransportConfig(listen=(f"tcp/127.0.0.1:{port}",))))
    result = {}
    thread = threading.Thread(target=lambda: result.update(sim.run()))
    thread.start()
    scripted = ScriptedController(scenario)
    bridge = Bridge("es", RobotRegistry(names), TransportConfig(connect=(f"tcp/127.0.0.1:{port}",)),
                    scripted, targets=dict(zip(names, scenario.targets, strict=True)),
                    object_pose=np.zeros(3))
    try:
        while bridge.stats.ticks < 15:
            bridge.step(timeout_s=1.0)
        bridge.link.raise_estop(7)
        while thread.is_alive():
            bridge.step(timeout_s=0.1)
    finally:
        thread.join(timeout=30)
        bridge.close()
    trace = result["trace"]
    assert max(trace[14]["speeds"]) > 0.05  # moving before the e-stop
    first = next(t["tick"] for t in trace if "estop" in t["modes"])
    assert all(t["modes"] == ["estop"] * 3 for t in trace[first + 2:])
    assert max(trace[first + 10]["speeds"]) < 1e-3
    assert result["collisions"] == {"robot": 0, "object": 0, "wall": 0}


def test_row_flags_brake_stale_and_non_finite_rows_and_rearm_fresh_faulted_ones():
    fresh, stale = 0.01, 0.5
    assert row_flags(CmdFlags(0), fresh, True, StateStatus(0), 0.15) == CmdFlags(0)
    assert row_flags(CmdFlags(0), stale, True, StateStatus(0), 0.15) == CmdFlags.BRAKE
    assert row_flags(CmdFlags(0), math.nan, True, StateStatus(0), 0.15) == CmdFlags.BRAKE
    assert row_flags(CmdFlags(0), fresh, False, StateStatus.FAULT, 0.15) == CmdFlags.BRAKE
    assert row_flags(CmdFlags(0), fresh, True, StateStatus.FAULT, 0.15) == CmdFlags.STOP
    assert row_flags(CmdFlags.BRAKE, fresh, True, StateStatus.FAULT, 0.15) \
        == CmdFlags.BRAKE | CmdFlags.STOP
    assert row_flags(CmdFlags(0), stale, True, StateStatus.FAULT, 0.15) == CmdFlags.BRAKE


def test_command_round_trips_are_measured_from_the_wire_and_passed_on(fleet):
    """r0 answers each command only after HOLD_S (as a robot acting on its next tick would):
    the bound handed to the controller must cover that, and come from no other source."""
    bridge, links, seen = fleet
    hold_s = 0.03
    link = links[0]
    for _ in range(20):
        before = link.latest_command.msg.seq if link.latest_command else 0
        tick(bridge, links, links[:1])
        last_flags(link, before)
        time.sleep(hold_s)
    delay = seen[-1].command_delay_s
    assert delay is not None and hold_s <= delay < hold_s + 0.1
    summary = bridge.summary()
    assert summary["round_trip_ms"]["count"] >= 15 and summary["command_delay_s"] >= hold_s
    assert summary["round_trip_ms"]["p50"] >= 1e3 * hold_s


def test_commands_in_flight_are_counted_from_the_state_s_last_cmd_seq(fleet):
    """A robot that says which command it acted on lets the controller count the ones still in
    flight (``FleetState.commands_pending``): 0 when it acted on the newest, 1 when one later
    command had not acted yet, -1 when the seq names no command the bridge sent."""
    bridge, links, seen = fleet
    link = links[0]
    for _ in range(3):
        before = link.latest_command.msg.seq if link.latest_command else 0
        tick(bridge, links, links)
        last_flags(link, before)
    newest = link.latest_command.msg.seq
    assert seen[0].commands_pending.tolist() == [-1, -1]       # nothing sent before the first state

    def pending_when(acted: int) -> int:
        before = link.latest_command.msg.seq
        for lk in links:
            lk.publish_state((0.3, 0.4), (0.0, 0.1), last_cmd_seq=acted if lk is link else None)
        bridge.step(timeout_s=0.1)
        last_flags(link, before)
        return int(seen[-1].commands_pending[0])

    assert pending_when(newest) == 0
    latest = link.latest_command.msg.seq                         # the answer to that state
    assert pending_when(latest - 1) == 1
    assert pending_when(10_000) == -1


def test_fleet_sim_reports_the_command_its_world_acted_on_not_the_latest_accepted():
    """A fleet-sim world with two ticks of command delay: the STATE's ``last_cmd_seq`` is the
    command in force two ticks before, so the bridge counts two in flight."""
    sim = FleetSim(FleetSimConfig(fleet="ac", scenario=make_scenario("paper-3"), transport=TransportConfig(), rate_hz=None,
                                  model_error=ModelError(delay_ticks=2)))
    sim.world.reset(seed=0)
    for k in range(1, 7):
        for robot in sim.robots:
            robot.accepted_seq = 10 + k
        sim.world.send_accelerations(np.zeros((3, 2)))
        sim._in_force.append(np.array([r.accepted_seq for r in sim.robots]))
        acted = sim._acted_seqs(sim.world.step())
        if k > 2:
            assert acted.tolist() == [10 + k - 2] * 3


@pytest.mark.parametrize("lockstep", [True, False])
def test_a_lockstep_bridge_counts_ages_in_fleet_ticks_not_wall_time(lockstep):
    """Lock-step: a silent robot's age is the fleet ticks answered since its state (0.05 s
    each), however long the machine took between them; on the wall clock it is the wait."""
    config = BridgeConfig(stale_after_s=0.2, estop_after_s=0.9, lockstep=lockstep, period_s=0.05)
    with linked_fleet(config) as (bridge, links, seen):
        tick(bridge, links, links)
        links[1].close()   # r1 leaves after its state of this tick
        assert bridge.link.wait_for(lambda: "r1" not in bridge.link.alive_robots, 5.0)
        for _ in range(3):
            time.sleep(0.25)   # a slow machine: 0.75 s of wall time over three ticks
            tick(bridge, links, links[:1])
        silent, state = seen[-1].silent, seen[-1]
        assert silent.ids == ("r1",)
        if lockstep:
            assert silent.age_s[0] == pytest.approx(0.15, abs=1e-9)   # three ticks since
            assert state.state_age_s[0] == 0.0 and state.time == pytest.approx(0.15, abs=1e-9)
            assert bridge.summary()["lockstep"] and bridge.link.lossless
        else:
            assert silent.age_s[0] > 0.75


def test_a_lockstep_burst_answered_in_two_parts_keeps_the_fleets_time():
    """Lock-step: r1's state of a tick arrives after the gather (0.2 s), so the bridge answers
    r0 alone, then r1: both parts at that tick's sim time, and the next burst one period on.
    Counting answered bursts instead put the bridge a tick ahead of the fleet from then on (the
    fleet-sim + bridge record test failed on that under load: positions 8 mm off their time)."""
    config = BridgeConfig(stale_after_s=0.2, estop_after_s=0.9, lockstep=True, period_s=0.05)
    with linked_fleet(config) as (bridge, links, seen):
        tick(bridge, links, links)
        first = tick(bridge, links, links[:1])          # r1's state is late
        assert first.robots == ROBOTS and seen[-1].state_age_s[1] == pytest.approx(0.05, abs=1e-9)
        late = tick(bridge, links, links[1:])
        assert late.robots == ROBOTS and late.tick == first.tick + 1
        tick(bridge, links, links)
        assert [s.time for s in seen] == pytest.approx([0.0, 0.05, 0.05, 0.10], abs=1e-9)
        assert seen[2].state_age_s.tolist() == [0.0, 0.0] and seen[3].state_age_s.tolist() == [0.0, 0.0]
        tick(bridge, links, links[:1])             # r1 sends nothing this tick (a fleet timeout)
        sent = {link.robot: link.publish_state((0.3, 0.4), (0.0, 0.1)).seq for link in links[::-1]}
        assert bridge.link.wait_for(lambda: all(bridge.link.latest_states()[r].msg.seq == q for r, q in sent.items()),
                                    5.0)
        bridge.step(timeout_s=0.1)                  # r1 came first in the next tick: not a late part
        assert bridge.step(timeout_s=0.05) is None   # nothing new: neither a tick nor a late part
        tick(bridge, links, links)
        assert [s.time for s in seen[4:]] == pytest.approx([0.15, 0.20, 0.25], abs=1e-9)
        assert bridge.summary()["late_parts"] == 1


def test_a_bridge_sends_lossless_once_the_fleet_says_it_is_lock_stepped(fleet):
    """A bridge started without --lossless, a fleet whose STATEs carry LOCKSTEP (fleet-sim
    --lockstep): from that tick on every command goes out with congestion control BLOCK (with
    DROP a starved machine lost answers the lock-stepped fleet then waited for)."""
    import zenoh

    bridge, links, _ = fleet
    assert not bridge.link.lossless
    tick(bridge, links, links)
    assert all(p.congestion_control == zenoh.CongestionControl.DROP for p in bridge.link._cmd_publishers.values())
    for link in links:
        link.publish_state((0.3, 0.4), (0.0, 0.1), StateStatus.LOCKSTEP)
    assert bridge.step(timeout_s=0.5) is not None
    assert bridge.link.lossless and bridge.summary()["lossless"]
    assert all(p.congestion_control == zenoh.CongestionControl.BLOCK for p in bridge.link._cmd_publishers.values())
    assert links[0].wait_for(lambda: links[0].latest_command is not None, 5.0)  # arrives async
    seq = links[0].latest_command.msg.seq
    tick(bridge, links, links)                      # the new publishers reach the robots
    assert links[0].wait_for(lambda: links[0].latest_command.msg.seq > seq, 5.0)


def test_the_first_tick_waits_for_every_registered_robot_to_join():
    """A fleet's first burst reaches the bridge over some time (liveliness and states of each
    robot through a router): the first tick waits, up to ``gather_s``, for the whole registered
    fleet instead of answering whoever came first (the robots then joined one tick at a time)."""
    port = free_tcp_port()
    bridge = Bridge("bj", REGISTRY, TransportConfig(listen=(f"tcp/127.0.0.1:{port}",)),
                    lambda state: np.zeros((state.num_robots, 2)), targets=TARGETS, object_pose=np.zeros(3),
                    config=BridgeConfig(ttl_ms=100, gather_s=5.0))
    robot_cfg = TransportConfig(connect=(f"tcp/127.0.0.1:{port}",))
    links: list[RobotLink] = []

    def late_robot():
        time.sleep(0.2)
        links.append(RobotLink("bj", "r1", REGISTRY, robot_cfg))
        links[-1].publish_state((0.8, 0.8), (0.0, 0.0))

    try:
        links.append(RobotLink("bj", "r0", REGISTRY, robot_cfg))
        assert bridge.link.wait_for(lambda: bridge.link.alive_robots == {"r0"}, 20.0)
        links[0].publish_state((0.2, 0.2), (0.0, 0.0))
        joiner = threading.Thread(target=late_robot)
        joiner.start()
        record = bridge.step(timeout_s=5.0)
        joiner.join()
        assert record is not None and record.robots == ROBOTS
        assert bridge.summary()["robot_counts"] == [(0, 2)]
    finally:
        for link in links:
            link.close()
        bridge.close()


def test_a_burst_that_comes_in_pieces_is_answered_in_one_tick():
    """r1's state reaches the bridge 15 ms after r0's, as over a link whose delay jitters: the
    default gather (25 ms) answers both in one tick; at the former 10 ms a tick answered r0
    alone and a second one r1, two commands to r0 in one fleet tick."""
    for gather, ticks in ((BridgeConfig().gather_s, 1), (0.01, 2)):
        with linked_fleet(BridgeConfig(stale_after_s=0.2, gather_s=gather)) as (bridge, links, seen):
            tick(bridge, links, links)                       # the first tick waits for everyone
            before = bridge.stats.ticks

            def late_r1():
                time.sleep(0.015)
                links[1].publish_state((0.7, 0.6), (0.0, 0.0))

            threading.Thread(target=late_r1).start()
            links[0].publish_state((0.3, 0.4), (0.0, 0.1))
            for _ in range(2):
                bridge.step(timeout_s=0.3)
            assert bridge.stats.ticks - before == ticks, gather


def test_a_live_robot_gone_quiet_is_not_waited_for_every_tick():
    """With a gather of a whole second, r1 (live, its states stopped) is waited for while it
    was heard lately, and not once it has been quiet for QUIET_PERIODS fleet periods."""
    from deploy.bridge import QUIET_PERIODS

    with linked_fleet(BridgeConfig(stale_after_s=0.2, estop_after_s=5.0, gather_s=1.0)) as (bridge, links, seen):
        tick(bridge, links, links)
        time.sleep(QUIET_PERIODS * bridge.config.period_s + 0.05)
        start = time.monotonic()
        tick(bridge, links, links[:1])
        assert time.monotonic() - start < 0.5
