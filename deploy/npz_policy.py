r"""The ``npz`` policy format: a typed actor's weights as numpy arrays, run by one compiled kernel.

    runner, meta = open_npz("policy.npz")        # digest and format checked, kernel warmed up
    accel, valid = runner(tokens, mask)          # the contract of deploy.export.contract

Needs numpy and numba only (no torch, no onnxruntime). ONNX Runtime spends about 1 us per graph
node and ~30 us per call whatever the graph computes, so at five robots the policy stage was
0.09-0.13 ms for a few hundred thousand multiply-adds; here the forward is one numba kernel whose
large products go to BLAS (``np.dot``): a policy stage of 0.04-0.07 ms in the 5-robot tick
(``bench/safety.py --only latency``).

The arrays are :class:`deploy.export.graph.TypedRows` in the layout this kernel reads
(:func:`deploy.export.formats.typed_rows_arrays` builds them; ``w`` the embedding's hidden width, ``D`` the embedding
width, ``H`` heads; kinds c: 0 self, 1 target, 2 other robot, 3 object)::

    embed_w1   (4, 4, w)        first layer of kind c on the token's 4 features (input scale in)
    embed_b1   (4, w)           its bias
    embed_w2   (4, w, D + 1)    second layer (a linear embedding: identities), last column 0
    embed_b2   (4, D + 1)       its bias, last entry 1 (the constant feature)
    scores     (D + 1, (D + 1) H)   U of TypedRows: ``u = x_0 U``, scores ``x_t u`` per head
    head_in    ((H + 1)(D + 1), h)  M of TypedRows on ``[x_0, pooled_1 .. pooled_H]``
    mlp_w{i}, mlp_b{i}          the rest of the head (in, out), ReLU between, none after the last
    heads, turning, two_layers, damping    0-d arrays: the forward's switches

For row b (robot i of N, ``T = 2N + 1`` tokens ``f``, unread ones zeroed; ``read_0`` always)::

    k        = argmax_q sum_t w_t m(f_t)_q,  m(f) = (-f_x, f_y, f_x, -f_y),
               w_t = [t target, read] / #read targets - [t object]
    f'_t     = f_t blockdiag(R_k^T, R_k^T)                   (the formation's quarter turn: exact)
    x_t      = act(f'_t W1_c + b1_c) W2_c + b2_c             (c: the kind of token t)
    p_j      = softmax_t over read t of (x_t u)_j,  u = x_0 U reshaped (D + 1, H)
    z        = MLP(relu([x_0, sum_t p_1t x_t, .., sum_t p_Ht x_t] M))
    a        = R_k^T (L tanh((z - k_v v') / L)),  v' = f'_0[2:4]
    accel    = a / max(1, |a| / L) if sum f + |a| is finite else 0;  valid = finiteness

Integrity: ``content_sha256`` (in the ``formation.meta`` member, a JSON string) is sha256 over the
canonical metadata and, in name order, each array's name, dtype, shape and bytes (:func:`npz_digest`).
"""

from __future__ import annotations

import hashlib
import io
import json
from pathlib import Path
from typing import Any

import numba
import numpy as np

META_MEMBER = "formation.meta"
HASH_FIELD = "content_sha256"
TURN_TIE = 1e-5   # [m] controllers.policy.layers.TURN_TIE (this file runs without the project)
EXPORT_FORMAT = "formation-stack/policy"
EXPORT_FORMAT_VERSION = 2
SELF, TARGET, ROBOT, OBJECT = 0, 1, 2, 3
SWITCHES = ("heads", "turning", "two_layers", "damping")
TURNS = np.array([[[1.0, 0.0], [0.0, 1.0]], [[0.0, -1.0], [1.0, 0.0]],
                  [[-1.0, 0.0], [0.0, -1.0]], [[0.0, 1.0], [-1.0, 0.0]]], dtype=np.float32)
"""R_k (row-major) of k quarter turns counter-clockwise, as :data:`deploy.export.graph.TURNS`."""


class NpzPolicyError(RuntimeError):
    """An ``npz`` policy file that cannot be trusted or run; the message says why and what to do."""


