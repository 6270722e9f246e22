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


class ModuleKernel:
    """A typed actor held in memory, run by the compiled kernel of ``.npz`` files.

    ``kernel(tokens (B, T, 4), mask (B, T)) -> (accel (B, 2) float32, valid (B,) bool)``, the
    contract of :mod:`deploy.export.contract`, computing ``actor.rows`` (the maths of
    :class:`deploy.export.graph.TypedRows`, to 1e-5) in one numba call with no torch op: the
    policy stage of a 5-robot tick falls from ~0.4 ms (TorchScript) or ~0.6 ms (eager) to
    ~0.1 ms. What ``formation eval`` runs from a checkpoint is then the kernel a fleet runs
    from the ``.npz`` file exported from it.

    The arrays are taken from the module's weights when the kernel is made (:meth:`of`, not in
    a tick) and taken again whenever a weight has changed since (an optimiser step or
    ``load_state_dict`` bumps a tensor's version counter), so a stack built on an actor still in
    training always runs its current weights.
    """

    def __init__(self, actor: nn.Module, rows: nn.Module):
        self.actor = actor
        self._tensors = [*actor.parameters(), *actor.buffers()]
        self._build(rows)

    @classmethod
    def of(cls, actor: nn.Module) -> ModuleKernel | None:
        """The kernel of ``actor``, its arrays built now; None where :meth:`refusal` names a reason."""
        reason, rows = _kernel_rows(actor)
        return None if reason is not None else cls(actor, rows)

    @staticmethod
    def refusal(actor: nn.Module) -> str | None:
        """Why the kernel cannot run ``actor`` as it is, or None: it runs an eager
        :class:`~controllers.policy.actor.TypedSDPAActor` (not a subclass, whose forward may
        differ) on the CPU, not made under inference mode, without token mixers, with a head of
        Linear and ReLU layers."""
        return _kernel_rows(actor)[0]

    def _versions(self) -> tuple[tuple[int, int], ...]:
        return tuple((t._version, t.data_ptr()) for t in self._tensors)

    def _build(self, rows: nn.Module) -> None:
        from deploy.export.formats import typed_rows_arrays
        from deploy.npz_policy import NpzRunner

        self._seen = self._versions()
        self._runner = NpzRunner(typed_rows_arrays(rows), self.actor.accel_limit)

    def __call__(self, tokens, mask):
        if self._versions() != self._seen:
            from deploy.export.graph import TypedRows

            self._build(TypedRows(self.actor))
        return self._runner(tokens, mask)


def _kernel_rows(actor: nn.Module) -> tuple[str | None, nn.Module | None]:
    """``(None, TypedRows of actor)`` where the npz kernel runs it, else ``(why not, None)``."""
    from controllers.policy.actor import TypedSDPAActor
    from deploy.export.formats import npz_refusal
    from deploy.export.graph import TypedRows

    if type(actor) is not TypedSDPAActor:
        return f"the kernel runs typed actors, not {type(actor).__name__}", None
    if any(p.device.type != "cpu" for p in actor.parameters()):
        return "the kernel runs weights held on the CPU", None
    if any(t.is_inference() for t in (*actor.parameters(), *actor.buffers())):
        return "weights made under torch.inference_mode keep no version counter to follow", None
    rows = TypedRows(actor)
    reason = npz_refusal(rows)
    return reason, (rows if reason is None else None)
