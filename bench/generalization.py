"""One policy for any team: the generalist against the paper's specialist, zero-shot on a grid.

Trains, for each seed of ``--seeds`` (a count K for seeds 0..K-1, a range 2-4 or a list 0,3,7, as
``formation sweep --seeds``) on Ray Tune (:mod:`stack.sweep`, one CPU each):

    generalist   SDPA-MAPPO on the team sizes ``--team-sizes`` (a list or a range, default 3,4,5)
                 of the paper's layout at once (``MAPPOConfig.team_sizes``), budget ``--budget``
    specialist   SDPA-MAPPO on paper-3 alone (the paper's recipe: what 3 robots learned)

The generalist trains with the contact-penalty curriculum ``--penalty-curriculum`` (k of
``MAPPOConfig.penalty_curriculum``, default 3: contact penalties grow to 1 + k times as the
share of training episodes with every robot home grows; 2026-12-03, seeds 0-2 of the 3-5
generalist: 3 of 3 converged, median 1488 episodes, against 2 of 3 and 2832 without it) and
draws each episode's layout and actuator from ``--distribution`` (default
``none``: the paper's layout; ``broad`` varies object, direction and actuator, see
:mod:`sim.distribution`). It then judges every final policy, no further training, on a grid of ``--robots`` (default 1..10)
x layouts (:data:`LAYOUTS`: the default transport layout; its mirror, left to right; a larger
object; a hexagonal object), ``--eval-episodes`` deterministic episodes each in the batched world
(no filter, no MEC), and with ``--pymunk-episodes`` > 0 also in pymunk with model error (gain
0.85 +- 0.15, lag 0.03 s, one tick of command delay) through the default stack (filter + MEC).
A success needs every robot within the target tolerance at the end and no contact.

Fine-tuning (``--finetune-budget`` > 0, default 400): each generalist seed is trained further on
a held-out layout, :func:`held_out` (an L-shaped, non-convex object, which no distribution
draws, and 4 robots), with ``formation train --init-from`` and ``init_keep`` 1 (the weights as
they are), the convergence rule unchanged; reported are its zero-shot success (the evaluation
at episode 0) and the episodes to convergence (the budget where it does not converge).

``--json``: ``{"train": {"generalist": {"episodes": ..., "env_steps": ..., "wall_s": ...,
"converged_seeds": ...}, "specialist": {...}}, "grid": [{"policy", "seed", "scenario", "robots",
"world", "success", "collisions", "final_distance_mm"}, ...], "finetune": {"layout": ...,
"robots": ..., "budget": ..., "runs": [{"seed", "zero_shot_success", "episodes", "converged",
"wall_s"}], "median_episodes": ...}}``; pymunk rows also hold ``capture_radius`` and
``arrival_tick`` (the mean first tick the team stood on its targets, over the episodes it did).

    python bench/generalization.py --seeds 3                      # the full grid
    python bench/generalization.py --seeds 1 --robots 3,6 --eval-episodes 20 --json

``--policies RUN/checkpoint.pt,...`` judges those policies on the grid instead of training (no
``train`` or ``finetune`` then; each row's ``policy`` is the file). ``--capture-radius
default,0.12,0.06`` runs the pymunk cells once per docking setting (:mod:`controllers.docking`):
``default`` the stack's own (two tiers), a number R one tier capturing within R (release 2 cm
further), each row saying its ``capture_radius`` and ``stall_radius`` (0: one tier), in one run:

    python bench/generalization.py --policies a/checkpoint.pt,b/checkpoint.pt --layouts transport \
        --robots 3,4,5,6,7,8,9,10 --eval-episodes 50 --pymunk-episodes 10 --capture-radius default,0.06 --json
"""

from __future__ import annotations

import argparse
import json
import statistics
import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from bench._common import (  # noqa: E402
    L_OBJECT,
    add_output_args,
    json_object,
    nonnegative_int,
    positive_int,
    print_json,
    print_table,
    progress,
    robot_count_list,
)
from stack.commands import argtypes  # noqa: E402
from stack.sweep import SweepError, TrialSpec, resolve_fields, run_trials, summarize  # noqa: E402

LAYOUTS = ("transport", "mirrored", "large-object", "hexagon")
PYMUNK_ERROR = {"gain": 0.85, "gain_spread": 0.15, "lag_tau": 0.03, "delay_ticks": 1}


