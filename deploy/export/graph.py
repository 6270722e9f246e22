r"""The typed SDPA actor rewritten for export: the same numbers with fewer, larger operations.

:class:`TypedRows` computes :meth:`controllers.policy.actor.TypedSDPAActor.rows` (tokens
(B, T = 2N+1, 4) with masked tokens already zero, read mask (B, T) -> accelerations (B, 2))
from the actor's weights, rearranged once at export so that the graph has no per-N slicing,
no head reshapes and no gathers of weights, and keeps B and T free:

* **token kinds** ``K`` (T, 4), one-hot (self, target, other robot, object), is row T of a
  constant table built for every T up to ``2 * MAX_ROBOTS + 1``;
* **formation turn**: ``m = w^T P`` with ``w_t = [t target, read] / #read targets - [t object]``
  and P the token positions (B, T, 2); the candidates ``(-m_x, m_y, m_x, -m_y) = m C`` (C holds
  0 and +-1, so the product is exact); ``R = TURNS[argmax]`` (exact quarter turns);
* **embedding** of token t by the layers of its kind: the first layers of the four kinds side by
  side, ``h = relu(f S W_1 + b_1)`` (T, 4 h) (the input scale S folded into W_1), the blocks of
  the other kinds zeroed by ``K``, then ``x = h W_2 + K b_2`` with the four second layers stacked
  (4 h, D): every product with a zeroed block is an exact zero. A linear embedding keeps the
  selected block of ``f S W_1 + b_1`` (D wide) instead;
* **attention with one query** ``s = x_0`` per row and head j (width d = D / H)::

      score_tj = x_t . (W_k^j^T q_j) / sqrt(d) + q_j . b_k^j / sqrt(d),     q = W_q s + b_q
      out_j    = W_v^j (sum_t softmax_t(score_tj) x_t) + b_v^j

  as three products with block matrices built here: ``u = q K_b`` (D, H D), the offsets
  ``q O_b`` (D, H) and ``pooled V_b`` (H D, D); the key and value projections of the T tokens
  (2 T D^2 products a row) are never formed;
* the head's MLP as trained, ``a = L tanh((u - c v) / L)``, then ``R^T a``.

Only the order of float32 sums differs from the training forward (about 1e-8 on the actions);
:func:`deploy.export.export_policy` compares every file with the actor's own ``rows`` and
refuses one further off than ``TOLERANCE``. The ONNX graph has 85 nodes (the actor's own graph:
133); at 5 robots inside the control tick the policy stage takes about 0.7 of the time with
ONNX Runtime, 0.75 with the TorchScript file and 0.6 with the .pt2 (README, "Policies on robots").
"""

from __future__ import annotations

import copy
import math

import torch
import torch.nn.functional as F
from torch import nn

from sim.observations import token_types
from sim.scenario import MAX_ROBOTS

TURNS = ((1.0, 0.0, 0.0, 1.0), (0.0, -1.0, 1.0, 0.0), (-1.0, 0.0, 0.0, -1.0), (0.0, 1.0, -1.0, 0.0))
"""R_k = [[cos, -sin], [sin, cos]] of k quarter turns counter-clockwise, row-major."""


