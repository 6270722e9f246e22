"""The demo's outputs: ``metrics.json``, the figures, ``report.md`` and ``report.html``.

``metrics.json`` is rewritten after every stage (``"complete": false`` until the report stage),
so a stopped run keeps what it measured. Its keys (numbers as in ``stages.json``)::

    train.{"3","5","generalist"}  converged_episode (None: not converged), converged, success
                      (last evaluation's success rate), final_distance [m], episodes, budget,
                      ...; the generalist's also export {policy, max_abs_diff, verified}
    zero_shot_3to5    success rate of the 3-robot policy on paper-5 without training
    zero_shot         its details (episodes, final distance, seed)
    export            verified, files by format, max_abs_diff (max |file - eager|, and by format), ...
    fleet             episodes, success_rate, final_distance [m], collisions (onsets),
                      interventions (ticks the safety filter changed a command),
                      tracking_error_m, tick_ms / round_trip_ms {p50, p99}, per_episode [...]
    zero_shot_table   the generalist on 1..8 robots: [{robots, trained, success, collision_rate,
                      final_distance, episodes}, ...]
    fleet_unseen      as ``fleet``, the generalist on a team size it never trained on
    paper             the paper's numbers (PAPER)

The report is one list of blocks rendered twice: Markdown (figures linked as PNG files beside
it) and HTML (figures embedded as base64 data URIs, one self-contained file).
"""

from __future__ import annotations

import base64
import html
import os
import platform
import time
from pathlib import Path
from typing import Any

from tqdm import tqdm

from sim.provenance import provenance
from stack.demo.state import STAGES, StageBook, write_atomic, write_json

METRICS_FORMAT = "formation-stack/demo-metrics"
PAPER_SUCCESS = "all robots reach their targets (Figs. 11-13, 19-20)"
FIGURES = {"curves": "training_curves.png", "trajectories": "fleet_trajectories.png",
           "attention": "attention.png", "unseen": "fleet_unseen_trajectories.png"}

# The paper (Accelerated Transfer Learning for Cooperative Transportation Formation Change via
# SDPA-MAPPO): Table 1, Table 2, Sections 3.2 and 4.4.
PAPER = {
    "converged_episode_3": 1200,            # Table 1, SDPA(3)
    "converged_episode_5_scratch": 3200,    # Tables 1 and 2
    "converged_episode_5_transfer": 850,    # Table 2
    "final_distance_3_m": 0.0004,           # Section 3.2: 0.4 mm after about 1000 episodes
    "success": "all robots reach their targets (Figures 11-13, 19-20)",
    "zero_shot_3to5": None,                 # not reported
    "fleet": None,                          # no pymunk world, safety layer, MEC or Zenoh
}


# ------------------------------------------------------------------ metrics
def build_metrics(book: StageBook, *, complete: bool = False) -> dict[str, Any]:
    """``metrics.json`` from the finished stages of ``book`` (see the module docstring)."""
    import torch

    metrics: dict[str, Any] = {
        "format": METRICS_FORMAT, "version": 1, "complete": complete,
        "settings": book.settings.to_dict(),
        "stages": {name: {"done": book.done(name), "wall_s": book.stages.get(name, {}).get("wall_s")}
                   for name in STAGES},
        "train": {}, "paper": PAPER,
        "environment": {"python": platform.python_version(), "torch": torch.__version__,
                        "cpus": os.cpu_count(), "machine": platform.machine()},
        "provenance": provenance(),
    }
    for robots in ("3", "5"):
        if book.done(f"train-{robots}"):
            result = dict(book.result(f"train-{robots}"))
            shot = result.pop("zero_shot", None)
            metrics["train"][robots] = result
            if shot is not None:
                metrics["zero_shot_3to5"] = shot["success"]
                metrics["zero_shot"] = shot
    if book.done("generalist"):
        result = dict(book.result("generalist"))
        metrics["zero_shot_table"] = result.pop("zero_shot_table")
        metrics["train"]["generalist"] = result
    for stage, key in (("export", "export"), ("fleet", "fleet"), ("fleet-unseen", "fleet_unseen")):
        if book.done(stage):
            metrics[key] = book.result(stage)
    return metrics


def save_metrics(book: StageBook, *, complete: bool = False) -> Path:
    path = book.out / "metrics.json"
    write_json(path, build_metrics(book, complete=complete))
    return path


