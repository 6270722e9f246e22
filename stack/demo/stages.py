"""The learning stages of the demo: train paper-3, transfer to paper-5 (+ zero-shot), export,
and the generalist (one policy trained on 3, 4 and 5 robots; its zero-shot table; its export).

Every stage returns a JSON-able result dict that goes into ``stages.json``; paths in it are
relative to the demo folder ``out``.

Training uses the MAPPOConfig defaults (network, PPO and reward settings), with four PPO epochs
a rollout in the stages the demo waits on (:data:`FAST_FIELDS`) and the generalist's settings
(:data:`GENERALIST_FIELDS`); the demo sets the scenario, the episode budget, the seed, the run
folder and (``--quick``) the evaluation size.
Training stops at convergence (:mod:`controllers.mappo.evaluate`: the first evaluation with
success >= 0.9 whose next one is also >= 0.9) or at the budget. An interrupted stage continues
from its ``checkpoint.pt`` with the run's own ``config.json`` (so a changed default elsewhere
never breaks a resume); a run folder without a checkpoint is started again.
"""

from __future__ import annotations

import contextlib
import json
import shutil
import subprocess
import sys
import time
from pathlib import Path
from typing import Any

from tqdm import tqdm

from stack.demo.state import Children, DemoError, DemoSettings

SCENARIOS = {"3": "paper-3", "5": "paper-5", "generalist": "paper-3"}
FAST_FIELDS = {"update_epochs": 4}
"""Settings of the stages the demo waits on (paper-3, which the transfer starts from, and the
generalist) beside the MAPPOConfig defaults: four passes over each rollout in place of ten, the
fast recipe of docs/learning.md (``bench/paper_tables.py --config '{"update_epochs": 4}'``, 5
seeds: paper-3 median 624 episodes in 45.9 s against 960 in 175 s at ten, every seed converged).
Seed 0 on an AMD EPYC: paper-3 at 864 episodes in 169 s, against 2112 in 686 s at ten. The
transfer to paper-5 keeps the default ten (from that checkpoint: 720 episodes against 1440 at
four); it trains beside the generalist, which takes longer. The training default stays ten
because the MLP baseline converges in 2 of 5 seeds at four."""
GENERALIST_TEAM_SIZES = (3, 4, 5)
GENERALIST_FIELDS = {"team_sizes": list(GENERALIST_TEAM_SIZES), **FAST_FIELDS, "penalty_curriculum": 3.0}
"""The generalist's settings beside the MAPPOConfig defaults: those of ``bench/generalization.py``
(4 PPO epochs; the contact-penalty curriculum, with which every seed of it converged). The demo
trains it from scratch in a child process that starts with paper-3, so it waits for nothing.
From the 3-robot checkpoint it took 624, 1536 and 1824 episodes on seeds 0-2 (2026-12-03, Intel
Xeon), from scratch 1872, 1488 and 1296. On an AMD EPYC (2026-12-07, two runs at a time), from
the four-epoch 3-robot checkpoint against from scratch: seed 0 2256 episodes in 595 s (after
paper-3's 154 s) against 1536 in 396 s, seed 1 1968 in 533 s against 1248 in 351 s. Both of
seed 0's policies bring 20 of 20 unseen 6-robot teams home through the stack (``formation eval
--world pymunk --scenario transport-6``, the demo's model error)."""
ZERO_SHOT_ROBOTS = tuple(range(1, 9))   # the generalist's table: trained on 3-5, the rest unseen
UNSEEN_ROBOTS = max(GENERALIST_TEAM_SIZES) + 1   # the fleet-unseen stage's team size
CHECKPOINT = "checkpoint.pt"
POLICY_STEM = "policy"
POLICY = "policy.onnx"       # what the fleet stage runs: numpy + onnxruntime on a robot
GENERALIST_DIR = "generalist"   # the generalist's exported policy and golden file
GENERALIST_LOG = "train-generalist.log"   # output of its background training


def run_dir(out: Path, robots: str) -> Path:
    """Folder of the training run for ``robots`` ("3", "5" or "generalist")."""
    return out / f"train-{robots}"


def budget(settings: DemoSettings, robots: str) -> int:
    return {"3": settings.budget_3, "5": settings.budget_5, "generalist": settings.budget_generalist}[robots]


def train_config(settings: DemoSettings, robots: str, out: Path):
    """MAPPOConfig of a fresh training run (defaults plus budget, seed, evaluation size)."""
    from controllers.mappo import MAPPOConfig

    fields: dict[str, Any] = {"scenario": SCENARIOS[robots], "seed": settings.seed,
                              "total_episodes": budget(settings, robots),
                              "stop_at_convergence": True, "progress": True}
    fields.update({"3": FAST_FIELDS, "5": {}, "generalist": GENERALIST_FIELDS}[robots])
    if settings.eval_episodes is not None:
        fields["eval_episodes"] = settings.eval_episodes
    if settings.eval_interval is not None:
        fields["eval_interval"] = settings.eval_interval
    if robots == "5":          # the transfer starts from the 3-robot policy
        fields["init_from"] = str((run_dir(out, "3") / CHECKPOINT).resolve())
    return MAPPOConfig.from_dict(fields)


