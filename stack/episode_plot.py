"""One recorded stack episode as a figure: the paths, which layer was driving each robot, and
how far each robot was from its target.

:func:`robot_modes` reads an :class:`stack.recorder.EpisodeRecord` tick by tick, per robot
(later entries win)::

    POLICY     the policy's command went out as it was (up to the actuator's norm clip)
    DOCKING    the docking law drove it (controllers.docking)
    DETOUR     a detour drove it (controllers.detour)
    FILTER     the safety filter changed the command by more than ``tolerance`` [m/s^2]
    STALE      its state was stale or unknown: an obstacle, sent the braking law
    LINK       the link sent it BRAKE in place of the stack's command (the bridge's age rule,
               a failed or late answer)
    ABSENT     it had no row in the tick's state (silent: off the link)

:func:`plot_episode` draws three panels: the arena with every robot's true path (segments where
the filter changed its command drawn thick in orange, where it was stale, braked by the link or
absent dashed grey, a robot with no position in the whole record left out and named as absent,
contact onsets marked, a robot frozen by the world hatched at its end, and what a tracker saw
besides the robots dotted, its disc where it was seen last); a raster of the modes,
robots x time; and each robot's distance to the target it ended matched to (the episode's
assignment), the target tolerance dashed.
"""

from __future__ import annotations

import math
from enum import IntEnum
from pathlib import Path

import numpy as np

from sim.scenario import Scenario
from stack.plots import PlotError, draw_scene, new_figure, robot_colours, save_figure
from stack.recorder import EpisodeRecord
from stack.tick_types import FILTER_TOLERANCE, filter_changed


class Mode(IntEnum):
    """Which layer drove a robot at a tick (module docstring)."""

    POLICY = 0
    DOCKING = 1
    DETOUR = 2
    FILTER = 3
    STALE = 4
    LINK = 5
    ABSENT = 6


MODE_COLOURS = {Mode.POLICY: "#f2f2f2", Mode.DOCKING: "#2ca02c", Mode.DETOUR: "#9467bd",
                Mode.FILTER: "#ff7f0e", Mode.STALE: "#7f7f7f", Mode.LINK: "#8c564b", Mode.ABSENT: "#000000"}


def robot_modes(record: EpisodeRecord, accel_limit: float, tolerance: float = FILTER_TOLERANCE) -> np.ndarray:
    """(S, N) :class:`Mode` codes of every robot at every tick (module docstring)."""
    modes = np.full(record.stale.shape, Mode.POLICY, dtype=np.int64)
    modes[record.docking] = Mode.DOCKING
    modes[record.detour] = Mode.DETOUR
    modes[filter_changed(record.a_nom, record.a_safe, accel_limit, tolerance) & record.present] = Mode.FILTER
    modes[record.stale] = Mode.STALE
    modes[record.link_braked] = Mode.LINK
    modes[~record.present] = Mode.ABSENT
    return modes


def assigned_distances(record: EpisodeRecord) -> tuple[np.ndarray, np.ndarray]:
    """``(distance (S+1, N) [m], target column (N,))``: each robot's distance, at every tick, to
    the target it was matched to at the end (least total distance over the robots present at the
    last tick and their targets, :func:`sim.metrics.episode_outcome`; NaN and -1 for the rest)."""
    import torch

    from sim.metrics import episode_outcome

    _check_ticks(record)
    final, targets = record.positions[-1], record.targets[-1]
    keep = np.flatnonzero(np.isfinite(final).all(-1) & np.isfinite(targets).all(-1))
    dist, column = np.full(record.positions.shape[:2], np.nan), np.full(record.num_robots, -1)
    if len(keep):
        outcome = episode_outcome(torch.from_numpy(final[keep])[None], torch.from_numpy(targets[keep])[None],
                                  torch.tensor([False]), 0.0)
        column[keep] = keep[outcome.assignment[0].numpy()]
        dist[:, keep] = np.linalg.norm(record.positions[:, keep] - targets[column[keep]][None], axis=-1)
    return dist, column


