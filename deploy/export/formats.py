"""The file formats of an exported policy: TorchScript, ``torch.export`` (.pt2), ONNX and npz.

Each format writes :class:`deploy.export.contract.PolicyContract` with the metadata inside the
file and loads it back as a :data:`Runner`, checking the digest every time. Adding a format is
one more class here and one entry in :data:`FORMATS`.

=============  ========  ======================================  ============================
format         suffix    metadata                                digest (``content_sha256``)
=============  ========  ======================================  ============================
torchscript    ``.pt``   ``meta.json`` in ``_extra_files``        every member + metadata
pt2            ``.pt2``  ``meta.json`` in the archive's extras    every member + metadata
onnx           ``.onnx`` ``metadata_props["formation.meta"]``      every byte of the file
npz            ``.npz``  the ``formation.meta`` array (JSON)       every array + metadata
=============  ========  ======================================  ============================

TorchScript is scripted (never traced: a trace bakes in one N). ``torch.export`` and ONNX keep
B and T dynamic (``T`` in 3..2*21+1, every team a scenario can hold); a typed actor's graph is
:class:`deploy.export.graph.TypedRows`. The npz format holds that module's arrays for the compiled
kernel of :mod:`deploy.npz_policy` (typed actors without token mixers only).
"""

from __future__ import annotations

import contextlib
import hashlib
import io
import json
import logging
import warnings
import zipfile
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np
import torch

from deploy.export.contract import (
    HASH_FIELD,
    MAX_ROBOTS,
    PolicyContract,
    archive_digest,
    check_meta,
)
from deploy.export.graph import TypedRows
from deploy.npz_policy import META_MEMBER, NpzPolicyError, npz_bytes, open_npz
from deploy.robot import (
    META_KEY,
    PLACEHOLDER,
    RobotPolicyError,
    hash_needle,
    onnx_meta_json,
    open_onnx,
)

META_FILE = "meta.json"
Runner = Callable[[np.ndarray, np.ndarray], tuple[np.ndarray, np.ndarray]]
"""``(tokens (B, T, 4) float32, mask (B, T) bool) -> (accel (B, 2) float32, valid (B,) bool)``."""


class ExportError(RuntimeError):
    """An export, a load or a check that failed; the message says what differs and what to do."""


@contextlib.contextmanager
def quiet():
    """TorchScript's deprecation and the exporters' chatter say nothing new here."""
    loggers = [logging.getLogger(name) for name in ("torch.onnx", "torch.export", "torch._export")]
    levels = [logger.level for logger in loggers]
    for logger in loggers:
        logger.setLevel(logging.ERROR)
    with warnings.catch_warnings(), contextlib.redirect_stdout(io.StringIO()):
        warnings.filterwarnings("ignore", message=".*TorchScript.*")
        warnings.filterwarnings("ignore", category=DeprecationWarning)
        warnings.filterwarnings("ignore", category=UserWarning)
        warnings.filterwarnings("ignore", category=FutureWarning)
        try:
            yield
        finally:
            for logger, level in zip(loggers, levels, strict=True):
                logger.setLevel(level)


def example_inputs(fixed_n: int | None) -> tuple[torch.Tensor, torch.Tensor]:
    n = fixed_n or 3
    return torch.zeros(2, 2 * n + 1, 4), torch.ones(2, 2 * n + 1, dtype=torch.bool)


def dynamic_shapes(fixed_n: int | None):
    batch = torch.export.Dim("batch", min=1, max=1 << 20)
    if fixed_n:
        return ({0: batch}, {0: batch})
    tokens = torch.export.Dim("tokens", min=3, max=2 * MAX_ROBOTS + 1)
    return ({0: batch, 1: tokens}, {0: batch, 1: tokens})