@numba.njit(cache=True, nogil=True)
def _kind(t: int, n: int) -> int:
    if t == 0:
        return SELF
    if t <= n:
        return TARGET
    return ROBOT if t < 2 * n else OBJECT


@numba.njit(cache=True, nogil=True)
def _quarter_turn(f: np.ndarray, read: np.ndarray, n: int) -> int:
    """k of TypedRows._turn for one row: f (T, 4) with unread tokens zero, read (T,)."""
    count = np.float32(0.0)
    for t in range(1, n + 1):
        if read[t]:
            count += np.float32(1.0)
    count = max(count, np.float32(1.0))
    m = np.zeros(4, np.float32)
    for t in range(2 * n + 1):
        kind = _kind(t, n)
        w = (np.float32(1.0) if kind == TARGET and read[t] else np.float32(0.0)) / count
        if kind == OBJECT:
            w -= np.float32(1.0)
        m[0] += w * -f[t, 0]
        m[1] += w * f[t, 1]
        m[2] += w * f[t, 0]
        m[3] += w * -f[t, 1]
    top = max(m[0], m[1], m[2], m[3])
    for q in range(4):                  # the first within TURN_TIE of the largest (TypedRows._turn)
        if m[q] >= top - np.float32(TURN_TIE):
            return q
    return 0


@numba.njit(cache=True, nogil=True)
def _embed(tokens, mask, w1, b1, w2, b2, turning, two_layers, x, turned, totals, turns):
    """Fill x (B, T, D+1), the turned self tokens (B, 4), the feature sums (B,) and turns (B,)."""
    rows, t_count = tokens.shape[0], tokens.shape[1]
    n = (t_count - 1) // 2
    width = w1.shape[2]
    f = np.zeros((t_count, 4), np.float32)
    read = np.zeros(t_count, np.bool_)
    counts = np.array([1, n, n - 1, 1])
    starts = np.array([0, rows, rows * (n + 1), rows * 2 * n])
    feats = np.empty((rows * t_count, 4), np.float32)
    for b in range(rows):
        total = np.float32(0.0)
        for t in range(t_count):
            read[t] = t == 0 or mask[b, t]
            for q in range(4):
                f[t, q] = tokens[b, t, q] if read[t] else np.float32(0.0)
                total += f[t, q]
        totals[b] = total
        k = _quarter_turn(f, read, n) if turning else 0
        turns[b] = k
        r00, r01, r10, r11 = TURNS[k, 0, 0], TURNS[k, 0, 1], TURNS[k, 1, 0], TURNS[k, 1, 1]
        for t in range(t_count):
            kind = _kind(t, n)
            row = starts[kind] + b * counts[kind] + (t - 1 if kind == TARGET else t - n - 1 if kind == ROBOT else 0)
            for half in range(2):      # (x, y) R_k^T per pair: exact (entries 0 and +-1)
                fx, fy = f[t, 2 * half], f[t, 2 * half + 1]
                feats[row, 2 * half] = fx * r00 + fy * r01
                feats[row, 2 * half + 1] = fx * r10 + fy * r11
            if t == 0:
                turned[b] = feats[row]
    for kind in range(4):
        lo, hi = starts[kind], starts[kind] + rows * counts[kind]
        if hi == lo:
            continue
        h = np.dot(feats[lo:hi], w1[kind])
        for r in range(hi - lo):
            for j in range(width):
                v = h[r, j] + b1[kind, j]
                h[r, j] = v if (v > 0 or not two_layers) else np.float32(0.0)
        out = np.dot(h, w2[kind])
        for r in range(hi - lo):
            b, slot = r // counts[kind], r % counts[kind]
            t = 0 if kind == SELF else 1 + slot if kind == TARGET else n + 1 + slot if kind == ROBOT else 2 * n
            for j in range(out.shape[1]):
                x[b, t, j] = out[r, j] + b2[kind, j]


