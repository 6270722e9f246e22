"""`formation train`: train an SDPA-MAPPO (or MLP-MAPPO) policy on a scenario.

Every run writes, in its folder: ``config.json`` (the resolved configuration), ``train.csv`` /
``train.jsonl`` (per iteration), ``eval.csv`` / ``eval.jsonl`` (the convergence evaluations),
``checkpoint.pt`` (atomic, resumable) and ``result.json``. Ctrl-C keeps the last checkpoint;
``--resume`` continues the same curve.
"""

from __future__ import annotations

import json
import time
from pathlib import Path

from controllers.mappo import MAPPOConfig, TrainConfigError, train
from controllers.policy import PolicyConfigError
from sim.scenario import ScenarioError


def register(sub) -> None:
    p = sub.add_parser("train", help="train a policy (SDPA-MAPPO by default) on a scenario",
                       description=__doc__)
    p.add_argument("--scenario", default="paper-3", help="preset or transport-N (default paper-3)")
    p.add_argument("--episodes", type=int, default=2000, help="episode budget (default 2000)")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--variant", choices=("typed", "slot", "mlp"), default="typed",
                   help="actor: typed SDPA (any N), the paper's slot SDPA, or the MLP baseline")
    p.add_argument("--init-from", metavar="CKPT", help="start from an M-robot checkpoint (transfer)")
    p.add_argument("--config", metavar="JSON", help="MAPPOConfig fields as JSON, e.g. '{\"lr\": 5e-4}'")
    p.add_argument("--out", type=Path, help="run folder (default runs/train-<scenario>-<timestamp>)")
    p.add_argument("--resume", action="store_true", help="continue the run in --out")
    p.add_argument("--no-stop", action="store_true", help="keep training after convergence")
    p.set_defaults(func=run)


def run(args) -> int:
    if args.resume and args.out is None:
        print("error: --resume needs --out, the folder of the run to continue")
        return 2
    out = args.out or Path("runs") / time.strftime(f"train-{args.scenario}-%Y%m%d-%H%M%S")
    try:
        fields = json.loads(args.config) if args.config else {}
        if not isinstance(fields, dict):
            raise ValueError("--config must be a JSON object")
        fields["actor"] = {"variant": args.variant, **fields.get("actor", {})}
        if args.variant == "mlp":
            fields.setdefault("critic", {"variant": "mlp"})
        config = MAPPOConfig.from_dict({"scenario": args.scenario, "total_episodes": args.episodes,
                                        "seed": args.seed, "init_from": args.init_from,
                                        "stop_at_convergence": not args.no_stop, **fields})
    except (ValueError, TrainConfigError, PolicyConfigError, ScenarioError) as exc:
        print(f"error: {exc}")
        return 2
    result = train(config, out, resume=args.resume)
    conv = result.converged_episode
    print(f"run folder: {out}")
    print(f"episodes {result.episodes}, env steps {result.env_steps}, wall {result.wall_time_s:.0f} s, "
          + (f"converged at episode {conv}" if conv is not None else "not converged"))
    return 0
