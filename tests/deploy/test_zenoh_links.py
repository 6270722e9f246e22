"""FleetLink and RobotLink over real Zenoh sessions on 127.0.0.1 (multicast scouting off)."""

from __future__ import annotations

import json
import math
import struct
import time

import numpy as np
import pytest
import zenoh

from deploy.network import FleetKeys, TransportConfig, free_tcp_port
from deploy.robot_link import MAX_ANSWER_AGE_S, RobotLink
from deploy.transport import FleetLink
from deploy.wire import (
    CmdFlags,
    CmdMsg,
    EstopMsg,
    RobotRegistry,
    StateMsg,
    StateStatus,
    encode,
)

pytestmark = pytest.mark.realtime   # Zenoh links, liveliness and timeouts

FLEET = "testfleet"
WAIT_S = 5.0  # generous: waits end as soon as the condition holds
REGISTRY = RobotRegistry(["r0", "r1"])


@pytest.fixture
def port() -> int:
    return free_tcp_port()


@pytest.fixture
def controller(port):
    with FleetLink(FLEET, REGISTRY, TransportConfig(listen=(f"tcp/127.0.0.1:{port}",))) as link:
        yield link


def robot_link(port: int, robot: str = "r0", listen_port: int | None = None,
               **kwargs) -> RobotLink:
    listen = (f"tcp/127.0.0.1:{listen_port}",) if listen_port else ()
    config = TransportConfig(listen=listen, connect=(f"tcp/127.0.0.1:{port}",))
    t = time.perf_counter()
    link = RobotLink(FLEET, robot, REGISTRY, config, **kwargs)
    print("robot open", robot, time.perf_counter() - t)
    return link


def connected(controller: FleetLink, robot: RobotLink) -> None:
    """Both sides see each other's token, so each side's subscriptions are in place."""
    assert controller.wait_for(lambda: robot.robot in controller.alive_robots, WAIT_S)
    assert robot.wait_for(lambda: robot.controller_alive, WAIT_S)


def test_keys_and_config():
    keys = FleetKeys("f1")
    assert keys.state("r3") == "formation/f1/robot/r3/state"
    assert keys.cmd("r3") == "formation/f1/robot/r3/cmd"
    assert keys.robot_alive("r3") == "formation/f1/robot/r3/alive"
    assert (keys.ctrl_alive, keys.estop) == ("formation/f1/ctrl/alive", "formation/f1/estop")
    assert keys.robot_in("formation/f1/robot/r3/state", "state") == "r3"
    assert keys.robot_in("formation/f2/robot/r3/state", "state") is None
    assert keys.robot_in("formation/f1/robot/a/b/state", "state") is None
    with pytest.raises(ValueError, match="never '@'"):
        keys.state("@r0")
    config = TransportConfig(listen=("tcp/127.0.0.1:7447",), connect=("tcp/10.0.0.2:7447",),
                             lease_ms=1000, insecure=True).to_zenoh()
    assert json.loads(config.get_json("mode")) == "peer"
    assert json.loads(config.get_json("listen/endpoints")) == ["tcp/127.0.0.1:7447"]
    assert json.loads(config.get_json("connect/endpoints")) == ["tcp/10.0.0.2:7447"]
    assert json.loads(config.get_json("scouting/multicast/enabled")) is False
    assert json.loads(config.get_json("transport/link/tx/lease")) == 1000
    with pytest.raises(ValueError, match="not a Zenoh endpoint"):
        TransportConfig(listen=("127.0.0.1:7447",))
    with pytest.raises(ValueError, match="tuple of endpoints"):
        TransportConfig(connect="tcp/127.0.0.1:7447")
    with pytest.raises(ValueError, match="lease_ms"):
        TransportConfig(lease_ms=5)


