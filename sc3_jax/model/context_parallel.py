"""Context parallelism: attention over a token sequence split over the mesh's "context" axis.

Long samples (3 views x 28 frames x 300 tokens = 25k tokens at paper scale) make activations, and above all the
[N, M] attention scores, the memory bottleneck. With ``MeshConfig.context = C`` every activation is split along
its token axis into C contiguous blocks (``shard_tokens``); norms, projections and the MLP are per token and need
no communication. Attention is the one place where a query needs every key, written with ``jax.shard_map``:

* ``"context_parallel"`` (all-gather): each device gathers all keys/values (and their mask segments) and attends
  its N/C queries to them in one softmax: scores [N/C, M] per device, one all-gather per layer (its transpose, a
  reduce-scatter, in the backward pass).
* ``"ring"``: keys/values travel around the ring of C devices (``lax.ppermute``); each device folds one [N/C, M/C]
  block of scores at a time into an online (streaming) softmax, each block under ``jax.checkpoint`` so the
  backward pass recomputes scores instead of storing C of them: per-device score memory O(N M / C^2).

Both equal dense attention up to float rounding, forward and gradient (tests/test_context_parallel.py), including
grouped KV heads (query head h uses kv head h // (Hq / Hkv)) and masks. Masks are never materialised as [N, M]
booleans across devices: a :class:`SegmentMask` gives every token a small integer segment and a static table says
which query segment may attend to which key segment; each device builds only its own block. dit.py's causal
context attention is such a table (``CAUSAL_TABLE``).

The mesh is read from ``jax.sharding.get_abstract_mesh()``: trace and run under ``jax.set_mesh(mesh)``
(``sharding.bind_mesh`` does it for a jitted function). Without a mesh, without a "context" axis, or with
context = 1, both implementations fall back to the dense computation of ``layers.attention`` (same numbers), so a
config trained with context parallelism still runs rollouts on any mesh.

Shapes that do not divide by C are padded inside (padded keys get -inf scores, padded queries are dropped); batch
and heads stay sharded over ("data", "fsdp") and "tensor" when they divide, else they are gathered for the call.
"""
from __future__ import annotations

import dataclasses
import functools
import math

import jax
import jax.numpy as jnp
from jax.sharding import PartitionSpec as P

from sc3_jax.model import layers

AXIS = "context"
BATCH_AXES = ("data", "fsdp")
HEAD_AXIS = "tensor"


# ----------------------------------------------------------------------------------------------------------------
# Masks as per-token segments
# ----------------------------------------------------------------------------------------------------------------
@functools.partial(jax.tree_util.register_dataclass, data_fields=["q", "k"], meta_fields=["table"])
@dataclasses.dataclass(frozen=True)
class SegmentMask:
    """mask[b, i, j] = table[q[b, i]][k[b, j]]: query i may attend to key j. ``q`` int [B, N] (queries), ``k`` int
    [B, M] (keys), ``table`` a static tuple of tuples of bools."""
    q: jax.Array
    k: jax.Array
    table: tuple[tuple[bool, ...], ...]

    def allowed(self, q=None, k=None) -> jax.Array:
        """bool [B, Nq, M] for the given (or all) query and key segments."""
        q = self.q if q is None else q
        k = self.k if k is None else k
        table = jnp.asarray(self.table, bool)
        return table[q[:, :, None], k[:, None, :]]

    def dense(self) -> jax.Array:
        """The equivalent dense mask [B, 1, N, M] for ``layers.attention``."""
        return self.allowed()[:, None]


def causal_segments(noisy: jax.Array, n_ctx: int) -> jax.Array:
    """Segment ids [B, N] for dit's causal context attention: 2 * is_context + is_noisy."""
    is_ctx = (jnp.arange(noisy.shape[1]) < n_ctx)[None]
    return 2 * is_ctx.astype(jnp.int32) + noisy.astype(jnp.int32)


