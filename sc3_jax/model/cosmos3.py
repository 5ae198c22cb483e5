"""What ``ModelConfig.layout="cosmos3"`` changes in the DiT (``dit.py``): position ids, rotary frequencies, the
timestep embedding and the text ("understanding") pathway of diffusers' ``Cosmos3OmniTransformer``.

The transformer itself is ``dit.apply``; this module only holds the Cosmos3 conventions it switches on:

* Sequence ``[text (L) | video | actions]``; mRoPE position ids ``[N, 3]`` (time, row, col) as the Cosmos3 omni
  pipeline builds them: text ``arange(L)`` on all three axes; then ``offset = L + mrope_margin``; video frame f
  at ``t = f / (fps / tc) * (base_fps / tc) + offset`` (= offset + f * base_fps / fps), row/col = patch row/col;
  action i at ``t = (i + 1) / fps * (base_fps / tc) + offset``, row = col = 0 (tc = temporal_compression, so
  ``tc`` actions per latent frame). Without fps modulation (or a single frame / action) the time index is the
  integer ``f + int(offset)`` (``i + 1 + int(offset)``).
* Rotary inverse frequencies ``1 / theta ** (2i / head_dim)`` rounded as torch computes them (at large positions
  a one-ulp difference in a frequency is a visible phase error).
* Timestep embedding of ``floor(1000 t) * timestep_scale`` (the pipeline's integer scheduler timesteps), 256
  channels, ``cos | sin``.
* Text pathway: prompt token ids -> ``embed_tokens`` -> a separate stack of layers (``text_layers``, causal
  attention among text only). Its per-layer keys/values (after q/k norm and rotary) are a prefix that every
  generation token attends to; nothing in the text depends on the generation tokens, so they can be computed once
  per prompt (``dit.encode_text``, which runs that stack) and reused for every sampler step.
"""
from __future__ import annotations

import math

import jax
import jax.numpy as jnp
import numpy as np

from sc3_jax.core.config import ModelConfig
from sc3_jax.model import layers


def inv_freq(head_dim: int, theta: float) -> np.ndarray:
    """float32 ``1 / theta ** (arange(0, hd, 2) / hd)`` rounded like torch's float32 computation."""
    e = (np.arange(0, head_dim, 2, dtype=np.float32) / np.float32(head_dim)).astype(np.float64)
    return (np.float32(1.0) / np.float32(theta ** e)).astype(np.float32)


def timestep_embedding(t: jax.Array, dim: int, scale: float, max_period: float = 10000.0) -> jax.Array:
    """Sinusoid (``cos | sin``) of ``floor(1000 t) * scale``, fp32, as diffusers ``Timesteps(flip_sin_to_cos=True,
    downscale_freq_shift=0)`` applied to ``int(1000 t) * timestep_scale``."""
    half = dim // 2
    freqs = jnp.exp(-math.log(max_period) * jnp.arange(half, dtype=jnp.float32) / half)
    steps = jnp.floor(t.astype(jnp.float32) * jnp.float32(1000.0))
    args = (steps * jnp.float32(scale))[..., None] * freqs
    return jnp.concatenate([jnp.cos(args), jnp.sin(args)], axis=-1)


def text_positions(L: int) -> jax.Array:
    """[L, 3]: arange(L) on every axis."""
    return jnp.broadcast_to(jnp.arange(L, dtype=jnp.float32)[:, None], (L, 3))


def _time_index(cfg: ModelConfig, n: int, offset: int, fps: jax.Array, tps_div: float, start: int) -> jax.Array:
    """[B, n] time positions of n consecutive frames / actions (see the module docstring)."""
    idx = jnp.arange(n, dtype=jnp.float32)
    if cfg.fps_modulation and n > 1:
        tps = (fps / jnp.float32(tps_div))[:, None]  # [B, 1]
        base_tps = jnp.float32(cfg.base_fps / cfg.temporal_compression)
        return (idx + start) / tps * base_tps + jnp.float32(offset)
    return jnp.broadcast_to(idx + (int(offset) + start), (fps.shape[0], n))


def positions(cfg: ModelConfig, stride: jax.Array, L: int, V: int, F: int, K: int, grid: tuple[int, int],
              Ta: int) -> jax.Array:
    """[B, N, 3] position ids of the generation tokens in packed order (context video (V, K, P), future video
    (V, F - K, P), actions (Ta)), after L text tokens. Views share positions. A sample's fps is cfg.fps / stride."""
    rows, cols = grid
    B = stride.shape[0]
    fps = jnp.float32(cfg.fps) / stride.astype(jnp.float32)  # [B]
    offset = L + cfg.mrope_margin
    sp = 0 if cfg.reset_spatial_ids else int(offset)
    tv = _time_index(cfg, F, offset, fps, cfg.temporal_compression, 0)  # [B, F]
    r, c = jnp.meshgrid(jnp.arange(rows, dtype=jnp.float32), jnp.arange(cols, dtype=jnp.float32), indexing="ij")
    P = rows * cols
    rc = jnp.stack([r.reshape(-1), c.reshape(-1)], -1) + sp  # [P, 2]
    video = jnp.concatenate([jnp.broadcast_to(tv[:, :, None, None], (B, F, P, 1)),
                             jnp.broadcast_to(rc, (B, F, P, 2))], -1)  # [B, F, P, 3]
    video = jnp.broadcast_to(video[:, None], (B, V, F, P, 3))
    ctx, fut = video[:, :, :K].reshape(B, -1, 3), video[:, :, K:].reshape(B, -1, 3)
    ta = _time_index(cfg, Ta, offset, fps, 1.0, 1)  # [B, Ta]
    act = jnp.concatenate([ta[..., None], jnp.full((B, Ta, 2), float(sp), jnp.float32)], -1)
    return jnp.concatenate([ctx, fut, act], 1)


def rope_cos_sin(cfg: ModelConfig, pos: jax.Array):
    """``layers.rope_cos_sin`` (same interleaved sections, rotate-half layout) with Cosmos3's frequency rounding."""
    axis = layers.mrope_axis_index(cfg.head_dim, cfg.rope_axes_dim)
    freqs = jnp.take(pos.astype(jnp.float32), axis, axis=-1) * inv_freq(cfg.head_dim, cfg.rope_theta)
    emb = jnp.concatenate([freqs, freqs], axis=-1)
    return jnp.cos(emb), jnp.sin(emb)