def test_state_and_command_round_trip(controller, port):
    with robot_link(port, "r0") as r0, robot_link(port, "r1") as r1:
        connected(controller, r0)
        connected(controller, r1)
        sent = r0.publish_state((0.25, -0.5), (0.125, 0.0), StateStatus.FAULT)
        assert controller.wait_for(lambda: controller.state_of("r0") is not None, WAIT_S)
        got = controller.state_of("r0")
        assert got.msg == sent and got.robot == "r0"
        assert got.msg.position == (0.25, -0.5) and got.msg.velocity == (0.125, 0.0)
        assert got.msg.status == StateStatus.FAULT and got.msg.robot_id == 0

        cmd = controller.send_command("r0", (1.5, -2.0), ttl_ms=200, flags=CmdFlags.BRAKE,
                                      state_seq=got.msg.seq)
        assert r0.wait_for(lambda: r0.latest_command is not None, WAIT_S)
        received = r0.latest_command
        assert received.msg == cmd and received.msg.acceleration == (1.5, -2.0)
        assert received.msg.state_seq == sent.seq
        assert received.expires_at_ns == received.receive_time_ns + 200_000_000
        assert r0.command(received.receive_time_ns + 199_999_999) is received
        assert r0.command(received.receive_time_ns + 200_000_000) is None
        assert r0.publish_state((0.0, 0.0), (0.0, 0.0)).last_cmd_seq == cmd.seq

        r1_state = r1.publish_state((0.75, 0.5), (0.0, 0.0))
        assert controller.wait_for(lambda: controller.state_of("r1") is not None, WAIT_S)
        batch = controller.send_accelerations(["r0", "r1"], np.array([[0.1, 0.2], [0.3, 0.4]]),
                                              ttl_ms=100)
        assert batch[1].state_seq == r1_state.seq
        assert r1.wait_for(lambda: r1.latest_command is not None, WAIT_S)
        assert r1.latest_command.msg.acceleration == (0.3, 0.4)
        assert r0.wait_for(lambda: r0.latest_command.msg.seq == batch[0].seq, WAIT_S)
        assert r0.latest_command.msg.acceleration == (0.1, 0.2)
        assert set(controller.latest_states()) == {"r0", "r1"}
        assert controller.rejects.total == r0.rejects.total == r1.rejects.total == 0


def test_commands_with_nan_are_never_sent(controller, port):
    with robot_link(port) as r0:
        connected(controller, r0)
        with pytest.raises(ValueError, match="NaN"):
            controller.send_accelerations(["r0", "r1"], np.array([[0.0, 0.0], [math.nan, 0]]),
                                          ttl_ms=100)
        with pytest.raises(ValueError, match="acceleration"):
            controller.send_command("r0", (math.inf, 0.0), ttl_ms=100)
        with pytest.raises(ValueError, match="not in the registry"):
            controller.send_command("r9", (0.0, 0.0), ttl_ms=100)
        ok = controller.send_command("r0", (0.0, 1.0), ttl_ms=100)
        assert r0.wait_for(lambda: r0.latest_command is not None, WAIT_S)
        assert r0.latest_command.msg == ok  # nothing from the refused calls arrived first


def test_robot_join_and_leave_are_seen(controller, port):
    r1 = robot_link(port, "r1")
    assert controller.wait_for(lambda: "r1" in controller.alive_robots, WAIT_S)
    r1.close()
    assert controller.wait_for(lambda: "r1" not in controller.alive_robots, WAIT_S)
    events = [(e.robot, e.joined) for e in controller.pop_events()]
    assert events == [("r1", True), ("r1", False)]
    assert controller.pop_events() == []


def test_estop_is_latched_for_a_robot_that_joins_later(controller, port):
    controller.raise_estop(reason_code=3)
    assert controller.estop_engaged
    with robot_link(port, "r0") as late:
        assert late.wait_for(lambda: late.estopped, WAIT_S)
        assert late.estop_reason == 3
        assert late.publish_state((0.0, 0.0), (0.0, 0.0)).status & StateStatus.ESTOPPED
        controller.clear_estop()
        assert late.wait_for(lambda: not late.estopped, WAIT_S)
    with robot_link(port, "r1") as after_clear:
        assert after_clear.wait_for(lambda: after_clear.estop_synced, WAIT_S)
        assert not after_clear.estopped
        assert after_clear.rejects.total == 0


