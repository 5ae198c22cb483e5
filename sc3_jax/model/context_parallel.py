"""Context parallelism: attention over a token sequence split over the mesh's "context" axis.

Long samples (3 views x 28 frames x 300 tokens = 25k tokens at paper scale) make activations, and above all the
[N, M] attention scores, the memory bottleneck. With ``MeshConfig.context = C`` every activation is split along
its token axis into C contiguous blocks (``shard_tokens``); norms, projections and the MLP are per token and need
no communication. Attention is the one place where a query needs every key, written with ``jax.shard_map``:

* ``"context_parallel"`` (all-gather): each device gathers all keys/values (and their mask segments) and attends
  its N/C queries to them: one all-gather per layer (its transpose, a reduce-scatter, in the backward pass).
* ``"ring"``: keys/values travel around the ring of C devices (``lax.ppermute``); each device attends its queries
  to one visiting block at a time and merges the C partial results by their log-sum-exp.

Either way each device runs the blockwise (flash) kernel of attention.py on its share, so scores exist one
[block, block] tile at a time and per-device attention memory is O(N / C), not O(N M / C) or O(N M / C^2).

Both equal dense attention up to float rounding, forward and gradient (tests/test_context_parallel.py), including
grouped KV heads (query head h uses kv head h // (Hq / Hkv)) and masks. Masks are never materialised as [N, M]
booleans across devices: an ``attention.SegmentMask`` gives every token a small integer segment and a static table
says which query segment may attend to which key segment; each device builds only its own tiles. dit.py's causal
context attention is such a table (``CAUSAL_TABLE``).

The mesh is read from ``jax.sharding.get_abstract_mesh()``: trace and run under ``jax.set_mesh(mesh)``
(``sharding.bind_mesh`` does it for a jitted function). Without a mesh, without a "context" axis, or with
context = 1, both implementations fall back to the single-device blockwise kernel (same numbers up to rounding),
so a config trained with context parallelism still runs rollouts on any mesh.

Shapes that do not divide by C are padded inside (padded keys form a key segment no query sees, padded queries are
dropped); batch and heads stay sharded over ("data", "fsdp") and "tensor" when they divide, else they are gathered
for the call.
"""
from __future__ import annotations

import functools
import math

import jax
import jax.numpy as jnp
from jax.sharding import PartitionSpec as P

from sc3_jax.model import attention as attention_lib
from sc3_jax.model.attention import SegmentMask

AXIS = "context"
BATCH_AXES = ("data", "fsdp")
HEAD_AXIS = "tensor"


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
def attention(q, k, v, mask: SegmentMask | None = None, ring: bool = False, block: int = 512):
    """Same contract as ``layers.attention`` (q [B, N, Hq, hd], k/v [B, M, Hkv, hd]) with a :class:`SegmentMask`
    (or None), computed with the sequence split over the mesh's "context" axis; each device runs the blockwise
    kernel (``attention.blockwise_lse``, tiles of ``block`` tokens) on its share."""
    if mask is not None and mask.causal:
        raise NotImplementedError("context parallelism takes segment masks, not causal ones")
    mesh = jax.sharding.get_abstract_mesh()
    C = context_size(mesh)
    if C == 1:
        return attention_lib.blockwise(q, k, v, mask, block)
    B, N = q.shape[:2]
    M, Hkv = k.shape[1], k.shape[2]
    n_pad, m_pad = -N % C, -M % C
    if mask is None or mask.q is None:
        mask = attention_lib.full_mask(B, N, M)
    if n_pad:
        q = jnp.pad(q, ((0, 0), (0, n_pad), (0, 0), (0, 0)))
        mask = SegmentMask(jnp.pad(mask.q, ((0, 0), (0, n_pad))), mask.k, mask.table)
    if m_pad:  # padded keys: key segment -1, never attended (attention.SegmentMask)
        k = jnp.pad(k, ((0, 0), (0, m_pad), (0, 0), (0, 0)))
        v = jnp.pad(v, ((0, 0), (0, m_pad), (0, 0), (0, 0)))
        mask = SegmentMask(mask.q, jnp.pad(mask.k, ((0, 0), (0, m_pad)), constant_values=-1), mask.table)
    b, h = _batch_axes(mesh, B), _head_axis(mesh, Hkv)
    tok, seg = P(b, AXIS, h, None), P(b, AXIS)  # [B, N, H, hd] and per-token [B, N]: split along the sequence
    body = functools.partial(_ring_body if ring else _gather_body, table=mask.table, size=C, block=block)
    out = jax.shard_map(body, mesh=mesh, in_specs=(tok, tok, tok, seg, seg), out_specs=tok)(
        q, k, v, mask.q, mask.k)
    return out[:, :N]


def _gather_body(q, k, v, qs, ks, *, table, size, block):
    """One device: its query block against every key (all-gathered over the context axis), blockwise."""
    k = jax.lax.all_gather(k, AXIS, axis=1, tiled=True)
    v = jax.lax.all_gather(v, AXIS, axis=1, tiled=True)
    ks = jax.lax.all_gather(ks, AXIS, axis=1, tiled=True)
    return attention_lib.blockwise(q, k, v, SegmentMask(qs, ks, table), block)


def _ring_body(q, k, v, qs, ks, *, table, size, block):
    """One device: stream the C key/value blocks past its queries (block i comes from device (me - i) mod C),
    attend to each blockwise, and merge the partial results by their log-sum-exp: o = sum_i w_i o_i / sum_i w_i,
    w_i = exp(lse_i - max lse). Kept per device for the backward: C partial outputs [N/C, Hq, hd], O(N)."""
    perm = [(j, (j + 1) % size) for j in range(size)]
    outs, lses, counts = [], [], []
    blocks = (k, v, ks)
    for i in range(size):
        o, lse = attention_lib.blockwise_lse(q, blocks[0], blocks[1], SegmentMask(qs, blocks[2], table), block)
        outs.append(o.astype(jnp.float32))
        lses.append(lse)
        counts.append(jnp.sum(blocks[2] >= 0, axis=1).astype(jnp.float32))  # unpadded keys in this block [B]
        if i + 1 < size:
            blocks = tuple(jax.lax.ppermute(x, AXIS, perm) for x in blocks)
    lse = jnp.stack(lses)  # [C, B, n, Hq]
    top = jax.lax.stop_gradient(jnp.max(lse, axis=0))  # any shift is exact: no gradient needed
    w = jnp.exp(lse - top)
    # a row masked everywhere has lse = finfo.min in every block (log of the count rounds away): weigh its block
    # averages by their key counts instead, so it averages every key as layers.attention does
    masked = top <= attention_lib.MASKED / 2
    w = jnp.where(masked, jnp.stack(counts)[:, :, None, None], w)
    o = jnp.sum(w[..., None] * jnp.stack(outs), axis=0) / jnp.sum(w, axis=0)[..., None]
    return o.astype(v.dtype)
