"""Bridge and fleet-sim in this process over real Zenoh: stale robots, e-stop, bad controllers."""

from __future__ import annotations

import threading
import time

import numpy as np
import pytest

from controllers.scripted import ScriptedController
from deploy.bridge import ESTOP_STALE_PICTURE, Bridge, BridgeConfig
from deploy.fleet_sim import FleetSim, FleetSimConfig, robot_names
from deploy.transport import RobotLink, TransportConfig, free_tcp_port
from deploy.wire import CmdFlags, RobotRegistry
from sim.scenario import make_scenario

ROBOTS = ("r0", "r1")
REGISTRY = RobotRegistry(ROBOTS)
TARGETS = {"r0": np.array([0.2, 0.2]), "r1": np.array([0.8, 0.8])}


@pytest.fixture
def fleet():
    port = free_tcp_port()
    seen: list = []

    def controller(state):
        seen.append(state)
        return np.tile([0.1, -0.2], (state.num_robots, 1))

    config = BridgeConfig(ttl_ms=100, stale_after_s=0.2, estop_after_s=0.6)
    bridge = Bridge("bf", REGISTRY, TransportConfig(listen=(f"tcp/127.0.0.1:{port}",)), controller,
                    targets=TARGETS, object_pose=np.zeros(3), config=config)
    robot_cfg = TransportConfig(connect=(f"tcp/127.0.0.1:{port}",))
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


def _tick(bridge, links, publishing):
    for link in publishing:
        link.publish_state((0.3, 0.4), (0.0, 0.1))
    return bridge.step(timeout_s=0.1)


def test_stale_robot_is_left_out_then_the_old_picture_raises_the_estop(fleet):
    bridge, links, seen = fleet
    record = _tick(bridge, links, links)
    assert record.robots == ROBOTS and record.stale == ()
    assert seen[-1].num_robots == 2 and np.allclose(seen[-1].targets, [[0.2, 0.2], [0.8, 0.8]])
    assert links[1].wait_for(lambda: links[1].latest_command is not None, 5.0)
    start = time.monotonic()
    while time.monotonic() - start < 0.35:  # r1 falls silent; r0 keeps publishing
        record = _tick(bridge, links, links[:1])
        time.sleep(0.02)
    assert record.robots == ("r0",) and record.stale == ("r1",)
    assert seen[-1].robot_ids == ("r0",)
    assert bridge.stats.robot_counts == [(0, 2), (bridge.stats.robot_counts[1][0], 1)]
    assert not bridge.link.estop_engaged
    start = time.monotonic()
    while not bridge.link.estop_engaged and time.monotonic() - start < 5.0:
        assert _tick(bridge, links, []) is None  # nobody publishes: the picture ages
    assert bridge.link.estop_engaged and bridge.stats.estops == 1
    for link in links:
        assert link.wait_for(lambda lk=link: lk.estopped, 5.0)
        assert link.estop_reason == ESTOP_STALE_PICTURE


def test_a_failing_controller_brakes_every_robot_and_is_counted(fleet):
    bridge, links, _ = fleet
    bridge.controller = lambda state: np.full((state.num_robots, 2), np.nan)
    _tick(bridge, links, links)
    for link in links:
        assert link.wait_for(lambda lk=link: lk.latest_command is not None, 5.0)
        assert link.latest_command.msg.flags & CmdFlags.BRAKE
    bridge.controller = lambda state: np.zeros((state.num_robots + 1, 2))  # wrong shape
    _tick(bridge, links, links)
    assert bridge.stats.controller_faults == 2


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