@numba.njit(cache=True, nogil=True)
def _pool(x, mask, scores, heads, pooled):
    """pooled (B, (H+1)(D+1)) = [x_0, softmax-pooled tokens of each head] (module docstring)."""
    rows, t_count, width = x.shape
    s = np.ascontiguousarray(x[:, 0, :])
    u = np.dot(s, scores)
    for b in range(rows):
        xb = x[b]
        logits = np.dot(xb, u[b].reshape(width, heads))                 # (T, H)
        for j in range(heads):
            top = -np.inf
            for t in range(t_count):
                if t == 0 or mask[b, t]:
                    top = max(top, logits[t, j])
                else:
                    logits[t, j] = -np.inf
            total = np.float32(0.0)
            for t in range(t_count):
                logits[t, j] = np.exp(logits[t, j] - top)
                total += logits[t, j]
            for t in range(t_count):
                logits[t, j] /= total
        weighted = np.dot(np.ascontiguousarray(logits.T), xb)            # (H, D+1)
        pooled[b, :width] = xb[0]
        for j in range(heads):
            pooled[b, (j + 1) * width:(j + 2) * width] = weighted[j]


@numba.njit(cache=True, nogil=True)
def typed_rows_forward(tokens, mask, w1, b1, w2, b2, scores, head_in, mlp_w, mlp_b, heads,
                       turning, two_layers, damping, limit, accel, valid):
    """The contract around TypedRows (module docstring): tokens (B, T, 4) float32, mask (B, T)
    bool -> accel (B, 2) float32 and valid (B,) bool, written in place."""
    rows, t_count = tokens.shape[0], tokens.shape[1]
    width = w2.shape[2]
    x = np.empty((rows, t_count, width), np.float32)
    turned = np.empty((rows, 4), np.float32)
    totals = np.empty(rows, np.float32)
    turns = np.empty(rows, np.int64)
    _embed(tokens, mask, w1, b1, w2, b2, turning, two_layers, x, turned, totals, turns)
    pooled = np.empty((rows, (heads + 1) * width), np.float32)
    _pool(x, mask, scores, heads, pooled)
    z = np.dot(pooled, head_in)
    for b in range(rows):
        for j in range(z.shape[1]):
            z[b, j] = max(z[b, j], np.float32(0.0))
    for layer in range(len(mlp_w)):
        z = np.dot(z, mlp_w[layer])
        last = layer == len(mlp_w) - 1
        for b in range(rows):
            for j in range(z.shape[1]):
                v = z[b, j] + mlp_b[layer][j]
                z[b, j] = v if (last or v > 0) else np.float32(0.0)
    for b in range(rows):
        o0, o1 = z[b, 0] - damping * turned[b, 2], z[b, 1] - damping * turned[b, 3]
        a0, a1 = limit * np.tanh(o0 / limit), limit * np.tanh(o1 / limit)
        k = turns[b]
        a0, a1 = a0 * TURNS[k, 0, 0] + a1 * TURNS[k, 1, 0], a0 * TURNS[k, 0, 1] + a1 * TURNS[k, 1, 1]
        norm = np.sqrt(a0 * a0 + a1 * a1)
        check = totals[b] + norm
        ok = (check - check) == 0
        scale = max(norm / limit, np.float32(1.0))
        accel[b, 0] = a0 / scale if ok else np.float32(0.0)
        accel[b, 1] = a1 / scale if ok else np.float32(0.0)
        valid[b] = ok


def canonical_meta(meta: dict[str, Any]) -> bytes:
    """The metadata as the digest sees it: sorted keys, no whitespace, the digest left out."""
    return json.dumps({k: v for k, v in meta.items() if k != HASH_FIELD}, sort_keys=True,
                      separators=(",", ":")).encode()


def npz_digest(meta: dict[str, Any], arrays: dict[str, np.ndarray]) -> str:
    """``content_sha256`` of an npz policy: the canonical metadata, then each array (name order)
    as ``|name|dtype|shape|`` and its C-order bytes."""
    digest = hashlib.sha256(canonical_meta(meta))
    for name in sorted(arrays):
        array = np.ascontiguousarray(arrays[name])
        digest.update(f"|{name}|{array.dtype.str}|{array.shape}|".encode())
        digest.update(array.tobytes())
    return digest.hexdigest()


