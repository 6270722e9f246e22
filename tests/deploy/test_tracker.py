"""A tracker's sightings: what the controller keeps (hand-worked ages, GONE, stale and bad
messages), and the same over a real Zenoh session on 127.0.0.1."""

from __future__ import annotations

import time

import numpy as np
import pytest

from deploy.network import TransportConfig, free_tcp_port
from deploy.streams import WireDecoder
from deploy.tracker import SightingPublisher, SightingTable
from deploy.transport import FleetLink
from deploy.wire import RobotRegistry, SightingMsg, StateMsg, encode

MS = 1_000_000


class Clock:
    def __init__(self, ns: int):
        self.ns = ns

    def __call__(self) -> int:
        return self.ns


def sighting(obstacle: int, seq: int, sent_ns: int, position=(0.5, 0.6), radius=0.05, speed=0.3,
             capture_ms=0, gone=False, robot=None) -> bytes:
    return encode(SightingMsg(obstacle, 9, seq, sent_ns, position, radius, speed, capture_ms, gone, robot))


def test_the_table_ages_each_sighting_and_forgets_it_only_when_told():
    """Tracker clock 10 ms behind ours. Obstacle 1 sent at 0.990 s, received at 1.000, taken
    12 ms before sending: at 1.050 it is 50 + 12 = 62 ms old. Obstacle 2 sent at 1.000 and
    received at 1.040 took 30 ms longer than the fastest transfer (less the 200 ppm drift
    allowance over 40 ms): 10 + 29.992 ms old at 1.050."""
    clock = Clock(1000 * MS)
    table = SightingTable(WireDecoder(), clock)
    assert table.obstacles(clock.ns) is None
    table.receive(sighting(1, 1, 990 * MS, capture_ms=12))
    clock.ns = 1040 * MS
    table.receive(sighting(2, 1, 1000 * MS, position=(0.2, 0.3), radius=0.1, speed=0.0))
    obs = table.obstacles(1050 * MS)
    assert obs.ids == ("#1", "#2")
    np.testing.assert_allclose(obs.positions, [[0.5, 0.6], [0.2, 0.3]])
    np.testing.assert_allclose(obs.radii, [0.05, 0.1])
    np.testing.assert_allclose(obs.speed, [0.3, 0.0])
    np.testing.assert_allclose(obs.age_s, [0.062, 0.010 + 0.029992], atol=1e-9)
    # unreported, it stays and ages: losing sight of it is not its leaving
    np.testing.assert_allclose(table.obstacles(2050 * MS).age_s, [1.062, 1.039992], atol=1e-9)
    table.receive(sighting(1, 1, 995 * MS, position=(0.9, 0.9)))          # a repeat: stale
    table.receive(encode(StateMsg(1, 9, 2, 995 * MS, (0.0, 0.0), (0.0, 0.0))))  # not a sighting
    table.receive(sighting(1, 2, 1000 * MS, gone=True))
    table.receive(sighting(7, 1, 1000 * MS, gone=True))                      # never seen: nothing
    assert table.obstacles(1050 * MS).ids == ("#2",)
    assert table.summary() == {"accepted": 4, "gone": 1, "in_view": ["#2"]}
    assert table.decoder.rejects.snapshot() == {"UNEXPECTED_TYPE": 1, "STALE": 1}


@pytest.mark.parametrize("epochs", [(5, 5), (5, 6)])
def test_a_sighting_queued_on_the_uplink_is_aged_whether_obstacles_share_an_epoch_or_not(epochs):
    """Tracker clock 7 s behind ours. Both obstacles cross in 1 ms, then both queue 500 ms on the
    uplink: each is 499 ms old on receipt (500 less the fastest transfer, drift 200 ppm x 599 ms
    allowed). Each obstacle may be its own stream with its own epoch: before, each message of
    another epoch reset the tracker's floor, and both read as fresh (0 ms)."""
    clock = Clock(0)
    table = SightingTable(WireDecoder(), clock)
    for obstacle, (sent_ms, received_ms) in ((0, (0, 1)), (1, (0, 1)), (0, (100, 600)), (1, (100, 600))):
        clock.ns = received_ms * MS
        seq = 1 + (sent_ms > 0)
        table.receive(encode(SightingMsg(obstacle, epochs[obstacle], seq, 10**12 + sent_ms * MS - 7000 * MS,
                                         (0.2, 0.2 + 0.5 * obstacle), 0.05, 0.3)))
    allowance = 2e-4 * 0.599
    np.testing.assert_allclose(table.obstacles(600 * MS).age_s, [0.499 - allowance] * 2, atol=1e-9)


