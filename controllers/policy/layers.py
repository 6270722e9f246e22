"""Building blocks shared by the actors and critics (TorchScript-friendly, tensor-only forwards).

Shapes: ``B`` is a flat batch (``num_envs * num_robots`` for an actor), ``T`` tokens or slots,
``F`` token features (4), ``D`` embedding width, ``H`` attention heads.
"""

from __future__ import annotations

import math

import torch
import torch.nn.functional as F
from torch import nn


def exporting() -> bool:
    """True while ``torch.export`` (or the ONNX exporter on top of it) traces: the export path of
    the slot actor (:meth:`MultiHeadAttention.one_query`) computes the same numbers as training's
    with a graph that does less work (a typed actor is exported through
    :class:`deploy.export.graph.TypedRows`). Training keeps its kernels: one_query's numbers
    differ in rounding, which sends individual seeds elsewhere (paper-3, 5 seeds: episodes to
    convergence 528-2400 with one seed not converging, against 384-1200 with SDPA)."""
    return bool(torch.compiler.is_exporting())


def init_linear(layer: nn.Linear, gain: float) -> nn.Linear:
    """Orthogonal weights with ``gain`` and zero bias (the usual PPO initialisation)."""
    nn.init.orthogonal_(layer.weight, gain)
    nn.init.zeros_(layer.bias)
    return layer


def mlp(in_dim: int, hidden_sizes: tuple[int, ...], out_dim: int, out_gain: float) -> nn.Sequential:
    """``in_dim -> hidden (ReLU) ... -> out_dim``; hidden layers gain sqrt(2), output ``out_gain``."""
    layers: list[nn.Module] = []
    width = in_dim
    for h in hidden_sizes:
        layers += [init_linear(nn.Linear(width, h), math.sqrt(2.0)), nn.ReLU()]
        width = h
    layers.append(init_linear(nn.Linear(width, out_dim), out_gain))
    return nn.Sequential(*layers)


class SlotLinear(nn.Module):
    """One affine map per slot: ``(B, S, F) -> (B, S, D)``, ``y[b, s] = x[b, s] @ W[s] + b[s]``.

    Initialised like :class:`torch.nn.Linear` (uniform in ``+-1/sqrt(F)``); ``S`` may be 0.
    """

    def __init__(self, num_slots: int, in_dim: int, out_dim: int):
        super().__init__()
        self.weight = nn.Parameter(torch.empty(num_slots, in_dim, out_dim))
        self.bias = nn.Parameter(torch.empty(num_slots, out_dim))
        self.reset_slots(0, num_slots)

    @torch.jit.unused
    def reset_slots(self, start: int, stop: int, generator: torch.Generator | None = None) -> None:
        """Fresh initial weights for slots ``start..stop-1`` (new inputs of a grown model)."""
        bound = 1.0 / math.sqrt(self.weight.shape[1])
        with torch.no_grad():
            for p in (self.weight, self.bias):
                fresh = torch.rand(p[start:stop].shape, generator=generator, dtype=p.dtype)
                p[start:stop] = (fresh * 2 - 1) * bound

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return torch.einsum("bsf,sfd->bsd", x, self.weight) + self.bias


class TypedEmbedding(nn.Module):
    """One embedding per token type of the layout in :mod:`sim.observations`.

    ``(B, T = 2n+1, F) -> (B, T, D)``: token 0 (self) through ``embed_self``, tokens
    ``1..n`` (targets) through ``embed_target``, ``n+1..2n-1`` (other robots) through
    ``embed_robot`` and token ``2n`` (object) through ``embed_object``. Each is linear, or with
    ``hidden`` > 0 a ReLU layer of that width and a linear one (a linear embedding cannot form
    a distance such as the gap to the object out of the relative vector). The weights do not
    depend on n.
    """

    def __init__(self, in_dim: int, dim: int, hidden: int = 0):
        super().__init__()

        def embed() -> nn.Module:
            if hidden <= 0:
                return nn.Linear(in_dim, dim)
            return nn.Sequential(nn.Linear(in_dim, hidden), nn.ReLU(), nn.Linear(hidden, dim))

        self.embed_self = embed()
        self.embed_target = embed()
        self.embed_robot = embed()
        self.embed_object = embed()

    def forward(self, tokens: torch.Tensor, n: int) -> torch.Tensor:
        return torch.cat((self.embed_self(tokens[:, :1]),
                          self.embed_target(tokens[:, 1:n + 1]),
                          self.embed_robot(tokens[:, n + 1:2 * n]),
                          self.embed_object(tokens[:, 2 * n:])), 1)


TURN_TIE = 1e-5
"""[m] turn scores this close to the largest tie (:func:`formation_turn`); ``deploy/npz_policy.py``
holds the same number (it runs without the project)."""