# ------------------------------------------------------------------ figures
def fleet_trajectories(out: Path, folder: str = "fleet"):
    """:class:`stack.plots.Trajectories` of a fleet stage's episodes (true positions, ``folder/sim.json``)."""
    import json

    import numpy as np

    from stack.plots import Trajectories

    episodes = json.loads((out / folder / "sim.json").read_text())["episodes"]
    return Trajectories(positions=np.asarray([e["positions"] for e in episodes], dtype=np.float64),
                        contacts=np.asarray([e["contacts"] for e in episodes], dtype=bool),
                        success=np.asarray([e["success"] for e in episodes]),
                        final_distance=np.asarray([e["final_distance"] for e in episodes]),
                        assignment=np.asarray([e["assignment"] for e in episodes]),
                        seed=int(episodes[0]["seed"]))


def make_figures(book: StageBook) -> dict[str, Path]:
    """The PNG files of the report (training curves, fleet paths, attention, the unseen fleet's paths)."""
    from controllers.mappo import load_actor
    from sim.scenario import make_scenario
    from stack.attention_plot import attention_snapshot, plot_attention
    from stack.demo.fleet import SCENARIO, UNSEEN_DIR
    from stack.plots import (
        plot_training_curves,
        plot_trajectories,
    )

    out = book.out
    paths = {key: out / name for key, name in FIGURES.items()}
    with tqdm(total=len(FIGURES), unit="fig", desc="report figures", dynamic_ncols=True) as bar:
        plot_training_curves({"paper-3 from scratch": out / "train-3",
                              "paper-5 transfer from paper-3": out / "train-5",
                              "generalist: 3, 4 and 5 robots from scratch": out / "train-generalist"},
                             paths["curves"],
                             title="SDPA-MAPPO training: 3 robots from scratch, transfer to 5, the generalist")
        bar.update(1)
        scenario = make_scenario(SCENARIO)
        fleet = book.result("fleet")
        plot_trajectories(fleet_trajectories(out), scenario, paths["trajectories"],
                          title=f"{SCENARIO} in pymunk with model error, over Zenoh: {fleet['policy']} -> "
                                f"safety filter -> MEC ({fleet['episodes']} episodes)")
        bar.update(1)
        actor = load_actor(out / "train-5" / "checkpoint.pt")
        step = scenario.dynamics.episode_steps // 4
        weights, labels = attention_snapshot(actor, scenario, seed=book.settings.seed, step=step)
        plot_attention(weights, labels, paths["attention"],
                       title=f"Attention of the 5-robot policy at step {step} "
                             f"({step * scenario.dynamics.dt:g} s) of an episode")
        bar.update(1)
        unseen = book.result("fleet-unseen")
        plot_trajectories(fleet_trajectories(out, UNSEEN_DIR), make_scenario(unseen["scenario"]), paths["unseen"],
                          title=f"The generalist (trained on 3-5 robots) on {unseen['scenario']}, never seen: "
                                f"pymunk with model error, over Zenoh ({unseen['episodes']} episodes)")
        bar.update(1)
    return paths


# ------------------------------------------------------------------ formatting
def _num(x, digits: int = 3) -> str:
    if x is None:
        return "—"
    if isinstance(x, bool):
        return "yes" if x else "no"
    if isinstance(x, int):
        return str(x)
    return f"{x:.{digits}g}"


def _rate(x) -> str:
    return "—" if x is None else f"{x:.2f}"


def _counts(counts: list[int]) -> str:
    return f"{counts[0]}..{counts[-1]}" if len(counts) > 1 else str(counts[0])


def _mm(x) -> str:
    return "—" if x is None else f"{1000 * x:.2f} mm"


def _converged(train: dict) -> str:
    if train["converged_episode"] is not None:
        return f"{train['converged_episode']} episodes"
    return f"**did not converge** within its budget of {train['budget']} episodes"


def _ms(d: dict | None) -> str:
    if not d or d.get("p50") is None:
        return "—"
    return f"{d['p50']:.2f} / {d['p99']:.2f} ms"


def zero_shot_line(table: list[dict]) -> str:
    """``N: success`` for each row of the generalist's table, ``*`` on the trained sizes."""
    return ", ".join(f"{r['robots']}{'*' if r['trained'] else ''}: {r['success']:.2f}" for r in table)


