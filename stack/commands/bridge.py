"""`formation bridge`: the controller process of a fleet over Zenoh.

    formation bridge --fleet lab --scenario paper-5 --policy policy.pt --connect tcp/127.0.0.1:7447
    formation bridge --fleet lab --policy scripted --listen tcp/127.0.0.1:7447

The controller is a ControlStack (policy -> safety filter -> MEC); ``--policy scripted`` uses
the scripted reference controller as the policy. Robots are ``r0..r{N-1}`` of the scenario;
any subset may be present, and the count changes as robots join or leave.

With --episode-ticks T (a fleet that resets every T ticks, e.g. `fleet-sim --episodes`), the
stack is reset at each fleet episode and the --report gains "episodes": per episode the ticks
answered, safety events, the MEC tracking error and the stack's tick time (EpisodeCounters).
A robot whose state is older than --stale-after stays in the controller's picture (with its
age) and is sent BRAKE; a robot that left the link stays in it as a silent obstacle; any one
live robot silent for --estop-after raises the fleet e-stop; after a stall of the bridge itself
(frozen, starved) the old states are discarded, the stack's estimators reset and latched robots
re-armed as their fresh states come in (deploy/bridge.py has the rules). The --report adds the
measured command round trips ("round_trip_ms") and the delay bound given to the stack
("command_delay_s"). A robot the safety filter holds in place for a second, away from every
target, is logged with the robots not listening beside it (stack/hold_watch.py); the report
keeps every such hold ("holds"). What a tracker reports on formation/<fleet>/tracker/sightings
(deploy/tracker.py; fleet-sim --intruder simulates one) is kept clear of by the safety filter
until the tracker says it is gone; the report counts it ("sightings").
SIGINT/SIGTERM stop the loop and close the Zenoh session.
"""

from __future__ import annotations

import argparse
import json
import signal
import sys

import numpy as np
import torch
import zenoh

from controllers.scripted import ScriptedController
from deploy.bridge import Bridge, BridgeConfig
from deploy.bridge_timing import MIN_ROUND_TRIPS
from deploy.fleet_sim import robot_names, write_json
from deploy.startup import freeze_start_up_heap
from deploy.wire import RobotRegistry
from sim.fleet import FleetState
from sim.scenario import Scenario, make_scenario
from stack.commands import argtypes
from stack.commands.latency_args import add_command_delay_arg, latency_config
from stack.hold_watch import HoldWatch, WatchedStack


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
        self.scenario = scenario

    def reset(self) -> None:
        """A new episode (the ControlStack's reset calls it): plan afresh from the next state."""
        self.inner.reset()
        self.positions = self.scenario.starts.copy()
        self.velocities = np.zeros_like(self.positions)

    def __call__(self, state: FleetState) -> np.ndarray:
        rows = [self.names.index(r) for r in state.robot_ids]
        if state.silent is not None:   # robots off the link: where they were last seen
            self.positions[[self.names.index(r) for r in state.silent.ids]] = state.silent.positions
        self.positions[rows] = state.positions
        self.velocities[rows] = state.velocities
        self.velocities[[i for i in range(len(self.names)) if i not in rows]] = 0.0
        full = FleetState(state.time, state.step, self.positions, self.velocities,
                          self.targets, state.object_pose, self.names)
        present = np.zeros(len(self.names), bool)
        present[rows] = True
        return self.inner(full, present)[rows]


