"""Configuration of the policy networks (one dataclass per network, validated on creation)."""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass
from typing import Any

ACTOR_VARIANTS = ("typed", "slot", "mlp")
CRITIC_VARIANTS = ("attention", "mlp")


class PolicyConfigError(ValueError):
    """A network configuration that cannot be built; the message names the field and the fix."""


def _check_positive_int(owner: str, name: str, value: Any) -> None:
    if not isinstance(value, int) or isinstance(value, bool) or value < 1:
        raise PolicyConfigError(f"{owner}.{name} must be a positive integer, got {value!r}")


def is_number(value: Any) -> bool:
    """A finite int or float, not a bool (JSON's true is no learning rate)."""
    return isinstance(value, int | float) and not isinstance(value, bool) and math.isfinite(value)


def _check_range(owner: str, name: str, value: Any, lo: float, hi: float, unit: str = "") -> None:
    """``lo <= value <= hi`` (``lo`` excluded when it is 0 and ``hi`` is inf: > 0)."""
    positive = lo == 0.0 and hi == math.inf
    if not (is_number(value) and (value > 0 if positive else lo <= value <= hi)):
        want = "> 0" if positive else f"in [{lo:g}, {hi:g}]{unit}"
        raise PolicyConfigError(f"{owner}.{name} must be a number {want}, got {value!r}")


def _check_hidden(owner: str, hidden: Any) -> tuple[int, ...]:
    try:
        sizes = tuple(hidden)
    except TypeError:
        raise PolicyConfigError(f"{owner}.hidden_sizes must be a list of positive integers, "
                                f"got {hidden!r}") from None
    if not sizes or any(not isinstance(h, int) or isinstance(h, bool) or h < 1 for h in sizes):
        raise PolicyConfigError(f"{owner}.hidden_sizes must be a non-empty list of positive "
                                f"integers, got {hidden!r}")
    return sizes


FRAMES = ("formation", "world")


def _check_frame(owner: str, frame: Any, variant: str, turning: str) -> None:
    if frame not in FRAMES:
        raise PolicyConfigError(f"{owner}.frame must be one of {FRAMES}, got {frame!r}")
    if frame == "formation" and variant != turning:
        raise PolicyConfigError(f"{owner}.frame 'formation' applies to the {turning!r} variant only; "
                                f"set it to 'world' for variant {variant!r}")


def dataclass_from_dict(cls, data: dict, owner: str):
    """Build dataclass ``cls`` from a dict, rejecting unknown keys with a message naming them."""
    if not isinstance(data, dict):
        raise PolicyConfigError(f"{owner} must be a mapping of fields, got {type(data).__name__}")
    known = {f.name for f in dataclasses.fields(cls)}
    unknown = sorted(set(data) - known)
    if unknown:
        raise PolicyConfigError(f"unknown {owner} field(s) {unknown}; known fields: {sorted(known)}")
    return cls(**data)