def convergence_sentences(metrics: dict) -> list[str]:
    """Plain statements of what converged and what did not."""
    out = []
    names = {"3": "SDPA-MAPPO on paper-3 (from scratch)", "5": "the transfer to paper-5",
             "generalist": "the generalist (3, 4 and 5 robots at once)"}
    for robots in ("3", "5", "generalist"):
        t = metrics["train"][robots]
        thr = t["success_threshold"]
        if t["converged"]:
            out.append(f"{names[robots]} converged at episode {t['converged_episode']} (rule: two "
                       f"evaluations in a row of {t['eval_episodes']} episodes with success >= {thr:g}).")
        else:
            out.append(f"{names[robots]} did NOT converge within its budget of {t['budget']} episodes "
                       f"(ran {t['episodes']}; last evaluation success {_rate(t['success'])}, "
                       f"below the {thr:g} needed twice in a row); the later stages use its last "
                       f"checkpoint as it is.")
    return out


def report_blocks(metrics: dict, figures: dict[str, Path], out: Path) -> list[tuple]:
    """The report as blocks: ("h1"|"h2"|"p", text), ("ul", items), ("table", head, rows),
    ("img", path, caption). ``**bold**`` is the only inline markup."""
    return [*_opening_blocks(metrics, out), ("h2", "Summary: ours beside the paper"),
            ("table", ["quantity", "ours", "paper"], _summary_rows(metrics)),
            *_training_blocks(metrics, figures), *_export_and_fleet_blocks(metrics, figures),
            *generalist_blocks(metrics, figures), *_closing_blocks(metrics, figures)]


def _opening_blocks(metrics: dict, out: Path) -> list[tuple]:
    """Title, where and on what the demo ran, the quick-run warning and the convergence sentences."""
    s, env = metrics["settings"], metrics["environment"]
    total = sum(v["wall_s"] or 0 for v in metrics["stages"].values())
    blocks: list[tuple] = [
        ("h1", "formation demo: SDPA-MAPPO from training to a fleet over Zenoh"),
        ("p", f"Written {time.strftime('%Y-%m-%d %H:%M:%S')} into {out}. Python {env['python']}, "
              f"torch {env['torch']}, {env['cpus']} CPUs. Stages before the report took "
              f"{total:.0f} s of wall time."),
    ]
    if s["quick"]:
        blocks.append(("p", f"**Quick run (--quick)**: training budgets of {s['budget_3']} and "
                            f"{s['budget_5']} episodes, evaluations of {s['eval_episodes']} episodes, "
                            f"{s['fleet_episodes']} fleet episodes. Every part runs for real (training, "
                            "export, processes, Zenoh, report), but the policy is barely trained: "
                            "these numbers show that the pipeline works, not what the method reaches."))
    return blocks + [("p", " ".join(convergence_sentences(metrics)))]


def _summary_rows(metrics: dict) -> list[list[str]]:
    """The summary table's rows: quantity, ours, the paper's."""
    t3, t5, shot = metrics["train"]["3"], metrics["train"]["5"], metrics["zero_shot"]
    ex, fl = metrics["export"], metrics["fleet"]
    paper_fleet = "— (not in the paper)"
    floor = fl.get("tracking_noise_floor_m")
    tracking = _mm(fl["tracking_error_m"]) + ("" if floor is None else
                                              f" (measurement-noise floor {_mm(floor)})")
    return [
        ["paper-3: episodes to convergence", _converged(t3), str(PAPER["converged_episode_3"])],
        ["paper-3: success rate (last evaluation)", f"{_rate(t3['success'])} ({t3['eval_episodes']} episodes)",
         PAPER_SUCCESS],
        ["paper-3: final distance (last evaluation)", _mm(t3["final_distance"]), "0.4 mm"],
        ["paper-5, transfer from paper-3: episodes to convergence", _converged(t5),
         str(PAPER["converged_episode_5_transfer"])],
        ["paper-5, from scratch: episodes to convergence", "not run by the demo",
         str(PAPER["converged_episode_5_scratch"])],
        ["paper-5 transfer: success rate (last evaluation)",
         f"{_rate(t5['success'])} ({t5['eval_episodes']} episodes)", PAPER_SUCCESS],
        ["paper-5 transfer: final distance (last evaluation)", _mm(t5["final_distance"]), "—"],
        ["zero-shot: 3-robot policy on paper-5, success rate",
         f"{_rate(shot['success'])} ({shot['episodes']} episodes)", "— (not reported)"],
        [f"export: max abs diff file vs eager ({', '.join(ex['files'])})", f"{ex['max_abs_diff']:.2g} "
         f"({'verified' if ex['verified'] else 'NOT verified'}, tolerance {ex['tolerance']:g})", "—"],
        ["fleet: success rate (pymunk, model error, Zenoh)", f"{_rate(fl['success_rate'])} "
         f"({fl['episodes']} episodes)", paper_fleet],
        ["fleet: final distance (mean)", _mm(fl["final_distance"]), paper_fleet],
        ["fleet: collisions (onsets, all episodes)", str(fl["collisions"]), paper_fleet],
        ["fleet: safety interventions (ticks changed by the filter)",
         f"{fl['interventions']} of {fl['episodes'] * fl['episode_ticks']}", paper_fleet],
        ["fleet: MEC tracking error (mean one-tick position error)", tracking, paper_fleet],
        ["fleet: ControlStack tick time p50 / p99", _ms(fl["tick_ms"]), paper_fleet],
        ["fleet: Zenoh round trip per tick p50 / p99", _ms(fl["round_trip_ms"]), paper_fleet],
        ["generalist (3, 4 and 5 robots at once): episodes to convergence",
         _converged(metrics["train"]["generalist"]), "— (not in the paper)"],
        ["generalist: zero-shot success by team size (* trained)", zero_shot_line(metrics["zero_shot_table"]),
         "— (not in the paper)"],
        [f"generalist fleet on {metrics['fleet_unseen']['scenario']} (never trained): success / collisions",
         f"{_rate(metrics['fleet_unseen']['success_rate'])} / {metrics['fleet_unseen']['collisions']} "
         f"({metrics['fleet_unseen']['episodes']} episodes)", "— (not in the paper)"],
    ]


