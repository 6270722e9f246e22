"""Bridge and fleet-sim in this process over real Zenoh: stale, silent and rejoining robots, the
per-robot e-stop, the stall rule, measured command delay, bad controllers."""

from __future__ import annotations

import contextlib
import json
import math
import threading
import time

import numpy as np
import pytest

from controllers.scripted import ScriptedController
from deploy.bridge import ESTOP_STALE_PICTURE, Bridge, BridgeConfig, row_flags
from deploy.fleet_sim import FleetSim, FleetSimConfig, robot_names
from deploy.network import TransportConfig, free_tcp_port
from deploy.robot_link import RobotLink
from deploy.wire import CmdFlags, RobotRegistry, StateMsg, StateStatus, encode
from sim.pymunk_world import ModelError
from sim.scenario import make_scenario

pytestmark = pytest.mark.realtime   # bridges and robot links on Zenoh sessions, e-stop timing

ROBOTS = ("r0", "r1")
REGISTRY = RobotRegistry(ROBOTS)
TARGETS = {"r0": np.array([0.2, 0.2]), "r1": np.array([0.8, 0.8])}


@contextlib.contextmanager
def _fleet(config: BridgeConfig):
    """A bridge on ``config`` and a RobotLink for each of ROBOTS, all linked."""
    port = free_tcp_port()
    seen: list = []

    def controller(state):
        seen.append(state)
        return np.tile([0.1, -0.2], (state.num_robots, 1))

    bridge = Bridge("bf", REGISTRY, TransportConfig(listen=(f"tcp/127.0.0.1:{port}",)), controller,
                    targets=TARGETS, object_pose=np.zeros(3), config=config)
    robot_cfg = TransportConfig(connect=(f"tcp/127.0.0.1:{port}",))
    bridge.test_endpoint = f"tcp/127.0.0.1:{port}"   # for tests that reach the bridge themselves
    links = []
    try:   # close every session even when set-up fails, or the process aborts at exit
        links.extend(RobotLink("bf", r, REGISTRY, robot_cfg) for r in ROBOTS)
        for link in links:
            assert link.wait_for(lambda lk=link: lk.controller_alive and lk.estop_synced, 20.0)
        assert bridge.link.wait_for(lambda: bridge.link.alive_robots == set(ROBOTS), 20.0)
        yield bridge, links, seen
    finally:
        for link in links:
            link.close()
        bridge.close()


@pytest.fixture
def fleet():
    with _fleet(BridgeConfig(ttl_ms=100, stale_after_s=0.2, estop_after_s=0.6)) as parts:
        yield parts


def _tick(bridge, links, publishing):
    for link in publishing:
        link.publish_state((0.3, 0.4), (0.0, 0.1))
    return bridge.step(timeout_s=0.1)


def _last_flags(link, after_seq=0):
    assert link.wait_for(lambda: link.latest_command is not None
                         and link.latest_command.msg.seq > after_seq, 5.0)
    return link.latest_command.msg.flags


def test_a_stale_robot_stays_in_the_picture_is_braked_and_alone_raises_the_estop(fleet):
    bridge, links, seen = fleet
    record = _tick(bridge, links, links)
    assert record.robots == ROBOTS and record.stale == ()
    assert seen[-1].num_robots == 2 and np.allclose(seen[-1].targets, [[0.2, 0.2], [0.8, 0.8]])
    assert not _last_flags(links[1]) & CmdFlags.BRAKE
    silent_from = time.monotonic()
    while time.monotonic() - silent_from < 0.3:  # r1 falls silent; r0 keeps publishing
        record = _tick(bridge, links, links[:1])
        time.sleep(0.02)
    assert record.robots == ROBOTS and record.stale == ("r1",)   # kept, not dropped
    assert seen[-1].robot_ids == ROBOTS
    ages = seen[-1].state_age_s
    assert ages[1] > 0.2 and ages[0] < 0.1
    assert record.flags[1] == CmdFlags.BRAKE and not record.flags[0] & CmdFlags.BRAKE
    assert _last_flags(links[1]) == CmdFlags.BRAKE    # what r1 actually received
    assert not _last_flags(links[0]) & CmdFlags.BRAKE
    assert not bridge.link.estop_engaged
    while not bridge.link.estop_engaged and time.monotonic() - silent_from < 5.0:
        _tick(bridge, links, links[:1])   # r0 stays fresh: only r1's silence can raise it
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
    _tick(bridge, links, links[:1])
    links[1].close()   # r1 leaves the link: its liveliness token goes at once
    assert bridge.link.wait_for(lambda: "r1" not in bridge.link.alive_robots, 5.0)
    start = time.monotonic()
    while time.monotonic() - start < 0.8:   # longer than estop_after_s
        record = _tick(bridge, links, links[:1])
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
    record = _tick(bridge, links, links[1:2])     # live again, but no state since: still silent
    assert record.robots == ("r0",) and record.silent == ("r1",)
    assert _last_flags(rejoined) == CmdFlags.BRAKE and rejoined.latest_command.msg.state_seq == 0
    sent = rejoined.publish_state((0.71, 0.6), (0.0, 0.0))
    assert bridge.link.wait_for(lambda: bridge.link.state_of("r1").msg.epoch == sent.epoch, 5.0)
    record = _tick(bridge, links, links[1:2])
    assert record.robots == ROBOTS and record.silent == ()
    assert np.allclose(seen[-1].positions[1], [0.71, 0.6])


