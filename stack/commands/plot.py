"""`formation plot`: figures of training runs, or of recorded stack episodes, as PNG files.

Writes into --out (default RUN_DIR/plots of the first run):

* curves.png        episode return, final distance [m] and evaluation success rate [%] against
                    training episodes (the paper's Figures 8-13, 17-20), every RUN_DIR overlaid
                    (e.g. a run from scratch and a transfer run), the converged episode marked;
* trajectories.png  robot paths of --episodes deterministic episodes of the first run's policy
                    (Figures 14-15, 21-22), starts drawn with --seed;
* attention.png     the first run's attention weights, robots x tokens, at --step of the first
                    of those episodes (Figure 5); not for the MLP baseline, which has none.

Each RUN_DIR is a folder written by `formation train --out RUN_DIR` (train.jsonl, eval.jsonl,
config.json, checkpoint.pt). --scenario runs the policy on another task, e.g. a 3-robot policy
on paper-5 (typed actors run any N; slot actors get fresh slots for the new robots).

Given episode records instead (``episode_SEED.npz`` of `formation eval --record DIR`, or
``record_KKKKK.npz`` of `formation bridge --record DIR`), it draws
each as EPISODE.png (into --out, default beside the record): the robots' paths, which layer
drove each robot tick by tick (policy, docking, detour, safety filter, stale, absent) and each
robot's distance to its target (:mod:`stack.episode_plot`).
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

from stack.commands import argtypes


def register(sub) -> None:
    p = sub.add_parser("plot", description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("run_dirs", nargs="+", type=Path, metavar="RUN_DIR",
                   help="run folders of `formation train`, or episode records (.npz) of `formation eval --record` "
                        "or `formation bridge --record`")
    p.add_argument("--labels", nargs="+", metavar="LABEL",
                   help="legend label per RUN_DIR (default: the folder names)")
    p.add_argument("--out", type=argtypes.out_folder, help="output folder (default: RUN_DIR/plots of the first run)")
    p.add_argument("--episodes", type=argtypes.int_range(1, 16), default=4, metavar="K",
                   help="episodes in trajectories.png, 1..16 (default 4)")
    p.add_argument("--scenario", help="preset, transport-N or scenario file for trajectories and attention (default: the run's own)")
    p.add_argument("--seed", type=argtypes.seed, default=0, help="seed of the start jitter (default 0)")
    p.add_argument("--step", type=argtypes.count, default=0, metavar="TICK",
                   help="episode tick of the attention snapshot (default 0)")
    p.add_argument("--curves-only", action="store_true",
                   help="only curves.png (runs without checkpoint.pt)")
    p.set_defaults(func=run)


def run(args) -> int:
    from controllers.mappo.checkpoint import CheckpointError
    from sim.scenario import ScenarioError
    from stack.plots import PlotError

    try:
        paths = make_plots(args)
    except (PlotError, CheckpointError, ScenarioError) as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 2
    for path in paths:
        print(path)
    return 0


def make_plots(args) -> list[Path]:
    """Check the arguments, then write the figures; returns the PNG paths (raises on bad input)."""
    from stack.plots import PlotError, load_run, plot_training_curves

    records = [p for p in args.run_dirs if p.suffix == ".npz"]
    if records:
        if len(records) != len(args.run_dirs):
            raise PlotError("give run folders or episode records (.npz of formation eval --record), not both")
        return _record_plots(records, args.out)
    labels = args.labels or [_default_label(d, args.run_dirs) for d in args.run_dirs]
    if len(labels) != len(args.run_dirs):
        raise PlotError(f"--labels has {len(labels)} labels for {len(args.run_dirs)} RUN_DIRs; give one per run")
    if len(set(labels)) != len(labels):
        raise PlotError(f"labels must differ, got {labels}; give --labels")
    runs = {label: load_run(d, label) for label, d in zip(labels, args.run_dirs, strict=True)}
    checkpoint = args.run_dirs[0] / "checkpoint.pt"
    if not args.curves_only and not checkpoint.is_file():
        raise PlotError(f"{str(checkpoint)!r} is missing: `formation train` writes it into the run folder; "
                        "give --curves-only to plot the curves alone")
    policy = None if args.curves_only else _load_policy(args, checkpoint)
    out = args.out or args.run_dirs[0] / "plots"
    paths = [plot_training_curves(runs, out / "curves.png")]
    if policy is not None:
        paths += _policy_plots(args, *policy, labels[0], out)
    return paths


def _record_plots(records: list[Path], out: Path | None) -> list[Path]:
    """EPISODE.png of each episode record, into ``out`` or beside the record."""
    from sim.scenario import Scenario
    from stack.episode_plot import plot_episode
    from stack.plots import PlotError
    from stack.recorder import RecordError, load_record

    paths = []
    for path in records:
        try:
            record = load_record(path)
        except RecordError as exc:
            raise PlotError(str(exc)) from None
        if "scenario" not in record.meta:
            raise PlotError(f"{path}: the record names no scenario; record it with formation eval --record")
        scenario = Scenario.from_dict(record.meta["scenario"])
        paths.append(plot_episode(record, scenario, (out or path.parent) / f"{path.stem}.png"))
    return paths


def _load_policy(args, checkpoint: Path):
    """(actor, scenario, note) for the policy figures; raises before anything is written."""
    import torch

    from controllers.mappo.checkpoint import checkpoint_config, load_actor, load_checkpoint
    from sim.scenario import make_scenario

    torch.set_num_threads(1)
    trained = checkpoint_config(load_checkpoint(checkpoint)).build_scenario()
    scenario = make_scenario(args.scenario) if args.scenario else trained
    actor = load_actor(checkpoint, scenario.num_robots)
    return actor, scenario, "" if scenario.name == trained.name else f" (trained on {trained.name})"


def _policy_plots(args, actor, scenario, moved: str, label: str, out: Path) -> list[Path]:
    from stack.attention_plot import attention_snapshot, plot_attention
    from stack.plots import (
        plot_trajectories,
        record_trajectories,
    )

    traj = record_trajectories(actor, scenario, episodes=args.episodes, seed=args.seed)
    paths = [plot_trajectories(traj, scenario, out / "trajectories.png",
                               title=f"{label}: {scenario.name}{moved}, deterministic policy, "
                                     f"starts drawn with seed {args.seed}")]
    if not hasattr(actor, "attention"):
        print(f"note: no attention.png: the {type(actor).__name__} has no attention weights", file=sys.stderr)
        return paths
    weights, tokens = attention_snapshot(actor, scenario, seed=args.seed, step=args.step)
    paths.append(plot_attention(weights, tokens, out / "attention.png",
                                title=f"{label}: attention on {scenario.name}{moved}, step {args.step} "
                                      f"({args.step * scenario.dynamics.dt:g} s) of episode 1 (seed {args.seed})"))
    return paths


def _default_label(run_dir: Path, all_dirs: list[Path]) -> str:
    """The folder name, or parent/name when two runs share a name."""
    names = [d.resolve().name for d in all_dirs]
    name = run_dir.resolve().name
    return name if names.count(name) == 1 else f"{run_dir.resolve().parent.name}/{name}"