def _training_blocks(metrics: dict, figures: dict[str, Path]) -> list[tuple]:
    """The two specialist runs: curves, their table and the zero-shot sentence."""
    t3, t5, shot = metrics["train"]["3"], metrics["train"]["5"], metrics["zero_shot"]
    return [
        ("h2", "Training"),
        ("p", "SDPA-MAPPO with the MAPPOConfig defaults (four PPO epochs on paper-3): first the "
              f"paper's three robots from scratch (budget {t3['budget']} episodes), then five robots "
              f"starting from the 3-robot checkpoint (budget {t5['budget']}). Panels: episode return (sum of rewards, mean over "
              "robots), final robot-target distance [m] and the evaluation success rate, against "
              "training episodes; dotted lines mark convergence."),
        ("img", figures["curves"], "Training curves: paper-3 from scratch and paper-5 with transfer"),
        ("table", ["run", "episodes run", "converged", "success", "final distance", "wall time"],
         [[name, str(t["episodes"]), _converged(t), _rate(t["success"]), _mm(t["final_distance"]),
           f"{t['wall_time_s']:.0f} s"] for name, t in (("paper-3", t3), ("paper-5 (transfer)", t5))]),
        ("p", f"Zero-shot: the 3-robot policy run on five robots without further training has a "
              f"success rate of {_rate(shot['success'])} over {shot['episodes']} deterministic "
              f"episodes (final distance {_mm(shot['final_distance'])})."),
    ]


FORMAT_NAMES = {"torchscript": "TorchScript", "pt2": "torch.export", "onnx": "ONNX",
                "npz": "npz for the compiled kernel"}


def _export_and_fleet_blocks(metrics: dict, figures: dict[str, Path]) -> list[tuple]:
    """The exported files and their checks, then the fleet stage: setting, episodes, paths."""
    ex, fl = metrics["export"], metrics["fleet"]
    return [
        ("h2", "Export"),
        ("p", f"{', '.join(ex['files'].values())} "
              f"({', '.join(FORMAT_NAMES.get(name, name) for name in ex['files'])}; robots "
              f"{_counts(ex['robot_counts'])}) with one golden file {ex['golden']}: each reloaded, its "
              f"digest checked, and compared with the eager actor for N = 1..21 "
              f"({ex['comparisons']} comparisons in all), then re-checked against the golden file as a "
              "robot does at start-up. Max abs diff by format: "
              + ", ".join(f"{k} {v:.2g}" for k, v in ex["max_abs_diff_by_format"].items())
              + f" (tolerance {ex['tolerance']:g}): {'verified' if ex['verified'] else 'NOT verified'}. "
              f"The fleet runs {ex['policy']}, which needs only numpy and onnxruntime on a robot."),
        ("h2", "Fleet over Zenoh"),
        ("p", f"`fleet-sim` (pymunk, {fl['scenario']}, lock-step) and `bridge` (ControlStack: "
              f"{fl['policy']} -> barrier-QP safety filter -> Kalman MEC) ran as two processes on loopback "
              f"Zenoh (multicast scouting off) for {fl['episodes']} episodes of {fl['episode_ticks']} "
              f"ticks. Model error: {_model_error_text(fl['model_error'])}. Collisions are judged on "
              "the true state; the MEC tracking error compares each measured position with the "
              "nominal model's prediction from the previous measured state and the safe command; "
              "measurement noise alone gives the noise floor, so an error near it means the robots "
              "move as the nominal model does. Lock-step timeouts (a tick whose answer "
              f"did not arrive within the timeout): {fl['lockstep_timeouts']}."),
        _episode_table(fl),
        ("img", figures["trajectories"], "Robot paths of the fleet episodes (true positions)"),
    ]