def layout(name: str, n: int):
    """The scenario of layout ``name`` for ``n`` robots (module docstring)."""
    import dataclasses

    import numpy as np

    from sim.scenario import rectangle, transport_scenario

    if name == "transport":
        return transport_scenario(n)
    if name == "mirrored":
        sc = transport_scenario(n)
        return dataclasses.replace(sc, name=f"mirrored-{n}", start_slots=sc.target_slots, target_slots=sc.start_slots)
    if name == "large-object":
        return transport_scenario(n, object_vertices=rectangle((0.5, 0.5), (0.24, 0.36)), name=f"large-object-{n}")
    if name == "hexagon":
        angles = np.arange(6) * np.pi / 3
        hexagon = np.stack([0.5 + 0.15 * np.cos(angles), 0.5 + 0.15 * np.sin(angles)], 1)
        return transport_scenario(n, object_vertices=hexagon, name=f"hexagon-{n}")
    raise ValueError(f"unknown layout {name!r}; choose from {LAYOUTS}")


def held_out(n: int = 4):
    """The fine-tuning layout: an L-shaped (non-convex) object of the preset's 0.2 x 0.3 box."""
    from sim.scenario import transport_scenario

    return transport_scenario(n, object_vertices=L_OBJECT, name=f"l-shape-{n}")


def _base(args) -> dict:
    """MAPPOConfig fields of both runs: the paper's layout, ``--update-epochs`` and ``--budget``."""
    return {"scenario": "paper-3", "update_epochs": args.update_epochs, "total_episodes": args.budget}


def trials(args, out: Path) -> list[TrialSpec]:
    base = _base(args)
    specs = []
    generalist = {**args.config, "team_sizes": args.team_sizes, "distribution": args.distribution,
                  "penalty_curriculum": args.penalty_curriculum}
    for seed in args.seeds:
        for name, extra in (("generalist", generalist), ("specialist", {})):
            folder = out / name / f"seed-{seed}"
            specs.append(TrialSpec(name, seed, resolve_fields({**base, **extra}, {}, seed), str(folder.resolve())))
    return specs


def judge(checkpoint: str, args) -> list[dict]:
    """The grid rows of one policy (module docstring)."""
    import torch

    from controllers.docking import DockingConfig
    from controllers.mappo import evaluate, load_actor
    from sim.pymunk_world import ModelError, PymunkWorld
    from stack.pipeline import ControlStack, StackConfig, run_episode

    torch.set_num_threads(1)
    actor = load_actor(checkpoint)
    rows = []
    for name in args.layouts:
        for n in args.robots:
            sc = layout(name, n)
            r = evaluate(actor, sc, episodes=args.eval_episodes, seed=10_000)
            rows.append({"scenario": sc.name, "layout": name, "robots": n, "world": "batched",
                         "success": r.success_rate, "collisions": r.collision_rate,
                         "final_distance_mm": 1000 * r.final_distance})
            for radius in args.capture_radius if args.pymunk_episodes else ():
                docking = DockingConfig() if radius is None else DockingConfig(
                    capture_radius=radius, release_radius=radius + 0.02, stall_radius=0.0)
                config = StackConfig(docking=docking)
                runs = [run_episode(PymunkWorld(sc, ModelError(**PYMUNK_ERROR)), ControlStack(sc, actor, config),
                                    10_000 + k) for k in range(args.pymunk_episodes)]
                ok = [m.final_distance for m in runs if m.success]
                arrived = [m.arrival_step for m in runs if m.arrival_step is not None]
                rows.append({"scenario": sc.name, "layout": name, "robots": n, "world": "pymunk",
                             "success": sum(m.success for m in runs) / len(runs),
                             "collisions": sum(m.collided for m in runs) / len(runs),
                             "final_distance_mm": 1000 * statistics.mean(ok) if ok else None,
                             "capture_radius": docking.capture_radius, "stall_radius": docking.stall_radius,
                             "arrival_tick": statistics.mean(arrived) if arrived else None})
    return rows


def judge_given(args) -> list[dict]:
    """The grid rows of ``--policies``, ``--cpus`` policies at a time."""
    from concurrent.futures import ProcessPoolExecutor

    with ProcessPoolExecutor(min(args.cpus, len(args.policies))) as pool:
        rows = pool.map(judge, args.policies, [args] * len(args.policies))
        return [{"policy": path, "seed": None, **row} for path, policy_rows in zip(args.policies, rows, strict=True)
                for row in policy_rows]