def test_a_robots_sighting_is_named_by_the_registry_and_refused_without_one():
    """Obstacle 5 is robot id 1 (r1 in the registry {r0: 0, r1: 1}); obstacle 6 is nobody. The
    obstacles name r1 beside #5 and None beside #6; a robot id the registry lacks, or a table
    with no registry to name it, is UNKNOWN_ROBOT and not kept."""
    clock = Clock(1000 * MS)
    table = SightingTable(WireDecoder(RobotRegistry(["r0", "r1"])), clock, uplink=False)
    table.receive(sighting(5, 1, 1000 * MS, robot=1))
    table.receive(sighting(6, 1, 1000 * MS))
    table.receive(sighting(8, 1, 1000 * MS, robot=7))
    obs = table.obstacles(1000 * MS)
    assert obs.ids == ("#5", "#6") and obs.robots == ("r1", None)
    blind = SightingTable(WireDecoder(), clock, uplink=False)
    blind.receive(sighting(5, 1, 1000 * MS, robot=1))
    assert blind.obstacles(1000 * MS) is None
    assert table.decoder.rejects.snapshot() == blind.decoder.rejects.snapshot() == {"UNKNOWN_ROBOT": 1}


def test_a_publisher_refuses_bad_fields_by_name():
    port = free_tcp_port()
    with TransportConfig(listen=(f"tcp/127.0.0.1:{port}",)).open() as session:
        publisher = SightingPublisher(session, "t")
        with pytest.raises(ValueError, match="obstacle_id must be an int in"):
            publisher.publish(0xFFFF, (0.5, 0.5), 0.05, 0.1)
        with pytest.raises(ValueError, match="radius=-0.05 must be > 0"):
            publisher.publish(1, (0.5, 0.5), -0.05, 0.1)
        with pytest.raises(ValueError, match="capture_age_s must be in"):
            publisher.publish(1, (0.5, 0.5), 0.05, 0.1, capture_age_s=-1.0)
        publisher.close()


@pytest.mark.realtime
def test_sightings_reach_the_controller_over_zenoh_until_gone():
    port = free_tcp_port()
    with FleetLink("t", RobotRegistry(["r0"]), TransportConfig(listen=(f"tcp/127.0.0.1:{port}",)),
                   shared_clock=True) as link, \
            TransportConfig(connect=(f"tcp/127.0.0.1:{port}",)).open() as session:
        table = SightingTable.listening(link)
        publisher = SightingPublisher(session, "t")
        time.sleep(0.5)                       # the subscriber's declaration reaches the publisher
        publisher.publish(4, (0.25, 0.75), 0.06, 0.2, capture_age_s=0.02, robot=0)
        assert link.wait_for(lambda: table.obstacles(link.clock_ns()) is not None, 5.0)
        obs = table.obstacles(link.clock_ns())
        assert obs.ids == ("#4",) and obs.positions.tolist() == [[0.25, 0.75]] and obs.robots == ("r0",)
        assert 0.02 <= obs.age_s[0] < 0.5
        publisher.gone(4)
        deadline = time.monotonic() + 5.0
        while table.obstacles(link.clock_ns()) is not None and time.monotonic() < deadline:
            time.sleep(0.01)
        assert table.summary() == {"accepted": 2, "gone": 1, "in_view": []}
        assert link.rejects.total == 0
        publisher.close()