def _closing_blocks(metrics: dict, figures: dict[str, Path]) -> list[tuple]:
    """Attention heatmap, the files of the run folder and the stage times."""
    ex = metrics["export"]
    return [
        ("h2", "Attention"),
        ("p", "Attention weights of each robot (rows) over its tokens (own state, targets G, other "
              "robots R, object O) for the 5-robot policy, mean over heads and per head."),
        ("img", figures["attention"], "Attention heatmap of the 5-robot policy"),
        ("h2", "Files"),
        ("ul", ["metrics.json: every number above", "stages.json: finished stages (--resume skips them)",
                "train-3/, train-5/: run folders (config.json, train/eval logs, checkpoint.pt)",
                f"{', '.join(ex['files'].values())}, {ex['golden']}: the exported policy and its golden file",
                "fleet/: sim.json, bridge.json (per-episode reports), sim.log, bridge.log",
                "train-generalist/: the generalist's run folder; generalist/: its exported policy.onnx "
                "and golden file; fleet-unseen/: its fleet stage's reports and logs",
                ", ".join(FIGURES.values()) + ": the figures"]),
        ("h2", "Stage times"),
        ("table", ["stage", "wall time"],
         [[name, "—" if v["wall_s"] is None else f"{v['wall_s']:.1f} s"]
          for name, v in metrics["stages"].items() if name != "report"]),
    ]


def _episode_table(fl: dict) -> tuple:
    return ("table", ["episode", "seed", "success", "final distance", "collisions", "interventions",
                      "tracking error", "tick p50 / p99", "round trip p50 / p99"],
            [[str(r["episode"]), str(r["seed"]), _num(r["success"]), _mm(r["final_distance"]),
              str(r["collisions"]), _num(r["interventions"]), _mm(r["tracking_error_m"]),
              _ms(r["tick_ms"]), _ms(r["round_trip_ms"])] for r in fl["per_episode"]])


def generalist_blocks(metrics: dict, figures: dict[str, Path]) -> list[tuple]:
    """The report's section on the generalist: its training, zero-shot table and unseen fleet."""
    tg, table, fu = metrics["train"]["generalist"], metrics["zero_shot_table"], metrics["fleet_unseen"]
    ex = tg["export"]
    unseen = [r for r in table if not r["trained"]]
    return [
        ("h2", "One policy for any team size"),
        ("p", f"The generalist is one SDPA-MAPPO policy trained on 3, 4 and 5 robots at once (one "
              f"batched rollout of each size per update), from scratch "
              f"(budget {tg['budget']} episodes, 4 PPO epochs, the contact-penalty curriculum): it "
              + (f"converged at episode {tg['converged_episode']}" if tg["converged"] else
                 f"did not converge within its budget of {tg['budget']} episodes")
              + f" ({tg['wall_time_s']:.0f} s). The table runs it without further training on the default "
              f"layout of 1 to 8 robots ({table[0]['episodes']} deterministic episodes each, batched "
              f"world, no filter); sizes marked yes were trained on, the {len(unseen)} others never seen."),
        ("table", ["robots", "trained on", "success", "collision rate", "final distance"],
         [[str(r["robots"]), _num(r["trained"]), _rate(r["success"]), _rate(r["collision_rate"]),
           _mm(r["final_distance"])] for r in table]),
        ("p", f"Exported as {ex['policy']} (max abs diff to the eager actor {ex['max_abs_diff']:.2g}, "
              f"{'verified' if ex['verified'] else 'NOT verified'}), it ran the fleet stage on "
              f"{fu['scenario']}, a team size it never trained on: success {_rate(fu['success_rate'])} over "
              f"{fu['episodes']} episodes, {fu['collisions']} collisions, final distance "
              f"{_mm(fu['final_distance'])}, {fu['interventions']} of {fu['episodes'] * fu['episode_ticks']} "
              "ticks changed by the safety filter (same model error, filter and MEC as above)."),
        _episode_table(fu),
        ("img", figures["unseen"], f"The generalist's fleet episodes on {fu['scenario']} (true positions)"),
    ]


