"""Robot-side policy runtime: one file, needs only numpy and onnxruntime (copy it onto the robot).

    policy = RobotPolicy("policy.onnx")        # checks hash, layout and golden file, warms up
    accel, valid = policy.act(own_pos, own_vel, targets, others_pos, others_vel, polygon, arena)

The file is what ``formation export CKPT --format onnx`` writes; its golden file
(``policy.golden.npz``) must lie beside it. ``RobotPolicy("policy.npz")`` runs the npz format
instead (``--format npz``, the compiled kernel: numpy and numba, no onnxruntime), with
``npz_policy.py`` (``deploy/npz_policy.py``) copied beside this file. Loading refuses a file whose ``content_sha256``
does not match its bytes (:func:`onnx_content_ok`: any changed byte, weights or metadata), a
foreign format or observation layout, and a file whose actions differ from its golden file.

Observation tokens (layout version 1, the same as ``sim/observations.py`` of the project;
``meta.token_features`` of the file lists them). Robot i of N builds ``2N + 1`` tokens of 4
features (metres, m/s; arena (W, H) centred at (W/2, H/2))::

    self            [p_x - W/2, p_y - H/2, v_x, v_y]
    target k        [g_k - p, 0, 0]              k = 1..N, in the fleet's target order
    other robot j   [q_j - p, u_j - v]           j != i, ascending robot order
    object          [c - p, s - p]               c: polygon centroid, s: nearest boundary point

A file whose ``meta["own_target"]`` is true reads robot i's own target marked: target
``k = sigma_i`` of the team's one-to-one assignment of least total squared path length round
the object (:func:`own_targets`, with ``meta["own_target_margin"]``) has features
``[d, d min(1, 0.1 m / |d|)]``, ``d = g_k - p``; ``act`` works the assignment out from the
positions it is given, or takes ``own_target``. Ties are broken as training breaks them, by the
robots' order: ``act``'s ``index`` is the robot's place in it, so on a tie every robot of the
team still takes a different target.

The action is the policy's mean acceleration (2,) [m/s^2], bounded in norm by the file's
``accel_limit``; with any input non-finite it is (0, 0) and ``valid`` is False: brake.
"""

from __future__ import annotations

import hashlib
import itertools
import json
import math
from pathlib import Path
from typing import NamedTuple

import numpy as np

LAYOUT_VERSION = 1
TOKEN_DIM = 4
TOLERANCE = 1e-5
OWN_TARGET_REACH = 0.1               # [m] the own-target mark's length (sim/observations.py)
ENUMERATE_MAX_N = 4                  # teams up to this size: every matching tried (sim/metrics.py)
EXPORT_FORMAT = "formation-stack/policy"
EXPORT_FORMAT_VERSION = 2
META_KEY = "formation.meta"          # ONNX metadata_props key holding the metadata JSON
HASH_FIELD = "content_sha256"
PLACEHOLDER = "0" * 64


class RobotPolicyError(RuntimeError):
    """The policy file cannot be trusted on this robot; the message says why."""


class Action(NamedTuple):
    accel: np.ndarray   # (2,) [m/s^2]
    valid: bool         # False: an input was not finite, accel is 0: brake


def hash_needle(digest: str) -> bytes:
    """The bytes ``"content_sha256": "<digest>"`` as they stand in an ONNX file's metadata JSON."""
    return json.dumps({HASH_FIELD: digest})[1:-1].encode()


def onnx_meta_json(meta: dict) -> str:
    """The metadata as stored in an ONNX file: sorted keys, ``content_sha256`` as given."""
    return json.dumps(meta, sort_keys=True)


def onnx_content_ok(data: bytes, meta: dict) -> bool:
    """True when ``sha256(data with the stored digest zeroed) == meta["content_sha256"]``: the
    digest of an ONNX file covers every byte (weights, graph, metadata), written with the
    placeholder of 64 zeros in its place (``deploy.export.formats``)."""
    digest = meta.get(HASH_FIELD)
    if not isinstance(digest, str) or len(digest) != 64:
        return False
    needle = hash_needle(digest)
    if data.count(needle) != 1:
        return False
    return hashlib.sha256(data.replace(needle, hash_needle(PLACEHOLDER))).hexdigest() == digest


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