def test_a_robot_that_restarts_between_two_ticks_is_not_commanded_from_its_old_state(fleet):
    """r1 leaves and rejoins (a new link, a new epoch) while the bridge is between two looks, so no
    tick ever saw it gone: its state from before the restart must not stay a row (it did: the
    new link was commanded from the old link's state), but a silent obstacle until it reports."""
    bridge, links, seen = fleet
    record = _tick(bridge, links, links)
    assert record.robots == ROBOTS
    links[1].close()
    assert bridge.link.wait_for(lambda: "r1" not in bridge.link.alive_robots, 5.0)
    restarted = RobotLink("bf", "r1", REGISTRY, links[0].session)
    links.insert(0, restarted)   # closed before the session it borrows
    assert bridge.link.wait_for(lambda: "r1" in bridge.link.alive_robots, 5.0)
    record = _tick(bridge, links, links[1:2])     # r0 reports; r1 has not since its restart
    assert record.robots == ("r0",) and record.silent == ("r1",)
    sent = restarted.publish_state((0.71, 0.6), (0.0, 0.0))
    assert bridge.link.wait_for(lambda: bridge.link.state_of("r1").msg.epoch == sent.epoch, 5.0)
    record = _tick(bridge, links, links[1:2])
    assert record.robots == ROBOTS and np.allclose(seen[-1].positions[1], [0.71, 0.6])


def test_a_rejoining_robots_state_that_outruns_its_liveliness_token_is_answered_once_it_comes(fleet):
    """A new link's STATE and its liveliness token travel apart, and the STATE can come first
    (a clean-clone CI run: the lock-stepped fleet then stalled 2 s and re-armed the robot a tick
    late). Here the order is forced: r1 leaves, a STATE of a new epoch arrives without a token,
    then the token. The bridge must answer that STATE as a row, not wait for the robot's next
    one; a late STATE of the old link (its epoch) stays discarded."""
    bridge, links, seen = fleet
    _tick(bridge, links, links)
    old = links[1].publish_state((0.7, 0.6), (0.05, 0.0))   # the last STATE r1 sends
    _tick(bridge, links, links[:1])
    links[1].close()
    assert bridge.link.wait_for(lambda: "r1" not in bridge.link.alive_robots, 5.0)
    _tick(bridge, links, links[:1])
    keys, session, r1 = links[0].keys, links[0].session, REGISTRY.id_of("r1")

    def arrive(msg):
        """``msg`` reaches the bridge before r1's liveliness token; a tick, the token, a tick."""
        session.put(keys.state("r1"), encode(msg))
        assert bridge.link.wait_for(lambda: bridge.link.state_of("r1").msg == msg, 5.0)
        before = _tick(bridge, links, links[:1])
        assert before.robots == ("r0",) and before.silent == ("r1",)   # no token: an obstacle
        token = session.liveliness().declare_token(keys.robot_alive("r1"))
        assert bridge.link.wait_for(lambda: "r1" in bridge.link.alive_robots, 5.0)
        return _tick(bridge, links, links[:1]), token

    # a late STATE of the old link (its epoch), then a token: nothing to act on
    late = StateMsg(r1, old.epoch, old.seq + 1, time.monotonic_ns(), (0.7, 0.61), (0.0, 0.0))
    record, token = arrive(late)
    assert record.robots == ("r0",)
    token.undeclare()
    assert bridge.link.wait_for(lambda: "r1" not in bridge.link.alive_robots, 5.0)
    _tick(bridge, links, links[:1])
    # the rejoined link's first STATE (a new epoch), its token after it: a row at once
    fresh = StateMsg(r1, old.epoch % 1000 + 1, 1, time.monotonic_ns(), (0.72, 0.6), (0.0, 0.0))
    record, token = arrive(fresh)
    try:
        assert record.robots == ROBOTS and record.silent == ()
        assert np.allclose(seen[-1].positions[1], [0.72, 0.6])
    finally:
        token.undeclare()


