"""A bridge and a RobotLink for each of two robots, linked over Zenoh on loopback: what the
bridge tests that run in this process share (the ``fleet`` fixture: tests/deploy/conftest.py)."""

from __future__ import annotations

import contextlib

import numpy as np

from deploy.bridge import Bridge, BridgeConfig
from deploy.network import TransportConfig, free_tcp_port
from deploy.robot_link import RobotLink
from deploy.wire import RobotRegistry

ROBOTS = ("r0", "r1")
REGISTRY = RobotRegistry(ROBOTS)
TARGETS = {"r0": np.array([0.2, 0.2]), "r1": np.array([0.8, 0.8])}


@contextlib.contextmanager
def linked_fleet(config: BridgeConfig):
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


def tick(bridge, links, publishing):
    """Publish a state from each link of ``publishing``, then one bridge tick (its record)."""
    for link in publishing:
        link.publish_state((0.3, 0.4), (0.0, 0.1))
    return bridge.step(timeout_s=0.1)


def last_flags(link, after_seq=0):
    """The flags of the newest command ``link`` has received, once one after ``after_seq`` came."""
    assert link.wait_for(lambda: link.latest_command is not None
                         and link.latest_command.msg.seq > after_seq, 5.0)
    return link.latest_command.msg.flags