def test_estop_latch_survives_a_controller_restart(port):
    listen = TransportConfig(listen=(f"tcp/127.0.0.1:{port}",))
    with robot_link(port, "r0") as robot:
        with FleetLink(FLEET, REGISTRY, listen) as first:
            connected(first, robot)
            first.raise_estop()
            assert robot.wait_for(lambda: robot.estopped, WAIT_S)
        assert robot.wait_for(lambda: not robot.controller_alive, WAIT_S)
        with FleetLink(FLEET, REGISTRY, listen) as second:  # never raised: answers "none"
            assert robot.wait_for(lambda: robot.controller_alive and robot.estop_synced, WAIT_S)
            assert robot.estopped
            second.clear_estop()  # a new epoch: accepted as the controller's restart
            assert robot.wait_for(lambda: not robot.estopped, WAIT_S)


def _raw_session(port: int) -> zenoh.Session:
    return zenoh.open(TransportConfig(connect=(f"tcp/127.0.0.1:{port}",)).to_zenoh())


def _inject(session: zenoh.Session, key: str, payloads: list[bytes]) -> None:
    """Publish raw payloads once a subscriber on ``key`` is known (else Zenoh drops them)."""
    publisher = session.declare_publisher(key, congestion_control=zenoh.CongestionControl.BLOCK)
    deadline = time.monotonic() + WAIT_S
    while not publisher.matching_status and time.monotonic() < deadline:
        time.sleep(0.005)
    assert publisher.matching_status, f"no subscriber on {key}"
    for payload in payloads:
        publisher.put(payload)
    publisher.undeclare()


def test_bad_states_are_rejected_counted_and_the_controller_keeps_running(controller, port):
    with robot_link(port, "r0") as r0, _raw_session(port) as raw:
        connected(controller, r0)
        good = r0.publish_state((0.5, 0.5), (0.0, 0.0))
        assert controller.wait_for(lambda: controller.state_of("r0") is not None, WAIT_S)
        r0_key, r1_key = FleetKeys(FLEET).state("r0"), FleetKeys(FLEET).state("r1")
        nan_state = bytearray(encode(StateMsg(0, good.epoch, good.seq + 50, 0, (0.0, 0.0),
                                              (0.0, 0.0))))
        struct.pack_into("<d", nan_state, 24, math.nan)
        injected = {
            r0_key: [b"", b"hello", b"\xff" * 64,  # BAD_SIZE, BAD_SIZE, BAD_MAGIC
                     encode(good),  # replay: STALE
                     bytes(nan_state),  # NON_FINITE
                     encode(StateMsg(1, 9, 1, 0, (0.0, 0.0), (0.0, 0.0))),  # r1's id: MISMATCH
                     encode(CmdMsg(0, 9, 1, 0, (0.0, 0.0), 10)),  # UNEXPECTED_TYPE
                     b"FS\x03" + encode(good)[3:]],  # BAD_VERSION (1 and 2 are spoken)
            "formation/testfleet/robot/zz/state": [encode(good)],  # UNKNOWN_ROBOT
        }
        for key, payloads in injected.items():
            _inject(raw, key, payloads)
        expected = {"BAD_SIZE": 2, "BAD_MAGIC": 1, "STALE": 1, "NON_FINITE": 1,
                    "ROBOT_MISMATCH": 1, "UNEXPECTED_TYPE": 1, "BAD_VERSION": 1,
                    "UNKNOWN_ROBOT": 1}
        assert controller.wait_for(lambda: controller.rejects.total == 9, WAIT_S)
        assert controller.rejects.snapshot() == expected
        assert controller.state_of("r0").msg == good  # nothing bad replaced the good state
        assert r1_key not in controller.latest_states()
        newer = r0.publish_state((0.625, 0.5), (0.0, 0.0))
        assert controller.wait_for(lambda: controller.state_of("r0").msg == newer, WAIT_S)
        assert controller.internal_errors == 0


