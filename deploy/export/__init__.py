"""Export a trained actor as self-verifying policy files for robots, and load them back.

    export_checkpoint("checkpoint.pt", "out/policy", formats=("torchscript", "pt2", "onnx", "npz"))
      -> out/policy.pt, out/policy.pt2, out/policy.onnx, out/policy.npz and out/policy.golden.npz
    policy = load_exported("out/policy.onnx")      # digest checked; policy.run(tokens, mask)

Every file holds :class:`~deploy.export.contract.PolicyContract` (the interface, its mask,
NaN and bound rules are in :mod:`deploy.export.contract`) and its metadata::

    format, format_version     "formation-stack/policy", 2
    file_format                "torchscript" | "pt2" | "onnx" | "npz"
    layout_version, token_dim  sim.observations.LAYOUT_VERSION, 4
    token_features, io         each token feature with units; dtypes, shapes and mask rules
    dt, accel_limit            control period [s], acceleration bound (in norm) [m/s^2]
    trained_robots, scenario   N and the scenario (its dict) of the training task
    robot_counts               N the file runs: [1..21] (typed actor) or [N] (slot actor)
    variant, config            the actor class and the training config
    torch_version, source      torch at export, the checkpoint exported
    own_target, ..._margin     the policy reads its own target marked (target tokens below),
                               assigned on detours round the object inflated by the margin [m]
    golden_file, golden_sha256 the golden file beside it and its checksum
    content_sha256             digest of weights and metadata (checked on every load)

The golden file (``policy.golden.npz``, :func:`golden_path`, shared by the formats of one
export): for a few N, raw robot states (``n{N}_pos``, ``n{N}_vel``, ``n{N}_targets`` (1, N, 2))
on the training scenario's ``polygon`` (M, 2) and ``arena`` (2,), the tokens ``n{N}_tokens``
(1, N, 2N+1, 4) of :func:`sim.observations.tokens` and the eager contract's actions
``n{N}_actions`` (1, N, 2); for an ``own_target`` policy the tokens carry the mark of
:func:`sim.observations.mark_own_targets` and ``n{N}_own`` (1, N) is the assignment it marks
(on the exact detour). The robot runtime (:mod:`deploy.robot`) replays it at start-up.

The export verifies itself before anything is published: each file is reloaded (digest
checked) and compared with the eager contract for N = 1..21 (every team a scenario can
hold) at batch 1 and 16, with and without masked tokens, on random fleets in the arena
(:func:`random_fleet_rows`), max abs diff <= 1e-5; on failure no file is left. Files are written to
temporary names and moved into place (:func:`sim.files.atomic_path`).
"""

from __future__ import annotations

import contextlib
import io
import math
import time
from collections.abc import Iterable, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import torch
from torch import nn

from deploy.export.contract import (
    EXPORT_FORMAT,
    EXPORT_FORMAT_VERSION,
    IO_SPEC,
    MAX_ROBOTS,
    TOKEN_FEATURES,
    PolicyContract,
    check_io_shapes,
)
from deploy.export.formats import (
    FORMATS,
    META_FILE,
    ExportError,
    Runner,
    npz_refusal,
    quiet,
    sniff_format,
)
from sim.files import atomic_path, sha256_file
from sim.geometry import Polygon
from sim.observations import (
    LAYOUT_VERSION,
    OWN_TARGET_CLEARANCE,
    TOKEN_DIM,
    mark_own_targets,
    own_assignment,
    own_target_paths,
    tokens,
)
from sim.scenario import Scenario, make_scenario

TOLERANCE = 1e-5
VERIFY_COUNTS = tuple(range(1, MAX_ROBOTS + 1))
VERIFY_BATCHES = (1, 16)
GOLDEN_COUNTS = (1, 2, 3, 5, 8, 16)
DEFAULT_FORMATS = ("torchscript", "pt2", "onnx", "npz")
"""Every format; an export without ``formats`` writes those the actor can take (:func:`formats_for`)."""


