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
(paper-5's for the transfer: without paper-5 in ``--settings`` its MLP row alone is timed too;
the peer is measured in the same run: machines are noisy, ratios are not). Variants run
in turn, repeated ``--repeats`` times, the median kept.

The arithmetic floor: ``update_gflop_per_episode`` = the floating-point operations of the PPO
update per training episode (every epoch and minibatch, forward and backward of actor and
critic: matrix products and attention, counted by ``torch.utils.flop_counter`` on the first
update of an untimed run); ``update_floor_s_per_episode`` = that over the rate of a 512 x 512
matrix product on this machine and thread count (``matmul_gflop_s``: the most these networks'
products could reach, with no overhead at all); ``floor_vs_mlp`` = that floor over the MLP
row's *whole* seconds per episode. A ``floor_vs_mlp`` above a target ratio means no kernel work
can reach it with these networks on this machine.

    python bench/train_speed.py                 # table
    python bench/train_speed.py --episodes 96 --json
    -> {"rows": [{"setting", "variant", "s_per_episode", "env_steps_per_s", "vs_mlp",
                  "update_gflop_per_episode", "update_floor_s_per_episode", "floor_vs_mlp", ...}],
        "matmul_gflop_s": ...}
"""

from __future__ import annotations

import argparse
import math
import statistics
import sys
import tempfile
import time
from collections.abc import Callable
from contextlib import AbstractContextManager, contextmanager
from pathlib import Path

import torch
from torch.utils.flop_counter import FlopCounterMode

_BENCH = Path(__file__).resolve().parent
for _path in (_BENCH, _BENCH.parent):
    if str(_path) not in sys.path:
        sys.path.insert(0, str(_path))

from _common import (  # noqa: E402
    add_output_args,
    add_seed_arg,
    positive_int,
    print_json,
    print_table,
    progress,
    set_threads,
)

from controllers.mappo.config import MAPPOConfig  # noqa: E402
from controllers.mappo.trainer import MAPPOTrainer  # noqa: E402

SETTINGS = {"paper-3": ("paper-3", False), "paper-5": ("paper-5", False), "transfer-3to5": ("paper-5", True)}
VARIANTS = {"sdpa": "typed", "mlp": "mlp"}


def run_config(scenario: str, variant: str, episodes: int, seed: int, init_from: str | None) -> MAPPOConfig:
    """The defaults, with the actor (and for MLP-MAPPO the critic) of ``variant``."""
    fields = {"scenario": scenario, "seed": seed, "total_episodes": episodes, "progress": False,
              "stop_at_convergence": False, "init_from": init_from, "actor": {"variant": variant}}
    if variant == "mlp":                       # as `formation train --variant mlp` sets it
        fields["critic"] = {"variant": "mlp"}
    return MAPPOConfig.from_dict(fields)


def around_update(trainer: MAPPOTrainer, context: Callable[[], AbstractContextManager]) -> None:
    """Run every PPO update of ``trainer`` inside a fresh ``context()``."""
    update = trainer._update

    def wrapped(*args, **kwargs):
        with context():
            return update(*args, **kwargs)

    trainer._update = wrapped


@contextmanager
def adding_time_to(spent: list[float]):
    """Add the seconds spent inside to ``spent[0]``."""
    start = time.perf_counter()
    try:
        yield
    finally:
        spent[0] += time.perf_counter() - start


def update_flops(config: MAPPOConfig) -> tuple[int, int]:
    """(FLOPs of one PPO update, environment steps of the rollout it learns from): the first
    iteration of an untimed run, its update under ``FlopCounterMode``."""
    counters: list[FlopCounterMode] = []

    def counter() -> FlopCounterMode:
        counters.append(FlopCounterMode(display=False))
        return counters[-1]

    with tempfile.TemporaryDirectory() as tmp:
        trainer = MAPPOTrainer(config, Path(tmp) / "run")
        around_update(trainer, counter)
        trainer._iteration()
        return counters[0].get_total_flops(), trainer.env_steps


def matmul_rate(size: int = 512, reps: int = 40) -> float:
    """FLOP/s of a ``size`` x ``size`` matrix product on this machine's torch threads, best of 3."""
    a, b = torch.randn(size, size), torch.randn(size, size)
    a @ b
    best = math.inf
    for _ in range(3):
        start = time.perf_counter()
        for _ in range(reps):
            a @ b
        best = min(best, time.perf_counter() - start)
    return 2 * size**3 * reps / best


def timed_run(scenario: str, variant: str, episodes: int, seed: int, init_from: str | None) -> dict:
    """One short training run; its episodes, env steps and wall seconds."""
    config = run_config(scenario, variant, episodes, seed, init_from)
    with tempfile.TemporaryDirectory() as tmp:
        trainer = MAPPOTrainer(config, Path(tmp) / "run")
        spent = [0.0]                       # the profile: the PPO update's share of the wall
        around_update(trainer, lambda: adding_time_to(spent))
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


