"""The learning stages of the demo: train paper-3, transfer to paper-5 (+ zero-shot), export.

Every stage returns a JSON-able result dict that goes into ``stages.json``; paths in it are
relative to the demo folder ``out``.

Training uses the MAPPOConfig defaults (network, PPO and reward settings); the demo sets only
the scenario, the episode budget, the seed, the run folder and (``--quick``) the evaluation size.
Training stops at convergence (:mod:`controllers.mappo.evaluate`: the first evaluation with
success >= 0.9 whose next one is also >= 0.9) or at the budget. An interrupted stage continues
from its ``checkpoint.pt`` with the run's own ``config.json`` (so a changed default elsewhere
never breaks a resume); a run folder without a checkpoint is started again.
"""

from __future__ import annotations

import json
import shutil
from pathlib import Path
from typing import Any

from tqdm import tqdm

from stack.demo.state import DemoError, DemoSettings

SCENARIOS = {"3": "paper-3", "5": "paper-5"}
CHECKPOINT = "checkpoint.pt"
POLICY_STEM = "policy"
POLICY = "policy.onnx"       # what the fleet stage runs: numpy + onnxruntime on a robot


def run_dir(out: Path, robots: str) -> Path:
    """Folder of the training run for ``robots`` ("3" or "5")."""
    return out / f"train-{robots}"


def train_config(settings: DemoSettings, robots: str, out: Path):
    """MAPPOConfig of a fresh training run (defaults plus budget, seed, evaluation size)."""
    from controllers.mappo import MAPPOConfig

    fields: dict[str, Any] = {"scenario": SCENARIOS[robots], "seed": settings.seed,
                              "total_episodes": settings.budget_3 if robots == "3" else settings.budget_5,
                              "stop_at_convergence": True, "progress": True}
    if settings.eval_episodes is not None:
        fields["eval_episodes"] = settings.eval_episodes
    if settings.eval_interval is not None:
        fields["eval_interval"] = settings.eval_interval
    if robots == "5":
        fields["init_from"] = str((run_dir(out, "3") / CHECKPOINT).resolve())
    return MAPPOConfig.from_dict(fields)


def train_stage(settings: DemoSettings, robots: str, out: Path) -> dict[str, Any]:
    """Train (or continue) the run of ``robots`` until convergence or the budget."""
    from controllers.mappo import MAPPOConfig, TrainConfigError, train

    folder = run_dir(out, robots)
    budget = settings.budget_3 if robots == "3" else settings.budget_5
    if (folder / CHECKPOINT).is_file():
        saved = json.loads((folder / "config.json").read_text())
        config = MAPPOConfig.from_dict({**saved, "total_episodes": budget, "progress": True})
        resume = True
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
    return {"scenario": config.scenario_name, "num_robots": int(robots), "budget": budget,
            "episodes": result.episodes, "iterations": result.iterations, "env_steps": result.env_steps,
            "converged_episode": result.converged_episode,
            "converged": result.converged_episode is not None,
            "success": last.get("success_rate"), "final_distance": last.get("final_distance"),
            "episode_return": last.get("episode_return"), "collision_rate": last.get("collision_rate"),
            "eval_episodes": config.eval_episodes, "eval_interval": config.eval_interval,
            "success_threshold": config.success_threshold, "wall_time_s": result.wall_time_s,
            "run_dir": folder.name, "checkpoint": f"{folder.name}/{CHECKPOINT}",
            "init_from": "train-3/checkpoint.pt" if robots == "5" else None}


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


def export_stage(settings: DemoSettings, out: Path) -> dict[str, Any]:
    """Export the 5-robot actor as TorchScript, torch.export and ONNX (each verified against the
    eager actor for N = 1..21), then re-check every file against the golden file as a robot
    would. The fleet stage runs the ONNX file (:data:`POLICY`)."""
    from deploy.export import TOLERANCE, ExportError, check_export, export_checkpoint

    with tqdm(total=2, unit="step", desc="export torchscript, pt2, onnx", dynamic_ncols=True) as bar:
        try:
            exported = export_checkpoint(run_dir(out, "5") / CHECKPOINT, out / POLICY_STEM,
                                         seed=settings.seed)
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


__all__ = ["POLICY", "POLICY_STEM", "export_stage", "run_dir", "train_config", "train_stage", "transfer_stage",
           "zero_shot"]
