"""`formation bridge`: the controller process of a fleet over Zenoh.

    formation bridge --fleet lab --scenario paper-5 --policy policy.pt --connect tcp/127.0.0.1:7447
    formation bridge --fleet lab --policy scripted --no-safety --no-mec --listen tcp/127.0.0.1:7447

The controller is a ControlStack (policy -> safety filter -> MEC); ``--policy scripted`` uses
the scripted reference controller as the policy. Robots are ``r0..r{N-1}`` of the scenario;
any subset may be present, and the count changes as robots join or leave.
SIGINT/SIGTERM stop the loop and close the Zenoh session.
"""

from __future__ import annotations

import argparse
import json
import signal
import sys
from pathlib import Path

import numpy as np
import torch

from controllers.scripted import ScriptedController
from deploy.bridge import Bridge, BridgeConfig
from deploy.fleet_sim import robot_names, write_json
from deploy.transport import TransportConfig
from deploy.wire import RobotRegistry
from sim.fleet import FleetState
from sim.scenario import Scenario, make_scenario


class ScriptedFleetController:
    """The scripted controller for whichever robots are present: it plans once for the whole
    scenario (robots not seen yet at their start slots, robots gone at their last position)
    and answers rows for the present robots only, so a join or leave never re-plans others."""

    def __init__(self, scenario: Scenario):
        self.names = robot_names(scenario.num_robots)
        self.inner = ScriptedController(scenario)
        self.positions = scenario.starts.copy()
        self.velocities = np.zeros_like(self.positions)
        self.targets = scenario.targets

    def __call__(self, state: FleetState) -> np.ndarray:
        rows = [self.names.index(r) for r in state.robot_ids]
        self.positions[rows] = state.positions
        self.velocities[rows] = state.velocities
        self.velocities[[i for i in range(len(self.names)) if i not in rows]] = 0.0
        full = FleetState(state.time, state.step, self.positions, self.velocities,
                          self.targets, state.object_pose, self.names)
        return self.inner(full)[rows]


def register(sub) -> None:
    p = sub.add_parser("bridge", help="run the controller of a fleet over Zenoh",
                       description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--fleet", required=True)
    p.add_argument("--scenario", default="paper-5")
    p.add_argument("--policy", required=True,
                   help="TorchScript file, training checkpoint, or 'scripted'")
    p.add_argument("--listen", action="append", default=[])
    p.add_argument("--connect", action="append", default=[])
    p.add_argument("--no-safety", action="store_true", help="skip the safety filter")
    p.add_argument("--no-mec", action="store_true", help="skip the model error compensator")
    p.add_argument("--ttl-ms", type=int, default=150)
    p.add_argument("--stale-after", type=float, default=0.3, help="state age to leave a robot out [s]")
    p.add_argument("--estop-after", type=float, default=1.0, help="state age to e-stop the fleet [s]")
    p.add_argument("--ticks", type=int, default=None, help="stop after this many ticks")
    p.add_argument("--report", type=Path, default=None, help="write a JSON summary on exit")
    p.add_argument("--trace", action="store_true",
                   help='print one JSON line per tick on stdout: {"tick": k, "robots": [...]}')
    p.set_defaults(func=run)


def build_controller(scenario: Scenario, policy: str, safety: bool, mec: bool):
    """ControlStack(policy -> safety -> MEC) as a callable FleetState -> (N, 2)."""
    from stack.pipeline import ControlStack, StackConfig

    source = ScriptedFleetController(scenario) if policy == "scripted" else policy
    stack = ControlStack(scenario, source, StackConfig(safety=safety, mec=mec))
    return lambda state: stack.tick(state).a_cmd


def _print_tick(record) -> None:
    print(json.dumps({"tick": record.tick, "robots": list(record.robots)}), flush=True)


def run(args) -> int:
    torch.set_num_threads(1)
    try:
        scenario = make_scenario(args.scenario)
        controller = build_controller(scenario, args.policy, not args.no_safety, not args.no_mec)
        names = robot_names(scenario.num_robots)
        transport = TransportConfig(listen=tuple(args.listen), connect=tuple(args.connect))
        config = BridgeConfig(ttl_ms=args.ttl_ms, stale_after_s=args.stale_after,
                              estop_after_s=args.estop_after)
        c = scenario.object_center
        bridge = Bridge(args.fleet, RobotRegistry(names), transport, controller,
                        targets=dict(zip(names, scenario.targets, strict=True)),
                        object_pose=np.array([c[0], c[1], 0.0]), config=config)
    except (ValueError, OSError) as err:
        print(f"error: {err}", file=sys.stderr)
        return 2
    for sig in (signal.SIGINT, signal.SIGTERM):
        signal.signal(sig, lambda *_: bridge.stop())
    print(f"bridge {args.fleet}: {scenario.name}, policy {args.policy}", file=sys.stderr, flush=True)
    with bridge:
        bridge.run(max_ticks=args.ticks, on_tick=_print_tick if args.trace else None)
        summary = bridge.summary()
    if args.report:
        write_json(args.report, summary)
    print(json.dumps(summary), flush=True)
    return 0