@dataclass(frozen=True)
class ActorConfig:
    """The decentralised actor (one network shared by every robot).

    Attributes:
        variant: ``"typed"``: one linear embedding per token *type* (self, target, robot,
            object), so the same weights run any number of robots; ``"slot"``: the paper's
            Figure 1/2, one embedding per input *slot* (P, V, G_1..G_N, R_1..R_{N-1}, object),
            grown for more robots with :func:`controllers.policy.grow_slot_actor`;
            ``"mlp"``: the MLP-MAPPO baseline on the flat vector (fixed N).
        embed_dim: width D of the token embeddings (attention variants).
        num_heads: attention heads; must divide ``embed_dim``.
        embed_hidden: width of a ReLU layer inside each token-type embedding of the typed
            actor (0: the paper's linear embeddings; None: 32 for ``typed``, 0 otherwise). A
            linear embedding cannot form the gap to the object out of the relative vector, and
            the typed actor learned paper-3 faster and held it longer with the layer.
        hidden_sizes: hidden ReLU layers of the head (the paper: one layer of 128).
        init_log_std: initial log standard deviation of the Gaussian action noise [log m/s^2].
        input_scale: observation features [m, m/s] are multiplied by this before embedding
            (10: relative positions of ~0.1-0.5 m become inputs of order 1, and the centimetres
            that separate a near miss from a contact stay visible; 4 learned the way but not to
            keep off the object).
        velocity_damping: k_v [1/s] of the output ``accel_limit * tanh((u - k_v v) / accel_limit)``
            (v: the robot's own velocity); 0 gives the plain ``tanh`` output.
        frame: ``"formation"``: the network sees every robot's tokens turned by the quarter turn
            that brings its formation into the right-to-left frame and its output is turned
            back (:func:`controllers.policy.layers.formation_turn`): the square arena, the task
            and so the policy are the same under quarter turns, which the network then need
            not learn (exactly so in a square arena; in an oblong one only the half turn is a
            symmetry, and a quarter-turned formation sees its walls where it never trained);
            ``"world"``: the tokens as they are. None: ``"formation"`` for the typed actor,
            ``"world"`` otherwise (checkpoints from before the field: ``"world"``).
        token_layers: residual self-attention blocks over the embedded tokens before the
            robot's own query pools them (typed actor only; 0: the paper's single pooling).
            One pooling weighs each token by its pair with the robot alone, so it cannot tell
            whether a target is nearer another robot than itself; a block lets every token
            attend to the others first (:class:`controllers.policy.layers.TokenMixer`).
        own_target: the actor reads tokens with each robot's own target marked
            (:func:`sim.observations.mark_own_targets`: the assignment the reward judges the
            robot by), so it need not work out from its view which target is its own (typed
            actor only). The worlds and the ControlStack mark the tokens they give it.
    """

    variant: str = "typed"
    embed_dim: int = 64
    num_heads: int = 4
    embed_hidden: int | None = None
    hidden_sizes: tuple[int, ...] = (128,)
    init_log_std: float = -0.5
    input_scale: float = 10.0
    velocity_damping: float = 0.0
    frame: str | None = None
    token_layers: int = 0
    own_target: bool = False

    def __post_init__(self) -> None:
        object.__setattr__(self, "hidden_sizes", _check_hidden("actor", self.hidden_sizes))
        if self.embed_hidden is None:
            object.__setattr__(self, "embed_hidden", 32 if self.variant == "typed" else 0)
        if self.frame is None:
            object.__setattr__(self, "frame", "formation" if self.variant == "typed" else "world")
        self.validate()

    def validate(self) -> None:
        if self.variant not in ACTOR_VARIANTS:
            raise PolicyConfigError(f"actor.variant must be one of {ACTOR_VARIANTS}, got {self.variant!r}")
        _check_positive_int("actor", "embed_dim", self.embed_dim)
        _check_positive_int("actor", "num_heads", self.num_heads)
        if self.embed_dim % self.num_heads:
            raise PolicyConfigError(f"actor.num_heads ({self.num_heads}) must divide actor.embed_dim "
                                    f"({self.embed_dim}); e.g. embed_dim=64, num_heads=4")
        if not isinstance(self.embed_hidden, int) or isinstance(self.embed_hidden, bool) or self.embed_hidden < 0:
            raise PolicyConfigError(f"actor.embed_hidden must be an integer >= 0 (0: linear), got {self.embed_hidden!r}")
        if self.embed_hidden and self.variant != "typed":
            raise PolicyConfigError(f"actor.embed_hidden applies to the typed actor only; set it to 0 for "
                                    f"variant {self.variant!r}")
        _check_range("actor", "init_log_std", self.init_log_std, -5.0, 2.0)
        _check_range("actor", "input_scale", self.input_scale, 0.0, math.inf)
        _check_range("actor", "velocity_damping", self.velocity_damping, 0.0, 100.0, " 1/s")
        _check_frame("actor", self.frame, self.variant, "typed")
        if not isinstance(self.token_layers, int) or isinstance(self.token_layers, bool) or not 0 <= self.token_layers <= 4:
            raise PolicyConfigError(f"actor.token_layers must be an integer in [0, 4], got {self.token_layers!r}")
        if not isinstance(self.own_target, bool):
            raise PolicyConfigError(f"actor.own_target must be true or false, got {self.own_target!r}")
        if self.own_target and self.variant != "typed":
            raise PolicyConfigError(f"actor.own_target applies to the typed actor only; set it to false for "
                                    f"variant {self.variant!r}")
        if self.token_layers and self.variant != "typed":
            raise PolicyConfigError(f"actor.token_layers applies to the typed actor only; set it to 0 for "
                                    f"variant {self.variant!r}")

    @property
    def obs_kind(self) -> str:
        """The observation the actor reads: ``"flat"`` for the MLP baseline, else ``"tokens"``."""
        return "flat" if self.variant == "mlp" else "tokens"

    def to_dict(self) -> dict:
        d = dataclasses.asdict(self)
        d["hidden_sizes"] = list(self.hidden_sizes)
        return d

    @classmethod
    def from_dict(cls, data: dict) -> ActorConfig:
        return dataclass_from_dict(cls, data, "actor")


