"""`formation fleet-sim`: the pymunk world as a fleet of robots over Zenoh.

    formation fleet-sim --fleet lab --scenario paper-5 --rate-hz 20 --listen tcp/127.0.0.1:7447
    formation fleet-sim --fleet lab --scenario paper-5 --lockstep --connect tcp/127.0.0.1:7447
    formation fleet-sim --fleet lab --lockstep --episodes 5 --listen tcp/127.0.0.1:7447

With --episodes K the world is reset (seed + k) every episode of the scenario and the process
ends after K episodes; each finished episode prints one JSON line on stdout
({"episode": k, "success": ..., "final_distance": ..., "collisions": ...}) and the --report
holds every episode's record (positions, contacts, round trips).

With --intruder the fleet's simulated tracker reports discs crossing the arena (on the fleet's
sightings key, which `formation bridge` listens to); each episode's line says how close the
robots came ("intruders": min_gap_mm, drive_in_ticks).

With --lockstep the robots' states are sent lossless (Zenoh congestion control BLOCK) and the
world waits for every answer: start the bridge with --lockstep too, or a command lost on a busy
machine stalls the tick for --lockstep-timeout.

See deploy/fleet_sim.py for the watchdog (brake, latch, re-arm) and lock-step rules.
"""

from __future__ import annotations

import argparse
import json
import signal
import sys

import zenoh

from deploy.fleet_sim import FleetSim, FleetSimConfig, WatchdogConfig, robot_names, write_json
from deploy.startup import freeze_start_up_heap
from sim.intruders import RobotSightings
from sim.scenario import make_scenario
from stack.commands import argtypes
from stack.commands.latency_args import MODEL_ERROR_HELP, parse_model_error


def _event(kind: str):
    def parse(text: str) -> tuple[int, str, str]:
        robot, _, tick = text.partition("@")
        if not robot or not tick.isdigit():
            raise argparse.ArgumentTypeError(f"expected ROBOT@TICK (e.g. r4@30), got {text!r}")
        return int(tick), robot, kind
    return parse