def test_a_failing_controller_brakes_every_robot_and_is_counted(fleet):
    """... and the controller is told (``on_sent``) which rows got BRAKE in its place: none on
    a good tick, every row on a failed one."""
    bridge, links, seen = fleet
    told = []
    bridge.on_sent = lambda state, braked: told.append((state, braked.tolist()))
    _tick(bridge, links, links)
    assert told == []
    bridge.controller = lambda state: np.full((state.num_robots, 2), np.nan)
    _tick(bridge, links, links)
    for link in links:
        assert _last_flags(link, after_seq=1) & CmdFlags.BRAKE
    bridge.controller = lambda state: np.zeros((state.num_robots + 1, 2))  # wrong shape
    _tick(bridge, links, links)
    assert bridge.stats.controller_faults == 2
    assert [braked for _, braked in told] == [[True, True], [True, True]]
    assert told[0][0].robot_ids == ROBOTS and told[0][0] is not seen[-1]


def test_a_row_braked_for_its_age_is_reported_to_the_controller_and_a_failing_report_is_logged(fleet, caplog):
    bridge, links, seen = fleet
    told = []
    bridge.on_sent = lambda state, braked: told.append((state, braked.tolist()))
    _tick(bridge, links, links)
    time.sleep(0.25)                                  # r1 falls silent past stale_after_s 0.2
    record = _tick(bridge, links, links[:1])
    assert record.stale == ("r1",)
    assert len(told) == 1 and told[0][0] is seen[-1] and told[0][1] == [False, True]
    bridge.on_sent = lambda state, braked: 1 / 0
    time.sleep(0.02)
    assert _tick(bridge, links, links[:1]) is not None   # the tick completes
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
        _tick(bridge, links, links[:1])
        _last_flags(link, before)
        time.sleep(hold_s)
    delay = seen[-1].command_delay_s
    assert delay is not None and hold_s <= delay < hold_s + 0.1
    summary = bridge.summary()
    assert summary["round_trip_ms"]["count"] >= 15 and summary["command_delay_s"] >= hold_s
    assert summary["round_trip_ms"]["p50"] >= 1e3 * hold_s


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


def test_commands_in_flight_are_counted_from_the_state_s_last_cmd_seq(fleet):
    """A robot that says which command it acted on lets the controller count the ones still in
    flight (``FleetState.commands_pending``): 0 when it acted on the newest, 1 when one later
    command had not acted yet, -1 when the seq names no command the bridge sent."""
    bridge, links, seen = fleet
    link = links[0]
    for _ in range(3):
        before = link.latest_command.msg.seq if link.latest_command else 0
        _tick(bridge, links, links)
        _last_flags(link, before)
    newest = link.latest_command.msg.seq
    assert seen[0].commands_pending.tolist() == [-1, -1]       # nothing sent before the first state

    def pending_when(acted: int) -> int:
        before = link.latest_command.msg.seq
        for lk in links:
            lk.publish_state((0.3, 0.4), (0.0, 0.1), last_cmd_seq=acted if lk is link else None)
        bridge.step(timeout_s=0.1)
        _last_flags(link, before)
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
    with _fleet(config) as (bridge, links, seen):
        _tick(bridge, links, links)
        links[1].close()   # r1 leaves after its state of this tick
        assert bridge.link.wait_for(lambda: "r1" not in bridge.link.alive_robots, 5.0)
        for _ in range(3):
            time.sleep(0.25)   # a slow machine: 0.75 s of wall time over three ticks
            _tick(bridge, links, links[:1])
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
    with _fleet(config) as (bridge, links, seen):
        _tick(bridge, links, links)
        first = _tick(bridge, links, links[:1])          # r1's state is late
        assert first.robots == ROBOTS and seen[-1].state_age_s[1] == pytest.approx(0.05, abs=1e-9)
        late = _tick(bridge, links, links[1:])
        assert late.robots == ROBOTS and late.tick == first.tick + 1
        _tick(bridge, links, links)
        assert [s.time for s in seen] == pytest.approx([0.0, 0.05, 0.05, 0.10], abs=1e-9)
        assert seen[2].state_age_s.tolist() == [0.0, 0.0] and seen[3].state_age_s.tolist() == [0.0, 0.0]
        _tick(bridge, links, links[:1])             # r1 sends nothing this tick (a fleet timeout)
        sent = {link.robot: link.publish_state((0.3, 0.4), (0.0, 0.1)).seq for link in links[::-1]}
        assert bridge.link.wait_for(lambda: all(bridge.link.latest_states()[r].msg.seq == q for r, q in sent.items()),
                                    5.0)
        bridge.step(timeout_s=0.1)                  # r1 came first in the next tick: not a late part
        assert bridge.step(timeout_s=0.05) is None   # nothing new: neither a tick nor a late part
        _tick(bridge, links, links)
        assert [s.time for s in seen[4:]] == pytest.approx([0.15, 0.20, 0.25], abs=1e-9)
        assert bridge.summary()["late_parts"] == 1


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
        _tick(bridge, links, links[:1])                     # r1 silent: the bridge raises it
        time.sleep(0.02)
    assert bridge.link.estop_engaged
    code, answer = operator("release")
    assert code == 1 and not answer["ok"] and answer["silent_robot"] == "r1"
    assert "silent" in answer["reason"] and bridge.link.estop_engaged
    for _ in range(3):
        _tick(bridge, links, links)                         # r1 is back
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
        record = record or _tick(bridge, links, links)
    assert record.flags == (CmdFlags.BRAKE, CmdFlags.BRAKE) and not record.commands.any()
    code, answer = operator("status")
    assert code == 0 and answer["estop"] == "engaged"


