"""``ModelConfig.attention_impl`` -> the kernel that computes one attention call: dense (``layers.attention``),
blockwise / fused (``attention.py``) or sharded over the mesh's context axis (``context_parallel.py``)."""
from __future__ import annotations

from sc3_jax.core.config import ATTENTION_IMPLS as IMPLS
from sc3_jax.model import attention, context_parallel, layers


def attend(impl: str, q, k, v, mask=None, block: int = 512):
    """q [B, N, Hq, hd], k/v [B, M, Hkv, hd] -> [B, N, Hq, hd] with ``ModelConfig.attention_impl`` ``impl``.
    ``mask``: None, a dense bool [B, 1, N, M] (dense only) or a :class:`attention.SegmentMask`."""
    if impl == "dense":
        if isinstance(mask, attention.SegmentMask):
            mask = mask.dense(q.shape[1], k.shape[1])
        return layers.attention(q, k, v, mask)
    if mask is not None and not isinstance(mask, attention.SegmentMask):
        raise TypeError(f"attention_impl {impl!r} needs a SegmentMask (or None), got {type(mask).__name__}")
    if impl in ("context_parallel", "ring"):
        return context_parallel.attention(q, k, v, mask, ring=impl == "ring", block=block)
    if impl == "fused" and attention.fused_ok(q, k, mask):
        return attention.fused(q, k, v, mask)
    if impl in ("blockwise", "fused"):
        return attention.blockwise(q, k, v, mask, block)
    raise ValueError(f"unknown attention_impl {impl!r}; known: {', '.join(IMPLS)}")
