"""The episodes of `formation eval` (stack.commands.eval) in each world, the result's resolved
settings, and the ``--record`` files."""

from __future__ import annotations

import argparse
import dataclasses
import sys
from pathlib import Path

import numpy as np
import torch
from tqdm import tqdm

from sim.intruders import IntruderFleet, RobotSightings
from sim.provenance import provenance
from sim.pymunk_world import ModelError, PymunkWorld
from stack.commands import argtypes
from stack.commands.latency_args import latency_config, parse_model_error


class EvalArgumentError(ValueError):
    """A bad command-line value; the message names the flag and the fix."""


def batched(args, scenario) -> dict:
    """The batched world: :func:`controllers.mappo.evaluate`, or the scripted controller through
    a stack with both stages off."""
    from stack.pipeline import ControlStack, StackConfig, load_policy

    if args.policy == "scripted":
        from controllers.scripted import ScriptedController
        from sim.fleet import BatchedFleet

        stack = ControlStack(scenario, ScriptedController(scenario), StackConfig(safety=False, mec=False))
        return episodes(args, BatchedFleet(scenario), stack, safety=False, mec=False)[0] | {
            "config": resolved_config(args, scenario, stack)}
    from controllers.mappo.evaluate import evaluate

    if args.episode_ticks is not None:
        raise EvalArgumentError("--episode-ticks applies to --world pymunk or zenoh, or --policy scripted "
                                "(the batched world runs a policy's full episodes)")
    actor = load_policy(args.policy_path, scenario.num_robots)
    with torch.inference_mode():
        result = evaluate(actor, scenario, episodes=args.episodes, seed=args.seed)
    d = result.to_dict()
    return {k: d[k] for k in ("success_rate", "final_distance", "collision_rate", "robot_collisions",
                              "object_collisions", "wall_collisions", "episode_return")} | {
        "safety": False, "mec": False, "model_error": None, "config": resolved_config(args, scenario, None)}


def stack_episodes(args, scenario, model_error: ModelError) -> dict:
    """The pymunk world or a fleet over Zenoh, through the ControlStack."""
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
        return _zenoh_episodes(args, scenario, stack, safety=safety, mec=mec)
    try:             # the world checks the model error against the team (a frozen robot it has)
        world = PymunkWorld(scenario, model_error, seed=args.seed)
    except ValueError as exc:
        raise EvalArgumentError(str(exc)) from None
    if args.intruder or args.track_robots:
        world = IntruderFleet(world, args.intruder, sighting_delay_ticks=int(args.track_robots),
                              robots=RobotSightings(seed=args.seed) if args.track_robots else None)
    out, recorded = episodes(args, world, stack, safety=safety, mec=mec)
    _draw_records(recorded, scenario)
    out["model_error"] = dataclasses.asdict(model_error)
    out["command_delay_ms"], out["policy_runtime"] = args.command_delay_ms, stack.policy_runtime
    out["config"] = resolved_config(args, scenario, stack)
    return out


def _zenoh_episodes(args, scenario, stack, *, safety: bool, mec: bool) -> dict:
    from deploy.zenoh_fleet import FleetMismatch, FleetTimeout

    last = scenario.dynamics.episode_steps - 1      # the fleet's last published state (eval's docstring)
    if args.episode_ticks is not None and args.episode_ticks > last:
        raise EvalArgumentError(f"--episode-ticks for --world zenoh is at most {last}: the fleet publishes "
                                f"{last + 1} states an episode")
    args = with_(args, episode_ticks=args.episode_ticks or last)
    try:
        with zenoh_fleet(args, scenario) as fleet:
            out, recorded = episodes(args, fleet, stack, safety=safety, mec=mec)
    except FleetMismatch as exc:
        raise EvalArgumentError(_mismatch(args.scenario, exc)) from None
    except FleetTimeout as exc:         # no fleet there (--fleet, --connect), or one that lost robots
        raise EvalArgumentError(f"--world zenoh: {exc}") from None
    _draw_records(recorded, scenario)
    out["model_error"] = None         # the fleet's own
    out["command_delay_ms"], out["policy_runtime"] = args.command_delay_ms, stack.policy_runtime
    out["config"] = resolved_config(args, scenario, stack)
    return out


def _mismatch(scenario: str, exc) -> str:
    """What ``eval --world zenoh`` says of a fleet that runs other robots than ``--scenario``'s."""
    from deploy.zenoh_fleet import robot_span

    n = len(exc.fleet_robots)
    like = f" (e.g. --scenario paper-{n})" if 3 <= n <= 5 else (f" (e.g. --scenario transport-{n})" if n else "")
    return (f"--scenario {scenario} has robots {robot_span(exc.scenario_robots)}, but fleet {exc.fleet!r} runs "
            f"{robot_span(exc.fleet_robots) or 'none'}: give --scenario the scenario the fleet runs{like}, "
            "the one its `formation fleet-sim --scenario` was given")


