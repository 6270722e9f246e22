"""Figures of a run as PNG files, in the spirit of the paper's figures.

* :func:`plot_training_curves` - episode return, final distance and evaluation success rate
  against training episodes (Figures 8-13 and 17-20), several runs overlaid (e.g. "from scratch"
  vs "transfer"), the converged episode marked.
* :func:`record_trajectories` + :func:`plot_trajectories` - robot paths of a few deterministic
  episodes (Figures 14-15 and 21-22): arena, object, start slots, targets with the tolerance
  circle, robot discs at start and end, collisions marked.
* the attention heatmap (Figure 5) is :mod:`stack.attention_plot`'s.

matplotlib is imported inside the plotting functions only (Figure objects drawn by the Agg canvas,
no pyplot state), so importing this module needs numpy alone; torch is imported by the functions
that run a policy. Units: metres, seconds.
"""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np

DPI = 120


class PlotError(ValueError):
    """Input that cannot be plotted; the message names the file or value and the fix."""


# ------------------------------------------------------------------ training curves
@dataclass
class RunCurves:
    """The logs of one training run.

    train: rows of ``train.jsonl`` (one per iteration; ``episodes``, ``return_mean``,
        ``final_distance`` [m], None where no episode ended in the iteration).
    eval: rows of ``eval.jsonl`` (one per evaluation; ``episodes``, ``success_rate`` in [0, 1],
        ``final_distance`` [m], ``episode_return``).
    converged_episode: training episodes at convergence (None: not converged).
    """

    label: str
    train: list[dict]
    eval: list[dict] = dataclasses.field(default_factory=list)
    converged_episode: int | None = None
    success_threshold: float = 0.9
    target_tolerance: float | None = None


def _read_jsonl(path: Path) -> list[dict]:
    """The rows of a run's log (:func:`controllers.mappo.logs.read_jsonl`: a torn last line is
    skipped); a damaged one is a PlotError naming the file and line."""
    from controllers.mappo.logs import LogFileError, read_jsonl

    try:
        return read_jsonl(path)
    except LogFileError as exc:
        raise PlotError(str(exc)) from None
    except OSError as exc:
        raise PlotError(f"{path}: cannot be read ({exc.strerror}); check the run folder") from None


def _read_json(path: Path) -> dict:
    """An optional JSON file of a run (result.json, config.json) through :func:`sim.files.read_config`;
    a damaged one is a PlotError naming it."""
    from sim.files import ConfigFileError, read_config

    try:
        return read_config(path, str(path))
    except (ConfigFileError, OSError, UnicodeDecodeError) as exc:
        raise PlotError(f"{exc}; the file is damaged: remove it (the curves need train.jsonl "
                        "alone) or give another run folder") from None


def load_run(run_dir: str | Path, label: str | None = None) -> RunCurves:
    """Read ``train.jsonl`` (required), ``eval.jsonl``, ``result.json`` and ``config.json`` of a run."""
    run_dir = Path(run_dir)
    if run_dir.exists() and not run_dir.is_dir():
        raise PlotError(f"{str(run_dir)!r} is a file, not a run folder; give a folder written by "
                        "`formation train --out DIR`, or episode records (.npz)")
    if not run_dir.is_dir():
        raise PlotError(f"run folder {str(run_dir)!r} does not exist; give a folder written by "
                        "`formation train --out DIR`")
    train_path = run_dir / "train.jsonl"
    if not train_path.is_file():
        raise PlotError(f"{str(train_path)!r} is missing: it is the per-iteration log that "
                        "`formation train` writes into its run folder")
    eval_path, result_path, config_path = (run_dir / n for n in ("eval.jsonl", "result.json", "config.json"))
    evals = _read_jsonl(eval_path) if eval_path.is_file() else []
    converged = next((r["converged_episode"] for r in evals if r.get("converged_episode") is not None), None)
    if result_path.exists():
        converged = _read_json(result_path).get("converged_episode", converged)
    threshold, tolerance = 0.9, None
    if config_path.exists():
        config = _read_json(config_path)
        try:
            threshold = float(config.get("success_threshold", threshold))
        except (TypeError, ValueError):
            raise PlotError(f"{config_path}: success_threshold {config['success_threshold']!r} is not a "
                            "number; fix or remove the file") from None
        tolerance = _tolerance(config.get("scenario"))
    return RunCurves(label or run_dir.name, _read_jsonl(train_path), evals, converged, threshold, tolerance)


