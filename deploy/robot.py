"""Robot-side policy runtime: one file, needs only torch and numpy (copy it onto the robot).

    policy = RobotPolicy("policy.pt")          # loads, checks the golden file, warms up
    accel = policy.act(own_pos, own_vel, targets, others_pos, others_vel, polygon, arena)

Observation tokens (layout version 1, the same as ``sim/observations.py`` of the project;
the file's ``meta.json`` must say ``layout_version`` 1). Robot i of N builds ``2N + 1`` tokens
of 4 features (metres, m/s; arena (W, H) centred at (W/2, H/2))::

    self            [p_x - W/2, p_y - H/2, v_x, v_y]
    target k        [g_k - p, 0, 0]              k = 1..N, in the fleet's target order
    other robot j   [q_j - p, u_j - v]           j != i, ascending robot order
    object          [c - p, s - p]               c: polygon centroid, s: nearest boundary point

The action is the policy's mean acceleration (2,) [m/s^2], finite and bounded by the
file's ``accel_limit``; a non-finite result raises instead of reaching the motors.
"""

from __future__ import annotations

import hashlib
import json
import warnings
from pathlib import Path

import numpy as np
import torch

LAYOUT_VERSION = 1
TOKEN_DIM = 4
TOLERANCE = 1e-5


class RobotPolicyError(RuntimeError):
    """The policy file cannot be trusted on this robot; the message says why."""


def polygon_centroid(poly: np.ndarray) -> np.ndarray:
    """(M, 2) counter-clockwise vertices -> (2,) area centroid [m]."""
    x, y = poly[:, 0], poly[:, 1]
    xn, yn = np.roll(x, -1), np.roll(y, -1)
    cross = x * yn - xn * y
    area = 0.5 * cross.sum()
    return np.array([((x + xn) * cross).sum(), ((y + yn) * cross).sum()]) / (6.0 * area)


def nearest_boundary_point(point: np.ndarray, poly: np.ndarray) -> np.ndarray:
    """(2,) point, (M, 2) polygon -> (2,) nearest point on the polygon's edges [m]."""
    a = poly
    e = np.roll(poly, -1, axis=0) - a
    t = np.clip(((point - a) * e).sum(1) / (e * e).sum(1), 0.0, 1.0)
    candidates = a + t[:, None] * e
    return candidates[np.argmin(((candidates - point) ** 2).sum(1))]


def robot_tokens(own_pos, own_vel, targets, others_pos, others_vel, polygon,
                 arena) -> np.ndarray:
    """One robot's (2N+1, 4) float64 tokens; shapes (2,), (2,), (N, 2), (N-1, 2), (N-1, 2),
    (M, 2), (2,) in metres and m/s (see the module docstring)."""
    p = np.asarray(own_pos, dtype=np.float64).reshape(2)
    v = np.asarray(own_vel, dtype=np.float64).reshape(2)
    g = np.asarray(targets, dtype=np.float64).reshape(-1, 2)
    q = np.asarray(others_pos, dtype=np.float64).reshape(-1, 2)
    u = np.asarray(others_vel, dtype=np.float64).reshape(-1, 2)
    poly = np.asarray(polygon, dtype=np.float64).reshape(-1, 2)
    n = len(g)
    if len(q) != n - 1 or len(u) != n - 1:
        raise ValueError(f"others_pos/others_vel need N-1 = {n - 1} rows for {n} targets, "
                         f"got {len(q)} and {len(u)}")
    for name, arr in (("own_pos", p), ("own_vel", v), ("targets", g), ("others_pos", q),
                      ("others_vel", u), ("polygon", poly)):
        if not np.all(np.isfinite(arr)):
            raise ValueError(f"{name} contains NaN or inf; refusing to act on it")
    w, h = float(arena[0]), float(arena[1])
    out = np.zeros((2 * n + 1, TOKEN_DIM))
    out[0] = (p[0] - w / 2, p[1] - h / 2, v[0], v[1])
    out[1:n + 1, :2] = g - p
    out[n + 1:2 * n, :2] = q - p
    out[n + 1:2 * n, 2:] = u - v
    out[2 * n, :2] = polygon_centroid(poly) - p
    out[2 * n, 2:] = nearest_boundary_point(p, poly) - p
    return out