def detour_distances(points, targets, polygon, margin: float) -> np.ndarray:
    """(P, K) shortest distances [m] from (P, 2) points to (K, 2) targets around a convex
    counter-clockwise polygon (M, 2) inflated by ``margin`` (the taut string; the project's
    ``sim.geometry.DetourDistance``): straight where the segment misses the inflated polygon,
    else point -> visible corner -> along the perimeter -> corner -> target; a point inside is
    first moved to the nearest boundary point. A non-convex polygon gives straight distances."""
    p = np.asarray(points, dtype=np.float64).reshape(-1, 2)
    g = np.asarray(targets, dtype=np.float64).reshape(-1, 2)
    v = np.asarray(polygon, dtype=np.float64).reshape(-1, 2)
    straight = np.linalg.norm(p[:, None] - g[None], axis=-1)
    e = np.roll(v, -1, axis=0) - v
    if not (e[:, 0] * np.roll(e[:, 1], -1) - e[:, 1] * np.roll(e[:, 0], -1) > 0).all():
        return straight
    normal = np.stack((e[:, 1], -e[:, 0]), -1) / np.linalg.norm(e, axis=1)[:, None]   # outward
    bis = normal + np.roll(normal, 1, axis=0)
    corners = v + bis / 2 * (margin / ((bis * bis).sum(1) / 4))[:, None]
    offset = (v * normal).sum(1) + margin - 1e-6

    def visible(a, b):                       # segments a -> b (broadcast (..., 2)) miss the polygon
        a, b = np.broadcast_arrays(a, b)
        num = offset - a @ normal.T
        den = (b - a) @ normal.T
        with np.errstate(divide="ignore", invalid="ignore"):
            ratio = num / np.where(den == 0, 1.0, den)
        t_enter = np.maximum(np.where(den < 0, ratio, -np.inf).max(-1), 0.0)
        t_exit = np.minimum(np.where(den > 0, ratio, np.inf).min(-1), 1.0)
        return ((den == 0) & (num < 0)).any(-1) | (t_enter >= t_exit)

    side = np.linalg.norm(np.roll(corners, -1, axis=0) - corners, axis=1)
    cum = np.concatenate(([0.0], np.cumsum(side)))
    fwd = (cum[None, :-1] - cum[:-1, None]) % cum[-1]
    perimeter = np.minimum(fwd, cum[-1] - fwd)                                      # (M, M)
    d_cg = np.where(visible(corners[:, None], g[None]), np.linalg.norm(corners[:, None] - g[None], axis=-1), np.inf)
    h = (perimeter[:, :, None] + d_cg[None]).min(1)                                 # (M, K)
    ce = np.roll(corners, -1, axis=0) - corners                                     # inflated edges
    r = p[:, None] - corners[None]
    t = np.clip((r * ce).sum(-1) / (ce * ce).sum(1), 0.0, 1.0)
    gap = r - t[..., None] * ce
    nearest = np.argmin((gap * gap).sum(-1), axis=1)
    rows = np.arange(len(p))
    inside = ((ce[None, :, 0] * r[..., 1] - ce[None, :, 1] * r[..., 0]) > 0).all(1)
    q = np.where(inside[:, None], corners[nearest] + t[rows, nearest, None] * ce[nearest], p)
    lead_in = np.where(inside, np.linalg.norm(gap[rows, nearest], axis=-1), 0.0)
    direct = visible(q[:, None], g[None])
    d_pc = np.where(visible(q[:, None], corners[None]), np.linalg.norm(q[:, None] - corners[None], axis=-1), np.inf)
    around = (d_pc[:, :, None] + h[None]).min(1)
    out = np.where(direct, np.linalg.norm(q[:, None] - g[None], axis=-1), around)
    return np.where(np.isinf(out), straight, out + lead_in[:, None])


def least_squares_assignment(path) -> np.ndarray:
    """(N,) int: the column of each row of an (N, N) matrix of path lengths [m] under the
    one-to-one assignment of least total squared length, ties broken as training breaks them
    (``sim.metrics.optimal_assignment``, which ``sim.observations.own_assignment`` solves): up to
    ``ENUMERATE_MAX_N`` rows the first matching in lexicographic order of least total (squares
    summed in row order), above that scipy's ``linear_sum_assignment`` step for step. numpy
    only; ValueError where a squared length is not finite."""
    cost = np.square(np.asarray(path, dtype=np.float64))
    if not np.isfinite(cost).all():                    # NaN or inf: no least total to find
        raise ValueError("least_squares_assignment: every path length must be finite (and its square)")
    if len(cost) <= ENUMERATE_MAX_N:
        return _first_least_matching(cost.tolist())
    return _shortest_augmenting_path(cost)


def _first_least_matching(cost: list[list[float]]) -> np.ndarray:
    """Every matching in ``itertools.permutations`` order; the first whose total, summed from
    row 0 on as torch sums a row of up to four, is least (torch's ``argmin`` keeps the first)."""
    best, best_total = None, math.nan
    for perm in itertools.permutations(range(len(cost))):
        total = 0.0
        for i, j in enumerate(perm):
            total += cost[i][j]
        if best is None or total < best_total:
            best, best_total = perm, total
    return np.array(best, dtype=np.int64)


