"""Checkpoints: atomic writes, ``torch.load(weights_only=True)``, policy loading and transfer.

A checkpoint is a dict of tensors and plain Python values only::

    format, format_version          "formation-stack/mappo", 1
    layout_version                  sim.observations.LAYOUT_VERSION the policy was trained on
    num_robots, scenario            the training task
    config                          MAPPOConfig.to_dict()
    actor, critic, value_norm       state dicts
    actor_optimizer, critic_optimizer
    counters                        iteration, episodes, env_steps, last_eval_episodes, ...
    convergence                     evaluation history (ConvergenceTracker.state_dict())
    rng                             sampler and environment generator states (uint8 tensors)
    env_state                       the training world mid-episode (so a resume is exact), with a
                                    distribution its layout, draw streams and actuators too
"""

from __future__ import annotations

import warnings
from pathlib import Path
from typing import Any

import torch
from torch import nn

from controllers.mappo.config import MAPPOConfig
from controllers.policy import (
    ActorConfig,
    CriticConfig,
    SlotSDPAActor,
    build_actor,
    build_critic,
    grow_slot_actor,
)
from sim.batched_env import BatchedFormationEnv
from sim.files import atomic_path
from sim.observations import LAYOUT_VERSION
from sim.scenario import Scenario

CHECKPOINT_FORMAT = "formation-stack/mappo"
CHECKPOINT_VERSION = 1
# The parts of BatchedFormationEnv that define where every episode stands.
_ENV_TENSORS = ("pos", "vel", "t", "collided", "ret", "counts", "prev_contact", "prev_near_contact",
                "assignment")


class CheckpointError(ValueError):
    """A checkpoint that cannot be used here; the message says why and what to do."""


def save_checkpoint(path: str | Path, payload: dict[str, Any]) -> None:
    """Write ``payload`` with ``torch.save`` atomically (:func:`sim.files.atomic_path`)."""
    with atomic_path(path) as tmp:
        torch.save({"format": CHECKPOINT_FORMAT, "format_version": CHECKPOINT_VERSION,
                    "layout_version": LAYOUT_VERSION, **payload}, tmp)


def load_checkpoint(path: str | Path) -> dict[str, Any]:
    """Load and check a checkpoint (``weights_only=True``: tensors and plain values only)."""
    path = Path(path)
    if not path.is_file():
        raise CheckpointError(f"checkpoint {str(path)!r} does not exist; give the path of a "
                              "checkpoint.pt written by training")
    try:
        with warnings.catch_warnings():   # torch's own hint on TorchScript files says the same
            warnings.simplefilter("ignore")
            data = torch.load(path, map_location="cpu", weights_only=True)
    except Exception as err:  # torch's message advises weights_only=False: never for a file we did not write
        raise CheckpointError(f"{str(path)!r} is neither a training checkpoint nor a policy file of "
                              f"`formation export`: torch cannot read it as plain tensors "
                              f"({type(err).__name__}); give the checkpoint.pt of a training run "
                              "or an exported .pt/.pt2/.onnx") from None
    if not isinstance(data, dict) or data.get("format") != CHECKPOINT_FORMAT:
        raise CheckpointError(f"{str(path)!r} is not a {CHECKPOINT_FORMAT} checkpoint")
    if data.get("format_version") != CHECKPOINT_VERSION:
        raise CheckpointError(f"{str(path)!r} has checkpoint format version {data.get('format_version')}, "
                              f"this code reads version {CHECKPOINT_VERSION}; retrain or convert it")
    if data.get("layout_version") != LAYOUT_VERSION:
        raise CheckpointError(
            f"{str(path)!r} was trained on observation layout version {data.get('layout_version')} "
            f"but sim.observations is version {LAYOUT_VERSION}; the policy would read wrong inputs, "
            "retrain it on the current layout")
    return data


def checkpoint_config(data: dict[str, Any]) -> MAPPOConfig:
    algo = data.get("algo", "mappo")
    if algo != "mappo":
        raise CheckpointError(f"this is a {algo} checkpoint (`formation train --algo {algo}`): the "
                              "paper's baselines are measured in training (their run folder's eval.jsonl, "
                              "bench/paper_tables.py); export, eval and the ControlStack take SDPA-/MLP-MAPPO "
                              "checkpoints")
    config = dict(data["config"])
    for net in ("actor", "critic"):   # saved before token embeddings could have a hidden layer
        if isinstance(config.get(net), dict) and "embed_hidden" not in config[net]:
            config[net] = {**config[net], "embed_hidden": 0}
        if isinstance(config.get(net), dict) and "frame" not in config[net]:   # ... or turn tokens
            config[net] = {**config[net], "frame": "world"}
    return MAPPOConfig.from_dict(config)


