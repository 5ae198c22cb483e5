"""Memory-efficient attention: one mask description, a blockwise (flash) kernel in plain JAX, and the fused cuDNN
kernel where the mask allows it.

Why: the dense form (``layers.attention``) materialises fp32 scores [B, Hq, N, M] per layer -- 41 GB per
25k-token sample at paper scale. Here scores only ever exist one [block_q, block_k] tile at a time.

* **Mask description** (:class:`SegmentMask`): every query and key token carries a small integer segment id and a
  static boolean table says which query segment may attend to which key segment (``table[q_seg][k_seg]``), plus an
  optional static causal flag (key j visible to query i iff j <= i + M - N). Every mask dit.py uses is one of
  these: full (no mask), causal context attention (``CAUSAL_TABLE``: context -> context, clean -> clean,
  noisy -> all), the text prefix (one more key segment every query sees, ``with_prefix``), the text pathway's own
  causal attention (``causal_mask``) and padding (key segment -1: never attended). The same
  description maps onto TPU Pallas splash attention: per (q block, k block) the tile is empty, full or partial
  from the segment ids' and indices' ranges, which is what splash's block-sparse ``MaskInfo`` holds; the causal
  flag is its ``CausalMask``; the segment table is a small ``MultiHeadMask``-style lookup evaluated per tile.
* **Blockwise** (:func:`blockwise`): ``lax.map`` over query blocks, ``lax.scan`` over key blocks with an online
  softmax (running max, normaliser, fp32 accumulator), under a ``jax.custom_vjp`` whose backward pass is the
  flash-attention backward (recompute each tile's probabilities from the saved softmax statistics; dq carried
  over key blocks, dk/dv accumulated over query blocks). Saved for the backward: q, k, v, the output and each
  row's running max and normaliser, so memory is O(N) per layer, not O(N M); plain autodiff through the scans
  saves every tile's probabilities, O(N M) again (``python bench/attention_memory.py --kernel`` measures both). Runs on any backend (the CPU tests use it). Returns the log-sum-exp too
  (differentiable), which is how ring attention merges the per-device partial results.
* **Fused** (:func:`fused_ok`, ``jax.nn.dot_product_attention(implementation="cudnn")``): selected only on GPU, for
  bf16/fp16, head_dim a multiple of 8 and <= 128, and a mask that is full or purely causal (cuDNN cannot read a
  per-token segment table without a dense [N, M] bias); anything else falls back to the blockwise kernel.

Fully masked rows (never produced by dit.py) behave as in ``layers.attention``: masked scores are ``finfo.min``,
so such a row averages every (unpadded) key.
"""
from __future__ import annotations

import dataclasses
import functools
import math

import jax
import jax.numpy as jnp
import numpy as np


MASKED = float(jnp.finfo(jnp.float32).min)  # the score of a masked (query, key) pair, as layers.attention
_MIN = MASKED


# ----------------------------------------------------------------------------------------------------------------
# Mask description
# ----------------------------------------------------------------------------------------------------------------
@functools.partial(jax.tree_util.register_dataclass, data_fields=["q", "k"], meta_fields=["table", "causal"])
@dataclasses.dataclass(frozen=True)
class SegmentMask:
    """mask[b, i, j] = table[q[b, i]][k[b, j]] (and j <= i + M - N if ``causal``). ``q`` int [B, N], ``k`` int
    [B, M] (a key segment < 0 marks padding: never attended, even by a fully masked row) or both None (no segment
    table: only the causal flag, if any); ``table`` a static tuple of tuples of bools."""
    q: jax.Array | None
    k: jax.Array | None
    table: tuple[tuple[bool, ...], ...] | None
    causal: bool = False

    def allowed(self, q=None, k=None) -> jax.Array:
        """bool [B, Nq, M] for the given (or all) query and key segments (segment table only)."""
        q = self.q if q is None else q
        k = self.k if k is None else k
        return jnp.asarray(self.table, bool)[q[:, :, None], k[:, None, :]]

    def dense(self, n: int | None = None, m: int | None = None) -> jax.Array:
        """The equivalent dense mask [B or 1, 1, N, M] for ``layers.attention`` (n, m needed without segments)."""
        out = None if self.q is None else self.allowed()[:, None]
        if self.causal:
            n = self.q.shape[1] if n is None else n
            m = self.k.shape[1] if m is None else m
            c = (jnp.arange(m)[None, :] <= jnp.arange(n)[:, None] + (m - n))[None, None]
            out = c if out is None else out & c
        return out

    @property
    def is_full(self) -> bool:
        """True when nothing is masked (every table entry True, not causal)."""
        return not self.causal and (self.table is None or all(all(r) for r in self.table))