def _shortest_augmenting_path(cost: np.ndarray) -> np.ndarray:
    """scipy's ``linear_sum_assignment`` of a square finite matrix (Crouse's shortest augmenting
    path, as ``rectangular_lsap.cpp`` runs it: the same float operations, in the same order, so
    the same choice on every tie)."""
    n = len(cost)
    c = cost.tolist()
    u, v = [0.0] * n, [0.0] * n
    path, col4row, row4col = [-1] * n, [-1] * n, [-1] * n
    for cur in range(n):
        remaining = list(range(n - 1, -1, -1))     # reversed: a constant matrix gives the identity
        rows_seen, cols_seen = [False] * n, [False] * n
        shortest = [math.inf] * n
        min_val, i, sink = 0.0, cur, -1
        while sink == -1:
            index, lowest = -1, math.inf
            rows_seen[i] = True
            for it, j in enumerate(remaining):
                r = min_val + c[i][j] - u[i] - v[j]
                if r < shortest[j]:
                    path[j], shortest[j] = i, r
                if shortest[j] < lowest or (shortest[j] == lowest and row4col[j] == -1):
                    lowest, index = shortest[j], it
            min_val = lowest
            if index < 0 or min_val == math.inf:
                raise ValueError("least_squares_assignment: the squared path lengths overflow")
            j = remaining[index]
            if row4col[j] == -1:
                sink = j
            else:
                i = row4col[j]
            cols_seen[j] = True
            remaining[index] = remaining[-1]
            remaining.pop()
        u[cur] += min_val
        for k in range(n):
            if rows_seen[k] and k != cur:
                u[k] += min_val - shortest[col4row[k]]
        for j in range(n):
            if cols_seen[j]:
                v[j] -= min_val - shortest[j]
        j = sink
        while True:
            k = path[j]
            row4col[j] = k
            col4row[k], j = j, col4row[k]
            if k == cur:
                break
    return np.array(col4row, dtype=np.int64)


def own_targets(pos, targets, polygon, margin: float) -> np.ndarray:
    """(N,) int: each robot's own target for an ``own_target`` policy (the project's
    ``sim.observations.own_assignment``): the assignment of least total squared detour length
    round the polygon inflated by ``margin`` (``meta["own_target_margin"]``), for (N, 2)
    positions [m] in the fleet's robot order (it breaks ties) and (N, 2) targets [m]."""
    return least_squares_assignment(detour_distances(pos, targets, polygon, margin))


def robot_tokens(own_pos, own_vel, targets, others_pos, others_vel, polygon,
                 arena, own_target: int | None = None) -> np.ndarray:
    """One robot's (2N+1, 4) float64 tokens; shapes (2,), (2,), (N, 2), (N-1, 2), (N-1, 2),
    (M, 2), (2,) in metres and m/s (see the module docstring). Non-finite inputs pass through
    (the exported module answers them with braking). ``own_target`` k: the robot's own target
    (an ``own_target`` policy), whose token gets the mark ``[d, d min(1, 0.1 m / |d|)]``."""
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
    w, h = float(arena[0]), float(arena[1])
    out = np.zeros((2 * n + 1, TOKEN_DIM))
    out[0] = (p[0] - w / 2, p[1] - h / 2, v[0], v[1])
    out[1:n + 1, :2] = g - p
    out[n + 1:2 * n, :2] = q - p
    out[n + 1:2 * n, 2:] = u - v
    with np.errstate(invalid="ignore", divide="ignore"):
        out[2 * n, :2] = polygon_centroid(poly) - p
        out[2 * n, 2:] = nearest_boundary_point(p, poly) - p if np.isfinite(p).all() else np.nan
        if own_target is not None:
            d = out[1 + int(own_target), :2]
            out[1 + int(own_target), 2:] = d * (OWN_TARGET_REACH / max(float(np.hypot(*d)), OWN_TARGET_REACH))
    return out


def onnx_session(data: bytes, threads: int = 1):
    """An ``onnxruntime.InferenceSession`` of a serialized model with the control path's options:
    ``threads`` intra-op threads, the basic graph optimizations, the CPU provider."""
    import onnxruntime as ort

    options = ort.SessionOptions()
    options.intra_op_num_threads = threads
    options.inter_op_num_threads = 1
    options.log_severity_level = 3
    # the extended fusions regroup float32 sums: 1.3e-5 off the eager actor where basic keeps 9e-6
    options.graph_optimization_level = ort.GraphOptimizationLevel.ORT_ENABLE_BASIC
    return ort.InferenceSession(data, options, providers=["CPUExecutionProvider"])