class RobotPolicy:
    """An exported policy on one robot (see the module docstring).

    Args:
        path: the TorchScript file; its golden file (``meta.json: golden_file``) must lie beside.
        threads: torch intra-op threads (1 on the control path).
        warmup: forward passes at start-up (the first calls after loading are slow).
    """

    def __init__(self, path: str | Path, threads: int = 1, warmup: int = 20):
        torch.set_num_threads(threads)
        self.path = Path(path)
        extra = {"meta.json": ""}
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            self.module = torch.jit.load(str(self.path), map_location="cpu",
                                         _extra_files=extra).eval()
        self.meta = json.loads(extra["meta.json"])
        if self.meta.get("layout_version") != LAYOUT_VERSION:
            raise RobotPolicyError(f"{self.path}: observation layout "
                                   f"{self.meta.get('layout_version')} but this runtime builds "
                                   f"layout {LAYOUT_VERSION}; update robot.py or re-export")
        self.accel_limit = float(self.meta["accel_limit"])
        self.golden_diff = self._check_golden()
        for _ in range(warmup):
            self._forward(np.zeros((2 * 5 + 1, TOKEN_DIM)))

    def _check_golden(self) -> float:
        """Replay the golden file through this runtime's token builder and the model."""
        golden = self.path.with_name(self.meta["golden_file"])
        if not golden.is_file():
            raise RobotPolicyError(f"golden file {golden} is missing; copy it beside {self.path}")
        if hashlib.sha256(golden.read_bytes()).hexdigest() != self.meta["golden_sha256"]:
            raise RobotPolicyError(f"golden file {golden} does not belong to {self.path}")
        worst = 0.0
        with np.load(golden) as data:
            poly, arena = data["polygon"], data["arena"]
            for n in data["counts"]:
                pos, vel, tgt = (data[f"n{n}_{k}"][0] for k in ("pos", "vel", "targets"))
                for i in range(n):
                    others = [j for j in range(n) if j != i]
                    toks = robot_tokens(pos[i], vel[i], tgt, pos[others], vel[others], poly, arena)
                    token_diff = np.abs(toks - data[f"n{n}_tokens"][0, i]).max()
                    if not token_diff <= 1e-9:
                        raise RobotPolicyError(f"tokens of robot {i} of {n} differ from the golden "
                                               f"file by {token_diff:.3g}: layout mismatch")
                    diff = np.abs(self._forward(toks) - data[f"n{n}_actions"][0, i]).max()
                    worst = max(worst, float(diff) if np.isfinite(diff) else float("inf"))
        if not worst <= TOLERANCE:
            raise RobotPolicyError(f"{self.path} gives actions {worst:.3g} away from its golden "
                                   f"file (> {TOLERANCE}); do not run it")
        return worst

    @torch.no_grad()
    def _forward(self, toks: np.ndarray) -> np.ndarray:
        x = torch.from_numpy(toks).float().unsqueeze(0)
        mask = torch.ones(x.shape[:2], dtype=torch.bool)
        return self.module.act(x, mask)[0].double().numpy()

    def act(self, own_pos, own_vel, targets, others_pos, others_vel, polygon,
            arena) -> np.ndarray:
        """The robot's mean acceleration (2,) [m/s^2] (arguments as :func:`robot_tokens`)."""
        a = self._forward(robot_tokens(own_pos, own_vel, targets, others_pos, others_vel,
                                       polygon, arena))
        if not np.all(np.isfinite(a)):
            raise RobotPolicyError("the policy produced a non-finite acceleration; brake")
        return a


__all__ = ["LAYOUT_VERSION", "RobotPolicy", "RobotPolicyError", "robot_tokens"]
