"""`formation train`: train an SDPA-MAPPO (or MLP-MAPPO, or a paper baseline) policy on a scenario.

Every run writes, in its folder: ``config.json`` (the resolved configuration, itself a valid
``--config`` file), ``run.json`` (git commit, package versions, threads, host), ``train.csv`` /
``train.jsonl`` (per iteration), ``eval.csv`` / ``eval.jsonl`` (the convergence evaluations),
``checkpoint.pt`` (atomic, resumable) and ``result.json``. Ctrl-C keeps the last checkpoint;
``--resume`` continues the same curve (a run stopped before its first checkpoint, written every
``checkpoint_interval`` iterations, has none: started again in the same folder, it starts over).

The configuration is :class:`controllers.mappo.MAPPOConfig`: its defaults (with ``--resume``:
the run's own ``config.json``), then ``--config`` (a .json or .toml file of any of its fields,
nested ``actor``/``critic``/``reward_weights`` tables included, or inline JSON), then the flags
given on the command line. Unknown fields are
refused with their name; ``reward_weights`` given change the training reward's
(``TRAINING_REWARD``) weights they name and keep the others. ``--print-config`` prints the
resolved configuration and exits.

    formation train --config runs/p3/config.json --seed 1 --out runs/p3-seed1
    formation train --config sweep.toml --print-config

``--algo maddpg`` trains the paper's MADDPG baseline instead (:mod:`controllers.baselines.maddpg`,
built from TorchRL's pieces; its fields are :class:`controllers.baselines.MADDPGConfig`),
``--algo gasil-maddpg`` the same with GASIL's self-imitation reward
(:mod:`controllers.baselines.gasil`), ``--algo ddq`` Deep Dyna-Q
(:class:`controllers.baselines.DDQConfig`), each on the same reward, episode length, evaluation
and convergence rule as SDPA-MAPPO, into the same kind of run folder:

    formation train --algo gasil-maddpg --scenario paper-3 --episodes 25000 --out runs/gasil-p3
    formation train --algo ddq --config '{"planning_steps": 10}' --out runs/ddq-p3
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

from controllers.mappo import MAPPOConfig, TrainConfigError, train
from controllers.mappo.checkpoint import CheckpointError
from controllers.mappo.config import user_fields
from controllers.policy import PolicyConfigError
from sim.files import ConfigFileError, read_config
from sim.scenario import ScenarioError
from stack.commands import argtypes


def register(sub) -> None:
    p = sub.add_parser("train", description=__doc__)
    p.add_argument("--algo", choices=ALGOS, default=None,
                   help="the learner: SDPA-/MLP-MAPPO (default) or a baseline (default: the "
                        "--config file's \"algo\", or on --resume the run's)")
    p.add_argument("--scenario", default=None, help="preset, transport-N or a .json/.toml scenario file (default paper-3)")
    p.add_argument("--episodes", type=argtypes.positive, default=None,
                   help="episode budget, total_episodes (default 2000)")
    p.add_argument("--seed", type=argtypes.seed, default=None, help="training seed (default 0)")
    p.add_argument("--variant", choices=("typed", "slot", "mlp"), default=None,
                   help="actor: typed SDPA (any N), the paper's slot SDPA, or the MLP baseline "
                        "(default: --config's actor.variant, else typed)")
    p.add_argument("--team-sizes", type=argtypes.int_list, metavar="LIST", default=None,
                   help="train one policy on several team sizes at once, e.g. 3,4,5 or 3-5 "
                        "(team_sizes; default: the scenario's own)")
    p.add_argument("--distribution", metavar="NAME_OR_FILE", default=None,
                   help="draw each training episode's layout and actuator from ranges: 'broad' or a "
                        ".json/.toml file (see `formation scenarios --show-distribution broad`) (default "
                        "none: the scenario's own layout and actuators)")
    p.add_argument("--init-from", metavar="CKPT", help="start from an M-robot checkpoint (transfer)")
    p.add_argument("--config", metavar="FILE_OR_JSON",
                   help="MAPPOConfig fields: a .json/.toml file or inline JSON, e.g. '{\"lr\": 5e-4}'")
    p.add_argument("--tensorboard", action=argparse.BooleanOptionalAction, default=None,
                   help="also write TensorBoard scalars to <out>/tensorboard (tensorboard --logdir <out>) "
                        "(default: --config's \"tensorboard\", else off)")
    p.add_argument("--print-config", action="store_true",
                   help="print the resolved configuration (a valid --config file) and exit")
    p.add_argument("--out", type=argtypes.out_folder, help="run folder (default runs/train-<scenario>-<timestamp>)")
    p.add_argument("--resume", action="store_true", help="continue the run in --out")
    p.add_argument("--stop", action=argparse.BooleanOptionalAction, default=None,
                   help="stop at convergence; --no-stop keeps training to the episode budget "
                        "(default: --config's \"stop_at_convergence\", else on)")
    p.set_defaults(func=run)


def given_fields(args) -> dict:
    """The fields of ``--config`` over, with ``--resume``, those of the run's ``config.json``."""
    saved = args.out / "config.json" if args.resume and args.out is not None else None
    fields = read_config(saved, "the run's config.json") if saved is not None and saved.is_file() else {}
    return fields | (read_config(args.config, "--config") if args.config else {})


