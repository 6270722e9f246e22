"""Export a trained actor as a self-verifying TorchScript file for robots.

Every TorchScript detail of the project lives in this module (PyTorch 2.x deprecates
TorchScript in favour of ``torch.export``; a switch is meant to stay local to this file).

What is written (``out`` = ``policy.pt``):

* ``policy.pt``: ``torch.jit.script`` (never trace: a trace bakes in one N) of
  :class:`DeployedPolicy`, the deterministic mean of the actor, with ``meta.json`` inside
  (``_extra_files``)::

      format, format_version     "formation-stack/torchscript-policy", 1
      layout_version, token_dim  sim.observations.LAYOUT_VERSION, 4
      dt, accel_limit            control period [s], acceleration bound [m/s^2]
      trained_robots             N of the training task
      robot_counts               N the file runs: "any" (typed actor) or [N] (slot actor)
      variant, config            the ActorConfig
      torch_version              torch.__version__ at export
      weights_sha256             sha256 over (name, dtype, shape, bytes) of every weight
      golden_file, golden_sha256 the golden file beside it and its checksum
      max_abs_diff               worst |scripted - eager| seen by the export check

* ``policy.golden.npz`` (:func:`golden_path`): for a few N, raw robot states
  (``n{N}_pos``, ``n{N}_vel``, ``n{N}_targets`` (1, N, 2)), the shared ``polygon`` (M, 2)
  and ``arena`` (2,), the tokens ``n{N}_tokens`` (1, N, 2N+1, 4) built by
  :func:`sim.observations.tokens`, and the eager actor's actions ``n{N}_actions`` (1, N, 2).
  The robot runtime (:mod:`deploy.robot`) replays it at start-up to check both its model
  and its own token builder.

The export verifies itself before anything is published: the file is reloaded and compared
with the eager actor for N = 1..16 at batch 1 and 16 (``forward`` on all robots and ``act``
on one robot's tokens), max abs diff <= 1e-5; on failure no file is left at ``out``.
Both files are written to temporary names and moved into place with ``os.replace``.
"""

from __future__ import annotations

import contextlib
import hashlib
import io
import json
import os
import tempfile
import time
import warnings
from collections.abc import Iterable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import torch
from torch import nn

from sim.observations import LAYOUT_VERSION, TOKEN_DIM, tokens
from sim.scenario import make_scenario

EXPORT_FORMAT = "formation-stack/torchscript-policy"
EXPORT_FORMAT_VERSION = 1
META_FILE = "meta.json"
TOLERANCE = 1e-5
VERIFY_COUNTS = tuple(range(1, 17))
VERIFY_BATCHES = (1, 16)
GOLDEN_COUNTS = (1, 2, 3, 5, 8, 16)


class ExportError(RuntimeError):
    """An export or a check that failed; the message says what differs and what to do."""


class DeployedPolicy(nn.Module):
    """The deterministic actor behind a tensor-only interface (scriptable).

    ``forward(obs (E, N, 2N+1, 4), mask (E, N, 2N+1) bool) -> (E, N, 2)`` mean accelerations
    [m/s^2]; ``act(tokens (B, 2N+1, 4), mask (B, 2N+1)) -> (B, 2)`` for robots that each hold
    only their own tokens. ``act`` broadcasts a robot's tokens over N rows (rows are
    independent in the actor, which needs N only to split the token types) and keeps row 0:
    N times the work of one row, well under a millisecond for N <= 21.
    """

    def __init__(self, actor: nn.Module):
        super().__init__()
        self.actor = actor

    def forward(self, obs: torch.Tensor, mask: torch.Tensor) -> torch.Tensor:
        return self.actor(obs, mask)

    @torch.jit.export
    def act(self, tokens: torch.Tensor, mask: torch.Tensor) -> torch.Tensor:
        b, t, f = tokens.shape[0], tokens.shape[1], tokens.shape[2]
        n = (t - 1) // 2
        obs = tokens.unsqueeze(1).expand(b, n, t, f)
        return self.actor(obs, mask.unsqueeze(1).expand(b, n, t))[:, 0]