def finetune(args, specs: list[TrialSpec], out: Path) -> dict:
    """Fine-tune every generalist seed on :func:`held_out` (module docstring)."""
    sc = held_out()
    runs = []
    for s in specs:
        if s.group != "generalist":
            continue
        base = {**s.fields, "team_sizes": [], "distribution": None, "scenario": sc.to_dict(),
                "init_from": str(Path(s.folder) / "checkpoint.pt"), "init_keep": 1.0,
                "total_episodes": args.finetune_budget}         # the generalist's settings otherwise
        fields = resolve_fields(base, {}, s.seed)
        runs.append(TrialSpec("finetune", s.seed, fields, str((out / "finetune" / f"seed-{s.seed}").resolve())))
    run_trials(runs, out, cpus=args.cpus, experiment="generalization-finetune", restore=False, verbose=0)
    rows = []
    for r in runs:
        summary = summarize(Path(r.folder), args.finetune_budget)
        first = (Path(r.folder) / "eval.jsonl").read_text().splitlines()[0]
        rows.append({"seed": r.seed, "zero_shot_success": json.loads(first)["success_rate"],
                     "episodes": summary["episodes"], "converged": summary["converged"],
                     "wall_s": summary["wall_s"]})
    return {"layout": sc.name, "robots": sc.num_robots, "budget": args.finetune_budget, "runs": rows,
            "median_episodes": statistics.median(r["episodes"] for r in rows) if rows else None}


def main(argv=None) -> int:
    p = argparse.ArgumentParser(allow_abbrev=False, description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--seeds", type=argtypes.seeds, default=list(range(3)),
                   help="training seeds: a count (3: seeds 0-2), a range (2-4) or a list (0,3,7) (default 3)")
    p.add_argument("--team-sizes", type=argtypes.int_list, default=[3, 4, 5], metavar="LIST",
                   help="the generalist's team sizes, e.g. 3,4,5 or 3-5 (default 3,4,5)")
    p.add_argument("--budget", type=positive_int, default=3200, help="episode budget of each run (default 3200)")
    p.add_argument("--update-epochs", type=positive_int, default=4, help="PPO epochs per rollout (default 4)")
    p.add_argument("--robots", type=robot_count_list, default=list(range(1, 11)), help="grid team sizes, comma-separated (default 1,2,...,10)")
    p.add_argument("--layouts", type=lambda s: s.split(","), default=list(LAYOUTS),
                   help=f"grid layouts, from {','.join(LAYOUTS)} (default all)")
    p.add_argument("--eval-episodes", type=positive_int, default=100,
                   help="batched episodes per cell of the grid (default 100)")
    argtypes.add_deprecated_alias(p, "--episodes", "--eval-episodes")
    p.add_argument("--pymunk-episodes", type=nonnegative_int, default=0, help="pymunk episodes per cell (default 0: skip)")
    p.add_argument("--distribution", default=None, metavar="NAME_OR_FILE",
                   help="the generalist's scenario distribution: none (default), broad or a file")
    p.add_argument("--penalty-curriculum", type=float, default=3.0, metavar="K",
                   help="the generalist's contact-penalty curriculum, MAPPOConfig.penalty_curriculum "
                        "(default 3; 0: off, as the specialist)")
    p.add_argument("--config", type=json_object, default={}, metavar="JSON",
                   help="extra MAPPOConfig fields as JSON for the generalist's runs, e.g. "
                        "'{\"actor\": {\"token_layers\": 1}}' (the specialist keeps the paper recipe; "
                        "default {}: none)")
    p.add_argument("--finetune-budget", type=int, default=400,
                   help="fine-tuning episodes on the held-out layout per generalist seed (default 400; 0: skip)")
    p.add_argument("--cpus", type=positive_int, default=2, help="trainings at once (default 2)")
    p.add_argument("--out", type=argtypes.out_folder, default=Path("runs/generalization"),
                   help="run folders (default runs/generalization)")
    p.add_argument("--policies", type=lambda s: s.split(","), default=None, metavar="CKPT,...",
                   help="judge these training checkpoints on the grid instead of training")
    p.add_argument("--capture-radius", type=radius_list, default=[None], metavar="R,...",
                   help="docking of the pymunk cells, comma-separated: 'default' (the stack's) or one-tier "
                        "capture radii [m] (default 'default')")
    add_output_args(p)
    args = p.parse_args(argv)
    if not args.penalty_curriculum >= 0:
        p.error(f"--penalty-curriculum must be a number >= 0, got {args.penalty_curriculum}")
    bad = sorted(set(args.layouts) - set(LAYOUTS))
    if bad:
        p.error(f"--layouts: unknown {bad}; choose from {','.join(LAYOUTS)}")
    missing = [path for path in args.policies or () if not Path(path).is_file()]
    if missing:
        p.error(f"--policies: no such file {missing[0]}")
    if args.policies:
        return report({"train": {}, "grid": judge_given(args), "finetune": None}, args)
    try:      # every run checked before any training: a bad value is a usage error naming its flag
        specs = trials(args, args.out)
    except SweepError as exc:
        p.error(f"{_flag_at_fault(args)}: {str(exc).removeprefix('the base config: ')}")
    progress(f"training {len(specs)} runs on {args.cpus} CPUs under {args.out}")
    run_trials(specs, args.out, cpus=args.cpus, experiment="generalization", restore=False, verbose=0)
    train, grid = {}, []
    for name in ("generalist", "specialist"):
        runs = [summarize(Path(s.folder), args.budget) for s in specs if s.group == name]
        train[name] = {"episodes": statistics.median(r["episodes"] for r in runs),
                       "env_steps": statistics.median(r["env_steps"] for r in runs),
                       "wall_s": statistics.median(r["wall_s"] for r in runs),
                       "converged_seeds": sum(r["converged"] for r in runs), "seeds": len(runs)}
    for s in specs:
        progress(f"judging {s.group} seed {s.seed}")
        grid += [{"policy": s.group, "seed": s.seed, **row} for row in judge(str(Path(s.folder) / "checkpoint.pt"), args)]
    doc = {"train": train, "grid": grid,
           "finetune": finetune(args, specs, args.out) if args.finetune_budget > 0 else None}
    return report(doc, args)