def _tolerance(scenario) -> float | None:
    from sim.scenario import Scenario, ScenarioError, make_scenario

    try:
        if isinstance(scenario, dict):
            return Scenario.from_dict(dict(scenario)).target_tolerance
        return make_scenario(scenario).target_tolerance if isinstance(scenario, str) else None
    except ScenarioError:
        return None


def _as_curves(label: str, source) -> RunCurves:
    if isinstance(source, RunCurves):
        return dataclasses.replace(source, label=label)
    if isinstance(source, str | Path):
        return load_run(source, label)
    if isinstance(source, Mapping):
        return RunCurves(label, list(source.get("train", [])), list(source.get("eval", [])),
                         source.get("converged_episode"))
    if isinstance(source, Sequence):
        return RunCurves(label, list(source))
    raise PlotError(f"run {label!r}: expected a run folder, RunCurves, a list of train rows or "
                    f"{{'train': rows, 'eval': rows}}, got {type(source).__name__}")


def _series(rows: list[dict], key: str) -> tuple[np.ndarray, np.ndarray]:
    """(episodes, values) of the rows where ``key`` is defined."""
    pts = [(r["episodes"], r[key]) for r in rows if r.get(key) is not None and r.get("episodes") is not None]
    if not pts:
        return np.zeros(0), np.zeros(0)
    x, y = np.asarray(pts, dtype=float).T
    return x, y


def moving_mean(y: np.ndarray, window: int) -> np.ndarray:
    """Centred moving mean over ``window`` points; windows shrink at the ends (same length as y)."""
    y = np.asarray(y, dtype=float)
    if window <= 1:
        return y.copy()
    half = window // 2
    c = np.concatenate(([0.0], np.cumsum(y)))
    idx = np.arange(len(y))
    lo, hi = np.maximum(idx - half, 0), np.minimum(idx + half + 1, len(y))
    return (c[hi] - c[lo]) / (hi - lo)


def new_figure(**kwargs):
    """A matplotlib Figure drawn by the Agg canvas (no pyplot: no global backend or state)."""
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure

    fig = Figure(layout="constrained", **kwargs)
    FigureCanvasAgg(fig)
    return fig


def colormap(name: str):
    """A matplotlib colormap by name (matplotlib imported on first use)."""
    from matplotlib import colormaps

    return colormaps[name]


def save_figure(fig, out_png: str | Path) -> Path:
    out = Path(out_png)
    out.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(out, dpi=DPI, bbox_inches="tight", facecolor="white")
    return out