def test_bad_commands_are_rejected_and_counted_by_the_robot(controller, port):
    now = time.monotonic_ns()
    robot_port = free_tcp_port()  # peers do not relay: the injector connects to the robot
    with (robot_link(port, "r0", listen_port=robot_port, shared_clock=True) as r0,
          _raw_session(robot_port) as raw):
        connected(controller, r0)
        good = controller.send_command("r0", (0.5, 0.0), ttl_ms=500)
        assert r0.wait_for(lambda: r0.latest_command is not None, WAIT_S)
        key = FleetKeys(FLEET).cmd("r0")
        injected = [
            encode(CmdMsg(0, good.epoch, good.seq + 1, now - 10**9, (9.0, 9.0), 100)),  # EXPIRED
            encode(CmdMsg(0, good.epoch, good.seq + 2, now + 10**10, (9.0, 9.0), 100)),  # FUTURE
            encode(good),  # STALE
            encode(CmdMsg(1, good.epoch, good.seq + 3, now, (9.0, 9.0), 100)),  # ROBOT_MISMATCH
            encode(EstopMsg(1, 1, now, True)),  # UNEXPECTED_TYPE
            encode(good)[:-1],  # BAD_SIZE
        ]
        _inject(raw, key, injected)
        assert r0.wait_for(lambda: r0.rejects.total == len(injected), WAIT_S)
        assert r0.rejects.snapshot() == {"BAD_SIZE": 1, "UNEXPECTED_TYPE": 1, "ROBOT_MISMATCH": 1,
                                         "STALE": 1, "EXPIRED": 1, "FROM_FUTURE": 1}
        assert r0.latest_command.msg == good
        assert not r0.estopped  # an ESTOP on the cmd key is not an e-stop
        later = controller.send_command("r0", (0.0, -0.5), ttl_ms=500)
        assert r0.wait_for(lambda: r0.latest_command.msg == later, WAIT_S)
        assert r0.internal_errors == 0


def test_links_tolerate_use_after_close(port):
    controller = FleetLink(FLEET, REGISTRY, TransportConfig(listen=(f"tcp/127.0.0.1:{port}",)))
    robot = robot_link(port)
    connected(controller, robot)
    robot.publish_state((0.1, 0.1), (0.0, 0.0))
    assert controller.wait_for(lambda: controller.state_of("r0") is not None, WAIT_S)
    robot.close()
    controller.close()
    controller.close()  # idempotent
    assert controller.closed and controller.state_of("r0") is not None
    assert controller.wait_for(lambda: False, timeout_s=WAIT_S) is False  # returns at once
    assert robot.latest_command is None and robot.command() is None
    with pytest.raises(RuntimeError, match="closed"):
        controller.send_command("r0", (0.0, 0.0), ttl_ms=10)
    with pytest.raises(RuntimeError, match="closed"):
        robot.publish_state((0.0, 0.0), (0.0, 0.0))


def test_links_can_share_one_session(controller, port):
    session = zenoh.open(TransportConfig(connect=(f"tcp/127.0.0.1:{port}",)).to_zenoh())
    try:
        robots = [RobotLink(FLEET, name, REGISTRY, session) for name in ("r0", "r1")]
        assert controller.wait_for(lambda: controller.alive_robots == {"r0", "r1"}, WAIT_S)
        robots[0].close()  # leaves the session open for the other robot
        assert controller.wait_for(lambda: controller.alive_robots == {"r1"}, WAIT_S)
        assert robots[1].wait_for(lambda: robots[1].controller_alive, WAIT_S)
        robots[1].publish_state((0.3, 0.3), (0.0, 0.0))
        assert controller.wait_for(lambda: controller.state_of("r1") is not None, WAIT_S)
        robots[1].close()
    finally:
        session.close()


@pytest.mark.parametrize("lossless, expected", [(False, zenoh.CongestionControl.DROP),
                                                (True, zenoh.CongestionControl.BLOCK)])