def causal_mask() -> SegmentMask:
    """Plain causal attention (the text pathway among its own tokens)."""
    return SegmentMask(None, None, None, causal=True)


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


def with_prefix(mask: SegmentMask, n: int) -> SegmentMask:
    """Every query also sees ``n`` prefix keys (the text) in front of the keys: one more key segment, visible to
    every query segment."""
    if n == 0:
        return mask
    if mask.causal or mask.q is None:
        raise ValueError("a prefix needs a segment mask (not a causal one)")
    extra = jnp.full((mask.k.shape[0], n), len(mask.table[0]), mask.k.dtype)
    return SegmentMask(mask.q, jnp.concatenate([extra, mask.k], axis=1), tuple(r + (True,) for r in mask.table))


def full_mask(B: int, N: int, M: int) -> SegmentMask:
    """One segment that sees itself (a segment-table form of "no mask")."""
    return SegmentMask(jnp.zeros((B, N), jnp.int32), jnp.zeros((B, M), jnp.int32), ((True,),))


def fused_ok(q, k, mask: SegmentMask | None, backend: str | None = None) -> bool:
    """Whether the cuDNN fused kernel can compute this call: GPU backend, half-precision inputs, head_dim a
    multiple of 8 up to 128, and a mask that is full or plain causal with as many queries as keys."""
    backend = jax.default_backend() if backend is None else backend
    if backend not in ("gpu", "cuda") or q.dtype not in (jnp.bfloat16, jnp.float16) or k.dtype != q.dtype:
        return False
    D = q.shape[-1]
    if D % 8 or D > 128:
        return False
    if mask is None or mask.is_full:
        return True
    return mask.causal and mask.q is None and q.shape[1] == k.shape[1]


def fused(q, k, v, mask: SegmentMask | None = None):
    """cuDNN flash attention (GPU only; check :func:`fused_ok` first)."""
    causal = mask is not None and mask.causal
    return jax.nn.dot_product_attention(q, k, v, is_causal=causal, implementation="cudnn")


# ----------------------------------------------------------------------------------------------------------------
# Blockwise (flash) attention
# ----------------------------------------------------------------------------------------------------------------
def blockwise(q, k, v, mask: SegmentMask | None = None, block: int = 512):
    """Same contract and numbers (up to float rounding) as ``layers.attention`` with ``mask.dense()``; scores
    exist one [block, block] tile at a time, forward and backward."""
    return blockwise_lse(q, k, v, mask, block)[0]


def blockwise_lse(q, k, v, mask: SegmentMask | None = None, block: int = 512):
    """(output [B, N, Hq, hd], log-sum-exp of each row's scores [B, N, Hq] fp32), both differentiable. A row
    whose keys are all padding has output 0 and log-sum-exp -inf."""
    B, N, Hq, D = q.shape
    M, Hkv = k.shape[1], k.shape[2]
    if Hq % Hkv:
        raise ValueError(f"query heads {Hq} must be a multiple of key/value heads {Hkv}")
    if mask is not None and mask.is_full:
        mask = None
    G = Hq // Hkv
    bq, bk = min(block, N), min(block, M)
    n_pad, m_pad = -N % bq, -M % bk
    qg = jnp.moveaxis(q.reshape(B, N, Hkv, G, D), 1, 3)  # [B, Hkv, G, N, D]: one kv head's query group together
    kk, vv = jnp.moveaxis(k, 1, 2), jnp.moveaxis(v, 1, 2)  # [B, Hkv, M, D]
    qg = jnp.pad(qg, ((0, 0), (0, 0), (0, 0), (0, n_pad), (0, 0)))
    kk = jnp.pad(kk, ((0, 0), (0, 0), (0, m_pad), (0, 0)))
    vv = jnp.pad(vv, ((0, 0), (0, 0), (0, m_pad), (0, 0)))
    segs, table, causal = None, None, False
    if mask is not None:
        causal = mask.causal
        if mask.q is not None:
            if mask.q.shape != (B, N) or mask.k.shape != (B, M):
                raise ValueError(f"mask segments {mask.q.shape} / {mask.k.shape} do not match queries {(B, N)} "
                                 f"and keys {(B, M)}")
            segs = (jnp.pad(mask.q.astype(jnp.int32), ((0, 0), (0, n_pad))),
                    jnp.pad(mask.k.astype(jnp.int32), ((0, 0), (0, m_pad))))
            table = mask.table
    o, lse = _flash(qg, kk, vv, segs, table, causal, M - N, M, bq, bk)
    o = jnp.moveaxis(o[:, :, :, :N], 3, 1).reshape(B, N, Hq, D)
    lse = jnp.moveaxis(lse[:, :, :, :N], 3, 1).reshape(B, N, Hq)
    return o, lse


