"""`formation eval`: judge a policy on a scenario, in the batched world or through the ControlStack in pymunk.

* ``--world batched``: :func:`controllers.mappo.evaluate` (deterministic mean actions, no safety
  filter, no MEC, no model error); the scripted controller runs there through a stack with both
  stages off.
* ``--world pymunk``: :func:`stack.pipeline.run_episode` with a :class:`stack.pipeline.ControlStack`
  (safety filter and MEC on by default) in :class:`sim.pymunk_world.PymunkWorld` with
  ``--model-error``. These worlds (and the scripted controller in the batched one) also report
  ``arrival_rate``, the fraction of episodes in which every robot stood within tolerance of its
  target at some tick, and ``arrival_tick``, the mean first such tick over those episodes
  (:attr:`stack.pipeline.EpisodeMetrics.arrival_step`; None when none arrived): how much a
  layer slows a team down, which the final success does not show. With ``--intruder`` the world
  carries discs that cross it, seen exactly by a tracker (:class:`sim.intruders.IntruderFleet`),
  and the result adds how close any robot came to one (``intruder_min_gap_mm``) and the fraction
  of episodes in which one drove into one (``intruder_drive_in_rate``).
* ``--world zenoh``: the same stack and episodes driving a fleet over Zenoh
  (:class:`deploy.zenoh_fleet.ZenohFleet`: a real one, or ``formation fleet-sim --episodes``),
  judged on the states it reports; the episodes and seeds are the fleet's own. A fleet publishes
  the states of ticks 0 .. T-1 of an episode (the state after its last command is the next
  episode's reset), so an episode is judged on tick T-1 (fleet-sim's own report judges tick T),
  and its last command is a brake::

      formation fleet-sim --fleet lab --lockstep --episodes 3 --listen tcp/127.0.0.1:7447
      formation eval --policy scripted --world zenoh --fleet lab --lockstep --episodes 3 \
          --scenario paper-5 --connect tcp/127.0.0.1:7447
"""

from __future__ import annotations

import dataclasses
import sys
from pathlib import Path

import numpy as np
import torch
from tqdm import tqdm

from sim.intruders import IntruderFleet, RobotSightings
from sim.provenance import provenance
from sim.pymunk_world import ModelError, PymunkWorld
from sim.scenario import ScenarioError, make_scenario
from stack.commands import argtypes
from stack.commands.latency_args import (
    MODEL_ERROR_HELP,
    LinkArgumentError,
    add_command_delay_arg,
    latency_config,
    parse_model_error,
)


class EvalArgumentError(ValueError):
    """A bad command-line value; the message names the flag and the fix."""


def register(sub) -> None:
    p = sub.add_parser("eval", description=__doc__)
    p.add_argument("policy_path", nargs="?", metavar="POLICY_FILE",
                   help="a training checkpoint or an exported policy (.pt, .pt2, .onnx, .npz)")
    p.add_argument("--policy", default=None, metavar="FILE|scripted",
                   help="the policy file as with bridge --policy (the same as POLICY_FILE), or "
                        "'scripted' for the built-in controller")
    p.add_argument("--scenario", default="paper-3", help="preset, transport-N or a .json/.toml scenario file (default paper-3)")
    p.add_argument("--world", choices=["batched", "pymunk", "zenoh"], default="batched",
                   help="batched: training world, no safety/MEC; pymunk: ControlStack with model error; "
                        "zenoh: ControlStack driving a fleet over Zenoh (--fleet and its endpoints)")
    p.add_argument("--episodes", type=int, default=100, help="episodes (default 100)")
    p.add_argument("--seed", type=argtypes.seed, default=0, help="seed of the first episode (default 0)")
    p.add_argument("--steps", type=int, default=None, help="ticks per episode (default: the scenario's)")
    argtypes.add_stage_flags(p, None, " in the pymunk world")
    p.add_argument("--model-error", default=None, metavar="K=V,...",
                   help=MODEL_ERROR_HELP + "; freeze=2:40: robot 2 goes silent at tick 40")
    add_command_delay_arg(p)
    argtypes.add_intruder_flag(p, "; --world pymunk (a fleet over Zenoh has its own: fleet-sim --intruder)")
    p.add_argument("--track-robots", action="store_true",
                   help="--world pymunk: a tracker over the arena also sees every robot, one tick late, "
                        "within 5 mm and 2 cm/s (motion capture; sim.intruders.RobotSightings): a silent "
                        "robot it sees at rest is bounded by that sighting")
    p.add_argument("--json", type=argtypes.out_file, default=None, metavar="OUT", help="write the result as JSON")
    p.add_argument("--trace", type=Path, default=None, metavar="DIR",
                   help="--world pymunk or zenoh: record every episode into DIR as episode_SEED.npz "
                        "(positions, the commands of each layer, the stack's flags, contacts: "
                        "stack.recorder) and draw it as episode_SEED.png (paths, which layer drove "
                        "each robot, distances to the targets: stack.episode_plot)")
    zenoh = p.add_argument_group("--world zenoh")
    zenoh.add_argument("--fleet", default=None, help="the fleet's name (Zenoh key chunk)")
    zenoh.add_argument("--lockstep", action="store_true",
                       help="the fleet is lock-stepped (fleet-sim --lockstep): sim time, lossless")
    argtypes.add_transport_flags(zenoh, "controller")
    p.set_defaults(func=run)