def test_lossless_links_publish_states_and_commands_with_block(port, lossless, expected):
    # A lock-stepped fleet awaits every message: with DROP a starved CPU lost answers (stalled
    # ticks); real-time links keep DROP so a stalled pipeline never queues old commands.
    config = TransportConfig(listen=(f"tcp/127.0.0.1:{port}",))
    with FleetLink(FLEET, REGISTRY, config, lossless=lossless) as controller:
        with robot_link(port, lossless=lossless) as robot:
            assert controller.data_congestion_control == expected == robot.data_congestion_control
            assert all(p.congestion_control == expected for p in controller._cmd_publishers.values())
            assert robot._state_publisher.congestion_control == expected
            assert controller._estop_publisher.congestion_control == zenoh.CongestionControl.BLOCK
            connected(controller, robot)   # and the lossless pair still talks
            robot.publish_state((0.1, 0.2), (0.0, 0.0))
            assert controller.wait_for(lambda: "r0" in controller.latest_states(), WAIT_S)
            controller.send_command("r0", (0.5, -0.5), 100)
            assert robot.wait_for(lambda: robot.latest_command is not None, WAIT_S)
            assert robot.latest_command.msg.acceleration == (0.5, -0.5)


def _burst_rounds(port: int, rounds: int, junk: int) -> tuple[list[int], RobotLink]:
    """Each round: one valid CMD (seq k) then ``junk`` undecodable messages, all at once; the
    seqs of the rounds whose valid command the robot never saw (within 1 s)."""
    robot_port = free_tcp_port()
    r0 = robot_link(port, "r0", listen_port=robot_port)
    lost = []
    with _raw_session(robot_port) as raw:
        key = FleetKeys(FLEET).cmd("r0")
        now = time.monotonic_ns()
        for k in range(1, rounds + 1):
            valid = encode(CmdMsg(0, 12345, k, now, (0.1, 0.0), 60000))
            _inject(raw, key, [valid] + [b"junk"] * junk)
            if not r0.wait_for(lambda k=k: r0.latest_command is not None and r0.latest_command.msg.seq == k, 1.0):
                lost.append(k)
        assert r0.wait_for(lambda: r0.rejects.total == rounds * junk, WAIT_S)
    return lost, r0


def test_a_burst_of_junk_never_pushes_a_valid_command_out_unseen(port):
    """50 junk messages right behind each valid command (a ring of 16 lost 19 % of the valid ones,
    uncounted): every valid command is seen, every junk message counted, nothing missed."""
    lost, r0 = _burst_rounds(port, 20, 50)
    with r0:
        assert lost == []
        assert r0.rejects.snapshot() == {"BAD_SIZE": 20 * 50}
        assert r0.missed_commands == 0


def test_a_robot_counts_the_commands_it_never_saw(controller, port):
    """The controller numbers its commands 1, 2, ...: a robot that sees 1 and then 4 missed two."""
    robot_port = free_tcp_port()
    with robot_link(port, "r0", listen_port=robot_port) as r0, _raw_session(robot_port) as raw:
        now, key = time.monotonic_ns(), FleetKeys(FLEET).cmd("r0")
        _inject(raw, key, [encode(CmdMsg(0, 99, 1, now, (0.0, 0.0), 500))])
        assert r0.wait_for(lambda: r0.latest_command is not None, WAIT_S)
        _inject(raw, key, [encode(CmdMsg(0, 99, 4, now, (0.0, 0.0), 500))])
        assert r0.wait_for(lambda: r0.latest_command.msg.seq == 4, WAIT_S)
        assert r0.missed_commands == 2
        _inject(raw, key, [encode(CmdMsg(0, 7, 1, now, (0.0, 0.0), 500))])   # a restart: no gap
        assert r0.wait_for(lambda: r0.latest_command.msg.epoch == 7, WAIT_S)
        assert r0.missed_commands == 2


