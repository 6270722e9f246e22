"""The paper's Table 1 and Table 2, measured here: episodes to convergence over several seeds.

Settings (each trained once per seed of ``--seeds``: a count K for seeds 0..K-1, a range 2-4 or a
list 0,3,7, as ``formation sweep --seeds``; MAPPOConfig defaults otherwise):

    sdpa-3 / sdpa-4 / sdpa-5   SDPA-MAPPO (typed actor) from scratch on paper-3 / -4 / -5
    mlp-3                      MLP-MAPPO (the paper's flat vector, no attention) on paper-3
    transfer-3to4 / -3to5      SDPA-MAPPO on paper-4 / -5 starting from the sdpa-3 run of the
                               same seed (``--init-from`` its final checkpoint)
    maddpg-3, gasil-maddpg-3,  the paper's Table 1 baselines on paper-3 (controllers.baselines:
    ddq-3                      MADDPG and GASIL-MADDPG from TorchRL's pieces, Deep Dyna-Q), their
                               own defaults, the paper's episodes as budget; with sdpa-3 in the
                               run, the measured "SDPA-MAPPO is Nx faster" beside the paper's
                               (``ratios``)

plus the zero-shot success of every sdpa-3 policy on paper-4 and paper-5 (100 deterministic
episodes each, no further training; the mean over seeds is reported).

Convergence is the rule of :mod:`controllers.mappo.evaluate` (100 deterministic episodes at
least every 50 training episodes; the first evaluation with success >= 0.9 whose next one is
also >= 0.9). A seed that does not converge within its budget counts as the budget, and
``converged_seeds`` says how many did. The paper's numbers are printed beside ours.

The runs are Ray Tune trials (:mod:`stack.sweep`, the engine of ``formation sweep``: one CPU
and one torch thread each, ``--cpus`` CPUs), each writing its usual run folder under ``--out``;
a finished run is reused when the table is produced again with the same settings, and an
interrupted one continues from its checkpoint.

    python bench/paper_tables.py                       # 5 seeds, every SDPA/MLP setting
    python bench/paper_tables.py --seeds 2 --settings sdpa-3,transfer-3to5 --json
    python bench/paper_tables.py --seeds 3 --settings sdpa-3,maddpg-3,gasil-maddpg-3,ddq-3 --json
"""

from __future__ import annotations

import argparse
import json
import shutil
import statistics
import sys
import time
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from bench._common import (  # noqa: E402
    json_object,
    positive_float,
    positive_int,
    print_json,
    print_table,
    progress,
)
from stack.commands import argtypes  # noqa: E402
from stack.sweep import SweepError, TrialSpec, resolve_fields, run_trials  # noqa: E402

PAPER_EPISODES = {"sdpa-3": 1200, "sdpa-4": 1500, "sdpa-5": 3200, "mlp-3": None,
                  "transfer-3to4": 650, "transfer-3to5": 850,
                  "maddpg-3": None, "gasil-maddpg-3": 25_000, "ddq-3": 40_000}
PAPER_BASELINES = {"GASIL-MADDPG (3)": 25_000, "Deep Dyna-Q (3)": 40_000}
PAPER_RATIOS = {"gasil-maddpg-3": 20.8, "ddq-3": 33.3}
"""Table 1's "SDPA-MAPPO is Nx faster" (25,000 / 1200 and 40,000 / 1200)."""
SETTINGS = tuple(PAPER_EPISODES)
BASELINE_SETTINGS = ("maddpg-3", "gasil-maddpg-3", "ddq-3")
DEFAULT_SETTINGS = tuple(n for n in SETTINGS if n not in BASELINE_SETTINGS)
"""What runs without ``--settings``: the baselines' budgets are hours of CPU; name them to run them."""
# Budget of each setting: twice the paper's episodes for SDPA-MAPPO (the MLP baseline gets the
# SDPA budget); the paper's own figure for the off-policy baselines (MADDPG, which the paper does
# not time, gets GASIL-MADDPG's): a seed that does not converge counts as the budget, so their
# ratios are lower bounds.
DEFAULT_BUDGET = {"sdpa-3": 2400, "sdpa-4": 3000, "sdpa-5": 6400, "mlp-3": 2400,
                  "transfer-3to4": 1300, "transfer-3to5": 1700,
                  "maddpg-3": 25_000, "gasil-maddpg-3": 25_000, "ddq-3": 40_000}


@dataclass(frozen=True)
class Setting:
    name: str
    scenario: str
    variant: str
    transfer_from: str | None = None   # the setting whose checkpoint seeds this run
    algo: str = "mappo"


