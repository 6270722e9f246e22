"""Centralised critics (MAPPO): everything the team sees -> a value per robot (E, N).

Both critics return values in the trainer's *normalised* value space (see
:class:`controllers.mappo.losses.ValueNormalizer`) and optionally mix them as in the paper's
Equation (2), written for N robots::

    V_joint^i = eps * V^i + (1 - eps) * mean_j V^j        (eps = ``value_mixing``; 1 = off)
"""

from __future__ import annotations

import torch
from torch import nn

from controllers.policy.config import CriticConfig
from controllers.policy.layers import (
    AttentionHead,
    MultiHeadAttention,
    TypedEmbedding,
    check_tokens,
    formation_turn,
    keep_self_valid,
    mlp,
    turn_tokens,
    zero_masked,
)
from sim.observations import TOKEN_DIM, flat_dim


def mix_values(values: torch.Tensor, eps: float) -> torch.Tensor:
    """(E, N) -> (E, N): ``eps * V^i + (1 - eps) * mean_j V^j`` (the paper's Equation (2))."""
    if eps >= 1.0:
        return values
    return eps * values + (1.0 - eps) * values.mean(1, keepdim=True)


class AttentionCritic(nn.Module):
    """Centralised critic for any N, permutation-equivariant in the robots.

    1. Each robot's token set (E, N, T, F) is embedded per token type and pooled by SDPA with
       the robot's own token as the query -> per-robot feature ``h_i`` (E, N, D).
    2. Robot-level SDPA: every ``h_i`` queries all ``h_j`` of its environment -> context ``c_i``.
    3. ``V^i = MLP([h_i, c_i])``, then optional value mixing.

    With ``config.frame == "formation"`` the tokens are turned first, as the actor's are.

    Token-level masks are honoured; all robots take part in step 2 (training always has the
    full team).
    """

    __jit_ignored_attributes__ = ["config"]
    obs_kind: str = "tokens"

    def __init__(self, config: CriticConfig):
        super().__init__()
        d = config.embed_dim
        self.config = config
        self.num_robots = -1
        self.input_scale = float(config.input_scale)
        self.value_mixing = float(config.value_mixing)
        self.turning = config.frame == "formation"
        self.token_dim = TOKEN_DIM
        self.embedding = TypedEmbedding(TOKEN_DIM, d, config.embed_hidden)
        self.token_pool = AttentionHead(d, config.num_heads, (), d, 1.0)
        self.robot_attention = MultiHeadAttention(d, config.num_heads)
        self.value_head = mlp(2 * d, config.hidden_sizes, 1, 1.0)

    def forward(self, obs: torch.Tensor, mask: torch.Tensor | None = None) -> torch.Tensor:
        check_tokens(obs, mask, self.token_dim)
        e, n, t = obs.shape[0], obs.shape[1], obs.shape[2]
        m = keep_self_valid(mask, e * n, t)
        f = zero_masked(obs, mask).reshape(e * n, t, self.token_dim)
        if self.turning:                    # the frame of ActorConfig.frame; a value does not turn
            f = turn_tokens(f, formation_turn(f, m))
        x = self.embedding(f * self.input_scale, n)
        h = torch.relu(self.token_pool(x[:, 0], x, m)).view(e, n, -1)
        c = self.robot_attention(h, h, None)                                   # (E, N, D)
        values = self.value_head(torch.cat((h, c), -1)).squeeze(-1)            # (E, N)
        return mix_values(values, self.value_mixing)


class MLPCritic(nn.Module):
    """MLP-MAPPO baseline critic for a fixed N: ``V^i = MLP([o_i, o_1, ..., o_N])``.

    Input: flat vectors (E, N, 4N+2); the global state is every robot's vector concatenated.
    """

    __jit_ignored_attributes__ = ["config"]
    obs_kind: str = "flat"

    def __init__(self, config: CriticConfig, num_robots: int):
        super().__init__()
        if not isinstance(num_robots, int) or num_robots < 1:
            raise ValueError(f"num_robots must be a positive integer, got {num_robots!r}")
        self.config = config
        self.num_robots = num_robots
        self.input_scale = float(config.input_scale)
        self.value_mixing = float(config.value_mixing)
        self.net = mlp((num_robots + 1) * flat_dim(num_robots), config.hidden_sizes, 1, 1.0)

    def forward(self, obs: torch.Tensor, mask: torch.Tensor | None = None) -> torch.Tensor:
        expected = 4 * self.num_robots + 2
        if obs.dim() != 3 or obs.shape[1] != self.num_robots or obs.shape[2] != expected:
            raise ValueError(f"obs must be flat vectors of shape (num_envs, {self.num_robots}, "
                             f"{expected}) for this MLP critic, got {obs.shape}")
        e, n = obs.shape[0], obs.shape[1]
        x = obs * self.input_scale
        joint = x.reshape(e, 1, n * expected).expand(e, n, n * expected)
        values = self.net(torch.cat((x, joint), -1)).squeeze(-1)
        return mix_values(values, self.value_mixing)


def build_critic(config: CriticConfig, num_robots: int) -> nn.Module:
    """The critic of ``config.variant`` (the attention critic runs any N)."""
    if config.variant == "attention":
        return AttentionCritic(config)
    return MLPCritic(config, num_robots)