def test_a_clock_is_shared_when_every_endpoint_is_on_loopback():
    from deploy.fleet_sim import FleetSimConfig
    from sim.scenario import make_scenario

    local = TransportConfig(listen=("tcp/127.0.0.1:7447",), connect=("udp/[::1]:7448", "tcp/localhost:1"))
    assert local.loopback_only()
    assert not TransportConfig(listen=("tcp/127.0.0.1:7447",), connect=("tcp/10.0.0.2:7447",),
                               insecure=True).loopback_only()
    assert not TransportConfig().loopback_only()                       # no endpoint: scouting decides
    assert not TransportConfig(listen=("tcp/127.0.0.1:7447",), multicast_scouting=True).loopback_only()
    sc = make_scenario("paper-3")
    assert FleetSimConfig(fleet="f", scenario=sc, transport=local).clock_is_shared()
    assert not FleetSimConfig(fleet="f", scenario=sc, transport=local, shared_clock=False).clock_is_shared()
    remote = TransportConfig(connect=("tcp/10.0.0.2:7447",), insecure=True)
    assert FleetSimConfig(fleet="f", scenario=sc, transport=remote, shared_clock=True).clock_is_shared()


def test_a_zenoh_config_file_is_the_base_and_the_flags_are_written_over_it(tmp_path, port):
    """--zenoh-config FILE: its settings hold (a lease, its endpoints) unless a flag says
    otherwise; a link opened from it talks; a plain endpoint off loopback in the file is refused
    as on the command line; a broken file names itself."""
    path = tmp_path / "zenoh.json5"
    endpoint = json.dumps([f"tcp/127.0.0.1:{port}"])
    path.write_text('{ mode: "peer", listen: { endpoints: ' + endpoint + ' },\n'
                    '  scouting: { multicast: { enabled: false } },  // comments are JSON5\n'
                    '  transport: { link: { tx: { lease: 2500 } } } }')
    config = TransportConfig(zenoh_config=str(path)).to_zenoh()
    assert json.loads(config.get_json("listen/endpoints")) == [f"tcp/127.0.0.1:{port}"]
    assert json.loads(config.get_json("transport/link/tx/lease")) == 2500
    other = free_tcp_port()
    flags = TransportConfig(listen=(f"tcp/127.0.0.1:{other}",), zenoh_config=str(path)).to_zenoh()
    assert json.loads(flags.get_json("listen/endpoints")) == [f"tcp/127.0.0.1:{other}"]
    with FleetLink(FLEET, REGISTRY, TransportConfig(zenoh_config=str(path))) as controller, \
            robot_link(port) as robot:
        connected(controller, robot)
    path.write_text('{ connect: { endpoints: ["tcp/10.0.0.9:7447"] } }')
    with pytest.raises(ValueError, match="off this host"):
        TransportConfig(zenoh_config=str(path)).to_zenoh()
    path.write_text("{ this is not json5")
    with pytest.raises(ValueError, match="zenoh.json5"):
        TransportConfig(zenoh_config=str(path)).to_zenoh()


def _takes(robot: RobotLink, msg) -> bool:
    """The robot's latest accepted command becomes ``msg`` within WAIT_S."""
    return robot.wait_for(lambda: robot.latest_command is not None and robot.latest_command.msg == msg, WAIT_S)


@pytest.mark.parametrize("bound", [MAX_ANSWER_AGE_S, None])
def test_a_robot_refuses_commands_answering_a_state_it_sent_too_long_ago(controller, port, bound):
    """By the robot's own clock (no shared clock needed): a CMD answering its STATE of 0.6 s
    ago is STALE_ANSWER (default bound 0.5 s), as is one naming a STATE it never sent; one
    answering its newest STATE, one answering none (state_seq 0) and BRAKE pass. With the rule
    off (None) the late command is taken: what a congested link would make a robot do."""
    clock = [10**12]
    with robot_link(port, "r0", clock_ns=lambda: clock[0], max_answer_age_s=bound) as r0:
        connected(controller, r0)
        first = r0.publish_state((0.5, 0.5), (0.0, 0.0))
        answered = controller.send_command("r0", (0.5, 0.0), ttl_ms=500, state_seq=first.seq)
        assert _takes(r0, answered)
        clock[0] += 600_000_000                                           # 0.6 s later
        controller.send_command("r0", (0.9, 0.0), ttl_ms=500, state_seq=first.seq)
        never = controller.send_command("r0", (0.9, 0.0), ttl_ms=500, state_seq=first.seq + 50)
        if bound is None:
            assert _takes(r0, never)
        else:
            assert r0.wait_for(lambda: r0.rejects.total == 2, WAIT_S)
            assert r0.latest_command.msg == answered
        expected = {} if bound is None else {"STALE_ANSWER": 2}
        assert r0.rejects.snapshot() == expected
        assert _takes(r0, controller.send_command("r0", (0.0, 0.0), ttl_ms=500, flags=CmdFlags.BRAKE,
                                                  state_seq=first.seq))
        assert _takes(r0, controller.send_command("r0", (0.2, 0.0), ttl_ms=500))
        fresh = r0.publish_state((0.5, 0.5), (0.0, 0.0))
        assert _takes(r0, controller.send_command("r0", (0.3, 0.0), ttl_ms=500, state_seq=fresh.seq))
        assert r0.rejects.snapshot() == expected


