"""The exported contract: one tensor-only wrapper and the metadata every format carries.

Every format (:mod:`deploy.export.formats`) holds the same module, :class:`PolicyContract`::

    forward(tokens (B, T, 4) float32, mask (B, T) bool) -> (accel (B, 2) float32, valid (B,) bool)

one row per robot, ``T = 2N + 1`` tokens of robot i of N in the layout of
:mod:`sim.observations` (:data:`TOKEN_FEATURES`); ``B`` and ``T`` are free (1..21 robots from one
file; a slot actor's file has one N). The module enforces the contract inside the file, so a
robot that calls it directly gets the same guarantees as the ControlStack:

* ``mask[b, t]`` True: token t of row b is valid; False: it is ignored (its features may hold
  anything, NaN included). Token 0 (the robot itself) is always read.
* a row whose read features are not all finite is answered with ``accel = 0`` and
  ``valid = False``: brake (the robot's own braking law), never act on it;
* ``accel = a / max(1, |a| / limit)``: bounded in norm by ``accel_limit`` (the actor bounds each
  component; the norm of a corner reached 1.31 m/s^2 at a 1.0 limit);
* parameters are frozen (``requires_grad=False``): any grad mode runs it.

Integrity: ``content_sha256`` in the metadata covers every other metadata field and all the
file holds besides (:func:`archive_digest` for the zip formats; every byte of an ONNX file,
:func:`deploy.robot.onnx_content_ok`). Every loader checks it.
"""

from __future__ import annotations

import copy
import hashlib
import zipfile
from pathlib import Path
from typing import Any

import torch
import torch.nn.functional as F
from torch import nn

from controllers.policy import TypedSDPAActor
from deploy.export.graph import TypedRows
from deploy.npz_policy import canonical_meta as canonical_json
from sim.observations import LAYOUT_VERSION, TOKEN_DIM
from sim.scenario import MAX_ROBOTS

EXPORT_FORMAT = "formation-stack/policy"
EXPORT_FORMAT_VERSION = 2
HASH_FIELD = "content_sha256"
UNHASHED_MEMBERS = ("extra/meta.json", ".data/serialization_id")

TOKEN_FEATURES: dict[str, Any] = {
    "tokens_per_robot": "T = 2N + 1 for robot i of N, in this order",
    "frame": "metres and m/s; the arena (W, H) is centred at (W/2, H/2)",
    "kinds": [
        {"token": "0", "kind": "self", "features": ["p_x - W/2 [m]", "p_y - H/2 [m]", "v_x [m/s]", "v_y [m/s]"]},
        {"token": "1..N", "kind": "target k", "features": ["g_kx - p_x [m]", "g_ky - p_y [m]", "0", "0"],
         "order": "the fleet's target order",
         "own_target": "when the metadata's own_target is true, robot i's own target k = sigma_i "
                       "(sigma: the team's one-to-one assignment of least total squared path "
                       "length round the object inflated by own_target_margin) has features "
                       "[d_x, d_y, m_x, m_y], d = g_k - p, m = d * min(1, 0.1 m / |d|)"},
        {"token": "N+1..2N-1", "kind": "other robot j", "features": [
            "q_jx - p_x [m]", "q_jy - p_y [m]", "u_jx - v_x [m/s]", "u_jy - v_y [m/s]"],
         "order": "ascending robot index, j != i"},
        {"token": "2N", "kind": "object", "features": [
            "c_x - p_x [m]", "c_y - p_y [m]", "s_x - p_x [m]", "s_y - p_y [m]"],
         "note": "c: polygon area centroid, s: nearest point of its boundary"},
    ],
}

IO_SPEC: dict[str, Any] = {
    "inputs": {
        "tokens": {"dtype": "float32", "shape": ["B", "T", TOKEN_DIM],
                   "note": "one row per robot; float64 must be cast"},
        "mask": {"dtype": "bool", "shape": ["B", "T"], "required": True,
                 "true_means": "the token is valid; False tokens are ignored (token 0 always read)"},
    },
    "outputs": {
        "accel": {"dtype": "float32", "shape": ["B", 2], "unit": "m/s^2",
                  "note": "bounded in norm by accel_limit"},
        "valid": {"dtype": "bool", "shape": ["B"],
                  "false_means": "a read feature was not finite: accel is 0, brake"},
    },
}