@dataclass(frozen=True)
class CriticConfig:
    """The centralised critic (one network, a value per robot).

    Attributes:
        variant: ``"attention"`` (entity tokens, any N) or ``"mlp"`` (flat vectors, fixed N;
            goes with the ``"mlp"`` actor).
        embed_dim, num_heads, embed_hidden, hidden_sizes: as in :class:`ActorConfig`.
        value_mixing: epsilon of the paper's Equation (2),
            ``V_joint^i = eps * V^i + (1 - eps) * mean_j V^j``; 1.0 turns mixing off.
        input_scale: as in :class:`ActorConfig`.
        frame: as in :class:`ActorConfig` (the value does not turn); None: ``"formation"`` for
            the attention critic, ``"world"`` for the MLP one.
    """

    variant: str = "attention"
    embed_dim: int = 64
    num_heads: int = 4
    embed_hidden: int = 0
    hidden_sizes: tuple[int, ...] = (128,)
    value_mixing: float = 1.0
    input_scale: float = 4.0
    frame: str | None = None

    def __post_init__(self) -> None:
        object.__setattr__(self, "hidden_sizes", _check_hidden("critic", self.hidden_sizes))
        if self.frame is None:
            object.__setattr__(self, "frame", "formation" if self.variant == "attention" else "world")
        self.validate()

    def validate(self) -> None:
        if self.variant not in CRITIC_VARIANTS:
            raise PolicyConfigError(f"critic.variant must be one of {CRITIC_VARIANTS}, got {self.variant!r}")
        _check_positive_int("critic", "embed_dim", self.embed_dim)
        _check_positive_int("critic", "num_heads", self.num_heads)
        if self.embed_dim % self.num_heads:
            raise PolicyConfigError(f"critic.num_heads ({self.num_heads}) must divide critic.embed_dim "
                                    f"({self.embed_dim})")
        if not isinstance(self.embed_hidden, int) or isinstance(self.embed_hidden, bool) or self.embed_hidden < 0:
            raise PolicyConfigError(f"critic.embed_hidden must be an integer >= 0 (0: linear), got {self.embed_hidden!r}")
        if self.embed_hidden and self.variant != "attention":
            raise PolicyConfigError("critic.embed_hidden applies to the attention critic only; set it to 0 "
                                    f"for variant {self.variant!r}")
        _check_range("critic", "value_mixing", self.value_mixing, 0.0, 1.0, " (1 = no mixing)")
        _check_range("critic", "input_scale", self.input_scale, 0.0, math.inf)
        _check_frame("critic", self.frame, self.variant, "attention")

    @property
    def obs_kind(self) -> str:
        return "flat" if self.variant == "mlp" else "tokens"

    def to_dict(self) -> dict:
        d = dataclasses.asdict(self)
        d["hidden_sizes"] = list(self.hidden_sizes)
        return d

    @classmethod
    def from_dict(cls, data: dict) -> CriticConfig:
        return dataclass_from_dict(cls, data, "critic")