def register(sub) -> None:
    p = sub.add_parser("bridge", description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    d = BridgeConfig()
    p.add_argument("--fleet", required=True, help="fleet name (Zenoh key chunk)")
    p.add_argument("--scenario", default="paper-5", help="preset, transport-N or a .json/.toml scenario file (default paper-5)")
    p.add_argument("--policy", required=True,
                   help="exported policy (.pt, .pt2, .onnx, .npz), training checkpoint, or 'scripted'")
    argtypes.add_transport_flags(p, "controller")
    argtypes.add_stage_flags(p, True)
    add_command_delay_arg(p)
    p.add_argument("--ttl-ms", type=argtypes.int_range(1, 65535), default=d.ttl_ms, metavar="MS",
                   help="command validity [ms], 1..65535: a robot drops a command older than this "
                        "(default %(default)s)")
    p.add_argument("--stale-after", type=argtypes.positive_seconds, default=d.stale_after_s, metavar="S",
                   help="state age [s] past which a robot is sent BRAKE whatever the controller "
                        "says (it stays in the controller's picture with its age); at most "
                        "--estop-after (default %(default)s)")
    p.add_argument("--estop-after", type=argtypes.positive_seconds, default=d.estop_after_s, metavar="S",
                   help="silence [s] of any one live robot that raises the fleet e-stop; also "
                        "the gap that counts as a stall of the bridge itself (after a stall the "
                        "old states are discarded and latched robots re-armed) (default %(default)s)")
    p.add_argument("--gather", type=argtypes.seconds, default=d.gather_s, metavar="S",
                   help="seconds a tick waits for the rest of a burst of states, in real time "
                        "(default %(default)s; --lockstep waits up to 0.2 s of wall time for the whole "
                        "burst instead)")
    p.add_argument("--delay-percentile", type=argtypes.percentile, default=d.delay_percentile, metavar="P",
                   help="the command delay passed to the controller is this percentile, in [50, 100], of "
                        "the recent command round trips (default %(default)s)")
    p.add_argument("--delay-window", type=argtypes.int_range(MIN_ROUND_TRIPS), default=d.delay_window, metavar="K",
                   help=f"how many recent command round trips the percentile is taken over, >= {MIN_ROUND_TRIPS} "
                        "(default %(default)s)")
    p.add_argument("--rearm-alarm-after", type=argtypes.positive, default=d.rearm_alarm_after, metavar="K",
                   help="re-arms in a row a robot leaves unanswered (still in FAULT) before an ERROR names "
                        "it and it is treated as a silent obstacle (default %(default)s)")
    p.add_argument("--ticks", type=argtypes.count, default=None, metavar="K",
                   help="stop after this many ticks in all (default: run until Ctrl-C / SIGTERM)")
    p.add_argument("--episode-ticks", type=argtypes.positive, default=None, metavar="T",
                   help="the fleet resets every T ticks: reset the stack, report per episode "
                        "(default: none, one run without episodes)")
    p.add_argument("--lossless", action="store_true",
                   help="the fleet waits for every command: send them with Zenoh congestion "
                        "control BLOCK, never dropped (default DROP: right for real robots, "
                        "where the next tick replaces a lost command)")
    argtypes.add_shared_clock_flag(p, "robots")
    p.add_argument("--lockstep", action="store_true",
                   help="the fleet is lock-stepped (fleet-sim --lockstep): run on sim time, one "
                        "scenario dt per answered burst, so ages, silences and delays count "
                        "fleet ticks and a run repeats however busy the machine; implies --lossless")
    p.add_argument("--report", type=argtypes.out_file, default=None, metavar="FILE",
                   help="write a JSON summary to FILE on exit")
    p.add_argument("--print-ticks", action="store_true",
                   help='print one JSON line per tick on stdout: {"tick": k, "robots": [...], '
                        '"stale": [...], "silent": [...]}')
    argtypes.add_deprecated_alias(p, "--trace", "--print-ticks", action="store_true")
    p.add_argument("--record", type=argtypes.out_folder, default=None, metavar="DIR",
                   help="record every tick into DIR/record_KKKKK.npz (stack.recorder: positions as "
                        "reported, each layer's command, the stack's flags), a file per fleet episode, "
                        "per stall of the bridge and per --record-ticks ticks, written off the control "
                        "loop; draw one with formation plot DIR/record_00000.npz")
    p.add_argument("--record-ticks", type=argtypes.positive, default=1200, metavar="K",
                   help="ticks per --record file at most (default %(default)s: a minute at 20 Hz)")
    p.set_defaults(func=run)


def build_stack(scenario: Scenario, policy: str, safety: bool, mec: bool, latency=None, docking: bool = True):
    """ControlStack(policy -> docking -> safety -> MEC); ``policy`` a file or 'scripted';
    ``latency`` a :class:`controllers.safety.latency.LatencyConfig` (default: 150 ms)."""
    from controllers.docking import DockingConfig
    from controllers.safety.latency import LatencyConfig
    from stack.pipeline import ControlStack, StackConfig

    source = ScriptedFleetController(scenario) if policy == "scripted" else policy
    return ControlStack(scenario, source, StackConfig(safety=safety, mec=mec, latency=latency or LatencyConfig(),
                                                      docking=DockingConfig(enabled=docking)))


def build_controller(scenario: Scenario, policy: str, safety: bool, mec: bool):
    """ControlStack(policy -> safety -> MEC) as a callable FleetState -> (N, 2)."""
    stack = build_stack(scenario, policy, safety, mec)
    return lambda state: stack.tick(state).a_cmd


class EpisodeCounters:
    """A ControlStack as the bridge's controller, with counters per fleet episode.

    ``start_episode(k)`` (the bridge's ``on_episode``) closes the running episode and resets the
    stack. Per tick it counts the safety events of :class:`stack.tick_types.TickResult`, keeps the
    stack's tick time and the one-tick tracking error ``mean_i |p_i(k+1) - p^_i(k+1)|`` [m],
    where ``p^(k+1)`` is :func:`stack.pipeline.nominal_step` from the measured state of tick k
    driven by ``a_safe`` (what the MEC makes the robots follow); it is measured only between two
    ticks of the same episode with the same robots.
    """

    COUNTERS = ("interventions", "infeasible", "fallbacks", "braking")

    def __init__(self, stack):
        self.stack = stack
        self.episodes: list[dict] = []
        self._current: dict | None = None
        self._predicted: tuple[tuple[str, ...], np.ndarray] | None = None

    def start_episode(self, k: int) -> None:
        self._close()
        self.stack.reset()
        self._predicted = None
        self._current = {"episode": int(k), "ticks": 0, **dict.fromkeys(self.COUNTERS, 0),
                         "tracking": [], "tick_ns": []}

    def on_stall(self) -> None:
        """The bridge stalled (:mod:`deploy.bridge`): the stack's estimates and the one-tick
        prediction saw none of what happened meanwhile."""
        self.stack.reset()
        self._predicted = None

    def __call__(self, state: FleetState) -> np.ndarray:
        from stack.pipeline import nominal_step

        if self._current is None:
            self.start_episode(0)
        ep = self._current
        if self._predicted is not None and self._predicted[0] == state.robot_ids:
            err = np.linalg.norm(state.positions - self._predicted[1], axis=1).mean()
            ep["tracking"].append(float(err))
        tick = self.stack.tick(state)
        predicted, _ = nominal_step(state.positions, state.velocities, tick.a_safe,
                                    self.stack.dynamics)
        self._predicted = (state.robot_ids, predicted)
        ep["ticks"] += 1
        for key, event in zip(self.COUNTERS, ("intervened", "infeasible", "fallback", "braking"),
                              strict=True):
            ep[key] += bool(getattr(tick, event))
        ep["tick_ns"].append(tick.timings_ns["total"])
        return tick.a_cmd

    def _close(self) -> None:
        ep, self._current = self._current, None
        if ep is None:
            return
        ms = np.asarray(ep.pop("tick_ns"), dtype=np.float64) / 1e6
        tracking = ep.pop("tracking")
        ep["tracking_error"] = float(np.mean(tracking)) if tracking else None
        ep["tick_ms"] = ({"p50": float(np.percentile(ms, 50)), "p99": float(np.percentile(ms, 99)),
                          "max": float(ms.max())} if len(ms) else None)
        self.episodes.append(ep)

    def summary(self) -> list[dict]:
        """Every episode's record (the running one closed first)."""
        self._close()
        return self.episodes


def _recorded(stack, args):
    """``stack`` recording into ``--record`` (the folder made, or a clear error)."""
    from stack.recorder import RecordedStack, record_folder

    return RecordedStack(stack, record_folder(args.record, "--record"), args.record_ticks,
                         meta={"fleet": args.fleet, "policy": args.policy, "world": "bridge"})


def _after_tick(record, watched: WatchedStack, print_ticks: bool) -> None:
    """Once a tick's commands are out: the hold watch, and the --print-ticks line."""
    watched.observe_last()
    if print_ticks:
        _print_tick(record)


def _print_tick(record) -> None:
    print(json.dumps({"tick": record.tick, "robots": list(record.robots),
                      "stale": list(record.stale), "silent": list(record.silent)}), flush=True)


def run(args) -> int:
    torch.set_num_threads(1)
    if args.stale_after > args.estop_after:
        print(f"error: --stale-after {args.stale_after:g} is longer than --estop-after {args.estop_after:g}: "
              "a robot is braked as stale before its silence raises the fleet e-stop; give "
              "--stale-after <= --estop-after [s]", file=sys.stderr)
        return 2
    try:
        scenario = make_scenario(args.scenario)
        stack = build_stack(scenario, args.policy, args.safety, args.mec,
                            latency_config(args), args.docking)
        if args.record is not None:
            stack = _recorded(stack, args)
        watch = HoldWatch(scenario.dynamics.dt, scenario.target_tolerance, scenario.dynamics.accel_limit)
        stack = watched = WatchedStack(stack, watch, deferred=True)
        recorder = EpisodeCounters(stack) if args.episode_ticks is not None else None
        controller = recorder or (lambda state: stack.tick(state).a_cmd)
        names = robot_names(scenario.num_robots)
        transport = argtypes.transport_config(args)
        config = BridgeConfig(ttl_ms=args.ttl_ms, stale_after_s=args.stale_after,
                              estop_after_s=args.estop_after, gather_s=args.gather,
                              episode_ticks=args.episode_ticks, lossless=args.lossless,
                              lockstep=args.lockstep, period_s=scenario.dynamics.dt,
                              delay_percentile=args.delay_percentile,
                              delay_window=args.delay_window, shared_clock=args.shared_clock,
                              rearm_alarm_after=args.rearm_alarm_after)
        c = scenario.object_center
        frozen = freeze_start_up_heap()
        bridge = Bridge(args.fleet, RobotRegistry(names), transport, controller,
                        targets=dict(zip(names, scenario.targets, strict=True)),
                        object_pose=np.array([c[0], c[1], 0.0]), config=config,
                        on_episode=recorder.start_episode if recorder else None,
                        on_stall=recorder.on_stall if recorder else stack.reset,
                        on_sent=stack.sent_braking)
    except (ValueError, OSError, zenoh.ZError) as err:
        print(f"error: {err}", file=sys.stderr)
        return 2
    bridge.stats.heap_frozen = frozen
    for sig in (signal.SIGINT, signal.SIGTERM):
        signal.signal(sig, lambda *_: bridge.stop())
    print(f"bridge {args.fleet}: {scenario.name}, policy {args.policy}", file=sys.stderr, flush=True)
    try:
        with bridge:
            bridge.run(max_ticks=args.ticks, on_tick=lambda record: _after_tick(record, watched, args.print_ticks))
            summary = bridge.summary()
    finally:
        if args.record is not None:
            records = stack.close()
            print(f"bridge {args.fleet}: {len(records)} record(s) in {args.record}", file=sys.stderr, flush=True)
    summary["holds"] = watch.summary()
    if recorder is not None:
        summary["episodes"] = recorder.summary()
    if args.report:
        write_json(args.report, summary)
    print(json.dumps(summary), flush=True)
    return 0