def run(args) -> int:
    from stack.pipeline import StackError
    from stack.plots import PlotError

    try:
        result = evaluate_from_args(args)
    except (EvalArgumentError, LinkArgumentError, ScenarioError, StackError, PlotError) as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 2
    print_result(result)
    if args.json is not None:
        from controllers.mappo.evaluate import write_json_atomic

        write_json_atomic(args.json, result)
        print(f"wrote {args.json}")
    return 0


def evaluate_from_args(args) -> dict:
    """The result document of ``formation eval`` for parsed ``args`` (raises on bad input)."""
    if (args.policy_path is None) == (args.policy is None):
        raise EvalArgumentError("give either a policy file (POLICY_FILE or --policy FILE) or --policy "
                                "scripted, not both and not neither")
    if args.policy not in (None, "scripted"):
        args = _with(args, policy_path=args.policy, policy=None)
    if args.episodes < 1:
        raise EvalArgumentError(f"--episodes must be a positive integer, got {args.episodes}")
    if args.steps is not None and args.steps < 1:
        raise EvalArgumentError(f"--steps must be a positive integer, got {args.steps}")
    scenario = make_scenario(args.scenario)
    if args.policy_path is not None and not Path(args.policy_path).is_file():
        raise EvalArgumentError(f"policy file {args.policy_path!r} does not exist; give a checkpoint "
                                "or exported policy file, or --policy scripted")
    notes = []
    if args.world == "batched":
        if args.intruder or args.track_robots:
            raise EvalArgumentError("--intruder and --track-robots need --world pymunk: the batched world has "
                                    "no tracker")
        ignored = [flag for flag, value in (("--safety", args.safety), ("--mec", args.mec),
                                            ("--docking", args.docking), ("--model-error", args.model_error))
                   if value is not None]
        if ignored:
            note = (f"{', '.join(ignored)} ignored: the batched world runs the policy alone with "
                    "the nominal model; use --world pymunk for the safety filter, MEC and model error")
            print(f"note: {note}", file=sys.stderr)
            notes.append(note)
        if args.trace is not None:
            raise EvalArgumentError("--trace records the ControlStack's episodes: use --world pymunk or "
                                    "--world zenoh (the batched world runs the policy alone)")
        metrics = _batched(args, scenario)
    else:
        _check_trace_dir(args.trace)
        metrics = _stack_episodes(args, scenario, parse_model_error(args.model_error))
    stack_config = metrics["config"]["stack"]
    return {"scenario": scenario.name, "num_robots": scenario.num_robots, "world": args.world,
            "policy": args.policy or str(args.policy_path), "episodes": args.episodes,
            "seed": args.seed, **metrics, "steps": metrics["config"]["steps"],
            "docking": bool(stack_config and stack_config["docking"]["enabled"]), "notes": notes,
            "provenance": provenance()}


def _batched(args, scenario) -> dict:
    from stack.pipeline import ControlStack, StackConfig, load_policy

    if args.policy == "scripted":
        from controllers.scripted import ScriptedController
        from sim.fleet import BatchedFleet

        stack = ControlStack(scenario, ScriptedController(scenario), StackConfig(safety=False, mec=False))
        return _episodes(args, BatchedFleet(scenario), stack, safety=False, mec=False)[0] | {
            "config": _resolved_config(args, scenario, stack)}
    from controllers.mappo.evaluate import evaluate

    if args.steps is not None:
        raise EvalArgumentError("--steps applies to --world pymunk (the batched world runs full episodes)")
    actor = load_policy(args.policy_path, scenario.num_robots)
    with torch.inference_mode():
        result = evaluate(actor, scenario, episodes=args.episodes, seed=args.seed)
    d = result.to_dict()
    return {k: d[k] for k in ("success_rate", "final_distance", "collision_rate", "robot_collisions",
                              "object_collisions", "wall_collisions", "episode_return")} | {
        "safety": False, "mec": False, "model_error": None, "config": _resolved_config(args, scenario, None)}