def setting(name: str) -> Setting:
    if name in BASELINE_SETTINGS:
        return Setting(name, "paper-3", "", algo=name[:-2])
    if name.startswith("sdpa-"):
        return Setting(name, f"paper-{name[5:]}", "typed")
    if name == "mlp-3":
        return Setting(name, "paper-3", "mlp")
    if name.startswith("transfer-3to"):
        return Setting(name, f"paper-{name[-1]}", "typed", transfer_from="sdpa-3")
    raise ValueError(name)


def settings_list(text: str) -> list[str]:
    names = [s.strip() for s in text.split(",") if s.strip()]
    unknown = [s for s in names if s not in SETTINGS]
    if unknown or not names:
        raise argparse.ArgumentTypeError(f"unknown setting(s) {unknown}; choose from {', '.join(SETTINGS)}")
    return names


def run_dir(out: Path, name: str, seed: int) -> Path:
    return out / name / f"seed-{seed}"


def trial(out: Path, name: str, seed: int, budget: int, config: dict) -> TrialSpec:
    """The sweep trial of one (setting, seed): its resolved fields and run folder."""
    s = setting(name)
    if s.algo != "mappo":      # --config holds MAPPOConfig fields: not the baselines'
        fields = {"algo": s.algo, "scenario": s.scenario, "total_episodes": budget}
        return TrialSpec(name, seed, resolve_fields(fields, {}, seed), str(run_dir(out, name, seed).resolve()))
    fields = {**config, "scenario": s.scenario, "total_episodes": budget,
              "actor": {**config.get("actor", {}), "variant": s.variant}}
    if s.transfer_from:
        fields["init_from"] = str((run_dir(out, s.transfer_from, seed) / "checkpoint.pt").resolve())
    return TrialSpec(name, seed, resolve_fields(fields, {}, seed), str(run_dir(out, name, seed).resolve()))


def train_all(specs: list[TrialSpec], out: Path, cpus: int, phase: str) -> dict[tuple[str, int], dict]:
    """Train ``specs`` as one Ray Tune sweep; a folder of another configuration (other settings,
    budget or config) is this benchmark's cache: it starts afresh."""
    for spec in specs:
        folder = Path(spec.folder)
        config = folder / "config.json"
        if config.exists() and json.loads(config.read_text()) != json.loads(json.dumps(spec.fields)):
            shutil.rmtree(folder)
    results = run_trials(specs, out, cpus=cpus, experiment=phase, restore=False, verbose=0)
    for r in results:
        progress(f"{r['group']} seed {r['seed']}: {'converged at' if r['converged'] else 'not converged within'} "
                 f"{r['episodes']} episodes, {r['wall_s']:.0f} s")
    return {(r["group"], r["seed"]): r for r in results}


def zero_shot(out: Path, seed: int, robots: int, episodes: int = 100) -> float:
    """Success rate of the sdpa-3 policy of ``seed`` on paper-``robots`` without training."""
    import torch

    from controllers.mappo.checkpoint import load_actor
    from controllers.mappo.evaluate import evaluate
    from sim.scenario import make_scenario

    torch.set_num_threads(1)
    actor = load_actor(run_dir(out, "sdpa-3", seed) / "checkpoint.pt", robots)
    return evaluate(actor, make_scenario(f"paper-{robots}"), episodes=episodes, seed=10_000 + seed).success_rate


def row(name: str, seeds: int, runs: list[dict]) -> dict:
    def med(key: str) -> float:
        return float(statistics.median(r[key] for r in runs))

    eps = sorted(r["episodes"] for r in runs)
    return {"setting": name, "seeds": seeds, "converged_seeds": sum(r["converged"] for r in runs),
            "episodes_median": med("episodes"), "env_steps_median": med("env_steps"),
            "wall_s_median": round(med("wall_s"), 1), "episodes_min": eps[0], "episodes_max": eps[-1],
            "episodes": [r["episodes"] for r in runs], "paper_episodes": PAPER_EPISODES[name]}


