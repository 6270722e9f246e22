"""`formation sweep`: train a grid of config overrides x seeds on Ray Tune, aggregated.

Each trial is a normal `formation train` run folder under ``<out>/trials/<k>/seed-<s>``, with
one CPU and one torch thread. The base configuration is ``--config`` (a .json/.toml file or
inline JSON of MAPPOConfig fields, as for `formation train`); each ``--grid KEY=V1,V2`` adds
an axis (dotted keys reach nested fields: ``actor.embed_dim=32,64``), and ``--seeds`` the
seeds. Every trial's configuration is checked before Ray starts.

The table gives, per override combination over its seeds: converged seeds, episodes to
convergence (median, min-max, 95 % bootstrap interval of the median; a seed that never
converged counts as its budget) and wall time. ``<out>/sweep.json`` holds it with every trial's
numbers, the sweep's options and provenance (git commit, package versions).

Ctrl-C stops the sweep with its state saved; the same command again (or ``--resume --out``)
continues it: finished trials are kept, interrupted ones continue from their checkpoints.
A sweep whose trials have all finished is summarised without starting Ray.

    formation sweep --config '{"scenario": "paper-3"}' --seeds 5 --grid lr=3e-4,1e-3
    formation sweep --config base.toml --seeds 0-2 --grid actor.embed_dim=32,64 --cpus 2
    formation sweep --resume --out runs/sweep-lr
    formation sweep ... --address ray://head:10001      # on an existing Ray cluster
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

from sim.files import ConfigFileError, atomic_write_text, read_config
from sim.interrupts import caused_by_interrupt
from sim.provenance import provenance
from stack.commands import argtypes
from stack.commands.argtypes import seeds as seeds_arg
from stack.sweep import (
    ADDRESS_TIMEOUT_S,
    SweepError,
    aggregate,
    check_ray_address,
    finished,
    grid_trials,
    parse_grid_option,
    run_trials,
)

OPTIONS_FILE = "sweep.json"


def register(sub) -> None:
    p = sub.add_parser("sweep", description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--config", metavar="FILE_OR_JSON", default=None,
                   help="base MAPPOConfig fields: a .json/.toml file or inline JSON (default: defaults)")
    p.add_argument("--grid", action="append", default=[], metavar="KEY=V1,V2",
                   help="an axis of the grid (repeat for more axes); values read as JSON")
    p.add_argument("--seeds", type=seeds_arg, default=None,
                   help="a count (5: seeds 0-4), a range (2-4) or a list (0,3,7) (default 3)")
    p.add_argument("--episodes", type=argtypes.positive, default=None, metavar="K",
                   help="episode budget of every trial (default: --config's total_episodes, else 2000)")
    p.add_argument("--cpus", type=argtypes.positive, default=None,
                   help="CPUs of the local Ray (one trial each; default: all of this machine)")
    p.add_argument("--address", default=None, metavar="HOST:PORT",
                   help="join the Ray cluster at this address (HOST:PORT of its head, or ray://HOST:PORT) "
                        "instead of starting a local one, which listens on 127.0.0.1 only; refused when "
                        f"nothing answers there within {ADDRESS_TIMEOUT_S:g} s")
    p.add_argument("--out", type=argtypes.out_folder, default=None,
                   help="sweep folder (default runs/sweep-<timestamp>)")
    p.add_argument("--resume", action="store_true",
                   help="continue the sweep in --out with the options it was started with")
    p.add_argument("--json", action="store_true", help="print the JSON document instead of the table")
    p.set_defaults(func=run)


def _saved_options(saved: Path) -> dict:
    """The options a sweep folder's ``sweep.json`` records (``base``, ``grid``, ``seeds``,
    checked); a damaged or foreign file is named."""
    try:
        if saved.is_dir():
            raise SweepError(f"{saved} is a folder, not a sweep's file; remove it or give another --out")
        options = read_config(saved, "sweep.json")["options"]
        problem = _options_problem(options)
    except (ConfigFileError, KeyError, OSError, UnicodeDecodeError) as exc:
        problem = f"{type(exc).__name__}: {exc}"
    if problem:
        raise SweepError(f"{saved} is not a sweep's file ({problem}); remove it to start this folder's "
                         "sweep anew, or give another --out")
    return options


def _options_problem(options) -> str | None:
    """What is wrong with the ``options`` of a ``sweep.json``, or None."""
    if not isinstance(options, dict):
        return f"'options' is a {type(options).__name__}, not a mapping"
    missing = [k for k in ("base", "grid", "seeds") if k not in options]
    if missing:
        return f"'options' lacks {', '.join(repr(k) for k in missing)}"
    if not isinstance(options["base"], dict):
        return "'base' is not a mapping of fields"
    grid = options["grid"]
    if not isinstance(grid, list) or not all(
            isinstance(axis, list) and len(axis) == 2 and isinstance(axis[0], str) and isinstance(axis[1], list)
            and axis[1] for axis in grid):
        return "'grid' is not a list of [key, [values]] axes"
    seeds = options["seeds"]
    if (not isinstance(seeds, list) or not seeds
            or not all(isinstance(x, int) and not isinstance(x, bool) and x >= 0 for x in seeds)
            or len(set(seeds)) != len(seeds)):
        return "'seeds' is not a list of distinct integers >= 0"
    return None


def _resume_options(args) -> dict:
    """The options saved in ``<out>/sweep.json``; a flag given with --resume must agree with them."""
    if args.out is None:
        raise SweepError("--resume needs --out, the folder of the sweep to continue")
    saved = args.out / OPTIONS_FILE
    if not saved.exists():
        raise SweepError(f"--resume: {saved} does not exist; start the sweep without --resume")
    options = _saved_options(saved)
    plain, given = (json.loads(json.dumps(o)) for o in (options, _flag_options(args)))
    base, given_base = plain["base"], given["base"]
    if args.episodes is not None or "total_episodes" not in given_base:
        # the saved total_episodes may be --episodes' (compared on its own below)
        base = {k: v for k, v in base.items() if k != "total_episodes"}
        given_base = {k: v for k, v in given_base.items() if k != "total_episodes"}
    differ = [flag for flag, given_it, same in (
        ("--config", args.config, given_base == base), ("--grid", args.grid, given["grid"] == plain["grid"]),
        ("--seeds", args.seeds is not None, given["seeds"] == plain["seeds"]),
        ("--episodes", args.episodes is not None,
         plain["base"].get("total_episodes") == given["base"].get("total_episodes")))
        if given_it and not same]
    if differ:
        raise SweepError(f"{args.out} was started with other options than the {', '.join(differ)} given "
                         f"now (see its {OPTIONS_FILE}); --resume keeps the saved options: drop those "
                         "flags, or give another --out for a new sweep")
    return options


def _flag_options(args) -> dict:
    """The sweep's options from the flags (a new sweep)."""
    base = read_config(args.config, "--config") if args.config else {}
    if args.episodes is not None:
        base["total_episodes"] = args.episodes
    grid = [parse_grid_option(g) for g in args.grid]
    keys = [k for k, _ in grid]
    if len(set(keys)) != len(keys) or "seed" in keys:
        raise SweepError("--grid: each key once, and not 'seed' (use --seeds)")
    return {"base": base, "grid": grid, "seeds": args.seeds or [0, 1, 2]}


