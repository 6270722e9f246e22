"""Decentralised actors: robot i's observation -> mean target acceleration (E, N, 2) [m/s^2].

Every actor has the same interface, shared by training, the ControlStack and TorchScript:

* ``forward(obs, mask=None) -> mean`` (E, N, 2), each component in ``(-accel_limit,
  accel_limit)``: ``accel_limit * tanh((u - velocity_damping * v) / accel_limit)`` with ``u``
  the network output and ``v`` the robot's own velocity (see
  :func:`controllers.policy.layers.bounded_acceleration`); the environment also clips the norm.
* ``log_std`` (2,): learned, state-independent log standard deviation of the Gaussian
  exploration noise (training only; deployment uses the mean).
* ``obs_kind`` (``"tokens"`` or ``"flat"``), ``num_robots`` (-1: any N), ``accel_limit``.
* ``attention(obs, mask=None)`` (attention variants): the weights (E, N, H, T) used for the
  paper's Figure 5 kind of plot.

Token observations are (E, N, T = 2N+1, F = 4) with mask (E, N, T) in the layout of
:mod:`sim.observations`; flat observations are (E, N, 4N+2).
"""

from __future__ import annotations

import torch
from torch import nn

from controllers.policy.config import ActorConfig
from controllers.policy.layers import (
    AttentionHead,
    SlotLinear,
    TokenMixer,
    TypedEmbedding,
    bounded_acceleration,
    check_tokens,
    formation_turn,
    keep_self_valid,
    mlp,
    turn_back,
    turn_tokens,
    zero_masked,
)
from sim.observations import TOKEN_DIM, flat_dim

ACTION_DIM = 2
OUT_GAIN = 0.01   # small initial means: the untrained policy barely moves


