"""A robot in its own process for tests/deploy/test_zenoh_processes.py (run as a script).

It connects to the controller at 127.0.0.1:<port>, prints one JSON line per phase and, with
``--exchanges N``, sends N states, each time waiting for the command that answers it, checking
that the command carries the acceleration the controller derives from that state
(``expected_acceleration``), and measuring the round trip on its own clock. Then it keeps its
liveliness token until it is killed.
"""

from __future__ import annotations

import argparse
import json
import sys
import time

from deploy.network import TransportConfig
from deploy.robot_link import RobotLink
from deploy.wire import RobotRegistry


def expected_acceleration(position: tuple[float, float]) -> tuple[float, float]:
    """What the test controller answers to a state: a = (-x, 2 y) [m/s^2]."""
    return (-position[0], 2.0 * position[1])


def emit(**fields) -> None:
    print(json.dumps(fields), flush=True)


def main() -> int:
    parser = argparse.ArgumentParser()
    parser.add_argument("--port", type=int, required=True)
    parser.add_argument("--fleet", required=True)
    parser.add_argument("--robot", required=True)
    parser.add_argument("--robots", required=True, help="comma-separated registry, in id order")
    parser.add_argument("--exchanges", type=int, default=0)
    parser.add_argument("--lease-ms", type=int, default=None)
    args = parser.parse_args()

    registry = RobotRegistry(args.robots.split(","))
    config = TransportConfig(connect=(f"tcp/127.0.0.1:{args.port}",), lease_ms=args.lease_ms)
    with RobotLink(args.fleet, args.robot, registry, config) as link:
        if not link.wait_for(lambda: link.controller_alive and link.estop_synced, 10.0):
            emit(phase="error", detail="controller not seen")
            return 1
        emit(phase="ready", estopped=link.estopped, estop_reason=link.estop_reason)
        rtts_us, wrong = [], 0
        for i in range(args.exchanges):
            position = (0.001 * i, 0.5 - 0.001 * i)
            sent = link.publish_state(position, (0.0, 0.0))
            answered = link.wait_for(lambda s=sent: link.latest_command is not None
                                     and link.latest_command.msg.state_seq == s.seq, 5.0)
            if not answered:
                emit(phase="error", detail=f"no command for state seq {sent.seq}")
                return 1
            received = link.latest_command
            rtts_us.append((received.receive_time_ns - sent.send_time_ns) / 1e3)
            wrong += received.msg.acceleration != expected_acceleration(position)
        if args.exchanges:
            emit(phase="exchanged", rtts_us=rtts_us, wrong=wrong, rejects=link.rejects.total)
        while True:  # hold the liveliness token until killed
            time.sleep(0.1)


if __name__ == "__main__":
    sys.exit(main())