def load_actor(path: str | Path, num_robots: int | None = None, *, seed: int = 0) -> nn.Module:
    """The trained actor of a checkpoint, in eval mode, for ``num_robots`` (default: as trained).

    Typed actors run any N as they are; a slot actor is grown (new slots fresh, drawn with
    ``seed``) for a different N; the MLP baseline only runs the N it was trained for.
    """
    data = load_checkpoint(path)
    actor = actor_from_state(checkpoint_config(data).actor, policy_state(data),
                             int(data["num_robots"]), num_robots, accel_limit=data["accel_limit"], seed=seed)
    return actor.eval()


def policy_state(data: dict[str, Any]) -> dict[str, torch.Tensor]:
    """The actor weights a checkpoint stands for: the averaged ``policy`` (see
    ``MAPPOConfig.policy_ema``), or the last ``actor`` weights of checkpoints without one."""
    return data.get("policy", data["actor"])


def actor_from_state(config: ActorConfig, state: dict[str, torch.Tensor], trained_robots: int,
                     num_robots: int | None, *, accel_limit: float, seed: int = 0) -> nn.Module:
    """Rebuild an actor trained with ``trained_robots`` robots and adapt it to ``num_robots``."""
    n = trained_robots if num_robots is None else num_robots
    actor = build_actor(config, trained_robots, accel_limit)
    actor.load_state_dict(state)
    if n == trained_robots or config.variant == "typed":
        return actor
    if config.variant == "slot":
        assert isinstance(actor, SlotSDPAActor)
        return grow_slot_actor(actor, n, seed=seed)
    raise CheckpointError(f"an MLP actor trained for {trained_robots} robots cannot run {n}: its input "
                          "size is fixed by N; use actor.variant='typed' or 'slot' for transfer")


def shrink_perturb(module: nn.Module, fresh: nn.Module, keep: float) -> nn.Module:
    """``w <- keep * w + (1 - keep) * w_fresh`` for every floating-point tensor of ``module``.

    ``fresh`` has the same architecture with a fresh initialisation; ``keep = 1`` leaves
    ``module`` unchanged. Returns ``module`` (changed in place).
    """
    if not 0.0 < keep <= 1.0:
        raise ValueError(f"keep must be in (0, 1], got {keep!r}")
    mine, theirs = module.state_dict(), fresh.state_dict()
    if mine.keys() != theirs.keys() or any(mine[k].shape != theirs[k].shape for k in mine):
        raise ValueError("shrink_perturb needs two networks of the same architecture")
    if keep < 1.0:
        with torch.no_grad():
            for name, value in mine.items():
                if value.is_floating_point():
                    value.mul_(keep).add_(theirs[name].to(value.device), alpha=1.0 - keep)
    return module


def critic_from_state(config: CriticConfig, state: dict[str, torch.Tensor], trained_robots: int,
                      num_robots: int) -> nn.Module:
    """Rebuild a critic and check it can serve ``num_robots`` (the attention critic runs any N)."""
    if config.variant == "mlp" and trained_robots != num_robots:
        raise CheckpointError(f"an MLP critic trained for {trained_robots} robots cannot serve {num_robots}")
    critic = build_critic(config, trained_robots if config.variant == "mlp" else num_robots)
    critic.load_state_dict(state)
    return critic


def env_state_dict(env: BatchedFormationEnv) -> dict[str, torch.Tensor]:
    """Everything that defines where each episode of ``env`` stands, plus its generator state."""
    state = {name: getattr(env, name).detach().cpu().clone() for name in _ENV_TENSORS}
    state["generator"] = env.generator.get_state()
    if env.distribution is not None:      # the layout drawn, the draws to come, the actuators
        state["layout"] = env.scenario.to_dict()
        state["draws"] = {"layout": env._layout_rng.bit_generator.state,
                          "actuator": env._actuator_rng.bit_generator.state}
        if env.actuators is not None:
            state["actuators"] = env.actuators.state_dict()
    return state


def load_env_state(env: BatchedFormationEnv, state: dict[str, torch.Tensor]) -> None:
    """Put ``env`` back into the state saved by :func:`env_state_dict`."""
    if "layout" in state:                 # first: a new layout clears the reward's memory
        env._set_layout(Scenario.from_dict(state["layout"]))
        env._layout_rng.bit_generator.state = state["draws"]["layout"]
        env._actuator_rng.bit_generator.state = state["draws"]["actuator"]
        if "actuators" in state and env.actuators is not None:
            env.actuators.load_state_dict(state["actuators"])
    for name in _ENV_TENSORS:
        current = getattr(env, name)
        if name not in state and name == "prev_near_contact":   # checkpoints from before the margin
            current.copy_(env.prev_contact)
            continue
        if name not in state and name == "assignment":          # ... and before sticky assignments
            current.fill_(-1)
            continue
        saved = state[name]
        if saved.shape != current.shape:
            raise CheckpointError(f"saved environment {name} has shape {tuple(saved.shape)} but this run's "
                                  f"is {tuple(current.shape)}; resume with the same num_envs and scenario")
        current.copy_(saved.to(current.device))
    env.generator.set_state(state["generator"])
    env._frame = None
    env._t_max = int(env.t.max())