def train_stage(settings: DemoSettings, robots: str, out: Path, announce: bool = True) -> dict[str, Any]:
    """Train (or continue) the run of ``robots`` until convergence or the budget (a run that
    got there already returns at once); ``announce``: say that an earlier run continues."""
    from controllers.mappo import MAPPOConfig, TrainConfigError, train

    folder = run_dir(out, robots)
    cap = budget(settings, robots)
    if (folder / CHECKPOINT).is_file():
        saved = json.loads((folder / "config.json").read_text())
        config = MAPPOConfig.from_dict({**saved, "total_episodes": cap, "progress": True})
        resume = True
        if announce:
            print(f"continuing the interrupted run in {folder} from its checkpoint", flush=True)
    else:
        if folder.exists():
            shutil.rmtree(folder)   # logs of a run stopped before its first checkpoint
        config = train_config(settings, robots, out)
        resume = False
    try:
        result = train(config, folder, resume=resume)
    except TrainConfigError as exc:
        raise DemoError(f"training {config.scenario_name} failed to start: {exc}") from None
    last = result.last_eval or {}
    return {"scenario": config.scenario_name, "num_robots": list(config.team_sizes) or int(robots),
            "budget": cap,
            "episodes": result.episodes, "iterations": result.iterations, "env_steps": result.env_steps,
            "converged_episode": result.converged_episode,
            "converged": result.converged_episode is not None,
            "success": last.get("success_rate"), "final_distance": last.get("final_distance"),
            "episode_return": last.get("episode_return"), "collision_rate": last.get("collision_rate"),
            "eval_episodes": config.eval_episodes, "eval_interval": config.eval_interval,
            "success_threshold": config.success_threshold, "wall_time_s": result.wall_time_s,
            "run_dir": folder.name, "checkpoint": f"{folder.name}/{CHECKPOINT}",
            "init_from": f"{run_dir(out, '3').name}/{CHECKPOINT}" if config.init_from else None}


def zero_shot(settings: DemoSettings, out: Path) -> dict[str, Any]:
    """Success of the finished 3-robot policy on paper-5 without further training."""
    from controllers.mappo import evaluate, load_actor
    from sim.scenario import make_scenario

    seed = 2_000_000 + settings.seed
    actor = load_actor(run_dir(out, "3") / CHECKPOINT, num_robots=5)
    result = evaluate(actor, make_scenario(SCENARIOS["5"]), episodes=settings.zero_shot_episodes,
                      seed=seed)
    return {"success": result.success_rate, "final_distance": result.final_distance,
            "collision_rate": result.collision_rate, "episodes": result.episodes, "seed": seed}


def transfer_stage(settings: DemoSettings, out: Path) -> dict[str, Any]:
    """Zero-shot evaluation of the 3-robot policy on 5 robots, then transfer training."""
    with tqdm(total=settings.zero_shot_episodes, unit="ep", desc="zero-shot paper-3 -> paper-5",
              dynamic_ncols=True) as bar:
        shot = zero_shot(settings, out)
        bar.update(settings.zero_shot_episodes)
        bar.set_postfix(success=f"{shot['success']:.2f}")
    result = train_stage(settings, "5", out)
    result["zero_shot"] = shot
    return result


DEMO_FORMATS = ("torchscript", "pt2", "onnx")
"""What the demo exports: its fleet runs the ONNX file; npz (``formation export`` writes it too)
would add its kernel's one-time compile (~13 s on a fresh machine) to the demo's 15 minutes."""


def export_stage(settings: DemoSettings, out: Path) -> dict[str, Any]:
    """Export the 5-robot actor as TorchScript, torch.export and ONNX (:data:`DEMO_FORMATS`, each
    verified against the eager actor for N = 1..21), then re-check every file against the golden
    file as a robot would. The fleet stage runs the ONNX file (:data:`POLICY`)."""
    from deploy.export import TOLERANCE, ExportError, check_export, export_checkpoint

    with tqdm(total=2, unit="step", desc="export torchscript, pt2, onnx", dynamic_ncols=True) as bar:
        try:
            exported = export_checkpoint(run_dir(out, "5") / CHECKPOINT, out / POLICY_STEM,
                                         formats=DEMO_FORMATS, seed=settings.seed)
            bar.update(1)
            checked = [check_export(report.path) for report in exported]
            bar.update(1)
        except ExportError as exc:
            raise DemoError(f"export failed: {exc}") from None
    by_format = {r.meta["file_format"]: max(r.max_abs_diff, c.max_abs_diff)
                 for r, c in zip(exported, checked, strict=True)}
    worst = max(by_format.values())
    return {"policy": POLICY, "golden": exported[0].golden.name, "verified": bool(worst <= TOLERANCE),
            "files": {r.meta["file_format"]: r.path.name for r in exported},
            "max_abs_diff": worst, "max_abs_diff_by_format": by_format, "tolerance": TOLERANCE,
            "comparisons": sum(r.cases for r in exported) + sum(c.cases for c in checked),
            "robot_counts": exported[0].meta["robot_counts"],
            "content_sha256": {r.meta["file_format"]: r.meta["content_sha256"] for r in exported}}