def _tile_mask(segs, table, causal, offset, M, i, j, bq, bk):
    """(allowed [B, bq, bk] or None, valid [B or 1, bk]) for query block i and key block j. Invalid keys (beyond
    M, or key segment < 0: padding) are never attended, not even by fully masked rows."""
    qi, kj = i * bq + jnp.arange(bq), j * bk + jnp.arange(bk)
    allowed, valid = None, (kj < M)[None]
    if segs is not None:
        qs = jax.lax.dynamic_slice_in_dim(segs[0], i * bq, bq, axis=1)
        ks = jax.lax.dynamic_slice_in_dim(segs[1], j * bk, bk, axis=1)
        allowed = jnp.asarray(table, bool)[qs[:, :, None], jnp.maximum(ks, 0)[:, None, :]]
        valid = valid & (ks >= 0)
    if causal:
        c = (kj[None, :] <= qi[:, None] + offset)[None]
        allowed = c if allowed is None else allowed & c
    return allowed, valid


def _tile_scores(qb, kb, allowed, valid):
    """fp32 scores [B, Hkv, G, bq, bk]: masked = finfo.min (as layers.attention), padded keys = -inf."""
    s = jnp.einsum("bhgqd,bhkd->bhgqk", qb, kb, preferred_element_type=jnp.float32) / math.sqrt(qb.shape[-1])
    if allowed is not None:
        s = jnp.where(allowed[:, None, None], s, _MIN)
    return jnp.where(valid[:, None, None, None, :], s, -jnp.inf)


def _fold(step, n: int):
    """``lax.scan(step, init, arange(n))`` where the first call gets carry None and builds the initial carry
    from its own tile: inside ``shard_map`` the carry then has the inputs' varying-axes type (a constant
    ``jnp.zeros`` init would not, and scan refuses a carry whose type changes)."""
    carry, y0 = step(None, 0)
    if n == 1:
        return carry, jax.tree.map(lambda y: y[None], y0)
    carry, ys = jax.lax.scan(step, carry, jnp.arange(1, n))
    return carry, jax.tree.map(lambda a, b: jnp.concatenate([a[None], b]), y0, ys)


def _slice(x, start, size, axis):
    return jax.lax.dynamic_slice_in_dim(x, start, size, axis=axis)


def _unblock(x, axis):
    """[n, ...] stacked blocks whose block axis is ``axis`` of each block -> the blocks joined along ``axis``."""
    x = jnp.moveaxis(x, 0, axis)
    return x.reshape(x.shape[:axis] + (-1,) + x.shape[axis + 2:])


@functools.partial(jax.custom_vjp, nondiff_argnums=(4, 5, 6, 7, 8, 9))
def _flash(q, k, v, segs, table, causal, offset, M, bq, bk):
    return _flash_fwd(q, k, v, segs, table, causal, offset, M, bq, bk)[0]