def plot_episode(record: EpisodeRecord, scenario: Scenario, out_png: str | Path, *,
                 title: str | None = None) -> Path:
    """Draw ``record`` (an episode of ``scenario``) into ``out_png`` (module docstring);
    :class:`stack.plots.PlotError` for a record without ticks."""
    from matplotlib.lines import Line2D
    from matplotlib.patches import Patch

    _check_ticks(record, Path(out_png).name)
    n, s, dt = record.num_robots, record.steps, scenario.dynamics.dt
    modes = robot_modes(record, scenario.dynamics.accel_limit)
    colours = robot_colours(n)
    fig = new_figure(figsize=(13, 6.2))
    grid = fig.add_gridspec(2, 2, width_ratios=(1.0, 1.25), height_ratios=(1, 1.2))
    scene, raster, dist = fig.add_subplot(grid[:, 0]), fig.add_subplot(grid[0, 1]), fig.add_subplot(grid[1, 1])
    _draw_paths(scene, record, scenario, modes, colours)
    _draw_obstacles(scene, record)
    _draw_modes(raster, modes, record, dt)
    _draw_distances(dist, record, scenario, colours, dt)
    legend = [Patch(facecolor=MODE_COLOURS[m], edgecolor="0.5", label=m.name.lower()) for m in Mode]
    legend += [Line2D([], [], color="#ff7f0e", lw=5, alpha=0.45, label="path: filter changed the command"),
               Line2D([], [], color="0.4", ls="--", lw=1.2, label="path: stale, link brake or absent"),
               Line2D([], [], color="red", marker="X", mfc="none", ls="none", ms=8, label="contact onset"),
               Patch(facecolor="white", edgecolor="black", hatch="xxx", label="frozen by the world")]
    if len(record.obstacle_ids):
        legend.append(Line2D([], [], color="0.15", ls=":", lw=1.5, label="obstacle a tracker saw, last seen"))
    fig.legend(handles=legend, loc="outside lower center", ncol=5, frameon=False, fontsize=8)
    m = record.meta.get("metrics", {})
    verdict = ("success" if m.get("success") else "failed") if m else ""
    fig.suptitle(title or f"{scenario.name}: {n} robots, {s} ticks ({s * dt:g} s), seed {record.meta.get('seed')}"
                 + (f", {verdict}, final distance {1000 * m['final_distance']:.1f} mm" if m else ""), fontsize=12)
    return save_figure(fig, out_png)


def _draw_paths(ax, record: EpisodeRecord, scenario: Scenario, modes: np.ndarray, colours: list) -> None:
    from matplotlib.patches import Circle

    draw_scene(ax, scenario)
    r = scenario.robot_radius
    pos = record.positions
    onset = record.contacts & ~np.concatenate((np.zeros_like(record.contacts[:1]), record.contacts[:-1]))
    nowhere = []
    for i in range(record.num_robots):
        path = pos[:, i]
        placed = path[np.isfinite(path).all(-1)]
        if not len(placed):             # no position in the whole record (silent, or it reported NaN)
            nowhere.append(str(record.ids[i]))
            continue
        ax.plot(path[:, 0], path[:, 1], color=colours[i], lw=1.4, alpha=0.9, zorder=3)
        for mask, style in ((modes[:, i] == Mode.FILTER, {"color": "#ff7f0e", "lw": 5, "alpha": 0.45}),
                            (modes[:, i] >= Mode.STALE, {"color": "0.4", "lw": 1.2, "ls": "--"})):
            for a, b in _runs(mask):        # tick k moves the robot from positions[k] to [k + 1]
                ax.plot(path[a:b + 1, 0], path[a:b + 1, 1], zorder=2, **style)
        start, end = placed[[0, -1]]
        ax.add_patch(Circle(start, r, facecolor=colours[i], alpha=0.3, edgecolor=colours[i], zorder=2))
        frozen = bool(record.frozen[:, i].any())
        ax.add_patch(Circle(end, r, facecolor=colours[i], alpha=0.95, edgecolor="black", lw=0.8, zorder=4,
                            hatch="xxx" if frozen else None))
        ax.text(*end, record.ids[i], ha="center", va="center", fontsize=7, color="white", fontweight="bold", zorder=5)
        hits = np.flatnonzero(onset[:, i].any(-1)) + 1
        ax.plot(pos[hits, i, 0], pos[hits, i, 1], "X", ms=8, mfc="none", mec="red", mew=1.6, zorder=6)
    if nowhere:
        ax.text(0.01, 0.01, f"absent (no position in the record): {', '.join(nowhere)}", transform=ax.transAxes,
                ha="left", va="bottom", fontsize=8, zorder=7,
                bbox={"facecolor": "white", "edgecolor": "0.5", "alpha": 0.85, "boxstyle": "round,pad=0.3"})
    ax.set_xlabel("x [m]")
    ax.set_ylabel("y [m]")


