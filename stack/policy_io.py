"""Loading a policy for the ControlStack: TorchScript files written by ``formation export``
(their ``meta.json`` checked) or training checkpoints."""

from __future__ import annotations

import inspect
import json
import warnings
import zipfile
from pathlib import Path

import torch
from torch import nn

from sim.observations import LAYOUT_VERSION, TOKEN_DIM


class StackError(ValueError):
    """A stack that cannot be built or a policy that cannot be loaded; the message says the fix."""


def is_torchscript_file(path: str | Path) -> bool:
    """True when ``path`` is a TorchScript archive (a zip holding ``*/constants.pkl``)."""
    try:
        with zipfile.ZipFile(path) as archive:
            return any(name.endswith("/constants.pkl") for name in archive.namelist())
    except (zipfile.BadZipFile, OSError):
        return False


def load_policy(path: str | Path, num_robots: int | None = None) -> nn.Module:
    """A policy module from a TorchScript file or a training checkpoint, in eval mode.

    A TorchScript file written by ``formation export`` carries ``meta.json``
    (:mod:`deploy.export`); its format and observation layout version must be the ones this code
    builds (:data:`sim.observations.LAYOUT_VERSION`), else :class:`StackError` says which differ:
    a policy trained on another token layout would silently read the wrong features. A bare
    ``torch.jit.save`` of an actor has no ``meta.json`` and no layout to check; it is loaded as is.
    """
    path = Path(path)
    if not path.is_file():
        raise StackError(f"policy file {str(path)!r} does not exist; give a TorchScript file or a "
                         "checkpoint.pt written by training")
    if is_torchscript_file(path):
        return _load_torchscript(path)
    from controllers.mappo.checkpoint import CheckpointError, load_actor

    try:
        return load_actor(path, num_robots)
    except CheckpointError as exc:
        raise StackError(str(exc)) from None
    except Exception as exc:  # a file torch cannot read at all: say what was expected
        raise StackError(f"{str(path)!r} is neither a TorchScript file nor a training checkpoint "
                         f"({type(exc).__name__}: {exc})") from None


def _load_torchscript(path: Path) -> torch.jit.ScriptModule:
    """Load a TorchScript policy and check its ``meta.json``, if it has one (see :func:`load_policy`)."""
    from deploy.export import EXPORT_FORMAT, EXPORT_FORMAT_VERSION, META_FILE

    extra = {META_FILE: ""}
    with warnings.catch_warnings():
        warnings.filterwarnings("ignore", category=DeprecationWarning, module="torch.jit")
        module = torch.jit.load(str(path), map_location="cpu", _extra_files=extra)
    if extra[META_FILE]:
        try:
            meta = json.loads(extra[META_FILE])
        except ValueError:
            raise StackError(f"{str(path)!r}: its {META_FILE} is not valid JSON; export the policy "
                             "again with `formation export`") from None
        if not isinstance(meta, dict):
            raise StackError(f"{str(path)!r}: its {META_FILE} is not a JSON object; export it again")
        fmt = (meta.get("format"), meta.get("format_version"))
        if fmt != (EXPORT_FORMAT, EXPORT_FORMAT_VERSION):
            raise StackError(f"{str(path)!r} is a {fmt[0]} v{fmt[1]} file, not {EXPORT_FORMAT} "
                             f"v{EXPORT_FORMAT_VERSION}; export it again with `formation export`")
        if meta.get("layout_version") != LAYOUT_VERSION:
            raise StackError(f"{str(path)!r} was exported for observation layout "
                             f"{meta.get('layout_version')!r} but this code builds layout "
                             f"{LAYOUT_VERSION}; export a policy trained on layout {LAYOUT_VERSION}")
        if meta.get("token_dim", TOKEN_DIM) != TOKEN_DIM:
            raise StackError(f"{str(path)!r} expects {meta.get('token_dim')} features per token but "
                             f"this code builds {TOKEN_DIM}; export a policy trained on this layout")
    return module.eval()


def _mask_is_optional(network: nn.Module) -> bool:
    """True when ``network.forward(obs, mask)`` accepts ``mask=None`` (or takes no mask)."""
    if isinstance(network, torch.jit.ScriptModule):
        args = [a for a in network.forward.schema.arguments if a.name != "self"]
        return len(args) < 2 or isinstance(args[1].type, torch.OptionalType)
    params = list(inspect.signature(network.forward).parameters.values())
    return len(params) < 2 or params[1].default is None
