r"""The typed SDPA actor rewritten for export: the same numbers in as few graph nodes as we could.

At 5 robots a forward pass is a few thousand multiply-adds; what an interpreter (ONNX Runtime,
TorchScript) spends is about 1 us per graph node, so the graph is built for few nodes, not for
few flops. :class:`TypedRows` computes :meth:`controllers.policy.actor.TypedSDPAActor.rows`
(tokens (B, T = 2N+1, 4) with unread ones zero, read mask (B, T) -> accelerations (B, 2)) from
the actor's weights, rearranged once at export so that B and T stay free and the graph has no
per-N slicing, no head reshapes, no gathers of weights and no bias additions inside the
attention:

* **one table** row T (``2 * MAX_ROBOTS + 1`` rows): for each of the T tokens the first layers'
  bias masked to its kind (self, target, other robot, object; below), and whether it is a target
  and the object. One gather by T gives every per-token constant;
* **formation turn**: ``w_t = [t target, read] / #read targets - [t object]``, ``m = w^T f C``
  with C (4, 4) holding 0 and +-1 (``m C = (-m_x, m_y, m_x, -m_y)``, exact); ``k = argmax``. The
  quarter turn is folded into the first layer: ``W_1^(k) = blockdiag(R_k^T, R_k^T) W_1`` (entries
  of R are 0 and +-1, so the fold is exact), four copies gathered by k;
* **embedding** of token t by the layers of its kind, with a constant 1 riding along as an extra
  feature: ``h = relu(f W_1^(k) + B~_T)``, where the table's ``B~`` holds the first-layer bias in
  the token's own kind's block and -inf in the other kinds' blocks (relu(-inf) = 0: the blocks
  of the other kinds are exact zeros; a read infinite feature makes NaN, in a row the contract
  answers with braking anyway), plus 4 columns of weight 0 whose bias is 1 for the
  token's kind (they become the kind one-hot K). Then ``x = h W_2'`` with
  ``W_2' = [W_2 0; B_2 1]``: ``x = [h W_2 + K B_2, 1]`` (T, D + 1), the last column exactly 1.
  A linear embedding keeps the selected block of ``f S W_1 + b_1`` (the table holds the 0/1
  block mask instead, ``W_2`` is stacked identities);
* **attention with one query** ``s = x_0`` per row and head j (width d = D / H)::

      score_tj = q_j . (W_k^j x_t + b_k^j) / sqrt(d),     q = W_q s + b_q
      out_j    = W_v^j (sum_t softmax_t(score_tj) x_t) + b_v^j

  With the constant 1 in x, ``q``, the key projection and its bias fold into one matrix
  ``U = [W_q^T; b_q] K_b`` (D + 1, (D + 1) H): ``u = s U`` is already the (D + 1, H) matrix of
  the scores ``x u`` (the key bias is the 1's row). The T keys and values are never formed;
* **the head's MLP**: its first layer takes ``[s, out]``; ``out`` is linear in the pooled
  tokens, so ``W_v`` and ``b_v`` fold into it: ``z = [s, pooled_1 .. pooled_H] M`` with
  ``M = [W_s; b_1 + b_v W_p; W_v^1^T W_p^1; 0; ...]`` (the pooled 1s, which sum the softmax,
  get a zero row). Then the rest of the MLP as trained, ``a = L tanh((u - c v) / L)``, ``R_k^T a``.
* **token mixing blocks** (``ActorConfig.token_layers``), if any, run as trained on the D
  embedded columns between the embedding and the pooling; the constant 1 rides past them.

Products of weights folded here are formed in float64 and rounded once. The order of float32
sums differs from the training forward (about 1e-8 on the actions at the verify states);
:func:`deploy.export.export_policy` compares every file with the actor's own ``rows`` and
refuses one further off than ``TOLERANCE``. The default actor's ONNX graph has 54 nodes with the
contract around it (the actor's own graph: 133; this module's first form: 85).
"""

from __future__ import annotations

import copy
import math

import torch
import torch.nn.functional as F
from torch import nn

from controllers.policy.layers import first_turn
from sim.observations import token_types
from sim.scenario import MAX_ROBOTS

TURNS = ((1.0, 0.0, 0.0, 1.0), (0.0, -1.0, 1.0, 0.0), (-1.0, 0.0, 0.0, -1.0), (0.0, 1.0, -1.0, 0.0))
"""R_k = [[cos, -sin], [sin, cos]] of k quarter turns counter-clockwise, row-major."""

F64 = torch.float64