@dataclass(frozen=True)
class ExportReport:
    """Result of :func:`export_policy` or :func:`check_export`."""

    path: Path
    golden: Path
    meta: dict[str, Any]
    max_abs_diff: float
    cases: int  # comparisons made


def golden_path(policy: str | Path) -> Path:
    """``policy.pt`` -> ``policy.golden.npz`` (same folder)."""
    policy = Path(policy)
    return policy.with_name(policy.stem + ".golden.npz")


def weights_sha256(module: nn.Module) -> str:
    """sha256 over every state-dict entry in name order: name, dtype, shape, raw bytes."""
    digest = hashlib.sha256()
    for name, value in sorted(module.state_dict().items()):
        array = value.detach().cpu().contiguous()
        digest.update(f"{name}|{array.dtype}|{tuple(array.shape)}|".encode())
        digest.update(array.numpy().tobytes())
    return digest.hexdigest()


def _file_sha256(path: Path) -> str:
    return hashlib.sha256(path.read_bytes()).hexdigest()


@contextlib.contextmanager
def _quiet():
    """TorchScript's deprecation warnings say nothing new here; keep other warnings."""
    with warnings.catch_warnings():
        warnings.filterwarnings("ignore", message=".*TorchScript.*")
        warnings.filterwarnings("ignore", category=DeprecationWarning, module="torch.jit")
        yield


def script(actor: nn.Module) -> torch.jit.ScriptModule:
    """``torch.jit.script`` of :class:`DeployedPolicy` around ``actor`` (eval mode)."""
    with _quiet():
        return torch.jit.script(DeployedPolicy(actor.eval()))


def load_policy(path: str | Path) -> tuple[torch.jit.ScriptModule, dict[str, Any]]:
    """Load an exported file and its metadata (no golden check; see :func:`check_export`)."""
    path = Path(path)
    if not path.is_file():
        raise ExportError(f"policy file {str(path)!r} does not exist; write one with "
                          "`formation export CKPT --out policy.pt`")
    extra = {META_FILE: ""}
    try:
        with _quiet():
            module = torch.jit.load(str(path), map_location="cpu", _extra_files=extra)
    except Exception as err:  # a corrupt zip or archive: say which file
        raise ExportError(f"{str(path)!r} is not a loadable TorchScript file ({err}); "
                          "export it again") from None
    try:
        meta = json.loads(extra[META_FILE])
    except (ValueError, TypeError):
        raise ExportError(f"{str(path)!r} has no valid {META_FILE}; export it again") from None
    if meta.get("format") != EXPORT_FORMAT or meta.get("format_version") != EXPORT_FORMAT_VERSION:
        raise ExportError(f"{str(path)!r} is not a {EXPORT_FORMAT} v{EXPORT_FORMAT_VERSION} file")
    if meta.get("layout_version") != LAYOUT_VERSION:
        raise ExportError(f"{str(path)!r} uses observation layout {meta.get('layout_version')} but "
                          f"this code builds layout {LAYOUT_VERSION}; export a policy trained on it")
    return module.eval(), meta


def supported_counts(meta: dict[str, Any], wanted: Iterable[int]) -> list[int]:
    counts = meta["robot_counts"]
    return [n for n in wanted if counts == "any" or n in counts]


def _random_obs(n: int, batch: int, generator: torch.Generator, masked: bool):
    obs = torch.randn(batch, n, 2 * n + 1, TOKEN_DIM, generator=generator) * 0.5
    mask = torch.ones(batch, n, 2 * n + 1, dtype=torch.bool)
    if masked and n > 1:
        mask = torch.rand(batch, n, 2 * n + 1, generator=generator) > 0.3
    return obs, mask