def plot_training_curves(runs: Mapping[str, object], out_png: str | Path, *, title: str | None = None,
                         smooth: int | None = None) -> Path:
    """Three panels against training episodes, one colour per run, written to ``out_png``.

    Args:
        runs: label -> run folder, :class:`RunCurves`, list of ``train.jsonl`` rows, or
            ``{"train": rows, "eval": rows, "converged_episode": k}``.
        smooth: moving-mean window in points for the training curves (default ~1/25 of them).

    Panels: (1) episode return (undiscounted sum of rewards over an episode, mean over robots):
    training episodes (faint, and smoothed) and deterministic evaluations (markers);
    (2) final distance [m], the mean robot-to-assigned-target distance at the end, with the
    target tolerance; (3) evaluation success rate [%] with the convergence threshold. A dotted
    vertical line marks each run's converged episode.
    """
    if not runs:
        raise PlotError("no runs to plot: give at least one run")
    curves = [_as_curves(label, src) for label, src in runs.items()]
    from matplotlib.lines import Line2D

    fig = new_figure(figsize=(17, 5.2))
    axes = fig.subplots(1, 3)
    colours = colormap("tab10").colors
    handles = []
    for k, run in enumerate(curves):
        colour = colours[k % len(colours)]
        for ax, (train_key, eval_key) in zip(axes[:2], (("return_mean", "episode_return"),
                                                         ("final_distance", "final_distance")), strict=True):
            x, y = _series(run.train, train_key)
            if len(x):
                w = smooth or max(1, round(len(x) / 25)) | 1
                ax.plot(x, y, color=colour, alpha=0.2, lw=0.8)
                ax.plot(x, moving_mean(y, w), color=colour, lw=2)
            ex, ey = _series(run.eval, eval_key)
            if len(ex):
                ax.plot(ex, ey, color=colour, ls="--", marker="o", ms=3.5, lw=1)
        ex, ey = _series(run.eval, "success_rate")
        if len(ex):
            axes[2].plot(ex, 100 * ey, color=colour, marker="o", ms=3.5, lw=1.5)
        conv = run.converged_episode
        if conv is not None:
            for ax in axes:
                ax.axvline(conv, color=colour, ls=":", lw=1.6)
            axes[2].annotate(f"converged\n@ {conv}", (conv, 100 * run.success_threshold), xytext=(4, -30),
                             textcoords="offset points", color=colour, fontsize=8)
        state = f"converged at episode {conv}" if conv is not None else "not converged"
        handles.append(Line2D([], [], color=colour, lw=2, label=f"{run.label} ({state})"))
    tolerance = next((r.target_tolerance for r in curves if r.target_tolerance is not None), None)
    if tolerance is not None:
        _reference_line(axes[1], tolerance, f"target tolerance {tolerance:g} m")
    threshold = curves[0].success_threshold
    _reference_line(axes[2], 100 * threshold, f"convergence threshold {100 * threshold:g} %")
    axes[2].set_ylim(-3, 103)
    axes[1].set_ylim(bottom=0)
    labels = (("Episode return", "return per episode (sum of rewards, mean over robots)"),
              ("Final distance", "final robot-target distance [m]"),
              ("Evaluation success rate", "success rate [%] (deterministic episodes)"))
    for ax, (name, ylabel) in zip(axes, labels, strict=True):
        ax.set_title(name)
        ax.set_xlabel("training episodes")
        ax.set_ylabel(ylabel)
        ax.grid(alpha=0.3)
    styles = [Line2D([], [], color="0.4", lw=2, label="training (moving mean; raw faint)"),
              Line2D([], [], color="0.4", ls="--", marker="o", ms=3.5, lw=1, label="evaluation (mean action)"),
              Line2D([], [], color="0.4", ls=":", lw=1.6, label="converged episode")]
    fig.legend(handles=handles + styles, loc="outside lower center", ncol=min(3, len(handles) + 3),
               frameon=False)
    fig.suptitle(title or "Training curves: " + " vs ".join(r.label for r in curves), fontsize=13)
    return save_figure(fig, out_png)


def _reference_line(ax, y: float, text: str) -> None:
    ax.axhline(y, color="0.3", ls="-.", lw=1)
    ax.annotate(text, (0.01, y), xycoords=("axes fraction", "data"), xytext=(0, 3), textcoords="offset points",
                fontsize=8, color="0.3", bbox={"facecolor": "white", "edgecolor": "none", "alpha": 0.8, "pad": 1})


# ------------------------------------------------------------------ trajectories
@dataclass
class Trajectories:
    """Recorded episodes of one scenario.

    positions: (K, S+1, N, 2) robot centres [m]; index 0 is the start, S the end.
    contacts: (K, S, N, 3) bool, robot / object / wall contact after each step.
    success: (K,) bool; final_distance: (K,) mean assigned distance at the end [m];
    assignment: (K, N) target index of each robot at the end (min-sum matching).
    seed: the seed the starts were drawn with.
    """

    positions: np.ndarray
    contacts: np.ndarray
    success: np.ndarray
    final_distance: np.ndarray
    assignment: np.ndarray
    seed: int = 0


def rollout_env(scenario, episodes: int, seed: int, steps: int, actor):
    """A batched world of ``episodes`` envs whose episodes outlast ``steps`` (no auto-reset),
    giving ``actor`` the observations it reads."""
    from sim.batched_env import BatchedFormationEnv, reads

    long = dataclasses.replace(scenario, dynamics=dataclasses.replace(scenario.dynamics, episode_steps=steps + 1))
    return BatchedFormationEnv(long, episodes, seed=seed, **reads(actor))