class PolicyContract(nn.Module):
    """The deterministic actor (a frozen copy) behind the contract of the module docstring.

    ``PolicyContract(actor)`` runs the actor's own ``rows``: the reference every file is compared
    with. :meth:`for_export` is what the files hold: for a typed actor the same numbers through
    :class:`deploy.export.graph.TypedRows` (fewer operations), else the same as the reference.
    """

    def __init__(self, actor: nn.Module, rows: nn.Module | None = None):
        super().__init__()
        if not hasattr(actor, "rows"):
            raise TypeError(f"{type(actor).__name__} has no rows(tokens, mask); only token actors "
                            "(variant 'typed' or 'slot') can be exported")
        self.actor = rows if rows is not None else copy.deepcopy(actor).eval()
        for p in self.actor.parameters():
            p.requires_grad_(False)
        self.accel_limit = float(getattr(actor, "accel_limit", 1.0))

    @classmethod
    def for_export(cls, actor: nn.Module) -> PolicyContract:
        return cls(actor, TypedRows(actor) if isinstance(actor, TypedSDPAActor) else None)

    def forward(self, tokens: torch.Tensor, mask: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        # rows are independent (attention runs within a row), so a non-finite row spoils only
        # its own output; s - s == 0 holds for finite s only (NaN - NaN and inf - inf are NaN).
        # |a| stands for the actions in the check: the actor bounds them, so it is finite iff a is
        read = F.pad(mask[:, 1:], (1, 0), value=True)
        f = torch.where(read.unsqueeze(-1), tokens, torch.zeros((), dtype=tokens.dtype))
        a = self.actor.rows(f, read)
        norm = torch.linalg.vector_norm(a, dim=-1)
        total = f.sum((1, 2)) + norm
        valid = (total - total) == 0
        if self.accel_limit != 1.0:
            norm = norm * (1.0 / self.accel_limit)
        a = a / torch.clamp(norm, min=1.0).unsqueeze(-1)
        return torch.where(valid.unsqueeze(-1), a, torch.zeros((), dtype=a.dtype)), valid


def check_io_shapes(tokens: Any, mask: Any, robot_counts: frozenset[int] | None = None) -> None:
    """Raise ValueError unless ``tokens`` is (B, T, 4) and ``mask`` (B, T) with ``T = 2N + 1`` for
    a team of N robots the file runs (``robot_counts``; default 1..MAX_ROBOTS)."""
    shape, mask_shape = getattr(tokens, "shape", None), getattr(mask, "shape", None)
    if shape is None or len(shape) != 3 or shape[2] != TOKEN_DIM:
        raise ValueError(f"policy input: tokens must be (B, T, {TOKEN_DIM}), got shape {shape}")
    n, odd = divmod(shape[1] - 1, 2)
    counts = robot_counts or frozenset(range(1, MAX_ROBOTS + 1))
    if odd or n not in counts:
        raise ValueError(f"policy input: T = {shape[1]} tokens a row is not 2N + 1 for a team this file runs "
                         f"(N in {min(counts)}..{max(counts)})")
    if mask_shape is None or tuple(mask_shape) != tuple(shape[:2]):
        raise ValueError(f"policy input: mask must be (B, T) = {tuple(shape[:2])}, got shape {mask_shape}")


def archive_digest(path: Path, meta: dict[str, Any]) -> str:
    """``content_sha256`` of a zip-archive format (TorchScript, .pt2): sha256 over the canonical
    metadata and every member but the metadata itself and torch's random serialization id, in
    name order (name and sha256 of the content; names without the archive's top folder). The
    members are the code, the constants and the weights: any change to what runs shows."""
    digest = hashlib.sha256(canonical_json(meta))
    with zipfile.ZipFile(path) as archive:
        members = {info.filename.split("/", 1)[-1]: info for info in archive.infolist()}
        for name in sorted(members):
            if name in UNHASHED_MEMBERS:
                continue
            digest.update(f"|{name}|".encode())
            digest.update(hashlib.sha256(archive.read(members[name])).digest())
    return digest.hexdigest()


def check_meta(meta: Any, where: str, error: type[Exception]) -> dict[str, Any]:
    """Raise ``error`` unless ``meta`` is this code's format and observation layout."""
    if not isinstance(meta, dict):
        raise error(f"{where}: its metadata is not a JSON object; export the policy again")
    fmt = (meta.get("format"), meta.get("format_version"))
    if fmt != (EXPORT_FORMAT, EXPORT_FORMAT_VERSION):
        raise error(f"{where} is a {fmt[0]} v{fmt[1]} file, not {EXPORT_FORMAT} "
                    f"v{EXPORT_FORMAT_VERSION}; export it again with `formation export`")
    if meta.get("layout_version") != LAYOUT_VERSION:
        raise error(f"{where} was exported for observation layout {meta.get('layout_version')!r} "
                    f"but this code builds layout {LAYOUT_VERSION}; export a policy trained on it")
    if meta.get("token_dim") != TOKEN_DIM:
        raise error(f"{where} expects {meta.get('token_dim')} features per token but this code "
                    f"builds {TOKEN_DIM}; export a policy trained on this layout")
    return meta


__all__ = ["EXPORT_FORMAT", "EXPORT_FORMAT_VERSION", "HASH_FIELD", "IO_SPEC", "MAX_ROBOTS",
           "PolicyContract", "TOKEN_FEATURES", "archive_digest", "canonical_json", "check_io_shapes",
           "check_meta"]