def _torch_runner(module) -> Runner:
    @torch.no_grad()
    def run(tokens: np.ndarray, mask: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        accel, valid = module(torch.from_numpy(np.ascontiguousarray(tokens, dtype=np.float32)),
                              torch.from_numpy(np.ascontiguousarray(mask, dtype=bool)))
        return accel.numpy(), valid.numpy()
    return run


def _load_archive(path: Path, what: str, load: Callable[[dict[str, str]], Any]) -> tuple[Any, dict[str, Any]]:
    """``load(extra_files)`` of a zip-archive format, then its metadata and digest checked."""
    extra = {META_FILE: ""}
    try:
        with quiet():
            loaded = load(extra)
    except Exception as err:
        raise ExportError(f"{str(path)!r} is not a loadable {what} ({type(err).__name__}); "
                          "export it again") from None
    return loaded, _checked_torch_meta(path, extra[META_FILE])


def _checked_torch_meta(path: Path, raw: str) -> dict[str, Any]:
    try:
        meta = json.loads(raw)
    except (ValueError, TypeError):
        meta = None
    if not raw or meta is None:
        raise ExportError(f"{str(path)!r} has no valid {META_FILE}: not written by `formation "
                          "export`, or its metadata was removed; export it again")
    check_meta(meta, repr(str(path)), ExportError)
    try:
        digest = archive_digest(path, meta)
    except (zipfile.BadZipFile, OSError) as err:     # torch itself loads past a bad CRC
        raise ExportError(f"{str(path)!r} is corrupt ({err}); export it again") from None
    if digest != meta.get(HASH_FIELD):
        raise ExportError(f"{str(path)!r}: its code, weights or metadata do not match its "
                          f"{HASH_FIELD}: the file was changed after export; export it again")
    return meta


class TorchScriptFormat:
    name, suffix = "torchscript", ".pt"

    @staticmethod
    def write(contract: PolicyContract, path: Path, meta: dict[str, Any], fixed_n: int | None) -> None:
        with quiet():
            module = torch.jit.script(contract)
        with quiet():            # once to measure, once with the digest (the rest is identical)
            torch.jit.save(module, str(path), _extra_files={META_FILE: json.dumps(meta)})
            meta = meta | {HASH_FIELD: archive_digest(path, meta)}
            torch.jit.save(module, str(path), _extra_files={META_FILE: json.dumps(meta)})

    @staticmethod
    def load(path: Path) -> tuple[Runner, dict[str, Any]]:
        module, meta = _load_archive(path, "TorchScript file", lambda extra: torch.jit.load(
            str(path), map_location="cpu", _extra_files=extra))
        return _torch_runner(module.eval()), meta


class Pt2Format:
    name, suffix = "pt2", ".pt2"

    @staticmethod
    def write(contract: PolicyContract, path: Path, meta: dict[str, Any], fixed_n: int | None) -> None:
        with quiet():
            program = torch.export.export(contract, example_inputs(fixed_n),
                                          dynamic_shapes=dynamic_shapes(fixed_n))
        torch.export.save(program, str(path), extra_files={META_FILE: json.dumps(meta)})
        meta = meta | {HASH_FIELD: archive_digest(path, meta)}
        torch.export.save(program, str(path), extra_files={META_FILE: json.dumps(meta)})

    @staticmethod
    def load(path: Path) -> tuple[Runner, dict[str, Any]]:
        program, meta = _load_archive(path, "torch.export archive", lambda extra: torch.export.load(
            str(path), extra_files=extra))
        return _torch_runner(program.module()), meta


def onnx_model(contract: torch.nn.Module, fixed_n: int | None):
    """The ONNX ``ModelProto`` of ``contract`` (inputs ``tokens``, ``mask``; outputs ``accel``,
    ``valid``; B, and T unless ``fixed_n``, dynamic), without metadata."""
    with quiet():
        program = torch.onnx.export(contract, example_inputs(fixed_n), dynamo=True,
                                    dynamic_shapes=dynamic_shapes(fixed_n), verbose=False,
                                    input_names=["tokens", "mask"], output_names=["accel", "valid"])
    return program.model_proto


class OnnxFormat:
    name, suffix = "onnx", ".onnx"

    @staticmethod
    def write(contract: PolicyContract, path: Path, meta: dict[str, Any], fixed_n: int | None) -> None:
        OnnxFormat.write_signed(onnx_model(contract, fixed_n), path, meta)

    @staticmethod
    def write_signed(proto, path: Path, meta: dict[str, Any]) -> None:
        """Write the ONNX ``proto`` to ``path`` with ``meta`` as its only metadata, signed: the
        digest field holds the sha256 of the file with a placeholder in its place."""
        import onnx

        del proto.metadata_props[:]
        entry = proto.metadata_props.add()
        entry.key, entry.value = META_KEY, onnx_meta_json(meta | {HASH_FIELD: PLACEHOLDER})
        data = onnx._serialize(proto) if hasattr(onnx, "_serialize") else proto.SerializeToString()
        digest = hashlib.sha256(data).hexdigest()
        needle = hash_needle(PLACEHOLDER)
        if data.count(needle) != 1:
            raise ExportError("the ONNX file holds its digest placeholder more than once; cannot sign it")
        path.write_bytes(data.replace(needle, hash_needle(digest)))

    @staticmethod
    def load(path: Path) -> tuple[Runner, dict[str, Any]]:
        try:
            session, meta = open_onnx(path)
        except RobotPolicyError as err:
            raise ExportError(str(err)) from None
        except ImportError:
            raise ExportError("onnxruntime is not installed: `pip install onnxruntime` to run "
                              f"{str(path)!r}") from None
        check_meta(meta, repr(str(path)), ExportError)
        return BoundRunner(session), meta


class BoundRunner:
    """ONNX Runtime through an IO binding kept per input buffer (a control loop passes the same
    arrays every tick: ~10 % of the call saved); other inputs are bound afresh."""

    def __init__(self, session):
        self.session = session
        self._bound: dict[tuple, tuple[Any, np.ndarray, np.ndarray, np.ndarray, np.ndarray]] = {}

    def __call__(self, tokens: np.ndarray, mask: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        tokens = np.ascontiguousarray(tokens, dtype=np.float32)
        mask = np.ascontiguousarray(mask, dtype=bool)
        key = (id(tokens), tokens.shape, id(mask), mask.shape)    # the entry holds them: ids stay theirs
        entry = self._bound.get(key)
        if entry is None or entry[1] is not tokens or entry[2] is not mask:
            binding = self.session.io_binding()
            binding.bind_cpu_input("tokens", tokens)
            binding.bind_cpu_input("mask", mask)
            accel = np.zeros((len(tokens), 2), dtype=np.float32)
            valid = np.zeros(len(tokens), dtype=bool)
            binding.bind_output("accel", "cpu", 0, np.float32, accel.shape, accel.ctypes.data)
            binding.bind_output("valid", "cpu", 0, np.bool_, valid.shape, valid.ctypes.data)
            if len(self._bound) > 64:
                self._bound.clear()
            entry = self._bound[key] = (binding, tokens, mask, accel, valid)
        binding, _, _, accel, valid = entry
        self.session.run_with_iobinding(binding)
        return accel.copy(), valid.copy()


def npz_refusal(rows: torch.nn.Module) -> str | None:
    """Why the npz kernel cannot run ``rows`` (what a file holds, :meth:`PolicyContract.for_export`),
    or None when it can: a TypedRows without token mixers whose head is Linear, ReLU, ..., Linear."""
    if not isinstance(rows, TypedRows) or len(rows.mixers):
        return ("the npz format holds typed actors (actor.variant 'typed') without token "
                "mixers (actor.token_layers 0); export this one with --format onnx")
    layers = list(rows.mlp)
    if not all(isinstance(m, torch.nn.Linear) for m in layers[0::2]) or not all(
            isinstance(m, torch.nn.ReLU) for m in layers[1::2]) or len(layers) % 2 != 1:
        return ("the npz format runs heads of Linear layers with ReLU between them; "
                "export this actor with --format onnx")
    return None


def typed_rows_arrays(rows: torch.nn.Module) -> dict[str, np.ndarray]:
    """The arrays of an npz policy (:mod:`deploy.npz_policy`'s layout) from a TypedRows module;
    ExportError naming :func:`npz_refusal`'s reason for one the kernel does not run."""
    refusal = npz_refusal(rows)
    if refusal is not None:
        raise ExportError(refusal)
    linears = list(rows.mlp)[0::2]
    width, w1, w2 = (rows.wide - 4) // 4, rows.w1[0].numpy(), rows.w2.numpy()
    blocks = [slice(c * width, (c + 1) * width) for c in range(4)]
    arrays = {
        "embed_w1": np.stack([w1[:, b] for b in blocks]), "embed_b1": np.stack([rows.b1.numpy()[b] for b in blocks]),
        "embed_w2": np.stack([w2[b] for b in blocks]), "embed_b2": w2[4 * width:4 * width + 4],
        "scores": rows.scores.numpy(), "head_in": rows.head_in.numpy(),
        "heads": np.array(rows.heads), "turning": np.array(rows.turning),
        "two_layers": np.array(rows.two_layers), "damping": np.array(rows.damping),
    }
    for i, linear in enumerate(linears):
        arrays[f"mlp_w{i}"] = linear.weight.detach().numpy().T
        arrays[f"mlp_b{i}"] = linear.bias.detach().numpy()
    return {k: np.ascontiguousarray(v) if v.ndim else v for k, v in arrays.items()}


class NpzFormat:
    name, suffix = "npz", ".npz"

    @staticmethod
    def write(contract: PolicyContract, path: Path, meta: dict[str, Any], fixed_n: int | None) -> None:
        path.write_bytes(npz_bytes(typed_rows_arrays(contract.actor), meta))

    @staticmethod
    def load(path: Path) -> tuple[Runner, dict[str, Any]]:
        try:
            runner, meta = open_npz(path)
        except NpzPolicyError as err:
            raise ExportError(str(err)) from None
        check_meta(meta, repr(str(path)), ExportError)
        return runner, meta


FORMATS = {f.name: f for f in (TorchScriptFormat, Pt2Format, OnnxFormat, NpzFormat)}


def file_format(path: Path) -> str | None:
    """The export format a file's contents show (the suffix is only a hint), None for any other
    file (a training checkpoint, random bytes)."""
    try:
        with zipfile.ZipFile(path) as archive:
            names = archive.namelist()
    except (zipfile.BadZipFile, OSError):
        names = None
    if names is not None:
        if any(n.endswith("/constants.pkl") for n in names):
            return "torchscript"
        if f"{META_MEMBER}.npy" in names:
            return "npz"
        return "pt2" if any(n.endswith("/archive_format") for n in names) else None
    if path.suffix == ".npz":          # a zip it cannot read: the npz loader says what is wrong
        return "npz"
    if path.suffix == ".onnx" or META_KEY.encode() in path.read_bytes():
        return "onnx"
    return None


def sniff_format(path: Path) -> str:
    """:func:`file_format`, or ExportError for a missing file or one of no export format."""
    if not path.is_file():
        raise ExportError(f"policy file {str(path)!r} does not exist; write one with "
                          "`formation export CKPT --out policy`")
    name = file_format(path)
    if name is None:
        raise ExportError(f"{str(path)!r} is not an exported policy (TorchScript .pt, torch.export "
                          ".pt2, ONNX .onnx or npz .npz); export one with `formation export CKPT --out policy`")
    return name


__all__ = ["BoundRunner", "ExportError", "FORMATS", "META_FILE", "Runner", "dynamic_shapes", "example_inputs",
           "file_format", "npz_refusal", "onnx_model", "quiet", "sniff_format", "typed_rows_arrays"]