def npz_bytes(arrays: dict[str, np.ndarray], meta: dict[str, Any]) -> bytes:
    """The file: ``arrays`` and the metadata (its digest filled in) as one uncompressed .npz."""
    meta = meta | {HASH_FIELD: npz_digest(meta, arrays)}
    buffer = io.BytesIO()
    np.savez(buffer, **arrays, **{META_MEMBER: np.array(json.dumps(meta, sort_keys=True))})
    return buffer.getvalue()


class NpzRunner:
    """``(tokens (B, T, 4) float32, mask (B, T) bool) -> (accel (B, 2) float32, valid (B,) bool)``
    of an npz policy's arrays (module docstring); other dtypes are cast, shapes checked."""

    def __init__(self, arrays: dict[str, np.ndarray], accel_limit: float):
        f32 = {k: np.ascontiguousarray(v, dtype=np.float32) for k, v in arrays.items() if k not in SWITCHES}
        layers = sum(1 for k in f32 if k.startswith("mlp_w"))
        self.weights = (f32["embed_w1"], f32["embed_b1"], f32["embed_w2"], f32["embed_b2"], f32["scores"],
                        f32["head_in"], tuple(f32[f"mlp_w{i}"] for i in range(layers)),
                        tuple(f32[f"mlp_b{i}"] for i in range(layers)))
        heads, turning, two_layers, damping = (np.asarray(arrays[k]).item() for k in SWITCHES)
        self.switches = (int(heads), bool(turning), bool(two_layers), np.float32(damping), np.float32(accel_limit))
        self(np.zeros((2, 11, 4), np.float32), np.ones((2, 11), dtype=bool))    # compile or load now

    def __call__(self, tokens: np.ndarray, mask: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        tokens = np.ascontiguousarray(tokens, dtype=np.float32)
        mask = np.ascontiguousarray(mask, dtype=np.bool_)
        shape = tokens.shape
        if len(shape) != 3 or shape[2] != 4 or shape[1] % 2 == 0 or shape[1] < 3:
            raise NpzPolicyError(f"tokens must have shape (B, T = 2N + 1, 4) with N >= 1, got {shape}")
        if mask.shape != shape[:2]:
            raise NpzPolicyError(f"mask must have shape {shape[:2]} (the tokens' B, T), got {mask.shape}")
        accel, valid = np.empty((shape[0], 2), np.float32), np.empty(shape[0], np.bool_)
        typed_rows_forward(tokens, mask, *self.weights, *self.switches, accel, valid)
        return accel, valid


def open_npz(path: str | Path) -> tuple[NpzRunner, dict[str, Any]]:
    """``(runner, meta)`` of an npz policy file, its format and digest checked (not its layout:
    the caller's code knows which it builds); raises NpzPolicyError naming what is wrong."""
    path = Path(path)
    if not path.is_file():
        raise NpzPolicyError(f"policy file {str(path)!r} does not exist")
    try:
        with np.load(path, allow_pickle=False) as data:
            arrays = {name: data[name] for name in data.files}
        meta = json.loads(str(arrays.pop(META_MEMBER)))
    except Exception as err:
        raise NpzPolicyError(f"{str(path)!r} is not an npz policy ({type(err).__name__}: {err}); "
                             "export one with `formation export CKPT --format npz`") from None
    if not isinstance(meta, dict) or (meta.get("format"), meta.get("format_version")) != (
            EXPORT_FORMAT, EXPORT_FORMAT_VERSION):
        raise NpzPolicyError(f"{str(path)!r} is not a {EXPORT_FORMAT} v{EXPORT_FORMAT_VERSION} file; "
                             "export it again with `formation export`")
    if npz_digest(meta, arrays) != meta.get(HASH_FIELD):
        raise NpzPolicyError(f"{str(path)!r}: its weights or metadata do not match its {HASH_FIELD}: "
                             "the file was changed after export; export it again")
    try:
        return NpzRunner(arrays, float(meta["accel_limit"])), meta
    except (KeyError, ValueError, TypeError) as err:
        raise NpzPolicyError(f"{str(path)!r} lacks or mangles the array {err} the runtime needs; "
                             "export it again") from None


__all__ = ["META_MEMBER", "NpzPolicyError", "NpzRunner", "npz_bytes", "npz_digest", "open_npz",
           "typed_rows_forward"]