def resolved_config(args, scenario, stack) -> dict:
    """The settings the episodes ran with, defaults filled in (the JSON result's and every
    --record file's "config"): the scenario, the ticks an episode, the flags, and the
    StackConfig used (``stack`` None: the policy ran alone, the batched world). A setting that
    does not apply to the world is None."""
    world = args.world
    return {"scenario": scenario.to_dict(), "world": world, "policy": args.policy or str(args.policy_path),
            "episodes": args.episodes, "seed": args.seed,
            "steps": scenario.dynamics.episode_steps if args.episode_ticks is None else args.episode_ticks,
            "model_error": (dataclasses.asdict(parse_model_error(args.model_error)) if world == "pymunk"
                            else None),
            "command_delay_ms": None if world == "batched" else args.command_delay_ms,
            "intruder": [dataclasses.asdict(i) for i in args.intruder] if world == "pymunk" else None,
            "track_robots": args.track_robots if world == "pymunk" else None,
            "fleet": args.fleet if world == "zenoh" else None,
            "lockstep": args.lockstep if world == "zenoh" else None,
            "stack": None if stack is None else dataclasses.asdict(stack.config)}


def _record(args, stack, seed: int, recorder, metrics) -> Path:
    """Save episode ``seed``'s record under ``--record`` (drawn later by :func:`_draw_records`);
    the recorder adds the fleet's scenario."""
    record = recorder.finish({"seed": seed, "world": args.world,
                              "policy": args.policy or str(args.policy_path), "metrics": metrics.to_dict(),
                              "model_error": args.model_error, "command_delay_ms": args.command_delay_ms,
                              "safety": stack.safety is not None, "mec": stack.mec is not None,
                              "docking": stack.docking is not None,
                              "config": resolved_config(args, stack.scenario, stack), "provenance": provenance()})
    return record.save(args.record / f"episode_{seed}.npz")


def _draw_records(paths: list[Path], scenario) -> None:
    """episode_SEED.png beside each saved record; after the episodes, since a fleet over Zenoh
    waits for its next command while a figure is drawn."""
    from stack.episode_plot import plot_episode
    from stack.recorder import load_record

    for path in tqdm(paths, desc="record figures", unit="ep", file=sys.stderr, leave=False):
        plot_episode(load_record(path), scenario, path.with_suffix(".png"))


def with_(args, **changes) -> argparse.Namespace:
    """``args`` with ``changes``."""
    return argparse.Namespace(**{**vars(args), **changes})


def zenoh_fleet(args, scenario):
    """The :class:`deploy.zenoh_fleet.ZenohFleet` of the ``--world zenoh`` flags."""
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


def episodes(args, fleet, stack, *, safety: bool, mec: bool) -> tuple[dict, list[Path]]:
    """The metrics of ``args.episodes`` episodes, and the files saved under ``--record``."""
    from stack.pipeline import run_episode
    from stack.recorder import EpisodeRecorder, record_folder

    torch.set_num_threads(1)
    folder = args.record
    if folder is not None:
        try:
            record_folder(folder, "--record")
        except ValueError as exc:
            raise EvalArgumentError(str(exc)) from None
    rows, recorded, near = [], [], []
    for k in tqdm(range(args.episodes), desc="eval", unit="ep", file=sys.stderr, leave=False):
        recorder = EpisodeRecorder() if folder is not None else None
        rows.append(run_episode(fleet, stack, args.seed + k, args.episode_ticks, recorder=recorder))
        if isinstance(fleet, IntruderFleet) and fleet.intruders:
            near.append(fleet.watch.summary())
        if recorder is not None:
            recorded.append(_record(args, stack, args.seed + k, recorder, rows[-1]))

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
            "safety": safety, "mec": mec, **_intruder_metrics(near)}, recorded


def _intruder_metrics(near: list[dict]) -> dict:
    """With intruders: the closest any robot came to one over the episodes [mm] (None: none was
    in the arena), and the fraction of episodes in which a robot drove into one
    (:class:`sim.intruders.IntruderWatch`)."""
    if not near:
        return {}
    gaps = [e["min_gap_mm"] for e in near if e["min_gap_mm"] is not None]
    return {"intruder_min_gap_mm": min(gaps) if gaps else None,
            "intruder_drive_in_rate": float(np.mean([e["drive_in_ticks"] > 0 for e in near]))}