def open_onnx(path: str | Path, threads: int = 1):
    """``(onnxruntime.InferenceSession, meta)`` of an exported ONNX file, its digest and format
    checked (not its observation layout: the caller knows which it builds); raises
    RobotPolicyError naming what is wrong."""
    import onnxruntime  # noqa: F401  (a missing runtime raises ImportError here, not "a bad file")

    path = Path(path)
    if not path.is_file():
        raise RobotPolicyError(f"policy file {str(path)!r} does not exist")
    data = path.read_bytes()
    try:
        session = onnx_session(data, threads)
        meta = json.loads(session.get_modelmeta().custom_metadata_map[META_KEY])
    except Exception as err:
        raise RobotPolicyError(f"{str(path)!r} is not an exported ONNX policy "
                               f"({type(err).__name__}: {err}); export it with `formation export "
                               "CKPT --format onnx`") from None
    if not isinstance(meta, dict) or (meta.get("format"), meta.get("format_version")) != (
            EXPORT_FORMAT, EXPORT_FORMAT_VERSION):
        raise RobotPolicyError(f"{str(path)!r} is not a {EXPORT_FORMAT} v{EXPORT_FORMAT_VERSION} file")
    if not onnx_content_ok(data, meta):
        raise RobotPolicyError(f"{str(path)!r}: its bytes do not match its content_sha256: the "
                               "file was changed after export (weights or metadata); export it again")
    return session, meta


def _open_npz(path: Path):
    """``(runner, meta)`` of an npz policy through ``npz_policy.py`` (the project's, or a copy
    beside this file on a robot); RobotPolicyError naming what is wrong."""
    try:
        from deploy.npz_policy import NpzPolicyError, open_npz
    except ImportError:
        try:
            from npz_policy import NpzPolicyError, open_npz
        except ImportError as err:
            raise RobotPolicyError(f"{str(path)!r} is an npz policy: copy deploy/npz_policy.py beside "
                                   f"robot.py and `pip install numba` ({err})") from None
    try:
        return open_npz(path)
    except NpzPolicyError as err:
        raise RobotPolicyError(str(err)) from None


