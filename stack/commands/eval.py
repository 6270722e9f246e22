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
  and its last command is a brake. ``--scenario`` must be the fleet's own: a fleet that runs
  other robots than its ``r0 .. r{N-1}`` is refused (exit 2)::

      formation fleet-sim --fleet lab --lockstep --episodes 3 --listen tcp/127.0.0.1:7447
      formation eval --policy scripted --world zenoh --fleet lab --lockstep --episodes 3 \
          --scenario paper-5 --connect tcp/127.0.0.1:7447
"""

from __future__ import annotations

import sys
from pathlib import Path

from sim.provenance import provenance
from sim.scenario import ScenarioError, make_scenario
from stack.commands import argtypes
from stack.commands.eval_runs import EvalArgumentError, batched, stack_episodes, with_
from stack.commands.latency_args import (
    DEFAULT_COMMAND_DELAY_MS,
    MODEL_ERROR_HELP,
    LinkArgumentError,
    add_command_delay_arg,
    parse_model_error,
)

__all__ = ["EvalArgumentError", "evaluate_from_args", "print_result", "register", "run"]


def register(sub) -> None:
    p = sub.add_parser("eval", description=__doc__)
    p.add_argument("policy_path", nargs="?", metavar="POLICY_FILE",
                   help="a training checkpoint or an exported policy (.pt, .pt2, .onnx, .npz)")
    p.add_argument("--policy", default=None, metavar="FILE|scripted",
                   help="the policy file as with bridge --policy (the same as POLICY_FILE), or "
                        "'scripted' for the built-in controller")
    p.add_argument("--scenario", default="paper-3",
                   help="preset, transport-N or a .json/.toml scenario file (default paper-3; --world zenoh: "
                        "the fleet's own, e.g. paper-5 for a default fleet-sim: another is refused)")
    p.add_argument("--world", choices=["batched", "pymunk", "zenoh"], default="batched",
                   help="batched: training world, no safety/MEC; pymunk: ControlStack with model error; "
                        "zenoh: ControlStack driving a fleet over Zenoh (--fleet and its endpoints) "
                        "(default batched)")
    p.add_argument("--episodes", type=argtypes.positive, default=100, metavar="K", help="episodes (default 100)")
    p.add_argument("--seed", type=argtypes.seed, default=0, help="seed of the first episode (default 0)")
    p.add_argument("--episode-ticks", type=argtypes.positive, default=None, metavar="T",
                   help="ticks per episode (default: the scenario's; --world zenoh: at most one less)")
    argtypes.add_deprecated_alias(p, "--steps", "--episode-ticks")
    argtypes.add_stage_flags(p, None, " in the pymunk world")
    p.add_argument("--model-error", default=None, metavar="K=V,...",
                   help=MODEL_ERROR_HELP + "; freeze=2:40: robot 2 goes silent at tick 40 (--world pymunk; "
                        "default none: the nominal model)")
    add_command_delay_arg(p)
    p.set_defaults(command_delay_ms=None)        # None: not given (the batched world notes it ignored)
    argtypes.add_intruder_flag(p, "; --world pymunk (a fleet over Zenoh has its own: fleet-sim --intruder)")
    p.add_argument("--track-robots", action="store_true",
                   help="--world pymunk: a tracker over the arena also sees every robot, one tick late, "
                        "within 5 mm and 2 cm/s (motion capture; sim.intruders.RobotSightings): a silent "
                        "robot it sees at rest is bounded by that sighting")
    p.add_argument("--report", type=argtypes.out_file, default=None, metavar="FILE",
                   help="write the result as JSON to FILE")
    argtypes.add_deprecated_alias(p, "--json", "--report")
    p.add_argument("--record", type=argtypes.out_folder, default=None, metavar="DIR",
                   help="--world pymunk or zenoh: record every episode into DIR as episode_SEED.npz "
                        "(positions, the commands of each layer, the stack's flags, contacts: "
                        "stack.recorder) and draw it as episode_SEED.png (paths, which layer drove "
                        "each robot, distances to the targets: stack.episode_plot)")
    argtypes.add_deprecated_alias(p, "--trace", "--record")
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
    if args.report is not None:
        from controllers.mappo.evaluate import write_json_atomic

        write_json_atomic(args.report, result)
        print(f"wrote {args.report}")
    return 0


def evaluate_from_args(args) -> dict:
    """The result document of ``formation eval`` for parsed ``args`` (raises on bad input)."""
    if (args.policy_path is None) == (args.policy is None):
        raise EvalArgumentError("give either a policy file (POLICY_FILE or --policy FILE) or --policy "
                                "scripted, not both and not neither")
    if args.policy not in (None, "scripted"):
        args = with_(args, policy_path=args.policy, policy=None)
    model_error = parse_model_error(args.model_error)      # checked in every world
    _refuse_other_worlds_flags(args)
    scenario = make_scenario(args.scenario)
    if args.policy_path is not None and not Path(args.policy_path).is_file():
        raise EvalArgumentError(f"policy file {args.policy_path!r} does not exist; give a checkpoint "
                                "or exported policy file, or --policy scripted")
    notes = []
    if args.world == "batched":
        ignored = [flag for flag, value in (("--safety", args.safety), ("--mec", args.mec),
                                            ("--docking", args.docking), ("--model-error", args.model_error),
                                            ("--command-delay-ms", args.command_delay_ms))
                   if value is not None]
        if ignored:
            note = (f"{', '.join(ignored)} ignored: the batched world runs the policy alone with "
                    "the nominal model and no link; use --world pymunk for the safety filter, MEC, "
                    "model error and command delay")
            print(f"note: {note}", file=sys.stderr)
            notes.append(note)
        metrics = batched(args, scenario)
    else:
        if args.command_delay_ms is None:
            args = with_(args, command_delay_ms=DEFAULT_COMMAND_DELAY_MS)
        metrics = stack_episodes(args, scenario, model_error)
    stack_config = metrics["config"]["stack"]
    return {"scenario": scenario.name, "num_robots": scenario.num_robots, "world": args.world,
            "policy": args.policy or str(args.policy_path), "episodes": args.episodes,
            "seed": args.seed, **metrics, "steps": metrics["config"]["steps"],
            "docking": bool(stack_config and stack_config["docking"]["enabled"]), "notes": notes,
            "provenance": provenance()}


def _refuse_other_worlds_flags(args) -> None:
    """EvalArgumentError for flags of another world than ``--world``'s (a run without them would
    not be the run asked for): the tracker's outside pymunk, --record in the batched world, the
    fleet's and its link's outside zenoh."""
    if args.world == "batched" and (args.intruder or args.track_robots):
        raise EvalArgumentError("--intruder and --track-robots need --world pymunk: the batched world has "
                                "no tracker")
    if args.world == "batched" and args.record is not None:
        raise EvalArgumentError("--record records the ControlStack's episodes: use --world pymunk or "
                                "--world zenoh (the batched world runs the policy alone)")
    if args.world != "zenoh":
        fleet_flags = [flag for flag, given in (
            ("--fleet", args.fleet is not None), ("--lockstep", args.lockstep), ("--listen", bool(args.listen)),
            ("--connect", bool(args.connect)), ("--certs", args.certs is not None),
            ("--identity", args.identity != "controller"), ("--insecure", args.insecure),
            ("--zenoh-config", args.zenoh_config is not None), ("--lease-ms", args.lease_ms is not None)) if given]
        if fleet_flags:
            raise EvalArgumentError(f"{', '.join(fleet_flags)} apply to --world zenoh (a fleet over Zenoh), "
                                    f"not to --world {args.world}: add --world zenoh, or drop them")


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
