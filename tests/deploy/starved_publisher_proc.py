"""A publisher on a starved CPU: bursts of one message per robot, as a controller sends its
commands or a fleet simulation its states (run by tests/deploy/test_data_publishers.py).

    python starved_publisher_proc.py PORT SETTINGS ROBOTS BURSTS CPU

SETTINGS ``fleet``: the fleet's own publishers (:func:`deploy.network.declare_data_publisher`);
``express``: the ones before them (express, otherwise the same). The process pins itself and the threads it
starts to one CPU at nice 19 before it opens its session, prints ``ready`` once its publishers
are declared, waits for ``go`` on stdin (the test then loads that CPU), publishes ``BURSTS``
bursts of ``ROBOTS`` messages 20 ms apart, prints ``sent N`` and keeps its session open
until ``done`` on stdin.
"""

from __future__ import annotations

import json
import os
import sys
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[2]))


def main(port: int, settings: str, robots: int, bursts: int, cpu: int) -> None:
    os.sched_setaffinity(0, {cpu})
    os.nice(19)
    import zenoh

    from deploy.network import TransportConfig, declare_data_publisher

    session = TransportConfig(connect=(f"tcp/127.0.0.1:{port}",)).open()
    drop = zenoh.CongestionControl.DROP
    keys = [f"starved/robot/r{i}/cmd" for i in range(robots)]
    publishers = [declare_data_publisher(session, key, drop, express=settings == "express")
                  for key in keys]
    print("ready", flush=True)
    sys.stdin.readline()
    payload = json.dumps({"pad": "x" * 40}).encode()
    sent = 0
    for _ in range(bursts):
        for publisher in publishers:
            publisher.put(payload)
            sent += 1
        time.sleep(0.02)
    time.sleep(0.5)
    print(f"sent {sent}", flush=True)
    sys.stdin.readline()                     # "done": the test has counted what arrived
    session.close()


if __name__ == "__main__":
    main(int(sys.argv[1]), sys.argv[2], int(sys.argv[3]), int(sys.argv[4]), int(sys.argv[5]))