def register(sub) -> None:
    p = sub.add_parser("fleet-sim", description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--fleet", required=True, help="fleet name (Zenoh key chunk)")
    p.add_argument("--scenario", default="paper-5", help="preset, transport-N or a .json/.toml scenario file (default paper-5)")
    pace = p.add_mutually_exclusive_group()
    pace.add_argument("--rate-hz", type=argtypes.hertz, default=20.0, metavar="HZ",
                      help="real-time tick rate [Hz] (default %(default)s)")
    pace.add_argument("--lockstep", action="store_true",
                      help="advance when every command for the current states arrived "
                           "(pair with bridge --lockstep)")
    argtypes.add_transport_flags(p, "fleet-sim")
    p.add_argument("--model-error", default=None, metavar="K=V,...",
                   help=MODEL_ERROR_HELP + "; its playout_ticks is the playout of the link simulated inside "
                        "the world (with delay_ticks), not of the Zenoh link: that is --playout-ticks "
                        "(default none: the nominal model)")
    p.add_argument("--seed", type=argtypes.seed, default=0,
                   help="seed of the first episode; episode k plays seed + k (default 0)")
    p.add_argument("--ticks", type=argtypes.count, default=None, metavar="K",
                   help="stop after this many ticks in all (default: no limit)")
    p.add_argument("--episodes", type=argtypes.positive, default=None, metavar="K",
                   help="run this many episodes (world reset each), then stop (default: one run "
                        "without resets, until --ticks or Ctrl-C)")
    p.add_argument("--lockstep-timeout", type=argtypes.positive_seconds, default=0.5, metavar="S",
                   help="seconds a lock-stepped tick waits for the answers (default %(default)s: above "
                        "the bridge's 0.2 s gather)")
    p.add_argument("--start-timeout", type=argtypes.positive_seconds, default=30.0, metavar="S",
                   help="seconds to wait for the controller before the first tick (default %(default)s)")
    p.add_argument("--brake-after-ticks", type=argtypes.positive, default=1, metavar="K",
                   help="watchdog: brake on the K-th tick in a row whose state went unanswered "
                        "(default 1: on the first)")
    p.add_argument("--stop-after", type=argtypes.positive_seconds, default=0.5, metavar="S",
                   help="watchdog latch: seconds without a command before the robot holds at "
                        "rest until re-armed (default 0.5)")
    p.add_argument("--playout-ticks", type=argtypes.count, default=0, metavar="D",
                   help="the Zenoh link's playout: robots act on each command D ticks after the state "
                        "it answers (a playout buffer: a delay that jitters up to D ticks acts as a "
                        "steady D; the bridge's --ttl-ms must cover it; the simulated link inside the "
                        "world has its own, --model-error playout_ticks=) (default 0: on arrival)")
    p.add_argument("--drop-commands", type=argtypes.probability, default=0.0, metavar="P",
                   help="probability in [0, 1) of discarding an arriving command (tests; default 0)")
    p.add_argument("--leave", type=_event("leave"), action="append", default=[],
                   metavar="ROBOT@TICK", help="close a robot's link at a tick (repeatable)")
    p.add_argument("--join", type=_event("join"), action="append", default=[],
                   metavar="ROBOT@TICK", help="open a robot's link at a tick (repeatable)")
    argtypes.add_intruder_flag(p, "; the fleet's simulated tracker publishes it on the sightings key")
    p.add_argument("--track-robots", action="store_true",
                   help="the simulated tracker also identifies every robot, online or not, each tick, within "
                        "5 mm and 2 cm/s (motion capture; sim.intruders.RobotSightings): the controller bounds a "
                        "silent robot it sees at rest by that sighting")
    argtypes.add_shared_clock_flag(p, "controller")
    p.add_argument("--report", type=argtypes.out_file, default=None, metavar="FILE",
                   help="write a JSON summary to FILE on exit")
    p.set_defaults(func=run)


def _print_episode(record: dict) -> None:
    keys = ("episode", "ticks", "success", "final_distance", "collisions", "lockstep_timeouts", "intruders")
    print(json.dumps({k: record[k] for k in keys if k in record}), flush=True)


def _unknown_event_robot(events: list[tuple[int, str, str]], names: tuple[str, ...], scenario: str) -> str | None:
    """The error of a --leave/--join naming a robot the scenario lacks, or None."""
    for tick, robot, kind in events:
        if robot not in names:
            return (f"--{kind} {robot}@{tick}: {scenario} has robots {', '.join(names)}; name one of them")
    return None


def run(args) -> int:
    try:
        model_error = parse_model_error(args.model_error)
        scenario = make_scenario(args.scenario)
        problem = _unknown_event_robot(args.leave + args.join, robot_names(scenario.num_robots), scenario.name)
        if problem:
            raise ValueError(problem)
        config = FleetSimConfig(
            fleet=args.fleet, scenario=scenario,
            transport=argtypes.transport_config(args),
            model_error=model_error, seed=args.seed,
            rate_hz=None if args.lockstep else args.rate_hz,
            lockstep_timeout_s=args.lockstep_timeout, max_ticks=args.ticks,
            drop_commands=args.drop_commands, episodes=args.episodes,
            start_timeout_s=args.start_timeout,
            watchdog=WatchdogConfig(args.brake_after_ticks, args.stop_after),
            events=tuple(args.leave + args.join), shared_clock=args.shared_clock,
            playout_ticks=args.playout_ticks, intruders=tuple(args.intruder),
            track_robots=RobotSightings(seed=args.seed) if args.track_robots else None)
    except (ValueError, TypeError, OSError) as err:
        print(f"error: {err}", file=sys.stderr)
        return 2
    frozen = freeze_start_up_heap()
    sim = FleetSim(config, on_episode=_print_episode)
    for sig in (signal.SIGINT, signal.SIGTERM):
        signal.signal(sig, lambda *_: sim.stop())
    print(f"fleet-sim {args.fleet}: {config.scenario.name}, "
          f"{'lock-step' if args.lockstep else f'{args.rate_hz} Hz'}", file=sys.stderr, flush=True)
    try:
        summary = sim.run()
    except zenoh.ZError as err:            # e.g. a certificate the router refuses
        print(f"error: Zenoh: {err}", file=sys.stderr)
        return 2
    summary["heap_frozen"] = frozen
    if args.report:
        write_json(args.report, summary)
    print(json.dumps({k: v for k, v in summary.items() if k not in ("trace", "episodes")}), flush=True)
    return 0