def _stack_episodes(args, scenario, model_error: ModelError) -> dict:
    from controllers.docking import DockingConfig
    from stack.pipeline import ControlStack, StackConfig, load_policy

    safety = True if args.safety is None else args.safety
    mec = True if args.mec is None else args.mec
    if args.policy == "scripted":
        from controllers.scripted import ScriptedController

        policy = ScriptedController(scenario)
    else:
        policy = load_policy(args.policy_path, scenario.num_robots)
    try:
        latency = latency_config(args)
    except ValueError as exc:
        raise EvalArgumentError(str(exc)) from None
    docking = DockingConfig(enabled=True if args.docking is None else args.docking)
    stack = ControlStack(scenario, policy, StackConfig(safety=safety, mec=mec, latency=latency, docking=docking))
    if args.world == "zenoh":
        last = scenario.dynamics.episode_steps - 1      # the fleet's last published state (module docstring)
        if args.steps is not None and args.steps > last:
            raise EvalArgumentError(f"--steps for --world zenoh is at most {last}: the fleet publishes "
                                    f"{last + 1} states an episode")
        args = _with(args, steps=args.steps or last)
        with _zenoh_fleet(args, scenario) as fleet:
            out, traced = _episodes(args, fleet, stack, safety=safety, mec=mec)
        _draw_traces(traced, scenario)
        out["model_error"] = None         # the fleet's own
        out["command_delay_ms"], out["policy_runtime"] = args.command_delay_ms, stack.policy_runtime
        out["config"] = _resolved_config(args, scenario, stack)
        return out
    try:             # the world checks the model error against the team (a frozen robot it has)
        world = PymunkWorld(scenario, model_error, seed=args.seed)
    except ValueError as exc:
        raise EvalArgumentError(str(exc)) from None
    if args.intruder or args.track_robots:
        world = IntruderFleet(world, args.intruder, sighting_delay_ticks=int(args.track_robots),
                              robots=RobotSightings(seed=args.seed) if args.track_robots else None)
    out, traced = _episodes(args, world, stack, safety=safety, mec=mec)
    _draw_traces(traced, scenario)
    out["model_error"] = dataclasses.asdict(model_error)
    out["command_delay_ms"], out["policy_runtime"] = args.command_delay_ms, stack.policy_runtime
    out["config"] = _resolved_config(args, scenario, stack)
    return out


def _resolved_config(args, scenario, stack) -> dict:
    """The settings the episodes ran with, defaults filled in (the JSON result's and every
    --trace record's "config"): the scenario, the ticks an episode, the flags, and the
    StackConfig used (``stack`` None: the policy ran alone, the batched world)."""
    return {"scenario": scenario.to_dict(), "world": args.world, "policy": args.policy or str(args.policy_path),
            "episodes": args.episodes, "seed": args.seed,
            "steps": scenario.dynamics.episode_steps if args.steps is None else args.steps,
            "model_error": (dataclasses.asdict(parse_model_error(args.model_error)) if args.world == "pymunk"
                            else None),
            "command_delay_ms": args.command_delay_ms,
            "intruder": [dataclasses.asdict(i) for i in args.intruder], "track_robots": args.track_robots,
            "fleet": args.fleet, "lockstep": args.lockstep,
            "stack": None if stack is None else dataclasses.asdict(stack.config)}


def _check_trace_dir(folder: Path | None) -> None:
    from stack.recorder import record_folder

    if folder is not None:
        try:
            record_folder(folder, "--trace")
        except ValueError as exc:
            raise EvalArgumentError(str(exc)) from None


def _trace(args, stack, seed: int, recorder, metrics) -> Path:
    """Save episode ``seed``'s record under ``--trace`` (drawn later by :func:`_draw_traces`); the
    recorder adds the fleet's scenario."""
    record = recorder.finish({"seed": seed, "world": args.world,
                              "policy": args.policy or str(args.policy_path), "metrics": metrics.to_dict(),
                              "model_error": args.model_error, "command_delay_ms": args.command_delay_ms,
                              "safety": stack.safety is not None, "mec": stack.mec is not None,
                              "docking": stack.docking is not None,
                              "config": _resolved_config(args, stack.scenario, stack), "provenance": provenance()})
    return record.save(args.trace / f"episode_{seed}.npz")