def _draw_obstacles(ax, record: EpisodeRecord) -> None:
    """Each obstacle's seen centres dotted, its disc where it was seen last."""
    from matplotlib.patches import Circle

    for j, name in enumerate(record.obstacle_ids):
        seen = record.obstacles[:, j]
        seen = seen[np.isfinite(seen[:, 0])]
        if not len(seen):
            continue
        ax.plot(seen[:, 0], seen[:, 1], color="0.15", ls=":", lw=1.5, zorder=3)
        ax.add_patch(Circle(seen[-1, :2], seen[-1, 2], facecolor="0.3", alpha=0.35, edgecolor="0.1", lw=1.0,
                            zorder=4))
        ax.text(*seen[-1, :2], name, ha="center", va="center", fontsize=7, zorder=5)


def _draw_modes(ax, modes: np.ndarray, record: EpisodeRecord, dt: float) -> None:
    from matplotlib.colors import BoundaryNorm, ListedColormap

    cmap = ListedColormap([MODE_COLOURS[m] for m in Mode])
    norm = BoundaryNorm(np.arange(len(Mode) + 1) - 0.5, len(Mode))
    s, n = modes.shape
    ax.imshow(modes.T, aspect="auto", interpolation="nearest", cmap=cmap, norm=norm,
              extent=(0, s * dt, n - 0.5, -0.5))
    for i in range(n):
        frozen = np.flatnonzero(record.frozen[:, i])
        if len(frozen):
            ax.plot([frozen[0] * dt, s * dt], [i, i], color="red", lw=1, ls=":")
    ax.set_yticks(range(n), [str(x) for x in record.ids], fontsize=8)
    ax.set_ylabel("robot")
    ax.set_title("which layer drove each robot (red dotted: frozen by the world)", fontsize=10)


def _draw_distances(ax, record: EpisodeRecord, scenario: Scenario, colours: list, dt: float) -> None:
    dist, _ = assigned_distances(record)
    t = np.arange(len(dist)) * dt
    floor = 1e-4
    for i in range(record.num_robots):
        ax.plot(t, np.maximum(dist[:, i], floor), color=colours[i], lw=1.3, label=str(record.ids[i]))
    ax.axhline(scenario.target_tolerance, color="0.2", ls="--", lw=0.9)
    ax.annotate(f"tolerance {scenario.target_tolerance:g} m", (0.01, scenario.target_tolerance),
                xycoords=("axes fraction", "data"), xytext=(0, 3), textcoords="offset points", fontsize=8)
    onsets = np.flatnonzero((record.contacts & ~np.concatenate(
        (np.zeros_like(record.contacts[:1]), record.contacts[:-1]))).any((1, 2))) + 1
    for k in onsets:
        ax.axvline(k * dt, color="red", lw=0.8, alpha=0.6)
    ax.set_yscale("log")
    top = float(np.nanmax(dist)) if np.isfinite(dist).any() else 1.0
    ax.set_ylim(floor, max(1.0, math.ceil(top * 10) / 10))
    ax.set_xlim(0, len(dist) * dt)
    ax.set_xlabel("time [s]")
    ax.set_ylabel("distance to assigned target [m]")
    ax.legend(fontsize=7, ncol=max(1, record.num_robots // 5), loc="lower left")


def _check_ticks(record: EpisodeRecord, name: str = "") -> None:
    """PlotError when ``record`` has no ticks (an episode that stopped before its first)."""
    if record.steps == 0:
        raise PlotError(f"{'cannot draw ' + name + ': ' if name else ''}the record has no ticks (the episode "
                        "stopped before its first tick); record an episode of at least one tick")


def _runs(mask: np.ndarray) -> list[tuple[int, int]]:
    """``[(a, b), ...]``: the half-open index ranges where ``mask`` (S,) is True."""
    edges = np.diff(np.concatenate(([0], mask.astype(np.int8), [0])))
    return list(zip(np.flatnonzero(edges == 1), np.flatnonzero(edges == -1), strict=True))


__all__ = ["FILTER_TOLERANCE", "MODE_COLOURS", "Mode", "assigned_distances", "plot_episode", "robot_modes"]