def _flash_fwd(q, k, v, segs, table, causal, offset, M, bq, bk):
    """q [B, H, G, Np, D], k/v [B, H, Mp, D] (padded to whole blocks) -> o [B, H, G, Np, D], lse [B, H, G, Np]."""
    B, H, G, Np, D = q.shape
    nq, nk = Np // bq, k.shape[2] // bk

    def q_block(i):
        qb = _slice(q, i * bq, bq, 3)

        def k_step(carry, j):
            # m starts at finfo.min, not -inf: a tile of padded keys (-inf) then gives exp(-inf) = 0, never nan
            m, z, acc = (_MIN, 0.0, 0.0) if carry is None else carry
            kb, vb = _slice(k, j * bk, bk, 2), _slice(v, j * bk, bk, 2)
            s = _tile_scores(qb, kb, *_tile_mask(segs, table, causal, offset, M, i, j, bq, bk))
            m_new = jnp.maximum(m, jnp.max(s, axis=-1))
            p = jnp.exp(s - m_new[..., None])
            corr = jnp.exp(m - m_new)
            z = z * corr + jnp.sum(p, axis=-1)
            acc = acc * corr[..., None] + jnp.einsum("bhgqk,bhkd->bhgqd", p.astype(v.dtype), vb,
                                                     preferred_element_type=jnp.float32)
            return (m_new, z, acc), None

        (m, z, acc), _ = _fold(k_step, nk)
        return acc / jnp.where(z > 0, z, 1.0)[..., None], m, z

    acc, m, z = jax.lax.map(q_block, jnp.arange(nq))  # [nq, B, H, G, bq, (D)]
    o, m, z = _unblock(acc, 3).astype(q.dtype), _unblock(m, 3), _unblock(z, 3)
    # z = 0 only for a row whose keys are all padding (a ring block of padding): output 0, lse -inf
    lse = jnp.where(z > 0, m + jnp.log(jnp.where(z > 0, z, 1.0)), -jnp.inf)
    return (o, lse), (q, k, v, segs, o, m, z)


def _flash_bwd(table, causal, offset, M, bq, bk, res, cts):
    """Flash-attention backward: per tile p = exp(s - lse); dv += p^T do; ds = p (do v^T - delta + dlse);
    dq += ds k; dk += ds^T q (delta = rowsum(do * o)). Outer scan over key blocks (carrying dq), inner over query
    blocks (carrying that key block's dk, dv)."""
    q, k, v, segs, o, m, z = res
    do, dlse = cts
    B, H, G, Np, D = q.shape
    nq, nk = Np // bq, k.shape[2] // bk
    scale = 1.0 / math.sqrt(D)
    do32 = do.astype(jnp.float32)
    # d loss / d score_ij = p_ij (dp_ij - delta_i + dlse_i). p = exp(s - m) / z, not exp(s - lse): in a fully
    # masked row lse = finfo.min + log z rounds to finfo.min. Rows of padding only (z = 0) get p = 0.
    row = jnp.sum(do32 * o.astype(jnp.float32), axis=-1) - dlse.astype(jnp.float32)
    inv_z = 1.0 / jnp.where(z > 0, z, 1.0)

    def k_block(dq, j):
        kb, vb = _slice(k, j * bk, bk, 2), _slice(v, j * bk, bk, 2)

        def q_step(carry, i):
            dk, dv = (0.0, 0.0) if carry is None else carry
            qb, dob = _slice(q, i * bq, bq, 3), _slice(do, i * bq, bq, 3)
            allowed, valid = _tile_mask(segs, table, causal, offset, M, i, j, bq, bk)
            s = _tile_scores(qb, kb, allowed, valid)
            p = jnp.exp(s - _slice(m, i * bq, bq, 3)[..., None]) * _slice(inv_z, i * bq, bq, 3)[..., None]
            dv = dv + jnp.einsum("bhgqk,bhgqd->bhkd", p.astype(do.dtype), dob, preferred_element_type=jnp.float32)
            dp = jnp.einsum("bhgqd,bhkd->bhgqk", dob, vb, preferred_element_type=jnp.float32)
            ds = p * (dp - _slice(row, i * bq, bq, 3)[..., None])
            if allowed is not None:  # masked scores are constants (finfo.min): no gradient into q or k
                ds = jnp.where(allowed[:, None, None], ds, 0.0)
            ds = ds * scale
            dq_i = jnp.einsum("bhgqk,bhkd->bhgqd", ds, kb.astype(jnp.float32))
            dk = dk + jnp.einsum("bhgqk,bhgqd->bhkd", ds, qb.astype(jnp.float32))
            return (dk, dv), dq_i

        (dk, dv), dq_blocks = _fold(q_step, nq)
        return (0.0 if dq is None else dq) + _unblock(dq_blocks, 3), (dk, dv)

    dq, (dk, dv) = _fold(k_block, nk)
    dk, dv = _unblock(dk, 2), _unblock(dv, 2)
    dsegs = None if segs is None else tuple(np.zeros(s.shape, jax.dtypes.float0) for s in segs)
    return dq.astype(q.dtype), dk.astype(k.dtype), dv.astype(v.dtype), dsegs


_flash.defvjp(_flash_fwd, _flash_bwd)