def plan(settings: list[str]) -> list[tuple[str, tuple[str, ...]]]:
    """(setting, variants to time) in order. A transfer's peer is paper-5's MLP row: without
    paper-5 among ``settings``, that row alone is timed first."""
    jobs = [(name, tuple(VARIANTS)) for name in settings]
    if "transfer-3to5" in settings and "paper-5" not in settings:
        jobs.insert(settings.index("transfer-3to5"), ("paper-5", ("mlp",)))
    return jobs


def measure(settings: list[str], episodes: int, repeats: int, seed: int) -> tuple[list[dict], float]:
    """The rows, and the matrix-product rate [FLOP/s] their floors are worked from."""
    rows, rate_flops = [], matmul_rate()
    with tempfile.TemporaryDirectory() as tmp:
        source = source_checkpoint(Path(tmp), seed) if "transfer-3to5" in settings else None
        for name, variants in plan(settings):
            scenario, transfer = SETTINGS[name]
            runs: dict[str, list[dict]] = {v: [] for v in variants}
            for k in range(repeats):
                for variant in variants:
                    actor = VARIANTS[variant]
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
                flops, flop_steps = update_flops(run_config(scenario, VARIANTS[variant], episodes, seed,
                                                            source if transfer else None))
                gflop = flops / flop_steps * done[0]["env_steps"] / done[0]["episodes"] / 1e9
                rows.append({"setting": name, "variant": variant, "s_per_episode": per_episode,
                             "env_steps_per_s": rate, "episodes": done[0]["episodes"], "repeats": len(done),
                             "update_share": statistics.median(r["update_s"] / r["wall_s"] for r in done),
                             "update_gflop_per_episode": gflop,
                             "update_floor_s_per_episode": gflop * 1e9 / rate_flops})
                if name not in settings:
                    rows[-1]["note"] = "timed as the peer of transfer-3to5"
    for r in rows:              # the peer: MLP-MAPPO on the same robots (paper-5's for a transfer)
        robots = SETTINGS[r["setting"]][0]
        peer = next((m["s_per_episode"] for m in rows if SETTINGS[m["setting"]][0] == robots
                     and m["variant"] == "mlp" and m["s_per_episode"]), None)
        r["vs_mlp"] = r["s_per_episode"] / peer if (peer and r["s_per_episode"]) else None
        floor = r.get("update_floor_s_per_episode")
        r["floor_vs_mlp"] = floor / peer if (peer and floor) else None
    return rows, rate_flops


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(allow_abbrev=False, description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--settings", default=",".join(SETTINGS),
                        help=f"comma-separated subset of {','.join(SETTINGS)} (default: all of them)")
    parser.add_argument("--episodes", type=positive_int, default=96,
                        help="training episodes per timed run (default 96: 6 iterations of 16 "
                             "environments, two evaluations)")
    parser.add_argument("--repeats", type=positive_int, default=3,
                        help="timed runs per variant; the median is reported (default 3)")
    add_seed_arg(parser, "every timed training run (MAPPOConfig.seed)")
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
    rows, rate_flops = measure(settings, args.episodes, args.repeats, args.seed)
    doc = {"rows": rows, "threads": threads, "matmul_gflop_s": rate_flops / 1e9,
           "wall_s": time.perf_counter() - start}
    if args.json:
        print_json(doc)
        return 0

    def cell(row: dict, key: str, fmt: str) -> str:
        return "-" if row.get(key) is None else format(row[key], fmt)

    print_table(["setting", "variant", "s / episode", "env steps / s", "vs MLP-MAPPO", "update share",
                 "update GFLOP / episode", "update floor s / episode", "floor vs MLP-MAPPO"],
                [[r["setting"], r["variant"], cell(r, "s_per_episode", ".3f"), cell(r, "env_steps_per_s", ".0f"),
                  cell(r, "vs_mlp", ".2f") + "x" * (r["vs_mlp"] is not None), cell(r, "update_share", ".0%"),
                  cell(r, "update_gflop_per_episode", ".2f"), cell(r, "update_floor_s_per_episode", ".4f"),
                  cell(r, "floor_vs_mlp", ".2f") + "x" * (r.get("floor_vs_mlp") is not None)] for r in rows])
    print(f"matrix products here: {rate_flops / 1e9:.1f} GFLOP/s ({threads} thread(s)); the floor is the "
          "update's arithmetic at that rate, with no overhead")
    return 0


if __name__ == "__main__":
    sys.exit(main())
