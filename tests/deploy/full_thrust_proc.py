"""A controller process for tests/deploy/test_watchdog_stop_time.py (run as a script).

It runs a :class:`deploy.bridge.Bridge` whose controller commands every robot the full
acceleration limit along one heading, so a fleet reaches and holds the speed limit; the test
then kills or freezes this process. Prints one JSON line when its Zenoh link is up, then runs
until it is killed.
"""

from __future__ import annotations

import argparse
import json
import math
import sys

import numpy as np

from deploy.bridge import Bridge
from deploy.fleet_sim import robot_names
from deploy.network import TransportConfig
from deploy.wire import RobotRegistry
from sim.scenario import make_scenario


def main() -> int:
    parser = argparse.ArgumentParser()
    parser.add_argument("--connect", required=True)
    parser.add_argument("--fleet", required=True)
    parser.add_argument("--scenario", default="paper-5")
    parser.add_argument("--heading-deg", type=float, default=36.0)
    args = parser.parse_args()

    scenario = make_scenario(args.scenario)
    names = robot_names(scenario.num_robots)
    heading = math.radians(args.heading_deg)
    thrust = scenario.dynamics.accel_limit * np.array([math.cos(heading), math.sin(heading)])
    with Bridge(args.fleet, RobotRegistry(names), TransportConfig(connect=(args.connect,)),
                lambda state: np.tile(thrust, (state.num_robots, 1)),
                targets=dict(zip(names, scenario.targets, strict=True)),
                object_pose=np.zeros(3)) as bridge:
        print(json.dumps({"phase": "ready"}), flush=True)
        bridge.run()
    return 0


if __name__ == "__main__":
    sys.exit(main())