def record_trajectories(actor, scenario, *, episodes: int = 4, seed: int = 0,
                        steps: int | None = None) -> Trajectories:
    """Roll out ``actor``'s mean action for ``episodes`` episodes of ``scenario`` and record them.

    ``actor(obs, mask) -> (E, N, 2)`` [m/s^2] with ``obs_kind`` ``"tokens"`` or ``"flat"`` (eager
    or an exported file). The starts are the scenario's start slots jittered with ``seed``; ``steps``
    defaults to the scenario's episode length. The world is :class:`sim.batched_env.BatchedFormationEnv`
    (nominal dynamics, no safety filter, no contact forces: overlaps are only recorded as
    contacts); success and final distance follow :mod:`sim.metrics`.
    """
    import torch

    from sim.metrics import episode_outcome

    if not isinstance(episodes, int) or episodes < 1:
        raise PlotError(f"episodes must be a positive integer, got {episodes!r}")
    steps = scenario.dynamics.episode_steps if steps is None else int(steps)
    if steps < 1:
        raise PlotError(f"steps must be a positive integer, got {steps}")
    env = rollout_env(scenario, episodes, seed, steps, actor)
    positions = torch.empty(steps + 1, episodes, scenario.num_robots, 2)
    contacts = torch.empty(steps, episodes, scenario.num_robots, 3, dtype=torch.bool)
    with torch.inference_mode():
        obs, mask = env.reset()
        positions[0] = env.pos
        for t in range(steps):
            result = env.step(actor(obs, mask))
            obs, mask = result.obs, result.mask
            positions[t + 1], contacts[t] = env.pos, env.prev_contact
        out = episode_outcome(env.pos, env.targets, contacts.flatten(2).any(-1).any(0),
                              scenario.target_tolerance)
    return Trajectories(positions.transpose(0, 1).double().numpy(), contacts.transpose(0, 1).numpy(),
                        out.success.numpy(), out.final_distance.double().numpy(), out.assignment.numpy(), seed)


def robot_colours(n: int) -> list:
    """N distinct colours: the paper's red, blue, yellow, green, purple first."""
    base = ["#d62728", "#1f77b4", "#e6b800", "#2ca02c", "#9467bd", "#ff7f0e", "#17becf", "#8c564b",
            "#e377c2", "#7f7f7f"]
    if n <= len(base):
        return base[:n]
    return [colormap("turbo")(k / max(1, n - 1)) for k in range(n)]


def draw_scene(ax, scenario) -> None:
    from matplotlib.patches import Circle, Polygon, Rectangle

    w, h = scenario.arena
    ax.add_patch(Rectangle((0, 0), w, h, fill=False, lw=2, color="black"))
    ax.add_patch(Polygon(scenario.polygon, closed=True, facecolor="0.8", edgecolor="0.3", hatch="//", lw=1.2))
    ax.text(*scenario.object_center, "object", ha="center", va="center", fontsize=8, color="0.2",
            bbox={"facecolor": "white", "edgecolor": "none", "alpha": 0.7, "pad": 1})
    j = scenario.start_jitter
    for x, y in scenario.starts:
        ax.add_patch(Rectangle((x - j, y - j), 2 * j, 2 * j, fill=False, ls=":", lw=0.8, color="0.4", zorder=1))
        ax.plot(x, y, "+", color="0.45", ms=4, mew=0.7, zorder=1)
    side = 0.05 / math.sqrt(2)   # the paper's target points: 0.05 across
    for x, y in scenario.targets:
        ax.add_patch(Circle((x, y), scenario.target_tolerance, fill=False, ls="--", lw=0.9, color="0.2"))
        ax.add_patch(Rectangle((x - side / 2, y - side / 2), side, side, facecolor="0.15", edgecolor="none"))
    ax.set_xlim(-0.02, w + 0.02)
    ax.set_ylim(-0.02, h + 0.02)
    ax.set_aspect("equal")