class TypedSDPAActor(nn.Module):
    """SDPA actor with one embedding per token type; the same weights run any N.

    Per robot (B = E * N rows)::

        x_t = W_type(t) f_t + b_type(t)                  (T, D) embedded tokens
        x   = TokenMixer_L(... TokenMixer_1(x))          config.token_layers blocks (0: none)
        z   = MultiHeadSDPA(query = x_self, keys = values = x_valid)
        u    = MLP([x_self, z])                          one hidden layer of 128 ReLU
        mean = accel_limit * tanh((u - k_v v) / accel_limit)      k_v = velocity_damping

    With ``config.frame == "formation"`` the tokens f_t are first turned by the quarter turn R
    of :func:`~controllers.policy.layers.formation_turn` and the mean is ``R^T mean``: a scene
    turned by a quarter turn about the arena's centre gets its actions turned alike, exactly.
    Permuting robots permutes the outputs (the pooling is symmetric in the keys).
    """

    __jit_ignored_attributes__ = ["config"]
    obs_kind: str = "tokens"

    def __init__(self, config: ActorConfig, accel_limit: float = 1.0):
        super().__init__()
        self.config = config
        self.num_robots = -1
        self.accel_limit = float(accel_limit)
        self.token_dim = TOKEN_DIM
        self.action_dim = ACTION_DIM
        self.input_scale = float(config.input_scale)
        self.velocity_damping = float(config.velocity_damping)
        self.turning = config.frame == "formation"
        self.own_target = bool(config.own_target)
        self.embedding = TypedEmbedding(TOKEN_DIM, config.embed_dim, config.embed_hidden)
        self.mixers = nn.ModuleList(TokenMixer(config.embed_dim, config.num_heads)
                                    for _ in range(config.token_layers))
        self.head = AttentionHead(config.embed_dim, config.num_heads, config.hidden_sizes,
                                  ACTION_DIM, OUT_GAIN)
        self.log_std = nn.Parameter(torch.full((ACTION_DIM,), float(config.init_log_std)))

    def _encode(self, obs: torch.Tensor, mask: torch.Tensor | None):
        """Embedded tokens (B, T, D), key mask, the rows' turns (B, 2, 2) or None, and their
        own velocities (B, 2) in the frame the network sees."""
        check_tokens(obs, mask, self.token_dim)
        e, n, t = obs.shape[0], obs.shape[1], obs.shape[2]
        m = keep_self_valid(mask, e * n, t)
        f = zero_masked(obs, mask).reshape(e * n, t, self.token_dim)
        turn: torch.Tensor | None = None
        if self.turning:
            turn = formation_turn(f, m)
            f = turn_tokens(f, turn)
        return self._mix(self.embedding(f * self.input_scale, n), m), m, turn, f[:, 0, 2:4]

    def _mix(self, x: torch.Tensor, m: torch.Tensor | None) -> torch.Tensor:
        for mixer in self.mixers:
            x = mixer(x, m)
        return x

    def _act(self, out: torch.Tensor, velocity: torch.Tensor, turn: torch.Tensor | None) -> torch.Tensor:
        a = bounded_acceleration(out, velocity, self.velocity_damping, self.accel_limit)
        return a if turn is None else turn_back(a, turn)

    def forward(self, obs: torch.Tensor, mask: torch.Tensor | None = None) -> torch.Tensor:
        x, m, turn, velocity = self._encode(obs, mask)
        a = self._act(self.head(x[:, 0], x, m), velocity, turn)
        return a.view(obs.shape[0], obs.shape[1], self.action_dim)

    def rows(self, tokens: torch.Tensor, mask: torch.Tensor) -> torch.Tensor:
        """:meth:`forward` for robots as independent rows: tokens (B, T = 2N+1, F), mask (B, T)
        bool -> (B, 2); N follows from T. The reference of exported files, which compute it as
        :class:`deploy.export.graph.TypedRows`."""
        m = torch.cat((torch.ones_like(mask[:, :1]), mask[:, 1:].to(torch.bool)), 1)
        f = torch.where(m.unsqueeze(-1), tokens, torch.zeros((), dtype=tokens.dtype))
        turn: torch.Tensor | None = None
        if self.turning:
            turn = formation_turn(f, m)
            f = turn_tokens(f, turn)
        x = self._mix(self.embedding(f * self.input_scale, (tokens.shape[1] - 1) // 2), m)
        return self._act(self.head(x[:, 0], x, m), f[:, 0, 2:4], turn)

    @torch.jit.export
    def attention(self, obs: torch.Tensor, mask: torch.Tensor | None = None) -> torch.Tensor:
        """(E, N, H, T) attention weights of each robot's query over its tokens."""
        x, m, _, _ = self._encode(obs, mask)
        w = self.head.weights(x[:, 0], x, m)
        return w.view(obs.shape[0], obs.shape[1], w.shape[1], w.shape[2])


class SlotSDPAActor(nn.Module):
    """The paper's Figure 2: one embedding per input slot, built for a fixed N.

    Slots (S = 2N + 2): ``P`` (own position, 2 features), ``V`` (own velocity, 2),
    ``G_1..G_N`` (target tokens), ``R_1..R_{N-1}`` (other-robot tokens), ``O`` (object token).
    The query is ``e_P + e_V`` (the embedding of the robot's own state); keys and values are all
    slot embeddings. A model for more robots adds slots (``G_{M+1}..``, ``R_M..``) with fresh
    weights and copies the rest (:func:`grow_slot_actor`): "a new input layer is added".
    """

    __jit_ignored_attributes__ = ["config"]
    obs_kind: str = "tokens"

    def __init__(self, config: ActorConfig, num_robots: int, accel_limit: float = 1.0):
        super().__init__()
        if not isinstance(num_robots, int) or num_robots < 1:
            raise ValueError(f"num_robots must be a positive integer, got {num_robots!r}")
        d = config.embed_dim
        self.config = config
        self.num_robots = num_robots
        self.accel_limit = float(accel_limit)
        self.token_dim = TOKEN_DIM
        self.action_dim = ACTION_DIM
        self.input_scale = float(config.input_scale)
        self.velocity_damping = float(config.velocity_damping)
        self.embed_position = nn.Linear(2, d)
        self.embed_velocity = nn.Linear(2, d)
        self.embed_targets = SlotLinear(num_robots, TOKEN_DIM, d)
        self.embed_robots = SlotLinear(num_robots - 1, TOKEN_DIM, d)
        self.embed_object = nn.Linear(TOKEN_DIM, d)
        self.head = AttentionHead(d, config.num_heads, config.hidden_sizes, ACTION_DIM, OUT_GAIN)
        self.log_std = nn.Parameter(torch.full((ACTION_DIM,), float(config.init_log_std)))

    def _encode(self, obs: torch.Tensor, mask: torch.Tensor | None):
        check_tokens(obs, mask, self.token_dim)
        e, n, t = obs.shape[0], obs.shape[1], obs.shape[2]
        if n != self.num_robots:
            raise ValueError(f"this slot actor was built for {self.num_robots} robots but got {n}; "
                             f"grow it with controllers.policy.grow_slot_actor(actor, {n})")
        f = zero_masked(obs, mask).reshape(e * n, t, self.token_dim) * self.input_scale
        x = torch.cat((self.embed_position(f[:, :1, 0:2]), self.embed_velocity(f[:, :1, 2:4]),
                       self.embed_targets(f[:, 1:n + 1]), self.embed_robots(f[:, n + 1:2 * n]),
                       self.embed_object(f[:, 2 * n:])), 1)                      # (B, 2N+2, D)
        m: torch.Tensor | None = None
        if mask is not None:    # P and V both come from the (always valid) self token
            tm = mask.reshape(e * n, t).to(torch.bool)
            m = torch.cat((torch.ones_like(tm[:, :2]), tm[:, 1:]), 1)
        return x, m

    def forward(self, obs: torch.Tensor, mask: torch.Tensor | None = None) -> torch.Tensor:
        x, m = self._encode(obs, mask)
        out = self.head(x[:, 0] + x[:, 1], x, m).view(obs.shape[0], obs.shape[1], self.action_dim)
        return bounded_acceleration(out, obs[:, :, 0, 2:4], self.velocity_damping, self.accel_limit)

    def rows(self, tokens: torch.Tensor, mask: torch.Tensor) -> torch.Tensor:
        """:meth:`forward` for robots as independent rows: tokens (B, 2N+1, F), mask (B, 2N+1)
        bool -> (B, 2), N fixed by the slots."""
        return self.forward(tokens.unsqueeze(1).expand(-1, self.num_robots, -1, -1),
                            mask.unsqueeze(1).expand(-1, self.num_robots, -1))[:, 0]

    @torch.jit.export
    def attention(self, obs: torch.Tensor, mask: torch.Tensor | None = None) -> torch.Tensor:
        """(E, N, H, S = 2N+2) attention weights over the slots P, V, G.., R.., O."""
        x, m = self._encode(obs, mask)
        w = self.head.weights(x[:, 0] + x[:, 1], x, m)
        return w.view(obs.shape[0], obs.shape[1], w.shape[1], w.shape[2])


class MLPActor(nn.Module):
    """MLP-MAPPO baseline: the paper's flat vector (E, N, 4N+2) -> mean (E, N, 2); fixed N."""

    __jit_ignored_attributes__ = ["config"]
    obs_kind: str = "flat"

    def __init__(self, config: ActorConfig, num_robots: int, accel_limit: float = 1.0):
        super().__init__()
        if not isinstance(num_robots, int) or num_robots < 1:
            raise ValueError(f"num_robots must be a positive integer, got {num_robots!r}")
        self.config = config
        self.num_robots = num_robots
        self.accel_limit = float(accel_limit)
        self.token_dim = TOKEN_DIM
        self.action_dim = ACTION_DIM
        self.input_scale = float(config.input_scale)
        self.velocity_damping = float(config.velocity_damping)
        self.net = mlp(flat_dim(num_robots), config.hidden_sizes, ACTION_DIM, OUT_GAIN)
        self.log_std = nn.Parameter(torch.full((ACTION_DIM,), float(config.init_log_std)))

    def forward(self, obs: torch.Tensor, mask: torch.Tensor | None = None) -> torch.Tensor:
        expected = 4 * self.num_robots + 2
        if obs.dim() != 3 or obs.shape[1] != self.num_robots or obs.shape[2] != expected:
            raise ValueError(f"obs must be flat vectors of shape (num_envs, {self.num_robots}, "
                             f"{expected}) for this MLP actor, got {obs.shape}")
        return bounded_acceleration(self.net(obs * self.input_scale), obs[:, :, 2:4], self.velocity_damping,
                                    self.accel_limit)


def build_actor(config: ActorConfig, num_robots: int, accel_limit: float = 1.0) -> nn.Module:
    """The actor of ``config.variant`` for ``num_robots`` robots (the typed one runs any N)."""
    if config.variant == "typed":
        return TypedSDPAActor(config, accel_limit)
    if config.variant == "slot":
        return SlotSDPAActor(config, num_robots, accel_limit)
    return MLPActor(config, num_robots, accel_limit)


def grow_slot_actor(actor: SlotSDPAActor, num_robots: int, seed: int = 0) -> SlotSDPAActor:
    """A slot actor for ``num_robots`` that keeps every trained weight of ``actor`` (M robots).

    Shared layers (P, V, object embeddings, attention, MLP head, log-std) and the slots
    ``G_1..G_min(M,N)`` and ``R_1..R_min(M-1,N-1)`` are copied; slots beyond M get fresh
    initial weights drawn with ``seed``. With ``num_robots < M`` the extra slots are dropped.
    """
    if not isinstance(actor, SlotSDPAActor):
        raise TypeError(f"grow_slot_actor needs a SlotSDPAActor, got {type(actor).__name__}; "
                        "typed actors run any number of robots as they are")
    grown = SlotSDPAActor(actor.config, num_robots, actor.accel_limit)
    generator = torch.Generator().manual_seed(seed)
    grown.embed_targets.reset_slots(0, num_robots, generator)
    grown.embed_robots.reset_slots(0, num_robots - 1, generator)
    source = actor.state_dict()
    target = grown.state_dict()
    with torch.no_grad():
        for name, value in target.items():
            old = source[name]
            if name.startswith(("embed_targets.", "embed_robots.")):
                k = min(old.shape[0], value.shape[0])
                value[:k] = old[:k]
            else:
                value.copy_(old)
    grown.load_state_dict(target)
    return grown


def count_parameters(module: nn.Module) -> int:
    """Number of trainable scalars."""
    return sum(p.numel() for p in module.parameters() if p.requires_grad)
