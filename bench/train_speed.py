"""Training speed: seconds per training episode of SDPA-MAPPO beside MLP-MAPPO, same run.

For each setting, a short training run per variant with the MAPPOConfig defaults (one torch
thread, evaluations at their usual interval included, no early stop), timed by the trainer's own
``wall_time_s``::

    paper-3           from scratch on the paper's 3 robots
    paper-5           from scratch on 5 robots
    transfer-3to5     5 robots from a 3-robot checkpoint (``init_from``; the typed actor only:
                      an MLP actor's input is fixed to its N, its row says so)

``s_per_episode`` = wall seconds / training episodes; ``update_share`` = the PPO update's part
of the wall (the rest: rollouts, GAE, evaluations); ``env_steps_per_s`` = environment steps /
wall seconds; ``vs_mlp`` = the row's seconds per episode over the MLP row's on the same robots
(paper-5's for the transfer; the peer measured in the same run: machines are noisy, ratios are
not). Variants run
in turn, repeated ``--repeats`` times, the median kept.

    python bench/train_speed.py                 # table
    python bench/train_speed.py --episodes 96 --json
    -> {"rows": [{"setting", "variant", "s_per_episode", "env_steps_per_s", "vs_mlp", ...}]}
"""

from __future__ import annotations

import argparse
import statistics
import sys
import tempfile
import time
from pathlib import Path

_BENCH = Path(__file__).resolve().parent
for _path in (_BENCH, _BENCH.parent):
    if str(_path) not in sys.path:
        sys.path.insert(0, str(_path))

from _common import add_output_args, positive_int, print_json, print_table, progress, set_threads  # noqa: E402

from controllers.mappo.config import MAPPOConfig  # noqa: E402
from controllers.mappo.trainer import MAPPOTrainer  # noqa: E402

SETTINGS = {"paper-3": ("paper-3", False), "paper-5": ("paper-5", False), "transfer-3to5": ("paper-5", True)}
VARIANTS = {"sdpa": "typed", "mlp": "mlp"}


def timed_run(scenario: str, variant: str, episodes: int, seed: int, init_from: str | None) -> dict:
    """One short training run; its episodes, env steps and wall seconds."""
    fields = {"scenario": scenario, "seed": seed, "total_episodes": episodes, "progress": False,
              "stop_at_convergence": False, "init_from": init_from, "actor": {"variant": variant}}
    if variant == "mlp":                       # as `formation train --variant mlp` sets it
        fields["critic"] = {"variant": "mlp"}
    config = MAPPOConfig.from_dict(fields)
    with tempfile.TemporaryDirectory() as tmp:
        trainer = MAPPOTrainer(config, Path(tmp) / "run")
        update, spent = trainer._update, [0.0]

        def timed_update(*args, **kwargs):   # the profile: the PPO update's share of the wall
            start = time.perf_counter()
            try:
                return update(*args, **kwargs)
            finally:
                spent[0] += time.perf_counter() - start

        trainer._update = timed_update
        result = trainer.run()
    return {"episodes": result.episodes, "env_steps": result.env_steps, "wall_s": result.wall_time_s,
            "update_s": spent[0]}


def source_checkpoint(folder: Path, seed: int) -> str:
    """A 3-robot typed checkpoint to transfer from (a few episodes: the cost is what counts)."""
    config = MAPPOConfig.from_dict({"scenario": "paper-3", "seed": seed, "total_episodes": 16,
                                    "progress": False})
    trainer = MAPPOTrainer(config, folder / "source")
    trainer.run()
    return str(folder / "source" / "checkpoint.pt")


def measure(settings: list[str], episodes: int, repeats: int, seed: int) -> list[dict]:
    rows = []
    with tempfile.TemporaryDirectory() as tmp:
        source = source_checkpoint(Path(tmp), seed) if "transfer-3to5" in settings else None
        for name in settings:
            scenario, transfer = SETTINGS[name]
            runs: dict[str, list[dict]] = {v: [] for v in VARIANTS}
            for k in range(repeats):
                for variant, actor in VARIANTS.items():
                    if transfer and variant == "mlp":
                        continue
                    progress(f"{name} {variant} repeat {k + 1}/{repeats}")
                    runs[variant].append(timed_run(scenario, actor, episodes, seed, source if transfer else None))
            for variant, done in runs.items():
                if not done:
                    rows.append({"setting": name, "variant": variant, "s_per_episode": None,
                                 "env_steps_per_s": None, "note": "an MLP actor cannot start from another N"})
                    continue
                per_episode = statistics.median(r["wall_s"] / r["episodes"] for r in done)
                rate = statistics.median(r["env_steps"] / r["wall_s"] for r in done)
                rows.append({"setting": name, "variant": variant, "s_per_episode": per_episode,
                             "env_steps_per_s": rate, "episodes": done[0]["episodes"], "repeats": len(done),
                             "update_share": statistics.median(r["update_s"] / r["wall_s"] for r in done)})
    for r in rows:              # the peer: MLP-MAPPO on the same robots (paper-5's for a transfer)
        robots = SETTINGS[r["setting"]][0]
        peer = next((m["s_per_episode"] for m in rows if SETTINGS[m["setting"]][0] == robots
                     and m["variant"] == "mlp" and m["s_per_episode"]), None)
        r["vs_mlp"] = r["s_per_episode"] / peer if (peer and r["s_per_episode"]) else None
    return rows


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--settings", default=",".join(SETTINGS),
                        help=f"comma-separated subset of {','.join(SETTINGS)}")
    parser.add_argument("--episodes", type=positive_int, default=96,
                        help="training episodes per timed run (default 96: 6 iterations of 16 "
                             "environments, two evaluations)")
    parser.add_argument("--repeats", type=positive_int, default=3, help="timed runs per variant (median)")
    parser.add_argument("--seed", type=int, default=0)
    add_output_args(parser)
    args = parser.parse_args(argv)
    settings = [s.strip() for s in args.settings.split(",") if s.strip()]
    unknown = [s for s in settings if s not in SETTINGS]
    if unknown or not settings:
        print(f"error: --settings: unknown {unknown or args.settings!r}; choose from {','.join(SETTINGS)}",
              file=sys.stderr)
        return 2
    threads = set_threads(args.threads)
    start = time.perf_counter()
    rows = measure(settings, args.episodes, args.repeats, args.seed)
    doc = {"rows": rows, "threads": threads, "wall_s": time.perf_counter() - start}
    if args.json:
        print_json(doc)
        return 0
    print_table(["setting", "variant", "s / episode", "env steps / s", "vs MLP-MAPPO", "update share"],
                [[r["setting"], r["variant"], "-" if r["s_per_episode"] is None else f"{r['s_per_episode']:.3f}",
                  "-" if r["env_steps_per_s"] is None else f"{r['env_steps_per_s']:.0f}",
                  "-" if r["vs_mlp"] is None else f"{r['vs_mlp']:.2f}x",
                  f"{r['update_share']:.0%}" if r.get("update_share") is not None else "-"] for r in rows])
    return 0


if __name__ == "__main__":
    sys.exit(main())