def kind_table(max_tokens: int) -> torch.Tensor:
    """(max_tokens + 1, max_tokens, 4): row T holds the one-hot kinds (:func:`token_types`: self,
    targets, other robots, object) of the T = 2N + 1 tokens of a robot of N; other rows are zero."""
    table = torch.zeros(max_tokens + 1, max_tokens, 4)
    for t in range(3, max_tokens + 1, 2):
        table[t, :t] = F.one_hot(token_types((t - 1) // 2), 4).float()
    return table


def _layers(embed: nn.Module) -> list[nn.Linear]:
    return [embed] if isinstance(embed, nn.Linear) else [embed[0], embed[2]]


class TypedRows(nn.Module):
    """``rows(f, read) -> (B, 2)`` of a typed actor (module docstring); frozen weights."""

    def __init__(self, actor: nn.Module):
        super().__init__()
        embeds = [_layers(e) for e in (actor.embedding.embed_self, actor.embedding.embed_target,
                                       actor.embedding.embed_robot, actor.embedding.embed_object)]
        attention = actor.head.attention
        heads, d = attention.num_heads, attention.head_dim
        dim = heads * d
        self.accel_limit = float(actor.accel_limit)
        self.damping = float(actor.velocity_damping)
        self.turning = bool(actor.turning)
        self.two_layers = len(embeds[0]) == 2
        self.heads = heads
        self.first_width = embeds[0][0].out_features
        with torch.no_grad():
            self.register_buffer("kinds", kind_table(2 * MAX_ROBOTS + 1))
            self.register_buffer("turns", torch.tensor(TURNS).view(4, 2, 2))
            self.register_buffer("pick", torch.tensor([[-1.0, 0.0, 1.0, 0.0], [0.0, 1.0, 0.0, -1.0]]))
            self.register_buffer("w1", torch.cat([e[0].weight.t() * actor.input_scale for e in embeds], 1))
            self.register_buffer("b1", torch.cat([e[0].bias for e in embeds]))
            if self.two_layers:
                self.register_buffer("w2", torch.cat([e[1].weight.t() for e in embeds], 0))   # (4 h, D)
                self.register_buffer("b2", torch.stack([e[1].bias for e in embeds]))          # (4, D)
            else:
                self.register_buffer("w2", torch.zeros(0, dim))
                self.register_buffer("b2", torch.zeros(0, dim))
            wk, bk, wv = attention.key.weight, attention.key.bias, attention.value.weight
            key, offset, value = torch.zeros(dim, heads * dim), torch.zeros(dim, heads), torch.zeros(heads * dim, dim)
            for j in range(heads):
                rows = slice(j * d, (j + 1) * d)
                key[rows, j * dim:(j + 1) * dim] = wk[rows] / math.sqrt(d)
                offset[rows, j] = bk[rows] / math.sqrt(d)
                value[j * dim:(j + 1) * dim, rows] = wv[rows].t()
            self.register_buffer("wq", attention.query.weight.t().clone())
            self.register_buffer("bq", attention.query.bias.clone())
            self.register_buffer("key", key)
            self.register_buffer("offset", offset)
            self.register_buffer("value", value)
            self.register_buffer("bv", attention.value.bias.clone())
        self.mlp = copy.deepcopy(actor.head.mlp).eval()
        for p in self.parameters():
            p.requires_grad_(False)

    def _turn(self, f: torch.Tensor, read: torch.Tensor, kinds: torch.Tensor) -> torch.Tensor:
        """(B, 2, 2) quarter turn of each row (module docstring)."""
        targets = kinds[:, 1] * read.to(f.dtype)                                     # (B, T)
        weight = targets / targets.sum(1, keepdim=True).clamp_min(1.0) - kinds[:, 3]
        m = torch.matmul(weight.unsqueeze(1), f[:, :, 0:2]).squeeze(1)              # (B, 2)
        return self.turns[torch.matmul(m, self.pick).argmax(-1)]

    def _embed(self, f: torch.Tensor, kinds: torch.Tensor) -> torch.Tensor:
        """(B, T, D) token embeddings by kind."""
        b, t = f.shape[0], f.shape[1]
        h = torch.matmul(f, self.w1) + self.b1                                      # (B, T, 4 h)
        if self.two_layers:
            h = torch.relu(h).view(b, t, 4, self.first_width) * kinds.unsqueeze(-1)
            return torch.matmul(h.view(b, t, 4 * self.first_width), self.w2) + torch.matmul(kinds, self.b2)
        return (h.view(b, t, 4, self.first_width) * kinds.unsqueeze(-1)).sum(2)

    def rows(self, f: torch.Tensor, read: torch.Tensor) -> torch.Tensor:
        """``f`` (B, T, 4) tokens with unread ones zero, ``read`` (B, T) bool -> (B, 2) [m/s^2]."""
        b, t = f.shape[0], f.shape[1]
        kinds = self.kinds[t, :t]                                                   # (T, 4)
        turn: torch.Tensor | None = None
        if self.turning:
            turn = self._turn(f, read, kinds)
            f = torch.matmul(f.view(b, t, 2, 2), turn.transpose(1, 2).unsqueeze(1)).view(b, t, 4)
        x = self._embed(f, kinds)
        s = x[:, 0]
        q = torch.matmul(s, self.wq) + self.bq                                      # (B, D)
        u = torch.matmul(q, self.key).view(b, self.heads, -1)                       # (B, H, D)
        scores = torch.matmul(x, u.transpose(1, 2)) + torch.matmul(q, self.offset).unsqueeze(1)
        scores = scores.masked_fill(~read.unsqueeze(-1), float("-inf"))            # (B, T, H)
        pooled = torch.matmul(torch.softmax(scores, dim=1).transpose(1, 2), x).reshape(b, -1)
        out = self.mlp(torch.cat((s, torch.matmul(pooled, self.value) + self.bv), -1))
        if self.damping != 0.0:
            out = out - self.damping * f[:, 0, 2:4]
        a = self.accel_limit * torch.tanh(out / self.accel_limit)
        if turn is not None:
            a = torch.matmul(a.unsqueeze(1), turn).squeeze(1)                       # R^T a
        return a


__all__ = ["TURNS", "TypedRows", "kind_table"]