@dataclass(frozen=True)
class ExportReport:
    """Result of :func:`export_policy` (one per file) or :func:`check_export`."""

    path: Path
    golden: Path
    meta: dict[str, Any]
    max_abs_diff: float
    cases: int  # comparisons made


class ExportedPolicy:
    """A loaded policy file: ``run(tokens (B, T, 4), mask (B, T)) -> (accel (B, 2), valid (B,))``
    (numpy, the contract), and ``__call__(obs (E, N, T, 4), mask (E, N, T) or None) -> (E, N, 2)``
    (torch, the actors' interface; rows not valid get 0). ``obs_kind`` is ``"tokens"``."""

    obs_kind = "tokens"
    training = False            # a file is deployed: eval mode for good (train() is a no-op)

    def __init__(self, path: Path, runner: Runner, meta: dict[str, Any]):
        self.path, self.meta = path, meta
        self.runner = runner        # the file itself, shapes unchecked: for callers that build them (the stack)
        self.file_format = str(meta["file_format"])
        self.accel_limit = float(meta["accel_limit"])
        counts = meta["robot_counts"]
        self.robot_counts = frozenset(int(c) for c in counts)
        self.robot_counts_text = (f"{min(counts)}..{max(counts)}" if len(counts) > 1
                                  and len(counts) == max(counts) - min(counts) + 1 else str(counts))
        self.own_target = bool(meta.get("own_target", False))
        self.num_robots = counts[0] if len(counts) == 1 and meta["variant"] != "TypedSDPAActor" else -1

    def run(self, tokens: np.ndarray, mask: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """The file on ``tokens`` (B, T, 4) and ``mask`` (B, T), shapes checked first (a file fed
        other shapes may broadcast them and answer valid actions)."""
        check_io_shapes(tokens, mask, self.robot_counts)
        return self.runner(tokens, mask)

    def eval(self) -> ExportedPolicy:
        return self

    def train(self, mode: bool = True) -> ExportedPolicy:
        return self

    def __call__(self, obs: torch.Tensor, mask: torch.Tensor | None = None) -> torch.Tensor:
        e, n, t, f = obs.shape
        m = np.ones((e * n, t), dtype=bool) if mask is None else mask.reshape(e * n, t).numpy()
        accel, _ = self.run(obs.reshape(e * n, t, f).numpy(), m)
        return torch.from_numpy(np.asarray(accel)).view(e, n, 2)


def golden_path(policy: str | Path) -> Path:
    """``policy.pt`` (or ``.pt2``, ``.onnx``) -> ``policy.golden.npz`` (same folder)."""
    policy = Path(policy)
    return policy.with_name(policy.stem + ".golden.npz")


def load_exported(path: str | Path) -> ExportedPolicy:
    """Load an exported file of any format, its digest and metadata checked (not the golden
    file: :func:`check_export`); raises ExportError naming what is wrong."""
    path = Path(path)
    name = sniff_format(path)
    runner, meta = FORMATS[name].load(path)
    if meta.get("file_format") != name:
        raise ExportError(f"{str(path)!r} says it is {meta.get('file_format')!r} but holds {name}")
    return ExportedPolicy(path, runner, meta)


def random_fleet_rows(n: int, batch: int, generator: torch.Generator, scenario: Scenario,
                      masked: bool = False) -> tuple[torch.Tensor, torch.Tensor]:
    """Tokens (batch * n, 2n+1, 4) float32 and mask of ``batch`` random fleets of ``n`` robots on
    ``scenario``'s object: positions and targets uniform in the arena, speeds up to the speed
    limit (what a policy meets; unit-Gaussian features would be 1.5 m/s and 1.5 m off); the first
    fleet's targets moved so that their centroid lies on a diagonal from the object's (where the
    quarter turn of a formation frame ties, :func:`controllers.policy.layers.formation_turn`); with
    ``masked``, 30 % of the tokens after the first masked out."""
    arena = torch.as_tensor(scenario.arena, dtype=torch.float64)
    pos = (0.05 + 0.9 * torch.rand(batch, n, 2, generator=generator, dtype=torch.float64)) * arena
    targets = (0.05 + 0.9 * torch.rand(batch, n, 2, generator=generator, dtype=torch.float64)) * arena
    centre = torch.as_tensor(scenario.object_center, dtype=torch.float64)
    targets[0] += centre - 0.2 * arena.min() - targets[0].mean(0)
    angle = 2 * math.pi * torch.rand(batch, n, generator=generator, dtype=torch.float64)
    speed = scenario.dynamics.speed_limit * torch.rand(batch, n, generator=generator, dtype=torch.float64)
    vel = torch.stack((speed * torch.cos(angle), speed * torch.sin(angle)), -1)
    toks, mask = tokens(pos, vel, targets, torch.as_tensor(scenario.polygon, dtype=torch.float64), scenario.arena)
    if masked and n > 1:
        mask = mask & (torch.rand(mask.shape, generator=generator) > 0.3)
    return toks.float().reshape(batch * n, 2 * n + 1, TOKEN_DIM), mask.reshape(batch * n, 2 * n + 1)


@torch.no_grad()
def compare(runner: Runner, contract: PolicyContract, counts: Iterable[int], scenario: Scenario,
            batches: Iterable[int] = VERIFY_BATCHES, seed: int = 0) -> tuple[float, int]:
    """Max |file - eager contract| over N and batch, with and without masked tokens, on random
    fleets (:func:`random_fleet_rows`)."""
    generator = torch.Generator().manual_seed(seed)
    worst, cases = 0.0, 0
    for n in counts:
        for batch in batches:
            for masked in (False, True):
                rows, mask = random_fleet_rows(n, batch, generator, scenario, masked)
                want, want_ok = contract(rows, mask)
                got, ok = runner(rows.numpy(), mask.numpy())
                if not (np.isfinite(got).all() and (np.asarray(ok) == want_ok.numpy()).all()):
                    return float("inf"), cases + 1
                worst = max(worst, float(np.abs(got - want.numpy()).max()))
                cases += 1
    return worst, cases


@torch.no_grad()
def golden_cases(contract: PolicyContract, counts: Iterable[int], scenario: Scenario,
                 seed: int = 0, own_target: bool = False) -> dict[str, np.ndarray]:
    """Raw states, tokens and eager contract actions for each N (module docstring); with
    ``own_target`` the tokens carry the own-target mark and ``n{N}_own`` (1, N) the assignment."""
    polygon = torch.as_tensor(scenario.polygon, dtype=torch.float64)
    arena = scenario.arena
    rng = np.random.default_rng(seed)
    data: dict[str, np.ndarray] = {"polygon": polygon.numpy(), "arena": np.asarray(arena),
                                   "counts": np.asarray(list(counts), dtype=np.int64)}
    lo, hi = 0.05 * np.asarray(arena), 0.95 * np.asarray(arena)
    for n in data["counts"]:
        pos = torch.as_tensor(rng.uniform(lo, hi, (1, n, 2)))
        vel = torch.as_tensor(rng.uniform(-0.4, 0.4, (1, n, 2)))
        targets = torch.as_tensor(rng.uniform(lo, hi, (1, n, 2)))
        toks, mask = tokens(pos, vel, targets, polygon, arena)
        if own_target:
            sigma = own_assignment(own_target_paths(Polygon(polygon), targets[0], scenario.robot_radius)(pos))
            toks = mark_own_targets(toks, sigma)
            data[f"n{n}_own"] = sigma.numpy()
        actions, valid = contract(toks.float().reshape(n, 2 * n + 1, TOKEN_DIM), mask.reshape(n, -1))
        if not bool(valid.all()):
            raise ExportError(f"the actor gives non-finite actions for {n} robots on finite states "
                              "(non-finite weights?); nothing was written")
        for key, value in (("pos", pos), ("vel", vel), ("targets", targets), ("tokens", toks),
                           ("actions", actions.view(1, n, 2))):
            data[f"n{n}_{key}"] = value.numpy()
    return data


def formats_for(actor: nn.Module) -> tuple[str, ...]:
    """The formats ``actor`` can be written in: all of :data:`DEFAULT_FORMATS` for a typed actor
    without token mixers; npz (the compiled kernel's layout) left out for any other."""
    return _formats_of(PolicyContract.for_export(actor))


def _formats_of(exported: PolicyContract) -> tuple[str, ...]:
    """:func:`formats_for` of the contract the files would hold."""
    if npz_refusal(exported.actor) is None:
        return DEFAULT_FORMATS
    return tuple(f for f in DEFAULT_FORMATS if f != "npz")


def export_policy(actor: nn.Module, out: str | Path, *, dt: float, trained_robots: int,
                  scenario: Scenario | None = None, formats: Sequence[str] | None = None,
                  config: dict[str, Any] | None = None, source: str | None = None,
                  seed: int = 0) -> list[ExportReport]:
    """Write ``actor`` in each of ``formats`` beside one golden file, verify, publish atomically.

    ``out`` names the files: ``out/policy`` or ``out/policy.pt`` give ``out/policy.pt``,
    ``.pt2``, ``.onnx``, ``.npz`` and ``out/policy.golden.npz``; ``formats`` None: every format
    the actor can take (:func:`formats_for`). Raises ExportError (and publishes nothing) if any
    reloaded file differs from the eager contract by more than TOLERANCE.
    """
    if getattr(actor, "obs_kind", "tokens") != "tokens" or not hasattr(actor, "rows"):
        raise ExportError("only token actors (variant 'typed' or 'slot') can be exported: the "
                          "robot runtime builds entity tokens; retrain with actor.variant='typed'")
    exported = PolicyContract.for_export(actor).eval()  # what the files hold (same numbers)
    formats = _formats_of(exported) if formats is None else formats
    unknown = [f for f in formats if f not in FORMATS]
    if unknown or not formats:
        raise ExportError(f"unknown export format(s) {unknown or list(formats)}; choose from "
                          f"{', '.join(FORMATS)}")
    scenario = scenario or make_scenario("paper-5")
    out = Path(out)
    stem = out.with_suffix("") if out.suffix in {f.suffix for f in FORMATS.values()} else out
    stem.parent.mkdir(parents=True, exist_ok=True)
    contract = PolicyContract(actor).eval()             # the actor's own rows: the reference
    fixed_n = int(getattr(actor, "num_robots", -1))
    counts = VERIFY_COUNTS if fixed_n < 0 else (fixed_n,)
    golden = stem.with_name(stem.name + ".golden.npz")       # the stem may hold dots of its own
    buffer = io.BytesIO()
    own_target = bool(getattr(actor, "own_target", False))
    np.savez(buffer, **golden_cases(contract, GOLDEN_COUNTS if fixed_n < 0 else counts, scenario, seed,
                                    own_target))
    base = {
        "format": EXPORT_FORMAT, "format_version": EXPORT_FORMAT_VERSION,
        "layout_version": LAYOUT_VERSION, "token_dim": TOKEN_DIM, "token_features": TOKEN_FEATURES,
        "io": IO_SPEC, "dt": float(dt), "accel_limit": contract.accel_limit,
        "trained_robots": int(trained_robots), "scenario": scenario.to_dict(),
        "robot_counts": list(counts), "variant": type(actor).__name__, "config": config or {},
        "torch_version": torch.__version__, "source": source, "created_unix": time.time(),
        "golden_file": golden.name, "own_target": own_target,
        "own_target_margin": scenario.robot_radius + OWN_TARGET_CLEARANCE,
    }
    reports: list[ExportReport] = []
    with contextlib.ExitStack() as publish:    # every file verified, or none published
        tmp_golden = publish.enter_context(atomic_path(golden))
        tmp_golden.write_bytes(buffer.getvalue())
        base["golden_sha256"] = sha256_file(tmp_golden)
        for name in formats:
            fmt, path = FORMATS[name], stem.with_name(stem.name + FORMATS[name].suffix)
            tmp = publish.enter_context(atomic_path(path))
            try:
                fmt.write(exported, tmp, base | {"file_format": name}, fixed_n if fixed_n > 0 else None)
            except ExportError:
                raise
            except Exception as err:        # the exporter's own failure: say which format
                first = (str(err).strip().splitlines() or [""])[0]
                raise ExportError(f"the {name} exporter failed ({type(err).__name__}: {first}); "
                                  f"nothing was written; try --format without {name}") from err
            with quiet():
                runner, meta = fmt.load(tmp)
            worst, cases = compare(runner, contract, counts, scenario, seed=seed + 1)
            if not worst <= TOLERANCE:
                raise ExportError(f"the {name} file differs from the eager actor by {worst:.3g} "
                                  f"(> {TOLERANCE}); nothing was written to {str(path)!r}")
            reports.append(ExportReport(path, golden, meta, worst, cases))
    return reports


def export_checkpoint(checkpoint: str | Path, out: str | Path, formats: Sequence[str] | None = None,
                      seed: int = 0) -> list[ExportReport]:
    """Export the actor of a training checkpoint (``controllers.mappo`` format)."""
    from controllers.mappo.checkpoint import (
        CheckpointError,
        checkpoint_config,
        load_actor,
        load_checkpoint,
    )

    try:
        data = load_checkpoint(checkpoint)
        config = checkpoint_config(data)
        actor = load_actor(checkpoint)
    except CheckpointError as err:
        raise ExportError(str(err)) from None
    scenario = config.build_scenario()
    return export_policy(actor, out, dt=scenario.dynamics.dt, trained_robots=int(data["num_robots"]),
                         scenario=scenario, formats=formats, config=config.to_dict(),
                         source=str(checkpoint), seed=seed)


def check_export(path: str | Path) -> ExportReport:
    """Re-verify a file: format, digest, golden checksum and golden actions (every N of the
    golden file, all robots of an environment as one batch). Raises ExportError on a mismatch."""
    policy = load_exported(path)
    meta, path = policy.meta, Path(path)
    golden = path.with_name(str(meta.get("golden_file") or golden_path(path).name))
    if not golden.is_file():
        raise ExportError(f"golden file {str(golden)!r} is missing; keep it beside the policy")
    if sha256_file(golden) != meta.get("golden_sha256"):
        raise ExportError(f"golden file {str(golden)!r} does not match the checksum in "
                          f"{str(path)!r}; it belongs to another export")
    worst, cases = 0.0, 0
    with np.load(golden) as data:
        for n in data["counts"]:
            toks = data[f"n{n}_tokens"][0].astype(np.float32)
            accel, valid = policy.run(toks, np.ones(toks.shape[:2], dtype=bool))
            diff = float(np.abs(accel - data[f"n{n}_actions"][0]).max()) if np.all(valid) else np.inf
            worst = max(worst, diff if np.isfinite(diff) else float("inf"))
            cases += 1
    if not worst <= TOLERANCE:
        raise ExportError(f"{str(path)!r} gives actions {worst:.3g} away from its golden file "
                          f"(> {TOLERANCE}); do not deploy it")
    return ExportReport(path, golden, meta, worst, cases)


__all__ = ["DEFAULT_FORMATS", "ExportError", "ExportReport", "ExportedPolicy", "META_FILE",
           "TOLERANCE", "check_export", "compare", "random_fleet_rows", "export_checkpoint", "export_policy", "formats_for",
           "golden_path", "load_exported"]