def test_a_bridge_sends_lossless_once_the_fleet_says_it_is_lock_stepped(fleet):
    """A bridge started without --lossless, a fleet whose STATEs carry LOCKSTEP (fleet-sim
    --lockstep): from that tick on every command goes out with congestion control BLOCK (with
    DROP a starved machine lost answers the lock-stepped fleet then waited for)."""
    import zenoh

    bridge, links, _ = fleet
    assert not bridge.link.lossless
    _tick(bridge, links, links)
    assert all(p.congestion_control == zenoh.CongestionControl.DROP for p in bridge.link._cmd_publishers.values())
    for link in links:
        link.publish_state((0.3, 0.4), (0.0, 0.1), StateStatus.LOCKSTEP)
    assert bridge.step(timeout_s=0.5) is not None
    assert bridge.link.lossless and bridge.summary()["lossless"]
    assert all(p.congestion_control == zenoh.CongestionControl.BLOCK for p in bridge.link._cmd_publishers.values())
    assert links[0].wait_for(lambda: links[0].latest_command is not None, 5.0)  # arrives async
    seq = links[0].latest_command.msg.seq
    _tick(bridge, links, links)                      # the new publishers reach the robots
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


def test_a_robot_that_leaves_is_passed_on_with_its_commands_in_flight_counted(fleet):
    """``SilentRobots.commands_pending``: the commands sent after the one the robot's last state
    names, plus a tick for each tick since the bridge last sent it one (the controller records a
    braking row for it on each); -1 when the state names no command the bridge sent."""
    bridge, links, seen = fleet
    for _ in range(3):
        before = links[1].latest_command.msg.seq if links[1].latest_command else 0
        _tick(bridge, links, links)
        _last_flags(links[1], before)
    acted = links[1].latest_command.msg.seq - 1          # one command not acted on yet
    links[0].publish_state((0.3, 0.4), (0.0, 0.1))
    links[1].publish_state((0.7, 0.6), (0.05, 0.0), last_cmd_seq=acted)
    before = links[1].latest_command.msg.seq
    bridge.step(timeout_s=0.1)
    _last_flags(links[1], before)                        # answered: two after the acted one
    links[1].close()
    assert bridge.link.wait_for(lambda: "r1" not in bridge.link.alive_robots, 5.0)
    counts = []
    for _ in range(3):
        _tick(bridge, links, links[:1])
        counts.append(int(seen[-1].silent.pending()[0]))
    assert seen[-1].silent.ids == ("r1",)
    assert counts == [2, 3, 4]


def test_a_leaving_robot_whose_state_names_no_sent_command_is_passed_on_uncounted(fleet):
    bridge, links, seen = fleet
    _tick(bridge, links, links)
    links[1].publish_state((0.7, 0.6), (0.05, 0.0), last_cmd_seq=10_000)
    links[0].publish_state((0.3, 0.4), (0.0, 0.1))
    bridge.step(timeout_s=0.1)
    links[1].close()
    assert bridge.link.wait_for(lambda: "r1" not in bridge.link.alive_robots, 5.0)
    _tick(bridge, links, links[:1])
    assert seen[-1].silent.ids == ("r1",) and seen[-1].silent.pending().tolist() == [-1]


def test_a_burst_that_comes_in_pieces_is_answered_in_one_tick():
    """r1's state reaches the bridge 15 ms after r0's, as over a link whose delay jitters: the
    default gather (25 ms) answers both in one tick; at the former 10 ms a tick answered r0
    alone and a second one r1, two commands to r0 in one fleet tick."""
    for gather, ticks in ((BridgeConfig().gather_s, 1), (0.01, 2)):
        with _fleet(BridgeConfig(stale_after_s=0.2, gather_s=gather)) as (bridge, links, seen):
            _tick(bridge, links, links)                       # the first tick waits for everyone
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

    with _fleet(BridgeConfig(stale_after_s=0.2, estop_after_s=5.0, gather_s=1.0)) as (bridge, links, seen):
        _tick(bridge, links, links)
        time.sleep(QUIET_PERIODS * bridge.config.period_s + 0.05)
        start = time.monotonic()
        _tick(bridge, links, links[:1])
        assert time.monotonic() - start < 0.5