def _draw_traces(paths: list[Path], scenario) -> None:
    """episode_SEED.png beside each saved record; after the episodes, since a fleet over Zenoh
    waits for its next command while a figure is drawn."""
    from stack.episode_plot import plot_episode
    from stack.recorder import load_record

    for path in tqdm(paths, desc="trace figures", unit="ep", file=sys.stderr, leave=False):
        plot_episode(load_record(path), scenario, path.with_suffix(".png"))


def _with(args, **changes):
    import argparse

    return argparse.Namespace(**{**vars(args), **changes})


def _zenoh_fleet(args, scenario):
    from deploy.bridge import BridgeConfig
    from deploy.zenoh_fleet import ZenohFleet

    if not args.fleet:
        raise EvalArgumentError("--world zenoh needs --fleet NAME and the fleet's endpoint (--connect)")
    if args.model_error is not None or args.intruder or args.track_robots:
        raise EvalArgumentError("--model-error, --intruder and --track-robots apply to --world pymunk: a fleet "
                                "over Zenoh has its own (formation fleet-sim --model-error, --intruder)")
    try:
        transport = argtypes.transport_config(args)
        config = BridgeConfig(lockstep=args.lockstep, period_s=scenario.dynamics.dt)
        return ZenohFleet(scenario, args.fleet, transport, config)
    except (ValueError, OSError) as exc:
        raise EvalArgumentError(str(exc)) from None


def _episodes(args, fleet, stack, *, safety: bool, mec: bool) -> tuple[dict, list[Path]]:
    """The metrics of ``args.episodes`` episodes, and the records saved under ``--trace``."""
    from stack.pipeline import run_episode
    from stack.recorder import EpisodeRecorder

    torch.set_num_threads(1)
    trace = getattr(args, "trace", None)
    rows, traced, near = [], [], []
    for k in tqdm(range(args.episodes), desc="eval", unit="ep", file=sys.stderr, leave=False):
        recorder = EpisodeRecorder() if trace is not None else None
        rows.append(run_episode(fleet, stack, args.seed + k, args.steps, recorder=recorder))
        if isinstance(fleet, IntruderFleet) and fleet.intruders:
            near.append(fleet.watch.summary())
        if recorder is not None:
            traced.append(_trace(args, stack, args.seed + k, recorder, rows[-1]))

    def mean(name: str) -> float:
        return float(np.mean([getattr(r, name) for r in rows]))

    arrivals = [r.arrival_step for r in rows if r.arrival_step is not None]
    return {"success_rate": mean("success"), "final_distance": mean("final_distance"),
            "arrival_rate": len(arrivals) / len(rows),
            "arrival_tick": float(np.mean(arrivals)) if arrivals else None,
            "collision_rate": mean("collided"), "robot_collisions": mean("robot_collisions"),
            "object_collisions": mean("object_collisions"), "wall_collisions": mean("wall_collisions"),
            "interventions_per_episode": mean("interventions"), "infeasible_per_episode": mean("infeasible"),
            "fallbacks_per_episode": mean("fallbacks"), "braking_per_episode": mean("braking"),
            "tracking_error_m": mean("tracking_error"),
            "tick_p50_ms": float(np.median([r.p50_tick_ms for r in rows])),
            "tick_p99_ms": float(np.max([r.p99_tick_ms for r in rows])),
            "safety": safety, "mec": mec, **_intruder_metrics(near)}, traced


def _intruder_metrics(episodes: list[dict]) -> dict:
    """With intruders: the closest any robot came to one over the episodes [mm] (None: none was
    in the arena), and the fraction of episodes in which a robot drove into one
    (:class:`sim.intruders.IntruderWatch`)."""
    if not episodes:
        return {}
    gaps = [e["min_gap_mm"] for e in episodes if e["min_gap_mm"] is not None]
    return {"intruder_min_gap_mm": min(gaps) if gaps else None,
            "intruder_drive_in_rate": float(np.mean([e["drive_in_ticks"] > 0 for e in episodes]))}


def print_result(result: dict) -> None:
    print(f"formation eval: {result['policy']} on {result['scenario']} (N={result['num_robots']}), "
          f"{result['world']} world, {result['episodes']} episodes from seed {result['seed']}")
    skip = {"scenario", "num_robots", "world", "policy", "episodes", "seed", "notes", "model_error", "config",
            "provenance"}
    width = max(len(k) for k in result if k not in skip)
    for key, value in result.items():
        if key in skip:
            continue
        text = f"{value:.4f}" if isinstance(value, float) else str(value)
        print(f"  {key:<{width}}  {text}")
    if result.get("model_error"):
        me = {k: v for k, v in result["model_error"].items() if v not in (0, 0.0, (0.0, 0.0), [0.0, 0.0])}
        print(f"  {'model_error':<{width}}  {me or 'none'}")