@torch.no_grad()
def compare(scripted: torch.jit.ScriptModule, eager: nn.Module, counts: Iterable[int],
            batches: Iterable[int] = VERIFY_BATCHES, seed: int = 0) -> tuple[float, int]:
    """Max |scripted - eager| over ``forward`` and ``act`` for each N and batch; (diff, cases)."""
    generator = torch.Generator().manual_seed(seed)
    worst, cases = 0.0, 0
    for n in counts:
        for batch in batches:
            for masked in (False, True):
                obs, mask = _random_obs(n, batch, generator, masked)
                want = eager(obs, mask)
                got = scripted(obs, mask)
                row = int(torch.randint(n, (1,), generator=generator))
                got_one = scripted.act(obs[:, row], mask[:, row])
                if not (torch.isfinite(got).all() and torch.isfinite(got_one).all()):
                    return float("inf"), cases + 1
                worst = max(worst, float((got - want).abs().max()),
                            float((got_one - want[:, row]).abs().max()))
                cases += 2
    return worst, cases


@torch.no_grad()
def golden_cases(eager: nn.Module, counts: Iterable[int], seed: int = 0) -> dict[str, np.ndarray]:
    """Raw states, tokens and eager actions for each N (see the module docstring)."""
    scenario = make_scenario("paper-5")
    polygon = torch.as_tensor(scenario.polygon, dtype=torch.float64)
    arena = scenario.arena
    rng = np.random.default_rng(seed)
    data: dict[str, np.ndarray] = {"polygon": polygon.numpy(), "arena": np.asarray(arena),
                                   "counts": np.asarray(list(counts), dtype=np.int64)}
    for n in data["counts"]:
        pos = torch.as_tensor(rng.uniform(0.05, 0.95, (1, n, 2)))
        vel = torch.as_tensor(rng.uniform(-0.4, 0.4, (1, n, 2)))
        targets = torch.as_tensor(rng.uniform(0.05, 0.95, (1, n, 2)))
        toks, mask = tokens(pos, vel, targets, polygon, arena)
        actions = eager(toks.float(), mask)
        for key, value in (("pos", pos), ("vel", vel), ("targets", targets), ("tokens", toks),
                           ("actions", actions)):
            data[f"n{n}_{key}"] = value.numpy()
    return data


def _temp_beside(path: Path) -> Path:
    fd, tmp = tempfile.mkstemp(dir=path.parent, prefix=f".{path.name}.", suffix=".tmp")
    os.close(fd)
    os.chmod(tmp, 0o644)
    return Path(tmp)


def export_policy(actor: nn.Module, out: str | Path, *, dt: float, trained_robots: int,
                  config: dict[str, Any] | None = None, source: str | None = None,
                  seed: int = 0) -> ExportReport:
    """Script ``actor``, write ``out`` and its golden file, verify, publish atomically.

    Raises ExportError (and leaves nothing at ``out``) if the reloaded file differs from the
    eager actor by more than :data:`TOLERANCE` anywhere.
    """
    if getattr(actor, "obs_kind", "tokens") != "tokens":
        raise ExportError("only token actors (variant 'typed' or 'slot') can be exported: the "
                          "robot runtime builds entity tokens; retrain with actor.variant='typed'")
    out = Path(out)
    out.parent.mkdir(parents=True, exist_ok=True)
    eager = actor.eval()
    fixed_n = int(getattr(actor, "num_robots", -1))
    robot_counts: Any = "any" if fixed_n < 0 else [fixed_n]
    counts = VERIFY_COUNTS if fixed_n < 0 else (fixed_n,)
    golden_counts = GOLDEN_COUNTS if fixed_n < 0 else (fixed_n,)
    golden = golden_path(out)
    tmp_pt, tmp_golden = _temp_beside(out), _temp_beside(golden)
    try:
        buffer = io.BytesIO()
        np.savez(buffer, **golden_cases(eager, golden_counts, seed))
        tmp_golden.write_bytes(buffer.getvalue())
        meta = {
            "format": EXPORT_FORMAT, "format_version": EXPORT_FORMAT_VERSION,
            "layout_version": LAYOUT_VERSION, "token_dim": TOKEN_DIM, "dt": float(dt),
            "accel_limit": float(getattr(actor, "accel_limit", 1.0)),
            "trained_robots": int(trained_robots), "robot_counts": robot_counts,
            "variant": type(actor).__name__, "config": config or {},
            "torch_version": torch.__version__,
            "weights_sha256": weights_sha256(DeployedPolicy(eager)),
            "golden_file": golden.name, "golden_sha256": _file_sha256(tmp_golden),
            "source": source, "created_unix": time.time(),
        }
        scripted = script(eager)
        worst, cases = compare(scripted, eager, counts, seed=seed)
        meta["max_abs_diff"] = worst
        with _quiet():
            torch.jit.save(scripted, str(tmp_pt), _extra_files={META_FILE: json.dumps(meta)})
        reloaded, _ = load_policy(tmp_pt)
        worst_reload, more = compare(reloaded, eager, counts, seed=seed + 1)
        worst = max(worst, worst_reload)
        if not worst <= TOLERANCE:
            raise ExportError(f"exported policy differs from the eager actor by {worst:.3g} "
                              f"(> {TOLERANCE}); nothing was written to {str(out)!r}")
        os.replace(tmp_golden, golden)
        os.replace(tmp_pt, out)
    finally:
        tmp_pt.unlink(missing_ok=True)
        tmp_golden.unlink(missing_ok=True)
    return ExportReport(out, golden, meta, worst, cases + more)


