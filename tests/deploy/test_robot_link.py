"""RobotLink.missed_commands: commands the controller put on the wire that never reached the
robot's decoder, by hand-worked cases, against a reference over random arrivals, and over real
Zenoh sessions on 127.0.0.1 (multicast scouting off)."""

from __future__ import annotations

import math
import struct
import time
from types import SimpleNamespace

import pytest
import zenoh
from hypothesis import given, settings
from hypothesis import strategies as st

from deploy.network import FleetKeys, TransportConfig, free_tcp_port
from deploy.robot_link import GAP_WINDOW, CommandGaps, RobotLink, numbered_command
from deploy.transport import FleetLink
from deploy.wire import CmdMsg, EstopMsg, RobotRegistry, encode

FLEET = "linkfleet"
WAIT_S = 5.0
REGISTRY = RobotRegistry(["r0", "r1"])


def _cmd(seq: int, epoch: int = 99, *, nan: bool = False, robot_id: int = 0, ttl_ms: int = 500) -> bytes:
    """A CMD to ``robot_id``; ``nan``: its acceleration made NaN after encoding (NON_FINITE)."""
    data = bytearray(encode(CmdMsg(robot_id, epoch, seq, time.monotonic_ns(), (0.1, 0.0), ttl_ms)))
    if nan:
        struct.pack_into("<d", data, 24, math.nan)
    return bytes(data)


def _gaps(events: list[tuple[str, int]], epoch: int = 5) -> int:
    gaps = CommandGaps()
    for kind, seq in events:
        (gaps.accepted if kind == "a" else gaps.rejected)(epoch, seq)
    return gaps.missed


def test_hand_worked_gaps():
    # 1..10, 4 rejected (e.g. a stale answer), the rest accepted: nothing missed
    assert _gaps([("a", s) for s in (1, 2, 3)] + [("r", 4)] + [("a", s) for s in range(5, 11)]) == 0
    # 1..10 with 4 and 7 lost: two missed
    assert _gaps([("a", s) for s in (1, 2, 3, 5, 6, 8, 9, 10)]) == 2
    # 1, 2, 3 rejected malformed, 4, then 7 (5 and 6 lost), then 5 late (STALE): one missed
    assert _gaps([("a", 1), ("a", 2), ("r", 3), ("a", 4), ("a", 7), ("r", 5)]) == 1
    # the first command seen starts the count: joining at seq 40 misses nothing before it
    assert _gaps([("a", 40), ("a", 41)]) == 0
    # rejected before the first accepted one, reordered: 3 accepted, then 5 (rejected earlier)
    assert _gaps([("r", 5), ("a", 3), ("a", 7)]) == 2              # 4 and 6
    # only the span up to the newest accepted one counts: 1, then 3 rejected, nothing more
    assert _gaps([("a", 1), ("r", 3)]) == 0
    # a duplicate is not a retraction twice
    assert _gaps([("a", 1), ("a", 4), ("r", 2), ("r", 2)]) == 1


def test_a_restart_starts_a_new_span_and_keeps_what_was_counted():
    gaps = CommandGaps()
    for seq in (1, 3):
        gaps.accepted(11, seq)
    assert gaps.missed == 1
    gaps.accepted(12, 50)                      # a restarted controller (or a robot joining late)
    gaps.accepted(12, 51)
    assert gaps.missed == 1
    gaps.rejected(11, 2)                       # late, of a retired epoch: not retracted
    assert gaps.missed == 1


def test_a_huge_gap_is_counted_in_bounded_memory():
    gaps = CommandGaps()
    gaps.accepted(1, 1)
    gaps.accepted(1, 4_000_000_000)
    assert gaps.missed == 4_000_000_000 - 2
    assert len(gaps._holes) < GAP_WINDOW and len(gaps._hole_order) < GAP_WINDOW
    gaps.rejected(1, 4_000_000_000 - 5)        # late, within the window: retracted
    gaps.rejected(1, 10)                       # late, far behind: stays counted
    assert gaps.missed == 4_000_000_000 - 3


def test_only_numbered_commands_to_this_robot_are_read():
    assert numbered_command(_cmd(7, 42), 0) == (42, 7)
    assert numbered_command(_cmd(7, 42, nan=True), 0) == (42, 7)
    assert numbered_command(_cmd(7, 42)[:-1], 0) == (42, 7)         # BAD_SIZE, header intact
    assert numbered_command(_cmd(7, 42, robot_id=1), 0) is None    # another robot's
    assert numbered_command(encode(EstopMsg(42, 7, 0, True)), 0) is None
    assert numbered_command(b"junk", 0) is None
    assert numbered_command(b"XX" + _cmd(7, 42)[2:], 0) is None


# -- through the real decoder, against a reference --------------------------------------------
@pytest.fixture(scope="module")
def bare_link():
    """A robot link nobody talks to; commands are handed to its receive handler directly."""
    config = TransportConfig(listen=(f"tcp/127.0.0.1:{free_tcp_port()}",))
    with RobotLink(FLEET, "r0", REGISTRY, config, max_answer_age_s=None) as link:
        yield link


