"""A robots x tokens heatmap of an SDPA actor's attention weights (the paper's Figure 5).

:func:`attention_snapshot` rolls a policy a few steps and reads the weights of one observation,
rearranged by :func:`by_entity` so that column ``R_j`` is robot j in every row;
:func:`plot_attention` draws them (mean over heads and one panel per head). matplotlib and torch
are imported inside the functions, as in :mod:`stack.plots`.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from pathlib import Path

import numpy as np

from stack.plots import PlotError, colormap, new_figure, rollout_env, save_figure


def attention_weights(actor, obs, mask=None) -> np.ndarray:
    """Attention weights of one observation: ``obs`` (N, T, 4) or (1, N, T, 4) -> (N, H, T') numpy.

    T' = T for the typed actor (tokens self, G_1..G_N, other robots, object) and T + 1 for the
    slot actor (slots P, V, G_1..G_N, other robots, O). Each row sums to one over valid tokens.
    """
    import torch

    if not hasattr(actor, "attention"):
        raise PlotError(f"{type(actor).__name__} has no attention weights (the MLP baseline has none); "
                        "use an SDPA actor (variant typed or slot)")
    obs = torch.as_tensor(obs, dtype=torch.float32)
    if obs.dim() == 3:
        obs = obs.unsqueeze(0)
        mask = None if mask is None else torch.as_tensor(mask).unsqueeze(0)
    if obs.dim() != 4 or obs.shape[0] != 1:
        raise PlotError(f"obs must be one observation (N, T, 4) or (1, N, T, 4), got {tuple(obs.shape)}")
    with torch.inference_mode():
        return actor.attention(obs, None if mask is None else torch.as_tensor(mask, dtype=torch.bool))[0].double().numpy()


def by_entity(weights: np.ndarray) -> tuple[np.ndarray, list[str]]:
    """Rearrange (N, H, T') token weights so that column ``R_j`` is robot j for every row.

    A robot's own tokens list the other robots in ascending order skipping itself; here each
    robot j gets its own column ``R_j`` and the cell (i, R_i) is NaN. Returns (N, H, C) weights
    and the C column labels: ``self`` (typed) or ``P``, ``V`` (slot), ``G_1..G_N``, ``R_1..R_N``, ``O``.
    """
    w = np.asarray(weights, dtype=float)
    n, _, t = w.shape
    lead = {2 * n + 1: ["self"], 2 * n + 2: ["P", "V"]}.get(t)
    if lead is None:
        raise PlotError(f"weights for {n} robots must have 2N+1 (typed) or 2N+2 (slot) tokens, got {t}")
    s = len(lead)
    out = np.full((n, w.shape[1], s + 2 * n + 1), np.nan)
    out[:, :, :s + n] = w[:, :, :s + n]
    for i in range(n):
        for slot, j in enumerate(j for j in range(n) if j != i):   # others ascending, skipping i
            out[i, :, s + n + j] = w[i, :, s + n + slot]
    out[:, :, -1] = w[:, :, -1]
    labels = lead + [f"G{k + 1}" for k in range(n)] + [f"R{k + 1}" for k in range(n)] + ["O"]
    return out, labels


def attention_snapshot(actor, scenario, *, seed: int = 0, step: int = 0) -> tuple[np.ndarray, list[str]]:
    """Roll the actor's mean action ``step`` steps from a start drawn with ``seed``; return the
    attention of that observation rearranged by :func:`by_entity`: (N, H, C) weights, C labels."""
    import torch

    if step < 0:
        raise PlotError(f"step must be >= 0, got {step}")
    env = rollout_env(scenario, 1, seed, max(step, 1), actor)
    with torch.inference_mode():
        obs, mask = env.reset()
        for _ in range(step):
            result = env.step(actor(obs, mask))
            obs, mask = result.obs, result.mask
    return by_entity(attention_weights(actor, obs, mask))


def plot_attention(weights: np.ndarray, token_labels: Sequence[str], out_png: str | Path, *,
                   title: str | None = None, row_labels: Sequence[str] | None = None) -> Path:
    """Heatmap of attention weights, robots (rows) x tokens (columns), written to ``out_png``.

    ``weights`` is (N, T) or (N, H, T) with H heads: a large panel of the mean over heads and a
    small panel per head when H > 1. NaN cells (a robot's own column ``R_i``) are grey; values
    are printed in the cells of small maps.
    """
    w = np.asarray(weights, dtype=float)
    if w.ndim == 2:
        w = w[:, None]
    if w.ndim != 3 or w.shape[2] != len(token_labels):
        raise PlotError(f"weights must be (N, T) or (N, H, T) with T = {len(token_labels)} token labels, "
                        f"got shape {w.shape}")
    n, h, t = w.shape
    cell_w, cell_h = (0.36, 0.32) if t <= 16 else (0.22, 0.2)
    unit_w, unit_h = cell_w * t + 0.8, cell_h * n + 1.2
    heads = [f"h{k}" for k in range(h)] if h > 1 else []
    if t <= 16:   # the mean on the left (two units wide), the heads in a grid of two rows on the right
        grid_rows = 1 if h <= 2 else 2
        grid_cols = math.ceil(len(heads) / grid_rows)
        mosaic = [["mean"] + [heads[r * grid_cols + c] if r * grid_cols + c < len(heads) else "."
                              for c in range(grid_cols)] for r in range(grid_rows)]
        ratios = {"width_ratios": [2 if heads else 1] + [1] * grid_cols}
        figsize = (unit_w * (2 + grid_cols if heads else 1) + 1.0, unit_h * max(grid_rows, 1.6) + 0.6)
    else:         # many tokens: the mean on top, the heads two per row below it
        pairs = [heads[k:k + 2] + ["."] * (2 - len(heads[k:k + 2])) for k in range(0, len(heads), 2)]
        mosaic = [["mean", "mean"]] + pairs
        ratios = {"height_ratios": [2] + [1] * len(pairs)}
        figsize = (unit_w + 1.0, unit_h * (1 + len(pairs) / 2) + 0.6)
    fig = new_figure(figsize=figsize)
    axes = fig.subplot_mosaic(mosaic, **ratios)
    rows = list(row_labels) if row_labels is not None else [f"robot {i + 1}" for i in range(n)]
    finite = w[np.isfinite(w)]
    vmax = float(finite.max()) if finite.size else 1.0
    cmap = colormap("viridis").with_extremes(bad="0.85")
    panels = [("mean", "mean over heads" if h > 1 else "attention", np.mean(w, axis=1), 8)]
    panels += [(key, f"head {k + 1}", w[:, k], 6) for k, key in enumerate(heads)]
    image = None
    for key, name, m, size in panels:
        size = size if t <= 16 else 5
        ax = axes[key]
        image = ax.imshow(np.ma.masked_invalid(m), cmap=cmap, vmin=0.0, vmax=vmax, aspect="auto")
        ax.set_xticks(range(t), token_labels, fontsize=size + 1, rotation=90 if t > 16 else 0)
        ax.set_yticks(range(n), rows, fontsize=size + 1 if n <= 8 else size)
        ax.set_title(name, fontsize=11 if key == "mean" else 9)
        if key == "mean":
            ax.set_xlabel("token")
            ax.set_ylabel("robot (query)")
        if n * t <= 300:
            for i in range(n):
                for j in range(t):
                    text = "-" if not np.isfinite(m[i, j]) else f"{m[i, j]:.2f}"
                    light = np.isfinite(m[i, j]) and m[i, j] < 0.6 * vmax
                    ax.text(j, i, text, ha="center", va="center", fontsize=size,
                            color="white" if light else "black")
        for boundary in _groups(token_labels):
            ax.axvline(boundary - 0.5, color="white", lw=2)
    fig.colorbar(image, ax=list(axes.values()), label="attention weight (each row sums to 1)", shrink=0.9)
    fig.suptitle(title or "Attention weights of each robot over its tokens", fontsize=12)
    fig.supxlabel("tokens: G_k target k, R_j robot j (grey: the robot itself), O object, "
                  "self / P, V the robot's own state", fontsize=8, color="0.3")
    return save_figure(fig, out_png)


def _groups(labels: Sequence[str]) -> list[int]:
    """Column indices where the token group (own state, G, R, O) changes."""
    group = [label[0] if label[0] in "GRO" and label[1:].isdigit() or label == "O" else "S" for label in labels]
    return [j for j in range(1, len(group)) if group[j] != group[j - 1]]