def test_a_command_refused_as_a_stale_answer_does_not_take_the_command_stream(controller, port):
    """A CMD of another epoch (another node, or a controller before its restart) answering a STATE
    the robot never sent is STALE_ANSWER, and must leave the stream to the controller: before, it
    retired the controller's epoch and the robot refused every genuine command from then on."""
    own = free_tcp_port()
    with robot_link(port, "r0", listen_port=own) as r0, \
            zenoh.open(TransportConfig(connect=(f"tcp/127.0.0.1:{own}",)).to_zenoh()) as raw:
        connected(controller, r0)
        first = r0.publish_state((0.5, 0.5), (0.0, 0.0))
        assert _takes(r0, controller.send_command("r0", (0.1, 0.0), ttl_ms=500, state_seq=first.seq))
        foreign = raw.declare_publisher(FleetKeys(FLEET).cmd("r0"))
        deadline = time.monotonic() + WAIT_S
        while not foreign.matching_status and time.monotonic() < deadline:
            time.sleep(0.01)
        foreign.put(encode(CmdMsg(0, 2222, 1, time.monotonic_ns(), (0.4, 0.0), 500, state_seq=first.seq + 50)))
        assert r0.wait_for(lambda: r0.rejects.snapshot() == {"STALE_ANSWER": 1}, WAIT_S), r0.rejects.snapshot()
        fresh = r0.publish_state((0.5, 0.5), (0.0, 0.0))
        assert _takes(r0, controller.send_command("r0", (0.2, 0.0), ttl_ms=500, state_seq=fresh.seq))
        assert r0.rejects.snapshot() == {"STALE_ANSWER": 1}


def test_an_answer_age_bound_that_cannot_work_is_refused(port):
    with pytest.raises(ValueError, match="max_answer_age_s must be a positive number of seconds"):
        robot_link(port, "r0", max_answer_age_s=0.0)


def test_an_operator_release_after_a_controller_restart_frees_the_latched_robots(port):
    """Controller A latches the e-stop and restarts as B, which never raised one: `formation estop
    --release` through B frees the robots (before, it answered 'released' and sent nothing, and
    every robot stayed latched)."""
    from deploy.operator_channel import operator_answer

    endpoint = TransportConfig(listen=(f"tcp/127.0.0.1:{port}",))
    first = FleetLink(FLEET, REGISTRY, endpoint)
    with robot_link(port, "r0") as r0:
        try:
            connected(first, r0)
            first.raise_estop(1)
            assert r0.wait_for(lambda: r0.estopped, WAIT_S)
        finally:
            first.close()
        assert r0.wait_for(lambda: not r0.controller_alive, WAIT_S)
        with FleetLink(FLEET, REGISTRY, endpoint) as second:
            assert r0.wait_for(lambda: r0.controller_alive and r0.estop_synced, 3 * WAIT_S)
            assert r0.estopped
            answer = operator_answer("release", second, None, 1.0)
            assert answer["ok"] and answer["estop"] == "released"
            assert r0.wait_for(lambda: not r0.estopped, WAIT_S)