def _deliver(link: RobotLink, payload: bytes) -> None:
    link._on_cmd(SimpleNamespace(payload=SimpleNamespace(to_bytes=lambda: payload)))


_epochs = iter(range(1_000, 10**9))

arrivals = st.lists(st.tuples(st.integers(1, 60), st.booleans()), min_size=1, max_size=60)


@settings(max_examples=300, deadline=None)
@given(arrivals)
def test_missed_commands_match_the_definition(bare_link, arriving):
    """Arrivals of one epoch in any order, some malformed (NaN): missed == the seqs between
    the first and the newest accepted command that never arrived at all."""
    epoch = next(_epochs)
    before, accepted = bare_link.missed_commands, []
    for seq, malformed in arriving:
        previous = bare_link.latest_command
        _deliver(bare_link, _cmd(seq, epoch, nan=malformed))
        if bare_link.latest_command is not previous:
            accepted.append(seq)
    arrived = {seq for seq, _ in arriving}
    expected = 0 if not accepted else sum(
        1 for s in range(accepted[0], accepted[-1] + 1) if s not in arrived)
    assert bare_link.missed_commands - before == expected


# -- over Zenoh ---------------------------------------------------------------------------------
def _connected(controller: FleetLink, robot: RobotLink) -> None:
    assert controller.wait_for(lambda: robot.robot in controller.alive_robots, WAIT_S)
    assert robot.wait_for(lambda: robot.controller_alive, WAIT_S)


@pytest.mark.realtime
def test_rejected_and_refused_commands_are_not_missed():
    """The controller is asked for 10 commands: the 4th answers a state the robot never sent
    (STALE_ANSWER), the 7th has a NaN (refused, never sent). Nothing was lost on the wire:
    missed == 0, one rejection, and the 9 sent took seqs 1..9."""
    port = free_tcp_port()
    with FleetLink(FLEET, REGISTRY, TransportConfig(listen=(f"tcp/127.0.0.1:{port}",))) as controller, \
            RobotLink(FLEET, "r0", REGISTRY, TransportConfig(connect=(f"tcp/127.0.0.1:{port}",))) as robot:
        _connected(controller, robot)
        state = robot.publish_state((0.0, 0.0), (0.0, 0.0))
        sent = []
        for k in range(1, 11):
            if k == 7:
                with pytest.raises(ValueError, match="NaN"):
                    controller.send_command("r0", (math.nan, 0.0), ttl_ms=500)
                continue
            answers = state.seq + 50 if k == 4 else state.seq
            sent.append(controller.send_command("r0", (0.1, 0.0), ttl_ms=500, state_seq=answers).seq)
        assert robot.wait_for(lambda: robot.latest_command is not None
                              and robot.latest_command.msg.seq == sent[-1], WAIT_S)
        assert robot.rejects.snapshot() == {"STALE_ANSWER": 1}
        assert robot.missed_commands == 0
        assert sent == list(range(1, 10))


@pytest.mark.realtime
def test_a_command_lost_on_the_wire_is_missed_once():
    """Injected 1, 2, 3 (NaN), 4, 7, 5 (late): 3 and 5 reached the robot (rejected), only 6
    never did: missed == 1."""
    own = free_tcp_port()
    with RobotLink(FLEET, "r0", REGISTRY, TransportConfig(listen=(f"tcp/127.0.0.1:{own}",))) as robot, \
            zenoh.open(TransportConfig(connect=(f"tcp/127.0.0.1:{own}",)).to_zenoh()) as raw:
        publisher = raw.declare_publisher(FleetKeys(FLEET).cmd("r0"),
                                          congestion_control=zenoh.CongestionControl.BLOCK)
        deadline = time.monotonic() + WAIT_S
        while not publisher.matching_status and time.monotonic() < deadline:
            time.sleep(0.005)
        for seq, nan in ((1, False), (2, False), (3, True), (4, False), (7, False), (5, False)):
            publisher.put(_cmd(seq, 77, nan=nan))
        assert robot.wait_for(lambda: robot.rejects.total == 2, WAIT_S), robot.rejects.snapshot()
        assert robot.rejects.snapshot() == {"NON_FINITE": 1, "STALE": 1}
        assert robot.latest_command.msg.seq == 7
        assert robot.missed_commands == 1


@pytest.mark.realtime
def test_a_refused_state_takes_no_seq():
    """A robot's STATE seqs are its ticks to a lock-stepped controller (episode ``(seq - 1) // T``):
    a state refused for a NaN must not use one up."""
    port = free_tcp_port()
    with RobotLink(FLEET, "r0", REGISTRY, TransportConfig(listen=(f"tcp/127.0.0.1:{port}",))) as robot:
        first = robot.publish_state((0.1, 0.1), (0.0, 0.0)).seq
        with pytest.raises(ValueError, match="NaN"):
            robot.publish_state((math.nan, 0.1), (0.0, 0.0))
        assert robot.publish_state((0.1, 0.1), (0.0, 0.0)).seq == first + 1