def resolve_config(args) -> MAPPOConfig:
    """Defaults < the run's config (``--resume``) < ``--config`` < flags given (module
    docstring); raises ValueError-like errors."""
    fields = given_fields(args)
    flags = {"scenario": args.scenario, "total_episodes": args.episodes, "seed": args.seed,
             "init_from": args.init_from, "team_sizes": args.team_sizes, "distribution": args.distribution}
    fields |= {k: v for k, v in flags.items() if v is not None}
    if args.stop is not None:
        fields["stop_at_convergence"] = args.stop
    if args.tensorboard is not None:
        fields["tensorboard"] = args.tensorboard
    if args.variant is not None:
        fields["actor"] = {**fields.get("actor", {}), "variant": args.variant}
    return MAPPOConfig.from_dict(user_fields(fields))


ALGOS = ("mappo", "maddpg", "gasil-maddpg", "ddq")
MAPPO_ONLY = ("variant", "team_sizes", "distribution", "init_from", "tensorboard")


def resolve_baseline_config(args):
    """A baseline's configuration: defaults < ``--config`` < flags given; flags it has no use
    for are refused by name."""
    from controllers.baselines import BASELINES

    unused = [name for name in MAPPO_ONLY if getattr(args, name) not in (None, False)]
    if unused:
        raise ValueError(f"--algo {chosen_algo(args)} does not take --{unused[0].replace('_', '-')} (MAPPO only)")
    fields = given_fields(args)
    flags = {"scenario": args.scenario, "total_episodes": args.episodes, "seed": args.seed}
    fields |= {k: v for k, v in flags.items() if v is not None}
    if args.stop is not None:
        fields["stop_at_convergence"] = args.stop
    algo = chosen_algo(args)
    if algo == "gasil-maddpg":
        fields["self_imitation"] = True
    return BASELINES[algo][0].from_dict(fields)


def summary(out: Path, result) -> int:
    """Print where the run is and how it ended; exit status 0."""
    conv = result.converged_episode
    print(f"run folder: {out}")
    print(f"episodes {result.episodes}, env steps {result.env_steps}, wall {result.wall_time_s:.0f} s, "
          + (f"converged at episode {conv}" if conv is not None else "not converged"))
    return 0


def chosen_algo(args) -> str:
    """``--algo``, else the ``"algo"`` of the ``--config`` file, else (``--resume``) of the run's
    ``config.json``, else ``mappo``: a MADDPG run resumes, or is repeated, as itself."""
    if args.algo is not None:
        return args.algo
    sources = [args.config] if args.config else []
    if args.resume and args.out is not None and (args.out / "config.json").is_file():
        sources.append(args.out / "config.json")
    for source in sources:
        try:
            algo = read_config(source, "--config").get("algo")
        except ConfigFileError:
            continue                      # the MAPPO path reports the bad file
        if algo in ALGOS:
            return algo
    return "mappo"


def run_baseline(args) -> int:
    from controllers.baselines import BASELINES, BaselineConfigError

    try:
        import torchrl  # noqa: F401
    except ImportError:
        print(f"error: --algo {chosen_algo(args)} needs TorchRL: pip install -c constraints.txt -e '.[torchrl]'",
              file=sys.stderr)
        return 2

    try:
        config = resolve_baseline_config(args)
    except (ConfigFileError, BaselineConfigError, ScenarioError, ValueError) as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 2
    if args.print_config:
        print(json.dumps(config.to_dict(), indent=2))
        return 0
    out = args.out or Path("runs") / time.strftime(f"{config.algo}-{config.scenario_name}-%Y%m%d-%H%M%S")
    try:
        result = BASELINES[config.algo][1](config, out, resume=args.resume)
    except CheckpointError as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 2
    return summary(out, result)


def run(args) -> int:
    if args.resume and args.out is None:
        print("error: --resume needs --out, the folder of the run to continue", file=sys.stderr)
        return 2
    if chosen_algo(args) != "mappo":
        return run_baseline(args)
    try:
        config = resolve_config(args)
    except (ConfigFileError, TrainConfigError, PolicyConfigError, ScenarioError, ValueError) as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 2
    if args.print_config:
        print(json.dumps(config.to_dict(), indent=2))
        return 0
    out = args.out or Path("runs") / time.strftime(f"train-{config.scenario_name}-%Y%m%d-%H%M%S")
    try:
        result = train(config, out, resume=args.resume)
    except (TrainConfigError, CheckpointError) as exc:     # a resume the run's checkpoint refuses
        print(f"error: {exc}", file=sys.stderr)
        return 2
    return summary(out, result)