def plot_trajectories(traj: Trajectories, scenario, out_png: str | Path, *, title: str | None = None,
                      max_cols: int = 4) -> Path:
    """A grid of the recorded episodes, one panel each, written to ``out_png``.

    Each panel: the arena (W x H m), the object (hatched), start slots (+, dotted jitter box),
    target slots (black squares, dashed circle = target tolerance), robot paths (one colour per
    robot), robot discs (diameter 2 r) numbered at the start (faint) and solid at the end, and
    collision onsets (X robot-robot, diamond robot-object, square wall).
    """
    from matplotlib.lines import Line2D
    from matplotlib.patches import Circle, Patch

    pos = np.asarray(traj.positions)
    if pos.ndim != 4 or pos.shape[-1] != 2 or pos.shape[2] != scenario.num_robots:
        raise PlotError(f"positions must have shape (episodes, steps+1, {scenario.num_robots}, 2), "
                        f"got {pos.shape}")
    k, _, n, _ = pos.shape
    cols = min(k, max_cols)
    rows = math.ceil(k / cols)
    fig = new_figure(figsize=(4.3 * cols + 2.5 * (cols == 1), 4.5 * rows + 0.9))
    axes = fig.subplots(rows, cols, squeeze=False)
    colours = robot_colours(n)
    r = scenario.robot_radius
    contacts = np.asarray(traj.contacts, dtype=bool)
    onset = contacts & ~np.concatenate((np.zeros_like(contacts[:, :1]), contacts[:, :-1]), 1)   # (K,S,N,3)
    for e, ax in enumerate(axes.flat):
        if e >= k:
            ax.axis("off")
            continue
        draw_scene(ax, scenario)
        for i in range(n):
            path = pos[e, :, i]
            ax.plot(path[:, 0], path[:, 1], color=colours[i], lw=1.6, alpha=0.9)
            ax.add_patch(Circle(path[0], r, facecolor=colours[i], alpha=0.3, edgecolor=colours[i], zorder=2))
            ax.text(*path[0], str(i + 1), ha="center", va="center", fontsize=8, fontweight="bold", zorder=5)
            ax.add_patch(Circle(path[-1], r, facecolor=colours[i], alpha=0.95, edgecolor="black", lw=0.8,
                                zorder=4))
            ax.text(*path[-1], str(i + 1), ha="center", va="center", fontsize=8, color="white",
                    fontweight="bold", zorder=5)
            for kind, marker in enumerate(("X", "D", "s")):
                steps = np.flatnonzero(onset[e, :, i, kind]) + 1
                if len(steps):
                    ax.plot(pos[e, steps, i, 0], pos[e, steps, i, 1], marker, ms=8, mfc="none", mec="red", mew=1.6)
        n_coll = int(onset[e].any(-1).sum())
        verdict = "success" if bool(traj.success[e]) else "failed"
        ax.set_title(f"episode {e + 1}: {verdict}\nfinal distance {traj.final_distance[e]:.3f} m, "
                     f"{n_coll} collision onset{'s' * (n_coll != 1)}", fontsize=10,
                     color="darkgreen" if bool(traj.success[e]) else "darkred")
        ax.set_xlabel("x [m]")
        ax.set_ylabel("y [m]")
    legend = [Line2D([], [], color="0.3", marker="+", ls="none", ms=8, label="start slot (dotted: jitter)"),
              Line2D([], [], color="0.15", marker="s", ls="none", ms=6, label="target slot"),
              Line2D([], [], color="0.2", ls="--", label=f"target tolerance {scenario.target_tolerance:g} m"),
              Patch(facecolor="0.6", alpha=0.4, label=f"robot at start (diameter {2 * r:g} m)"),
              Patch(facecolor="0.3", edgecolor="black", label="robot at end"),
              Patch(facecolor="0.8", edgecolor="0.3", hatch="//", label="object"),
              Line2D([], [], color="red", marker="X", mfc="none", ls="none", ms=8, label="robot-robot contact"),
              Line2D([], [], color="red", marker="D", mfc="none", ls="none", ms=7, label="robot-object contact"),
              Line2D([], [], color="red", marker="s", mfc="none", ls="none", ms=7, label="wall contact")]
    if n <= 6:   # more robots: the numbers on the discs tell them apart
        legend += [Line2D([], [], color=colours[i], lw=2, label=f"robot {i + 1}") for i in range(n)]
    if cols > 1:
        fig.legend(handles=legend, loc="outside lower center", ncol=5, frameon=False, fontsize=8)
    else:
        fig.legend(handles=legend, loc="outside right center", frameon=False, fontsize=8)
    steps = pos.shape[1] - 1
    dt = scenario.dynamics.dt
    fig.suptitle(title or f"{scenario.name}: {n} robots, {steps} steps ({steps * dt:g} s), "
                 f"deterministic policy, starts drawn with seed {traj.seed}", fontsize=12)
    return save_figure(fig, out_png)