def _options(args) -> dict:
    """The sweep's options: from ``<out>/sweep.json`` with --resume, else from the flags."""
    return _resume_options(args) if args.resume else _flag_options(args)


def run(args) -> int:
    try:
        options = _options(args)
        out = args.out or Path("runs") / time.strftime("sweep-%Y%m%d-%H%M%S")
        trials = grid_trials(options["base"], options["grid"], options["seeds"], out)
        if args.address and not all(finished(Path(t.folder), t.budget) for t in trials):
            check_ray_address(args.address)      # before sweep.json: ray.init would wait for ever
    except (SweepError, ConfigFileError) as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 2
    saved = out / OPTIONS_FILE
    try:
        other = saved.exists() and _saved_options(saved) != json.loads(json.dumps(options))
    except SweepError as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 2
    if other:
        print(f"error: {out} holds another sweep; continue it with --resume --out {out}, or give "
              "another --out", file=sys.stderr)
        return 2
    out.mkdir(parents=True, exist_ok=True)
    doc = {"options": options, "trials": [], "rows": [], "provenance": provenance()}
    atomic_write_text(out / OPTIONS_FILE, json.dumps(doc, indent=2))
    print(f"sweep: {len(trials)} trials in {out}", file=sys.stderr, flush=True)
    try:
        results = run_trials(trials, out, cpus=args.cpus, address=args.address)
    except SweepError as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 1
    except BaseException as exc:        # a Ctrl-C may surface as another error (sim.interrupts)
        if not caused_by_interrupt(exc):
            raise
        print(f"interrupted: the sweep's state is saved; continue with "
              f"formation sweep --resume --out {out}", file=sys.stderr)
        return 130
    doc |= {"trials": results, "rows": aggregate(results)}
    atomic_write_text(out / OPTIONS_FILE, json.dumps(doc, indent=2))
    if args.json:
        print(json.dumps(doc, indent=2))
    else:
        print_rows(doc["rows"])
        print(f"results: {out / OPTIONS_FILE}")
    return 0


def print_rows(rows: list[dict]) -> None:
    headers = ["group", "converged", "episodes median", "95% CI", "min-max", "wall s median"]
    table = [[r["group"], f"{r['converged_seeds']}/{len(r['seeds'])}", f"{r['episodes_median']:.0f}",
              f"{r['episodes_ci95'][0]:.0f}-{r['episodes_ci95'][1]:.0f}",
              f"{r['episodes_min']}-{r['episodes_max']}", f"{r['wall_s_median']:.0f}"] for r in rows]
    widths = [max(len(str(x)) for x in col) for col in zip(headers, *table, strict=False)]
    for line in [headers, *table]:
        print("  ".join(str(x).ljust(w) for x, w in zip(line, widths, strict=True)))