class RobotPolicy:
    """An exported ONNX (or npz) policy on one robot (see the module docstring).

    Args:
        path: the ``.onnx`` (or ``.npz``) file; its golden file (``meta.golden_file``) must lie beside.
        threads: onnxruntime intra-op threads (1 on the control path).
        warmup: forward passes at start-up (the first calls after loading are slow).
    """

    def __init__(self, path: str | Path, threads: int = 1, warmup: int = 20):
        self.path = Path(path)
        if self.path.suffix == ".npz":
            self.session, self.meta = _open_npz(self.path)
        else:
            self.session, self.meta = open_onnx(self.path, threads)
        if self.meta.get("layout_version") != LAYOUT_VERSION or self.meta.get("token_dim") != TOKEN_DIM:
            raise RobotPolicyError(f"{str(path)!r}: observation layout {self.meta.get('layout_version')} "
                                   f"with {self.meta.get('token_dim')} features, but this runtime builds "
                                   f"layout {LAYOUT_VERSION} with {TOKEN_DIM}; update robot.py or re-export")
        self.accel_limit = float(self.meta["accel_limit"])
        self.own_target = bool(self.meta.get("own_target", False))
        self.own_target_margin = float(self.meta.get("own_target_margin", 0.0))
        counts = [int(c) for c in self.meta.get("robot_counts") or ()]
        self.robot_counts = frozenset(counts)     # the team sizes the file was verified for; empty: any
        self._counts_text = (f"{min(counts)}..{max(counts)}" if len(counts) > 1 else str(counts[0])) if counts else ""
        self.golden_diff = self._check_golden()
        n = min(counts) if counts else 5           # a slot file runs its own N only
        for _ in range(warmup):
            self._forward(np.zeros((1, 2 * n + 1, TOKEN_DIM)))

    def _check_golden(self) -> float:
        """Replay the golden file through this runtime's token builder and the model."""
        golden = self.path.with_name(str(self.meta.get("golden_file")))
        if not golden.is_file():
            raise RobotPolicyError(f"golden file {golden} is missing; copy it beside {self.path}")
        if hashlib.sha256(golden.read_bytes()).hexdigest() != self.meta.get("golden_sha256"):
            raise RobotPolicyError(f"golden file {golden} does not belong to {self.path}")
        worst = 0.0
        with np.load(golden) as data:
            poly, arena = data["polygon"], data["arena"]
            for n in data["counts"]:
                pos, vel, tgt = (data[f"n{n}_{k}"][0] for k in ("pos", "vel", "targets"))
                own = own_targets(pos, tgt, poly, self.own_target_margin) if self.own_target else [None] * n
                if self.own_target and not np.array_equal(own, data[f"n{n}_own"][0]):
                    raise RobotPolicyError(f"the own-target assignment of {n} robots differs from the "
                                           "golden file's: this runtime would mark other targets")
                rows = []
                for i in range(n):
                    others = [j for j in range(n) if j != i]
                    rows.append(robot_tokens(pos[i], vel[i], tgt, pos[others], vel[others], poly, arena,
                                             own[i]))
                toks = np.stack(rows)
                token_diff = np.abs(toks - data[f"n{n}_tokens"][0]).max()
                if not token_diff <= 1e-9:
                    raise RobotPolicyError(f"tokens of {n} robots differ from the golden file by "
                                           f"{token_diff:.3g}: layout mismatch")
                accel, valid = self._forward(toks)
                diff = np.abs(accel - data[f"n{n}_actions"][0]).max()
                if not valid.all():
                    diff = np.inf
                worst = max(worst, float(diff) if np.isfinite(diff) else float("inf"))
        if not worst <= TOLERANCE:
            raise RobotPolicyError(f"{self.path} gives actions {worst:.3g} away from its golden "
                                   f"file (> {TOLERANCE}); do not run it")
        return worst

    def _forward(self, toks: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """(B, T, 4) tokens, all valid -> accel (B, 2) float64, valid (B,) bool."""
        x = np.ascontiguousarray(toks, dtype=np.float32)
        mask = np.ones(x.shape[:2], dtype=bool)
        if callable(self.session):                      # the npz kernel
            accel, valid = self.session(x, mask)
        else:
            accel, valid = self.session.run(None, {"tokens": x, "mask": mask})
        return accel.astype(np.float64), valid

    def _own_target(self, team: np.ndarray, targets, polygon, index: int) -> int | None:
        """Robot ``index``'s target under :func:`own_targets` of ``team`` (N, 2) [m], in the
        fleet's robot order; None (nothing marked) where the picture has no assignment (a path
        length that is not finite): the policy then brakes on its invalid input."""
        try:
            return int(own_targets(team, targets, polygon, self.own_target_margin)[index])
        except ValueError:
            return None

    def act(self, own_pos, own_vel, targets, others_pos, others_vel, polygon, arena,
            own_target: int | None = None, index: int = 0) -> Action:
        """The robot's mean acceleration [m/s^2] and whether it is valid (arguments as
        :func:`robot_tokens`); never NaN. A policy that reads its own target marked
        (``meta["own_target"]``) gets target ``own_target`` marked, or when None the robot's
        target under :func:`own_targets` of the team it sees: ``index`` is this robot's place
        in the fleet's robot order (``others_pos`` holds the others in that order), so the team
        is ``others[:index] + [own] + others[index:]``, in the order training breaks ties by.
        A robot that passes the wrong index may, on a tie, take a teammate's target."""
        n = len(np.asarray(targets).reshape(-1, 2))
        if self.robot_counts and n not in self.robot_counts:
            raise ValueError(f"{self.path} runs teams of {self._counts_text} robots (meta robot_counts); "
                             f"this team has {n} targets: export a policy for {n} robots")
        if own_target is not None and not self.own_target:
            raise ValueError(f"{self.path} does not read an own target (its metadata's own_target is "
                             "false); call act without own_target")
        if own_target is not None and not 0 <= int(own_target) < n:
            raise ValueError(f"own_target must index one of the {n} targets, got {own_target}")
        if not 0 <= int(index) < n:
            raise ValueError(f"index must be this robot's place among the {n} robots, got {index}")
        if self.own_target and own_target is None:
            others = np.asarray(others_pos, dtype=np.float64).reshape(-1, 2)
            team = np.insert(others, int(index), np.asarray(own_pos, dtype=np.float64).reshape(2), axis=0)
            own_target = self._own_target(team, targets, polygon, int(index))
        toks = robot_tokens(own_pos, own_vel, targets, others_pos, others_vel, polygon, arena, own_target)
        accel, valid = self._forward(toks[None])
        return Action(accel[0], bool(valid[0]))


__all__ = ["Action", "RobotPolicy", "RobotPolicyError", "detour_distances", "hash_needle",
           "least_squares_assignment", "onnx_content_ok", "onnx_session", "open_onnx", "own_targets",
           "robot_tokens"]