def ratios(rows: list[dict]) -> list[dict]:
    """Median episodes of each baseline setting over sdpa-3's (both in the rows): ``lower_bound``
    when a baseline seed did not converge (it counts as its budget)."""
    by_name = {r["setting"]: r for r in rows}
    if "sdpa-3" not in by_name:
        return []
    sdpa = by_name["sdpa-3"]["episodes_median"]
    return [{"baseline": name, "ratio": round(by_name[name]["episodes_median"] / sdpa, 2),
             "lower_bound": by_name[name]["converged_seeds"] < by_name[name]["seeds"],
             "paper": PAPER_RATIOS.get(name)} for name in BASELINE_SETTINGS if name in by_name]


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(allow_abbrev=False, description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--seeds", type=argtypes.seeds, default=list(range(5)),
                   help="seeds of every setting: a count (5: seeds 0-4), a range (2-4) or a list (0,3,7) "
                        "(default 5)")
    p.add_argument("--settings", type=settings_list, default=list(DEFAULT_SETTINGS),
                   help=f"comma-separated subset of {','.join(SETTINGS)} (transfer needs sdpa-3; "
                        f"default: {','.join(DEFAULT_SETTINGS)})")
    p.add_argument("--cpus", type=positive_int, default=2,
                   help="CPUs of the local Ray: trials at a time (default 2)")
    argtypes.add_deprecated_alias(p, "--jobs", "--cpus")
    p.add_argument("--budget-scale", type=positive_float, default=1.0,
                   help="multiply every episode budget (default budgets: twice the paper's episodes)")
    p.add_argument("--config", type=json_object, default={}, metavar="JSON",
                   help="extra MAPPOConfig fields as JSON for every SDPA/MLP run (default {}: none)")
    p.add_argument("--out", type=argtypes.out_folder, default=Path("runs/paper-tables"),
                   help="folder of the runs (default runs/paper-tables)")
    p.add_argument("--json", action="store_true", help="print one JSON document instead of the table")
    args = p.parse_args(argv)
    config = args.config
    names = list(args.settings)
    if any(setting(n).transfer_from for n in names) and "sdpa-3" not in names:
        names.insert(0, "sdpa-3")
    budgets = {n: max(50, int(DEFAULT_BUDGET[n] * args.budget_scale)) for n in names}
    seeds = args.seeds
    start = time.perf_counter()
    results: dict[str, list[dict]] = {n: [] for n in names}

    transfers = [n for n in names if setting(n).transfer_from]
    scratch = [n for n in names if not setting(n).transfer_from]
    try:      # every trial checked before any training: a bad --config is a usage error
        scratch_specs = [trial(args.out, n, s, budgets[n], config) for n in scratch for s in seeds]
        transfer_specs = [trial(args.out, n, s, budgets[n], config) for n in transfers for s in seeds]
    except SweepError as exc:
        p.error(f"--config: {str(exc).removeprefix('the base config: ')}")
    # from-scratch settings first (sdpa-3 among them), then the transfers from sdpa-3's checkpoints
    done = train_all(scratch_specs, args.out, args.cpus, "scratch")
    if transfers:
        done |= train_all(transfer_specs, args.out, args.cpus, "transfer")
    for (name, _seed), r in sorted(done.items(), key=lambda kv: kv[0][1]):
        results[name].append(r)
    zero = {}
    if "sdpa-3" in names:
        with ThreadPoolExecutor(args.cpus) as pool:
            for robots in (4, 5):
                rates = list(pool.map(lambda s, k=robots: zero_shot(args.out, s, k), seeds))
                zero[f"3to{robots}"] = round(statistics.fmean(rates), 3)
    rows = [row(n, len(seeds), results[n]) for n in names]
    doc = {"rows": rows, "zero_shot": zero, "paper_baselines": PAPER_BASELINES,
           "ratios": ratios(rows), "budgets": budgets, "config": config,
           "wall_s_total": round(time.perf_counter() - start, 1)}
    if args.json:
        print_json(doc)
        return 0
    print_table(["setting", "converged", "episodes median", "min-max", "env steps median", "wall s median",
                 "paper"],
                [[r["setting"], f"{r['converged_seeds']}/{r['seeds']}", f"{r['episodes_median']:.0f}",
                  f"{r['episodes_min']}-{r['episodes_max']}", f"{r['env_steps_median']:.0f}",
                  f"{r['wall_s_median']:.0f}", r["paper_episodes"] or "-"] for r in rows])
    for key, value in zero.items():
        print(f"zero-shot success {key}: {value:.2f} (mean over {len(seeds)} seeds, 100 episodes each)")
    for r in doc["ratios"]:
        bound = "at least " if r["lower_bound"] else ""
        paper = f" (paper: {r['paper']}x)" if r["paper"] else ""
        print(f"SDPA-MAPPO is {bound}{r['ratio']:.1f}x faster than {r['baseline']} here, in median episodes{paper}")
    print("paper baselines (3 robots): " + ", ".join(f"{k} {v}" for k, v in PAPER_BASELINES.items()))
    return 0


if __name__ == "__main__":
    sys.exit(main())
