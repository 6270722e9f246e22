"""Loading a policy for the ControlStack: files written by ``formation export`` (TorchScript,
``torch.export`` or ONNX; digest and metadata checked on every load) or training checkpoints."""

from __future__ import annotations

import inspect
from pathlib import Path

import torch
from torch import nn


class StackError(ValueError):
    """A stack that cannot be built or a policy that cannot be loaded; the message says the fix."""


EXPORTED_SUFFIXES = (".pt2", ".onnx", ".npz")


def load_policy(path: str | Path, num_robots: int | None = None):
    """A policy from an exported file (:class:`deploy.export.ExportedPolicy`) or the actor of a
    training checkpoint (``nn.Module``, eval mode).

    An exported file must carry this code's format and observation layout
    (:data:`sim.observations.LAYOUT_VERSION`) and match its ``content_sha256``: a policy trained
    on another token layout would silently read the wrong features, and a changed byte
    (weights or metadata) is refused. A bare ``torch.jit.save`` without metadata is refused too.
    Raises :class:`StackError` naming the file and the fix.
    """
    from deploy.export import ExportError, load_exported
    from deploy.export.formats import file_format

    path = Path(path)
    if not path.is_file():
        raise StackError(f"policy file {str(path)!r} does not exist; give a file written by "
                         "`formation export` or a checkpoint.pt written by training")
    if path.suffix in EXPORTED_SUFFIXES or file_format(path) is not None:
        try:
            return load_exported(path)
        except ExportError as exc:
            raise StackError(str(exc)) from None
    from controllers.mappo.checkpoint import CheckpointError, load_actor

    try:
        return load_actor(path, num_robots)
    except CheckpointError as exc:
        raise StackError(str(exc)) from None


def _mask_is_optional(network: nn.Module) -> bool:
    """True when ``network.forward(obs, mask)`` accepts ``mask=None`` (or takes no mask)."""
    if isinstance(network, torch.jit.ScriptModule):
        args = [a for a in network.forward.schema.arguments if a.name != "self"]
        return len(args) < 2 or isinstance(args[1].type, torch.OptionalType)
    params = list(inspect.signature(network.forward).parameters.values())
    return len(params) < 2 or params[1].default is None