def kind_table(max_tokens: int) -> torch.Tensor:
    """(max_tokens + 1, max_tokens, 4): row T holds the one-hot kinds (:func:`token_types`: self,
    targets, other robots, object) of the T = 2N + 1 tokens of a robot of N; other rows are zero."""
    table = torch.zeros(max_tokens + 1, max_tokens, 4)
    for t in range(3, max_tokens + 1, 2):
        table[t, :t] = F.one_hot(token_types((t - 1) // 2), 4).float()
    return table


def _layers(embed: nn.Module) -> list[nn.Linear]:
    return [embed] if isinstance(embed, nn.Linear) else [embed[0], embed[2]]


def _turns() -> tuple[torch.Tensor, torch.Tensor]:
    """``(R (4, 2, 2), blockdiag(R^T, R^T) (4, 4, 4))`` of the quarter turns, float64."""
    turns = torch.tensor(TURNS, dtype=F64).view(4, 2, 2)
    return turns, torch.stack([torch.block_diag(r.t(), r.t()) for r in turns])


def _embedding(actor: nn.Module, width: int, dim: int) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """``(W_1 (4, 4 w + 4), b_1 (4 w + 4,), W_2' (4 w + 4, D + 1))`` float64 (module docstring)."""
    e = actor.embedding
    embeds = [_layers(m) for m in (e.embed_self, e.embed_target, e.embed_robot, e.embed_object)]
    w1 = torch.cat([m[0].weight.t().to(F64) * actor.input_scale for m in embeds] + [torch.zeros(4, 4, dtype=F64)], 1)
    b1 = torch.cat([m[0].bias.to(F64) for m in embeds] + [torch.ones(4, dtype=F64)])
    w2 = torch.zeros(4 * width + 4, dim + 1, dtype=F64)
    if len(embeds[0]) == 2:
        w2[:4 * width, :dim] = torch.cat([m[1].weight.t().to(F64) for m in embeds], 0)
        w2[4 * width:, :dim] = torch.stack([m[1].bias.to(F64) for m in embeds])
    else:
        w2[:4 * width, :dim] = torch.eye(dim, dtype=F64).repeat(4, 1)
    w2[4 * width:, dim] = 1.0
    return w1, b1, w2


def _attention(attention: nn.Module) -> torch.Tensor:
    """``U`` (D + 1, (D + 1) H) float64: ``(s U)[c H + j]`` is the weight of feature c of a token
    in the score of head j (feature D, the 1, carries the key bias)."""
    heads, d = attention.num_heads, attention.head_dim
    dim = heads * d
    wk, bk = attention.key.weight.to(F64), attention.key.bias.to(F64)
    key = torch.zeros(dim, dim + 1, heads, dtype=F64)
    for j in range(heads):
        rows = slice(j * d, (j + 1) * d)
        key[rows, :dim, j] = wk[rows] / math.sqrt(d)
        key[rows, dim, j] = bk[rows] / math.sqrt(d)
    wq = torch.cat([attention.query.weight.t().to(F64), attention.query.bias.to(F64)[None]], 0)
    return wq @ key.reshape(dim, (dim + 1) * heads)


def _head_input(attention: nn.Module, first: nn.Linear) -> torch.Tensor:
    """``M`` ((H + 1)(D + 1), hidden) float64: the MLP's first layer on ``[s, pooled_1..H]``
    with the value projection and both biases folded in."""
    heads, d = attention.num_heads, attention.head_dim
    dim = heads * d
    wv, bv = attention.value.weight.to(F64), attention.value.bias.to(F64)
    ws, wp = first.weight.to(F64)[:, :dim].t(), first.weight.to(F64)[:, dim:].t()
    m = torch.zeros((heads + 1) * (dim + 1), first.out_features, dtype=F64)
    m[:dim] = ws
    m[dim] = first.bias.to(F64) + bv @ wp
    for j in range(heads):
        rows, base = slice(j * d, (j + 1) * d), (j + 1) * (dim + 1)
        m[base:base + dim] = wv[rows].t() @ wp[rows]
    return m


class TypedRows(nn.Module):
    """``rows(f, read) -> (B, 2)`` of a typed actor (module docstring); frozen weights."""

    def __init__(self, actor: nn.Module):
        super().__init__()
        attention, mlp = actor.head.attention, actor.head.mlp
        width = _layers(actor.embedding.embed_self)[0].out_features
        dim = attention.num_heads * attention.head_dim
        self.accel_limit = float(actor.accel_limit)
        self.damping = float(actor.velocity_damping)
        self.turning = bool(actor.turning)
        self.two_layers = not isinstance(actor.embedding.embed_self, nn.Linear)
        self.heads, self.dim, self.wide = attention.num_heads, dim, 4 * width + 4
        with torch.no_grad():
            kinds = kind_table(2 * MAX_ROBOTS + 1)
            w1, b1, w2 = _embedding(actor, width, dim)
            blocks_of = torch.cat([kinds.repeat_interleave(width, -1), kinds], -1)       # 1: the token's kind
            if self.two_layers:      # relu(f W_1 + b_1 - inf) = 0 outside the token's own blocks
                blocks_of = torch.where(blocks_of > 0, b1.float(), torch.tensor(float("-inf")))
            table = torch.cat([blocks_of, kinds[..., 1:2], kinds[..., 3:4]], -1)
            turns, blocks = _turns()
            pick = torch.zeros(4, 4)
            pick[0, 0], pick[1, 1], pick[0, 2], pick[1, 3] = -1.0, 1.0, 1.0, -1.0
            self.register_buffer("table", table)                                          # (T+1, T, 4w+6)
            self.register_buffer("pick", pick)
            self.register_buffer("turns", turns.float())                                  # (4, 2, 2)
            self.register_buffer("blocks", blocks.float())                                # (4, 4, 4)
            self.register_buffer("w1", (blocks @ w1 if self.turning else w1[None]).float())   # (4 or 1, 4, 4w+4)
            self.register_buffer("b1", b1.float())
            self.register_buffer("w2", w2.float())
            self.register_buffer("scores", _attention(attention).float())
            self.register_buffer("head_in", _head_input(attention, mlp[0]).float())
            self.register_buffer("minus_inf", torch.tensor(float("-inf")))
        self.mlp = copy.deepcopy(mlp[2:]).eval()
        self.mixers = copy.deepcopy(actor.mixers).eval()
        for p in self.parameters():
            p.requires_grad_(False)

    def _turn(self, f: torch.Tensor, read: torch.Tensor, table: torch.Tensor) -> torch.Tensor:
        """(B,) index k of each row's quarter turn (module docstring)."""
        targets = torch.where(read.unsqueeze(-1), table[:, -2:-1], torch.zeros((), dtype=f.dtype))  # (B, T, 1)
        weight = targets / targets.sum(1, keepdim=True).clamp_min(1.0) - table[:, -1:]
        return first_turn((weight * torch.matmul(f, self.pick)).sum(1))

    def rows(self, f: torch.Tensor, read: torch.Tensor) -> torch.Tensor:
        """``f`` (B, T, 4) tokens with unread ones zero, ``read`` (B, T) bool -> (B, 2) [m/s^2]."""
        t = f.shape[1]
        table = self.table[t, :t]                                                     # (T, 4w+6)
        k = torch.zeros(1, dtype=torch.long)
        w1 = self.w1[0]
        if self.turning:
            k = self._turn(f, read, table)                                            # (B,)
            w1 = torch.index_select(self.w1, 0, k)                                    # (B, 4, 4w+4)
        if self.two_layers:
            h = torch.relu(torch.matmul(f, w1) + table[:, :self.wide])                 # (B, T, 4w+4)
        else:
            h = (torch.matmul(f, w1) + self.b1) * table[:, :self.wide]
        x = torch.matmul(h, self.w2)                                                  # (B, T, D+1)
        if len(self.mixers):
            y = x[..., :self.dim]
            for mixer in self.mixers:
                y = mixer(y, read)
            x = torch.cat((y, x[..., self.dim:]), -1)
        s = x[:, 0]
        u = torch.matmul(s, self.scores).view(-1, self.dim + 1, self.heads)
        scores = torch.where(read.unsqueeze(-1), torch.matmul(x, u), self.minus_inf).transpose(1, 2)
        pooled = torch.matmul(torch.softmax(scores, -1), x).reshape(-1, self.heads * (self.dim + 1))
        out = self.mlp(torch.relu(torch.matmul(torch.cat((s, pooled), -1), self.head_in)))
        if self.damping != 0.0:          # the robot's own velocity, in the turned frame
            velocity = torch.matmul(f[:, 0].unsqueeze(1), torch.index_select(self.blocks, 0, k)).squeeze(1)
            out = out - self.damping * velocity[:, 2:4] if self.turning else out - self.damping * f[:, 0, 2:4]
        a = torch.tanh(out) if self.accel_limit == 1.0 else self.accel_limit * torch.tanh(out / self.accel_limit)
        if self.turning:
            a = torch.matmul(a.unsqueeze(1), torch.index_select(self.turns, 0, k)).squeeze(1)   # R^T a
        return a


__all__ = ["TURNS", "TypedRows", "kind_table"]