def export_checkpoint(checkpoint: str | Path, out: str | Path, seed: int = 0) -> ExportReport:
    """Export the actor of a training checkpoint (``controllers.mappo`` format)."""
    from controllers.mappo.checkpoint import checkpoint_config, load_actor, load_checkpoint

    data = load_checkpoint(checkpoint)
    config = checkpoint_config(data)
    actor = load_actor(checkpoint)
    return export_policy(actor, out, dt=config.build_scenario().dynamics.dt,
                         trained_robots=int(data["num_robots"]), config=config.to_dict(),
                         source=str(checkpoint), seed=seed)


@torch.no_grad()
def check_export(path: str | Path) -> ExportReport:
    """Re-verify a file: metadata, weight checksum, golden checksum and golden actions.

    Raises ExportError naming the first mismatch.
    """
    path = Path(path)
    module, meta = load_policy(path)
    sha = weights_sha256(module)
    if sha != meta.get("weights_sha256"):
        raise ExportError(f"{str(path)!r}: weights checksum {sha[:12]}... differs from the "
                          f"exported {str(meta.get('weights_sha256'))[:12]}...: the file was "
                          "changed after export; export it again")
    golden = path.with_name(meta.get("golden_file") or golden_path(path).name)
    if not golden.is_file():
        raise ExportError(f"golden file {str(golden)!r} is missing; keep it beside the policy")
    if _file_sha256(golden) != meta.get("golden_sha256"):
        raise ExportError(f"golden file {str(golden)!r} does not match the checksum in "
                          f"{str(path)!r}; it belongs to another export")
    with np.load(golden) as data:
        worst, cases = 0.0, 0
        for n in data["counts"]:
            toks = torch.from_numpy(data[f"n{n}_tokens"]).float()
            mask = torch.ones(toks.shape[:3], dtype=torch.bool)
            want = torch.from_numpy(data[f"n{n}_actions"])
            got = module(toks, mask)
            # one robot at a time, in the (batch, tokens, features) layout the export verified
            # (the N robots of an environment as one batch is another GEMM shape: 1.2e-5 off)
            got_one = torch.stack([module.act(toks[:, r], mask[:, r]) for r in range(int(n))], 1)
            diff = max(float((got - want).abs().max()), float((got_one - want).abs().max()))
            worst = max(worst, diff if np.isfinite(diff) else float("inf"))
            cases += 2
    if not worst <= TOLERANCE:
        raise ExportError(f"{str(path)!r} gives actions {worst:.3g} away from its golden file "
                          f"(> {TOLERANCE}); do not deploy it")
    return ExportReport(path, golden, meta, worst, cases)


__all__ = ["DeployedPolicy", "ExportError", "ExportReport", "check_export", "compare",
           "export_checkpoint", "export_policy", "golden_path", "load_policy", "script",
           "weights_sha256"]