def first_turn(scores: torch.Tensor, tie: float = TURN_TIE) -> torch.Tensor:
    """(B,) the first of the (B, 4) quarter-turn ``scores`` within ``tie`` of the largest (an
    argument, not the global: TorchScript reads no module floats)."""
    near = scores >= scores.amax(-1, keepdim=True) - tie
    return near.to(scores.dtype).argmax(-1)                 # argmax: the first largest


def formation_turn(tokens: torch.Tensor, read: torch.Tensor | None) -> torch.Tensor:
    """(B, 2, 2): for each row of tokens (B, T = 2N+1, F) in the layout of
    :mod:`sim.observations` (masked tokens already zero; ``read`` (B, T) bool or None: all),
    the quarter turn ``R_k`` that brings its formation into the right-to-left frame.

    With ``m = mean_k (g_k - p) - (c - p) = mean_k g_k - c`` (the targets' centroid seen from the
    object's centroid, the same for every robot of a team), ``k = argmax_k -(R_k m)_x``: the
    targets come to lie left of the object, as in the presets. Scores within ``TURN_TIE`` of the
    largest count as tied and the first of them wins: on a diagonal layout (``|m_x| = |m_y|``)
    each robot's ``m``, summed from its own float32 tokens, differs in the last bits, and a plain
    argmax let rounding pick the turn, differently per robot and per exported format (0.5
    m/s^2 apart). The token kinds are found by
    index (targets 1..N, object 2N), not by slicing at N, so exported graphs keep T dynamic.
    Every token feature pair is a vector in the arena frame (the self token's position is
    relative to the arena's centre, about which the square arena is symmetric), so turning them
    all turns the scene; quarter turns are exact in floating point (entries 0 and +-1).
    """
    b, t = tokens.shape[0], tokens.shape[1]
    index = torch.arange(t, device=tokens.device)
    kind = (index >= 1).long() + (index >= (t + 1) // 2).long() + (index >= t - 1).long()
    target = (kind == 1).to(tokens.dtype).expand(b, t)
    if read is not None:
        target = target * read.to(tokens.dtype)
    weight = target / target.sum(1, keepdim=True).clamp_min(1.0) - (kind == 3).to(tokens.dtype)
    m = (tokens[..., 0:2] * weight.unsqueeze(-1)).sum(1)                      # (B, 2)
    k = first_turn(torch.stack((-m[:, 0], m[:, 1], m[:, 0], -m[:, 1]), -1))   # quarter turns, CCW
    c = (k == 0).to(tokens.dtype) - (k == 2).to(tokens.dtype)                  # cos, sin of k 90 deg
    s = (k == 1).to(tokens.dtype) - (k == 3).to(tokens.dtype)
    return torch.stack((torch.stack((c, -s), -1), torch.stack((s, c), -1)), 1)


def turn_tokens(tokens: torch.Tensor, turn: torch.Tensor) -> torch.Tensor:
    """(B, T, 4) tokens with both feature pairs turned by ``turn`` (B, 2, 2)."""
    b, t = tokens.shape[0], tokens.shape[1]
    pairs = tokens.reshape(b, t, 2, 2)
    return torch.matmul(pairs, turn.transpose(1, 2).unsqueeze(1)).reshape(b, t, 4)


def turn_back(vectors: torch.Tensor, turn: torch.Tensor) -> torch.Tensor:
    """(B, 2) vectors of the turned frame back in the arena frame: ``R^T a``."""
    return torch.matmul(turn.transpose(1, 2), vectors.unsqueeze(-1)).squeeze(-1)


def check_tokens(obs: torch.Tensor, mask: torch.Tensor | None, feature_dim: int) -> None:
    """Raise ValueError unless ``obs`` is (E, N, 2N+1, F) and ``mask`` None or (E, N, 2N+1)."""
    if obs.dim() != 4 or obs.shape[3] != feature_dim or obs.shape[2] != 2 * obs.shape[1] + 1:
        raise ValueError(f"obs must be entity tokens of shape (num_envs, num_robots, 2*num_robots+1, "
                         f"{feature_dim}), got {obs.shape}")
    if mask is not None and mask.shape != obs.shape[:3]:
        raise ValueError(f"mask must have shape (num_envs, num_robots, 2*num_robots+1) = "
                         f"{obs.shape[:3]}, got {mask.shape}")


def zero_masked(obs: torch.Tensor, mask: torch.Tensor | None) -> torch.Tensor:
    """(E, N, T, F) tokens with every masked token's features set to 0 (the robot's own token,
    column 0, always kept): attention gives a masked key weight 0, but 0 x NaN is NaN, so a
    masked token holding NaN or inf would still turn every action into NaN."""
    if mask is None:
        return obs
    keep = mask.to(torch.bool).clone()
    keep[..., 0] = True
    return torch.where(keep.unsqueeze(-1), obs, torch.zeros((), dtype=obs.dtype))


def keep_self_valid(mask: torch.Tensor | None, batch: int, width: int) -> torch.Tensor | None:
    """(..., T) token mask -> (batch, width) bool with column 0 (the robot itself) always valid."""
    if mask is None:
        return None
    m = mask.reshape(batch, width).to(torch.bool)
    return torch.cat((torch.ones_like(m[:, :1]), m[:, 1:]), 1)


class MultiHeadAttention(nn.Module):
    """Multi-head scaled dot-product attention (Vaswani et al., the paper's Equation (4))::

        q = W_q s,  k_t = W_k x_t,  v_t = W_v x_t          (each split into H heads of D/H)
        out_h = softmax(q_h k_h^T / sqrt(D/H), over valid t) v_h,    out = concat_h out_h

    Inputs: queries ``s`` (B, Q, D), keys/values ``x`` (B, T, D), ``mask`` (B, T) bool (True =
    valid key) or None. Output (B, Q, D). Every row needs at least one valid key (callers keep
    the robot's own token valid), otherwise the softmax has no support and gives NaN.
    """

    def __init__(self, dim: int, num_heads: int):
        super().__init__()
        self.num_heads = num_heads
        self.head_dim = dim // num_heads
        self.query = init_linear(nn.Linear(dim, dim), 1.0)
        self.key = init_linear(nn.Linear(dim, dim), 1.0)
        self.value = init_linear(nn.Linear(dim, dim), 1.0)

    def _heads(self, y: torch.Tensor) -> torch.Tensor:
        b, t, _ = y.shape                                     # (B, T, D) -> (B, H, T, D/H)
        return y.view(b, t, self.num_heads, self.head_dim).transpose(1, 2)

    def forward(self, s: torch.Tensor, x: torch.Tensor, mask: torch.Tensor | None) -> torch.Tensor:
        q, k, v = self._heads(self.query(s)), self._heads(self.key(x)), self._heads(self.value(x))
        attn_mask: torch.Tensor | None = None
        if mask is not None:
            attn_mask = mask.view(mask.shape[0], 1, 1, mask.shape[1])
        out = F.scaled_dot_product_attention(q, k, v, attn_mask=attn_mask)   # (B, H, Q, D/H)
        return out.transpose(1, 2).reshape(s.shape[0], s.shape[1], self.num_heads * self.head_dim)

    def one_query(self, s: torch.Tensor, x: torch.Tensor, mask: torch.Tensor | None) -> torch.Tensor:
        """:meth:`forward` for one query a row: ``s`` (B, D), ``x`` (B, T, D), ``mask`` (B, T)
        -> (B, D), the same numbers (to rounding) without projecting the T keys and values.

        With ``W_k^h`` (D/H, D) the rows of head h of the key projection, the score of token t is
        ``q_h . (W_k^h x_t + b_k^h) = x_t . (W_k^h^T q_h) + q_h . b_k^h``, and since the weights
        sum to one the head's output is ``W_v^h (sum_t w_t x_t) + b_v^h``: two (B, D) x (D, D)
        products in place of two (B T, D) x (D, D) ones (7x less work at N = 3, 2N + 1 x at N),
        and no flash-attention kernel, whose backward dominated a training step at this size.
        """
        b, t, dim = x.shape
        h, d = self.num_heads, self.head_dim
        q = self.query(s).view(b, h, d)
        u = torch.einsum("bhe,hed->bhd", q, self.key.weight.view(h, d, dim))          # (B, H, D)
        offset = (q * self.key.bias.view(h, d)).sum(-1)                               # (B, H)
        scores = (torch.einsum("btd,bhd->bth", x, u) + offset.unsqueeze(1)) / math.sqrt(d)
        if mask is not None:
            scores = scores.masked_fill(~mask.unsqueeze(-1), float("-inf"))
        weights = torch.softmax(scores, dim=1)                                        # (B, T, H)
        pooled = torch.einsum("bth,btd->bhd", weights, x)                             # (B, H, D)
        out = torch.einsum("bhd,hed->bhe", pooled, self.value.weight.view(h, d, dim))
        return (out + self.value.bias.view(h, d)).reshape(b, h * d)

    @torch.jit.export
    def weights(self, s: torch.Tensor, x: torch.Tensor, mask: torch.Tensor | None) -> torch.Tensor:
        """The attention weights (B, H, Q, T); each row sums to one over the valid keys."""
        q, k = self._heads(self.query(s)), self._heads(self.key(x))
        scores = torch.matmul(q, k.transpose(-2, -1)) / math.sqrt(self.head_dim)
        if mask is not None:
            scores = scores.masked_fill(~mask.view(mask.shape[0], 1, 1, mask.shape[1]), float("-inf"))
        return torch.softmax(scores, dim=-1)


class AttentionHead(nn.Module):
    """Attention with the robot's own embedding as the query, then an MLP on ``[s, attended]``
    (while exporting, the attention is :meth:`MultiHeadAttention.one_query`).

    ``s`` (B, D) is the robot's own embedding, ``x`` (B, T, D) the embedded tokens (keys and
    values), ``mask`` (B, T). Output (B, out_dim); :meth:`weights` gives (B, H, T).
    """

    def __init__(self, dim: int, num_heads: int, hidden_sizes: tuple[int, ...], out_dim: int,
                 out_gain: float):
        super().__init__()
        self.attention = MultiHeadAttention(dim, num_heads)
        self.mlp = mlp(2 * dim, hidden_sizes, out_dim, out_gain)

    def forward(self, s: torch.Tensor, x: torch.Tensor, mask: torch.Tensor | None) -> torch.Tensor:
        if not torch.jit.is_scripting():    # TorchScript compiles none of this block
            if exporting():
                return self.mlp(torch.cat((s, self.attention.one_query(s, x, mask)), -1))
        attended = self.attention(s.unsqueeze(1), x, mask).squeeze(1)
        return self.mlp(torch.cat((s, attended), -1))

    @torch.jit.export
    def weights(self, s: torch.Tensor, x: torch.Tensor, mask: torch.Tensor | None) -> torch.Tensor:
        return self.attention.weights(s.unsqueeze(1), x, mask).squeeze(2)


class TokenMixer(nn.Module):
    """One residual self-attention block over a robot's embedded tokens (no normalisation)::

        x <- x + W_o MultiHeadSDPA(query = x_t, keys = values = x_valid)
        x <- x + W_2 relu(W_1 x + b_1) + b_2                      (width 2D)

    ``x`` (B, T, D), ``mask`` (B, T) bool (True = valid; column 0 always valid) -> (B, T, D).
    ``W_o`` and ``W_2`` start at zero, so a fresh block is the identity: an actor trained
    without blocks computes the same actions with them, and fine-tuning starts where it was.
    Tokens stay tied to their robot's frame (every feature is relative to the robot), so the
    block is equivariant in the order of targets and of other robots.
    """

    def __init__(self, dim: int, num_heads: int):
        super().__init__()
        self.attention = MultiHeadAttention(dim, num_heads)
        self.out = init_linear(nn.Linear(dim, dim), 1.0)
        self.feed = nn.Sequential(init_linear(nn.Linear(dim, 2 * dim), math.sqrt(2.0)), nn.ReLU(),
                                  init_linear(nn.Linear(2 * dim, dim), 1.0))
        with torch.no_grad():
            self.out.weight.zero_()
            self.feed[2].weight.zero_()

    def forward(self, x: torch.Tensor, mask: torch.Tensor | None) -> torch.Tensor:
        x = x + self.out(self.attention(x, x, mask))
        return x + self.feed(x)


def bounded_acceleration(u: torch.Tensor, velocity: torch.Tensor, damping: float, limit: float) -> torch.Tensor:
    """The actor's mean acceleration [m/s^2] from the network output ``u`` (..., 2)::

        a = limit * tanh((u - damping * v) / limit)

    ``velocity`` v (..., 2) [m/s] is the robot's own velocity from its observation; with
    ``damping`` k > 0 [1/s] a zero output brakes the robot (a = -k v for small v), so an
    untrained or slightly biased network stops robots instead of driving them into a wall.
    """
    if damping != 0.0:
        u = u - damping * velocity
    return limit * torch.tanh(u / limit)


def gaussian_log_prob(actions: torch.Tensor, mean: torch.Tensor, log_std: torch.Tensor) -> torch.Tensor:
    """Log density of a diagonal Gaussian, summed over the last (action) dimension.

    ``actions``, ``mean`` (..., A); ``log_std`` (A,). Returns (...,)::

        log p = sum_a [ -(x_a - mu_a)^2 / (2 sigma_a^2) - log sigma_a - log(2 pi) / 2 ]
    """
    z = (actions - mean) * torch.exp(-log_std)
    return (-0.5 * z * z - log_std - 0.5 * math.log(2 * math.pi)).sum(-1)


def gaussian_entropy(log_std: torch.Tensor) -> torch.Tensor:
    """Entropy of a diagonal Gaussian: ``sum_a (1/2 + log(2 pi)/2 + log sigma_a)`` (a scalar)."""
    return (0.5 + 0.5 * math.log(2 * math.pi) + log_std).sum()