def _causal_table() -> tuple[tuple[bool, ...], ...]:
    """Context queries see context keys only; other clean queries see clean keys; noisy queries see everything
    (exactly dit._attention_mask)."""
    rows = []
    for qs in range(4):
        q_ctx, q_noisy = qs >= 2, bool(qs & 1)
        rows.append(tuple(bool((ks >= 2) if q_ctx else (q_noisy or not ks & 1)) for ks in range(4)))
    return tuple(rows)


CAUSAL_TABLE = _causal_table()


# ----------------------------------------------------------------------------------------------------------------
# Mesh helpers
# ----------------------------------------------------------------------------------------------------------------
def context_size(mesh=None) -> int:
    mesh = jax.sharding.get_abstract_mesh() if mesh is None else mesh
    if mesh is None or getattr(mesh, "empty", False) or AXIS not in mesh.shape:
        return 1
    return int(mesh.shape[AXIS])


def _batch_axes(mesh, batch: int):
    names = tuple(a for a in BATCH_AXES if a in mesh.shape and mesh.shape[a] > 1)
    if not names or batch % math.prod(mesh.shape[a] for a in names):
        return None
    return names


def _head_axis(mesh, kv_heads: int):
    if HEAD_AXIS in mesh.shape and mesh.shape[HEAD_AXIS] > 1 and kv_heads % mesh.shape[HEAD_AXIS] == 0:
        return HEAD_AXIS
    return None


def shard_tokens(x: jax.Array) -> jax.Array:
    """Constrain activations [B, N, ...] to be split along the token axis over "context" (and the batch over the
    data axes), so per-token layers run sequence-parallel. A no-op without a context axis or when N does not
    divide."""
    mesh = jax.sharding.get_abstract_mesh()
    C = context_size(mesh)
    if C == 1 or x.shape[1] % C:
        return x
    spec = P(_batch_axes(mesh, x.shape[0]), AXIS, *([None] * (x.ndim - 2)))
    return jax.lax.with_sharding_constraint(x, spec)


# ----------------------------------------------------------------------------------------------------------------
# Attention
# ----------------------------------------------------------------------------------------------------------------
def attention(q, k, v, mask: SegmentMask | None = None, ring: bool = False):
    """Same contract as ``layers.attention`` (q [B, N, Hq, hd], k/v [B, M, Hkv, hd]) with a :class:`SegmentMask`
    (or None), computed with the sequence split over the mesh's "context" axis."""
    mesh = jax.sharding.get_abstract_mesh()
    C = context_size(mesh)
    if C == 1:
        return layers.attention(q, k, v, None if mask is None else mask.dense())
    B, N = q.shape[:2]
    M, Hkv = k.shape[1], k.shape[2]
    n_pad, m_pad = -N % C, -M % C
    if mask is None:  # one segment that sees itself
        mask = SegmentMask(jnp.zeros((B, N), jnp.int32), jnp.zeros((B, M), jnp.int32), ((True,),))
    qs, ks = mask.q, mask.k
    valid = jnp.ones((B, M), bool)
    if n_pad:
        q = jnp.pad(q, ((0, 0), (0, n_pad), (0, 0), (0, 0)))
        qs = jnp.pad(qs, ((0, 0), (0, n_pad)))
    if m_pad:
        k = jnp.pad(k, ((0, 0), (0, m_pad), (0, 0), (0, 0)))
        v = jnp.pad(v, ((0, 0), (0, m_pad), (0, 0), (0, 0)))
        ks = jnp.pad(ks, ((0, 0), (0, m_pad)))
        valid = jnp.pad(valid, ((0, 0), (0, m_pad)))
    b, h = _batch_axes(mesh, B), _head_axis(mesh, Hkv)
    tok, seg = P(b, AXIS, h, None), P(b, AXIS)  # [B, N, H, hd] and per-token [B, N]: split along the sequence
    body = functools.partial(_ring_body if ring else _gather_body, table=mask.table, size=C)
    out = jax.shard_map(body, mesh=mesh, in_specs=(tok, tok, tok, seg, seg, seg), out_specs=tok)(
        q, k, v, qs, ks, valid)
    return out[:, :N]