def _flag_at_fault(args) -> str:
    """The flag whose value the generalist's config refuses: the first whose field alone, on the
    paper's layout, is refused; ``--config`` when none is."""
    for flag, fields in (("--budget", {"total_episodes": args.budget}),
                         ("--update-epochs", {"update_epochs": args.update_epochs}),
                         ("--distribution", {"distribution": args.distribution}),
                         ("--team-sizes", {"team_sizes": args.team_sizes})):
        try:
            resolve_fields({"scenario": "paper-3", **fields}, {}, 0)
        except SweepError:
            return flag
    return "--config"


def radius_list(text: str) -> list[float | None]:
    """``default,0.06`` -> ``[None, 0.06]``: the stack's docking (None) or one-tier radii in metres."""
    try:
        radii = [None if x.strip() == "default" else float(x) for x in text.split(",")]
    except ValueError:
        radii = []
    if not radii or not all(r is None or 0 < r < 1 for r in radii):
        raise argparse.ArgumentTypeError(f"expected 'default' or radii in metres between 0 and 1, e.g. "
                                         f"default,0.06; got {text!r}")
    return radii


def report(doc: dict, args) -> int:
    """Print ``doc`` as JSON (``--json``) or as tables: success per policy, world, layout and N."""
    if args.json:
        print_json(doc)
        return 0
    train = doc["train"]
    if train:
        print_table(["policy", "train episodes (median)", "converged", "wall s"],
                    [[k, v["episodes"], f"{v['converged_seeds']}/{v['seeds']}", v["wall_s"]] for k, v in train.items()])
    cells: dict[tuple, list[float]] = {}
    for row in doc["grid"]:
        docking = "default" if row.get("stall_radius") else f"one tier, {row.get('capture_radius', 0):g} m"
        world = row["world"] + (f" (docking {docking})" if len(args.capture_radius) > 1 and row["world"] == "pymunk"
                                else "")
        cells.setdefault((row["policy"], world, row["layout"], row["robots"]), []).append(row["success"])
    print_table(["policy", "world", "layout", *[f"N={n}" for n in args.robots]],
                [[pol, world, lay, *[f"{statistics.mean(cells[(pol, world, lay, n)]):.2f}" for n in args.robots]]
                 for pol, world, lay in sorted({k[:3] for k in cells}, key=lambda k: (k[0], k[1], args.layouts.index(k[2])))])
    if doc["finetune"]:
        ft = doc["finetune"]
        print_table([f"fine-tune on {ft['layout']}: seed", "zero-shot success", "episodes to converge", "wall s"],
                    [[r["seed"], f"{r['zero_shot_success']:.2f}", r["episodes"] if r["converged"]
                      else f">{ft['budget']}", f"{r['wall_s']:.0f}"] for r in ft["runs"]])
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