def zero_shot_table(settings: DemoSettings, checkpoint: Path) -> list[dict[str, Any]]:
    """The generalist on the default layout of each team size of :data:`ZERO_SHOT_ROBOTS`
    (:func:`sim.scenario.transport_scenario`; 3-5 are paper-3..5), deterministic, batched world."""
    from controllers.mappo import evaluate, load_actor
    from sim.scenario import transport_scenario

    actor = load_actor(checkpoint)
    seed = 3_000_000 + settings.seed
    rows = []
    with tqdm(ZERO_SHOT_ROBOTS, unit="N", desc="generalist zero-shot table", dynamic_ncols=True) as bar:
        for n in bar:
            r = evaluate(actor, transport_scenario(n), episodes=settings.zero_shot_episodes, seed=seed)
            rows.append({"robots": n, "trained": n in GENERALIST_TEAM_SIZES, "success": r.success_rate,
                         "collision_rate": r.collision_rate, "final_distance": r.final_distance,
                         "episodes": r.episodes})
            bar.set_postfix(N=n, success=f"{r.success_rate:.2f}")
    return rows


def start_generalist(out: Path, children: Children) -> subprocess.Popen:
    """Start the generalist's training in a child process (``python -m stack.demo.stages OUT``),
    so that it runs on the second core beside paper-3 and the transfer to paper-5 (the demo's own
    process trains on one thread); its output goes to ``train-generalist.log``."""
    with (out / GENERALIST_LOG).open("w") as log:
        return children.spawn([sys.executable, "-m", "stack.demo.stages", str(out)],
                              stdout=log, stderr=subprocess.STDOUT)


def _wait_for_generalist(child: subprocess.Popen, settings: DemoSettings, out: Path,
                         children: Children) -> None:
    """Wait for the background training, with a bar of its episodes (from its train.jsonl)."""
    rows = run_dir(out, "generalist") / "train.jsonl"
    cap = budget(settings, "generalist")
    with tqdm(total=cap, unit="ep", desc="generalist training (background)", dynamic_ncols=True) as bar:
        while child.poll() is None:
            time.sleep(1.0)
            with contextlib.suppress(OSError, ValueError, IndexError):
                lines = rows.read_text().splitlines()
                bar.update(min(cap, json.loads(lines[-1])["episodes"]) - bar.n)
    children.forget(child)
    if child.returncode != 0:
        tail = "".join((out / GENERALIST_LOG).read_text(errors="replace").splitlines(True)[-20:])
        raise DemoError(f"the generalist's training exited with code {child.returncode}; its log "
                        f"({out / GENERALIST_LOG}):\n{tail}")


def generalist_stage(settings: DemoSettings, out: Path, child: subprocess.Popen | None = None,
                     children: Children | None = None) -> dict[str, Any]:
    """Train one policy on 3, 4 and 5 robots at once from scratch (or wait for
    ``child``, the training :func:`start_generalist` started), judge it zero-shot on 1..8 robots,
    and export it into ``generalist/`` (golden file on the scenario it trained on)."""
    from deploy.export import TOLERANCE, ExportError, export_checkpoint

    if child is not None:
        _wait_for_generalist(child, settings, out, children or Children())
    result = train_stage(settings, "generalist", out, announce=child is None)
    checkpoint = run_dir(out, "generalist") / CHECKPOINT
    result["zero_shot_table"] = zero_shot_table(settings, checkpoint)
    folder = out / GENERALIST_DIR
    folder.mkdir(exist_ok=True)
    try:
        exported = export_checkpoint(checkpoint, folder / POLICY_STEM, formats=("onnx",), seed=settings.seed)
    except ExportError as exc:
        raise DemoError(f"export of the generalist failed: {exc}") from None
    result["export"] = {"policy": f"{GENERALIST_DIR}/{POLICY}", "max_abs_diff": exported[0].max_abs_diff,
                        "verified": bool(exported[0].max_abs_diff <= TOLERANCE), "tolerance": TOLERANCE}
    return result


def main(argv: list[str] | None = None) -> int:
    """``python -m stack.demo.stages OUT``: train (or continue) the generalist of the demo in OUT
    with the settings of its ``stages.json`` (the demo's background child)."""
    import torch

    from stack.demo.state import StageBook

    torch.set_num_threads(1)
    out = Path((argv or sys.argv[1:])[0])
    train_stage(StageBook.load(out).settings, "generalist", out)
    return 0


__all__ = ["GENERALIST_DIR", "GENERALIST_LOG", "POLICY", "POLICY_STEM", "UNSEEN_ROBOTS", "ZERO_SHOT_ROBOTS",
           "export_stage", "generalist_stage", "run_dir", "start_generalist", "train_config", "train_stage",
           "transfer_stage", "zero_shot", "zero_shot_table"]


if __name__ == "__main__":
    sys.exit(main())