def _scores(q, k, allowed, valid):
    """q [B, Hkv, G, n, D], k [B, m, Hkv, D] -> fp32 scores [B, Hkv, G, n, m]: masked = finfo.min (as
    layers.attention), padded keys = -inf (never attended, even by fully masked rows)."""
    s = jnp.einsum("bkgnd,bmkd->bkgnm", q, k, preferred_element_type=jnp.float32) / math.sqrt(q.shape[-1])
    s = jnp.where(allowed[:, None, None], s, jnp.finfo(jnp.float32).min)
    return jnp.where(valid[:, None, None, None, :], s, -jnp.inf)


def _split_heads(q, hkv):
    B, n, hq, D = q.shape
    return jnp.moveaxis(q.reshape(B, n, hkv, hq // hkv, D), 1, 3)  # [B, Hkv, G, n, D]


def _merge_heads(o):
    B, hkv, G, n, D = o.shape
    return jnp.moveaxis(o, 3, 1).reshape(B, n, hkv * G, D)


def _gather_body(q, k, v, qs, ks, valid, *, table, size):
    """One device: its query block against every key (all-gathered over the context axis)."""
    k = jax.lax.all_gather(k, AXIS, axis=1, tiled=True)
    v = jax.lax.all_gather(v, AXIS, axis=1, tiled=True)
    ks = jax.lax.all_gather(ks, AXIS, axis=1, tiled=True)
    valid = jax.lax.all_gather(valid, AXIS, axis=1, tiled=True)
    allowed = SegmentMask(qs, ks, table).allowed()
    s = _scores(_split_heads(q, k.shape[2]), k, allowed, valid)
    w = jax.nn.softmax(s, axis=-1).astype(v.dtype)  # fp32 scores and softmax whatever the activation dtype
    o = jnp.einsum("bkgnm,bmkd->bkgnd", w, v)
    return _merge_heads(o)


def _ring_body(q, k, v, qs, ks, valid, *, table, size):
    """One device: stream the C key/value blocks past its queries (block i comes from device (me - i) mod C) and
    fold each into an online softmax: running max m, normaliser z, unnormalised output acc (all fp32)."""
    qg = _split_heads(q, k.shape[2])
    B, hkv, G, n, D = qg.shape
    perm = [(j, (j + 1) % size) for j in range(size)]

    @jax.checkpoint  # keep only the carry per block; the backward pass recomputes the block's scores
    def fold(carry, k, v, ks, valid):
        m, z, acc = carry
        s = _scores(qg, k, SegmentMask(qs, ks, table).allowed(), valid)
        m_new = jax.lax.stop_gradient(jnp.maximum(m, jnp.max(s, axis=-1)))  # any m is exact; no gradient needed
        p = jnp.exp(s - m_new[..., None])
        corr = jnp.exp(m - m_new)
        z = z * corr + jnp.sum(p, axis=-1)
        acc = acc * corr[..., None] + jnp.einsum("bkgnm,bmkd->bkgnd", p, v.astype(jnp.float32))
        return m_new, z, acc

    # m starts at finfo.min, not -inf: a block of padded keys (-inf) then gives exp(-inf) = 0, never nan
    carry = (jnp.full((B, hkv, G, n), jnp.finfo(jnp.float32).min, jnp.float32),
             jnp.zeros((B, hkv, G, n), jnp.float32), jnp.zeros((B, hkv, G, n, D), jnp.float32))
    blocks = (k, v, ks, valid)
    for i in range(size):
        carry = fold(carry, *blocks)
        if i + 1 < size:
            blocks = tuple(jax.lax.ppermute(x, AXIS, perm) for x in blocks)
    _, z, acc = carry
    return _merge_heads((acc / z[..., None]).astype(v.dtype))