def _model_error_text(me: dict) -> str:
    return (f"gain {me['gain']:g} ± {me['gain_spread']:g}, lag {1000 * me['lag_tau']:g} ms, floor "
            f"friction {me['floor_friction']:g} m/s², noise {1000 * me['position_noise_std']:g} mm / "
            f"{1000 * me['velocity_noise_std']:g} mm/s")


def to_markdown(blocks: list[tuple], out: Path) -> str:
    lines: list[str] = []
    for block in blocks:
        kind = block[0]
        if kind == "h1":
            lines += [f"# {block[1]}", ""]
        elif kind == "h2":
            lines += [f"## {block[1]}", ""]
        elif kind == "p":
            lines += [block[1], ""]
        elif kind == "ul":
            lines += [f"- {item}" for item in block[1]] + [""]
        elif kind == "table":
            head, rows = block[1], block[2]
            lines.append("| " + " | ".join(head) + " |")
            lines.append("|" + "|".join("---" for _ in head) + "|")
            lines += ["| " + " | ".join(c.replace("|", "\\|") for c in row) + " |" for row in rows]
            lines.append("")
        elif kind == "img":
            lines += [f"![{block[2]}]({Path(block[1]).relative_to(out).as_posix()})", ""]
    return "\n".join(lines)


def _inline(text: str) -> str:
    """Escape, then ``**bold**`` -> <strong> and `code` -> <code>."""
    parts = html.escape(text).split("**")
    text = "".join(p if i % 2 == 0 else f"<strong>{p}</strong>" for i, p in enumerate(parts))
    parts = text.split("`")
    return "".join(p if i % 2 == 0 else f"<code>{p}</code>" for i, p in enumerate(parts))


STYLE = ("body{font-family:system-ui,sans-serif;max-width:1100px;margin:2em auto;padding:0 1em;"
         "color:#222}table{border-collapse:collapse;margin:1em 0}td,th{border:1px solid #ccc;"
         "padding:4px 8px;text-align:left}th{background:#f3f3f3}img{max-width:100%}"
         "figcaption{color:#555;font-size:90%}")


def to_html(blocks: list[tuple]) -> str:
    """One self-contained page: every figure is a ``data:image/png;base64`` URI."""
    body: list[str] = []
    title = next((b[1] for b in blocks if b[0] == "h1"), "formation demo")
    for block in blocks:
        kind = block[0]
        if kind in ("h1", "h2", "p"):
            body.append(f"<{kind}>{_inline(block[1])}</{kind}>")
        elif kind == "ul":
            body.append("<ul>" + "".join(f"<li>{_inline(i)}</li>" for i in block[1]) + "</ul>")
        elif kind == "table":
            head = "".join(f"<th>{_inline(c)}</th>" for c in block[1])
            rows = "".join("<tr>" + "".join(f"<td>{_inline(c)}</td>" for c in row) + "</tr>"
                           for row in block[2])
            body.append(f"<table><thead><tr>{head}</tr></thead><tbody>{rows}</tbody></table>")
        elif kind == "img":
            data = base64.b64encode(Path(block[1]).read_bytes()).decode("ascii")
            caption = html.escape(block[2])
            body.append(f'<figure><img alt="{caption}" src="data:image/png;base64,{data}">'
                        f"<figcaption>{caption}</figcaption></figure>")
    return (f'<!DOCTYPE html>\n<html lang="en"><head><meta charset="utf-8"><title>{html.escape(title)}'
            f"</title><style>{STYLE}</style></head><body>\n" + "\n".join(body) + "\n</body></html>\n")


def report_stage(book: StageBook) -> dict[str, Any]:
    """Figures, metrics.json (complete), report.md and report.html."""
    out = book.out
    figures = make_figures(book)
    metrics = build_metrics(book, complete=True)
    write_json(out / "metrics.json", metrics)
    blocks = report_blocks(metrics, figures, out)
    write_atomic(out / "report.md", to_markdown(blocks, out))
    write_atomic(out / "report.html", to_html(blocks))
    return {"files": ["report.md", "report.html", "metrics.json", *FIGURES.values()]}


__all__ = ["FIGURES", "PAPER", "build_metrics", "convergence_sentences", "fleet_trajectories", "generalist_blocks",
           "make_figures", "report_blocks", "report_stage", "save_metrics", "to_html", "to_markdown",
           "zero_shot_line"]
