"""The unified-dynamics DiT: a pure function of (params, tokens, noise levels, noisy masks, frame stride).

Token layout of one sample (packed, context first so a context key/value cache is a prefix):
    [ context video (V, K, P) | future video (V, T, P) | actions (T) ]
Video tokens get a 3-D RoPE position (time = frame * stride, row, col) and a learned per-view embedding; action j
(which moves frame K-1+j to K+j) sits at time (K - 0.5 + j) * stride, row = col = 0, plus the action-modality
embedding. The noise-level embedding is added to noisy tokens only; clean tokens get none.

Parameters are a plain nested dict of arrays; ``param_specs`` gives every parameter's shape, logical axis names and
initialiser in one place, so ``init_params`` and ``param_axes`` can never disagree. Layers are stacked on a leading
"layers" axis and run with ``lax.scan`` (one compiled block regardless of depth).
"""
from __future__ import annotations

import dataclasses
import math
from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from sc3_jax.core.config import ModelConfig
from sc3_jax.model import attention, attention_impl, context_parallel, cosmos3, layers


@dataclasses.dataclass(frozen=True)
class ParamSpec:
    shape: tuple[int, ...]
    axes: tuple[str | None, ...]  # logical axis names, mapped to mesh axes by sharding.RULES
    init: str = "normal"  # "normal" (fan-in scaled), "zeros", "ones"
    fan_in: int | None = None


def param_specs(cfg: ModelConfig, token_dim: int, grid: tuple[int, int] | None = None) -> dict:
    d = cfg.dim
    out_init = "zeros" if cfg.prediction == "residual" else "normal"  # residual: start as "copy the last frame"
    specs = {
        "proj_in": {"w": ParamSpec((token_dim, d), ("patch", "embed")), "b": ParamSpec((d,), ("embed",), "zeros")},
        "action_in": {"w": ParamSpec((cfg.num_action_domains, cfg.action_dim, d), ("domains", "action", "embed"),
                                     fan_in=cfg.action_dim),
                      "b": ParamSpec((cfg.num_action_domains, d), ("domains", "embed"), "zeros")},
        "action_modality_embed": ParamSpec((d,), ("embed",), fan_in=d),
        "time_embed": {"w1": ParamSpec((cfg.time_embed_dim, d), ("time_embed", "embed")),
                       "b1": ParamSpec((d,), ("embed",), "zeros"),
                       "w2": ParamSpec((d, d), ("embed_in", "embed")),
                       "b2": ParamSpec((d,), ("embed",), "zeros")},
        "layers": _layer_specs(cfg),
        "final_norm": ParamSpec((d,), ("embed",), "ones"),
        "proj_out": {"w": ParamSpec((d, token_dim), ("embed", "patch"), out_init),
                     "b": ParamSpec((token_dim,), ("patch",), "zeros")},
        "action_out": {"w": ParamSpec((cfg.num_action_domains, d, cfg.action_dim), ("domains", "embed", "action"),
                                      out_init, fan_in=d),
                       "b": ParamSpec((cfg.num_action_domains, cfg.action_dim), ("domains", "action"), "zeros")},
    }
    if cfg.view_embedding:
        specs["view_embed"] = ParamSpec((cfg.num_views, d), ("views", "embed"), fan_in=d)
    if cfg.anchor_conditioning:
        specs["anchor_in"] = ParamSpec((9 * token_dim, d), ("patch", "embed"))
    if cfg.action_to_frames:
        specs["action_to_frames"] = ParamSpec((2 * cfg.action_dim, d), ("action", "embed"))
    if cfg.action_reads_frames:
        if grid is None:
            raise ValueError("action_reads_frames needs the token grid (rows, cols) of a frame")
        n = cfg.num_views * grid[0] * grid[1] * token_dim
        specs["frames_to_action"] = ParamSpec((n, d), ("frame_features", "embed"))
    if cfg.pose_conditioning:
        if grid is None:
            raise ValueError("pose_conditioning needs the token grid (rows, cols) of a frame")
        specs["pose_in"] = {"w1": ParamSpec((cfg.action_dim, d), ("action", "embed")),
                            "b1": ParamSpec((d,), ("embed",), "zeros"),
                            "w2": ParamSpec((d, d), ("embed_in", "embed")),
                            "b2": ParamSpec((d,), ("embed",), "zeros")}
        specs["pose_unknown"] = ParamSpec((d,), ("embed",), fan_in=d)
        specs["token_pos_embed"] = ParamSpec((cfg.num_views, grid[0] * grid[1], d), ("views", "tokens", "embed"),
                                             fan_in=d)
    if cfg.context_noise:
        specs["context_noise_embed"] = {"w1": ParamSpec((cfg.time_embed_dim, d), ("time_embed", "embed")),
                                        "b1": ParamSpec((d,), ("embed",), "zeros"),
                                        "w2": ParamSpec((d, d), ("embed_in", "embed"), "zeros"),
                                        "b2": ParamSpec((d,), ("embed",), "zeros")}
    if cfg.text_pathway:  # Cosmos3 understanding pathway: its own layer stack, final norm, embeddings, LM head
        specs["text_layers"] = _layer_specs(cfg)
        specs["text_norm"] = ParamSpec((d,), ("embed",), "ones")
        specs["embed_tokens"] = ParamSpec((cfg.vocab_size, d), ("vocab", "embed"), fan_in=d)
        specs["lm_head"] = ParamSpec((cfg.vocab_size, d), ("vocab", "embed"), fan_in=d)
    return specs


def _layer_specs(cfg: ModelConfig) -> dict:
    d, L, hq, hkv, hd, m = cfg.dim, cfg.depth, cfg.num_heads, cfg.num_kv_heads, cfg.head_dim, cfg.mlp_dim
    return {
        "attn_norm": ParamSpec((L, d), ("layers", "embed"), "ones"),
        "wq": ParamSpec((L, d, hq, hd), ("layers", "embed", "heads", "head_dim"), fan_in=d),
        "wk": ParamSpec((L, d, hkv, hd), ("layers", "embed", "kv_heads", "head_dim"), fan_in=d),
        "wv": ParamSpec((L, d, hkv, hd), ("layers", "embed", "kv_heads", "head_dim"), fan_in=d),
        "q_norm": ParamSpec((L, hd), ("layers", "head_dim"), "ones"),
        "k_norm": ParamSpec((L, hd), ("layers", "head_dim"), "ones"),
        "wo": ParamSpec((L, hq, hd, d), ("layers", "heads", "head_dim", "embed"), fan_in=hq * hd * 2 * L),
        "mlp_norm": ParamSpec((L, d), ("layers", "embed"), "ones"),
        "w_gate": ParamSpec((L, d, m), ("layers", "embed", "mlp"), fan_in=d),
        "w_up": ParamSpec((L, d, m), ("layers", "embed", "mlp"), fan_in=d),
        "w_down": ParamSpec((L, m, d), ("layers", "mlp", "embed"), fan_in=m * 2 * L),
    }


def _is_spec(x):
    return isinstance(x, ParamSpec)


def init_params(cfg: ModelConfig, token_dim: int, key: jax.Array, grid: tuple[int, int] | None = None) -> dict:
    specs = param_specs(cfg, token_dim, grid)
    leaves, treedef = jax.tree.flatten(specs, is_leaf=_is_spec)
    keys = jax.random.split(key, len(leaves))
    dtype = jnp.dtype(cfg.param_dtype)

    def make(spec: ParamSpec, k):
        if spec.init == "zeros":
            return jnp.zeros(spec.shape, dtype)
        if spec.init == "ones":
            return jnp.ones(spec.shape, dtype)
        fan_in = spec.fan_in or spec.shape[-2]
        return (jax.random.normal(k, spec.shape, jnp.float32) / math.sqrt(fan_in)).astype(dtype)

    return jax.tree.unflatten(treedef, [make(s, k) for s, k in zip(leaves, keys)])


def param_axes(cfg: ModelConfig, token_dim: int, grid: tuple[int, int] | None = None) -> dict:
    """The logical axis names of every parameter (same tree structure as the params)."""
    return jax.tree.map(lambda s: s.axes, param_specs(cfg, token_dim, grid), is_leaf=_is_spec)


def decay_mask(cfg: ModelConfig, token_dim: int, grid: tuple[int, int] | None = None) -> dict:
    """True for weight matrices: parameters with two or more axes besides the stacking axes (layers, domains,
    views). Norm gains, biases and embeddings get no weight decay, however they are stacked; nor do the text
    vocabulary tables (``embed_tokens``: a lookup; ``lm_head``: unused by generation, so decay alone would shrink
    it while fine-tuning)."""
    stacking = ("layers", "domains", "views", "tokens")  # "tokens": per-position embedding tables
    return jax.tree.map(lambda s: "vocab" not in s.axes and sum(a not in stacking for a in s.axes) >= 2,
                        param_specs(cfg, token_dim, grid), is_leaf=_is_spec)


def count_params(params_or_shapes) -> int:
    return int(sum(np.prod(x.shape) for x in jax.tree.leaves(params_or_shapes)))


# ----------------------------------------------------------------------------------------------------------------
# Inputs and positions
# ----------------------------------------------------------------------------------------------------------------
class Inputs(NamedTuple):
    """One batch of tokens. Noise levels t in [0, 1]; ``*_noisy`` says which tokens are targets (get the timestep
    embedding and a loss); clean tokens are conditions."""
    video: jax.Array  # [B, V, F, P, Dp]  F = K context + T future frames
    actions: jax.Array  # [B, T, Da]
    video_t: jax.Array  # [B, V, F]
    video_noisy: jax.Array  # bool [B, V, F]
    action_t: jax.Array  # [B, T]
    action_noisy: jax.Array  # bool [B, T]
    stride: jax.Array  # int [B] frame stride (multi-FPS)
    text: jax.Array | None = None  # int [B, L] prompt token ids (only read by text_pathway configs)
    # normalised end-effector poses of the last context frame and the T future frames [B, T + 1, 7] (only read by
    # pose_conditioning configs; see imagination_state.frame_poses)
    pose: jax.Array | None = None
    context_level: jax.Array | None = None  # [B] noise level on the context frames (context_noise configs)
    # data.anchor: token frame 0 is the episode's first frame, this many data frames [B] before token frame 1
    anchor_gap: jax.Array | None = None


def positions(stride: jax.Array, V: int, F: int, grid: tuple[int, int], T: int, K: int,
              anchor_gap: jax.Array | None = None) -> jax.Array:
    """[B, N, 3] (time, row, col) in packed order (context video, future video, actions). Frame f sits at time
    f x stride; with ``anchor_gap`` [B] (data.anchor) frame 0 is the anchor, ``anchor_gap`` data frames before frame
    1: at time stride - anchor_gap."""
    rows, cols = grid
    f = jnp.arange(F, dtype=jnp.float32)
    r, c = jnp.meshgrid(jnp.arange(rows, dtype=jnp.float32), jnp.arange(cols, dtype=jnp.float32), indexing="ij")
    frame_pos = jnp.stack(jnp.broadcast_arrays(f[:, None], r.reshape(1, -1), c.reshape(1, -1)), -1)  # [F, P, 3]
    video = jnp.broadcast_to(frame_pos[None], (V,) + frame_pos.shape)  # [V, F, P, 3]
    ctx, fut = video[:, :K].reshape(-1, 3), video[:, K:].reshape(-1, 3)
    act_t = K - 0.5 + jnp.arange(T, dtype=jnp.float32)
    act = jnp.stack([act_t, jnp.zeros(T), jnp.zeros(T)], -1)
    pos = jnp.concatenate([ctx, fut, act], 0)  # [N, 3]
    scale = jnp.asarray([1.0, 0.0, 0.0]) * (stride.astype(jnp.float32)[:, None, None] - 1.0) + 1.0
    pos = pos[None] * scale  # time axis scaled by the stride
    if anchor_gap is None:
        return pos
    is_anchor = jnp.zeros((V, K, rows * cols), bool).at[:, 0].set(True).reshape(-1)  # the context's frame 0
    is_anchor = jnp.concatenate([is_anchor, jnp.zeros(pos.shape[1] - is_anchor.shape[0], bool)])
    t = (stride - anchor_gap).astype(jnp.float32)[:, None]
    return pos.at[..., 0].set(jnp.where(is_anchor[None], t, pos[..., 0]))


# ----------------------------------------------------------------------------------------------------------------
# Forward
# ----------------------------------------------------------------------------------------------------------------
def _neighbourhood(frame: jax.Array, grid: tuple[int, int]) -> jax.Array:
    """[B, V, P, D] tokens -> [B, V, P, 9 D]: each patch with its 8 neighbours (zero outside the frame)."""
    B, V, P, D = frame.shape
    rows, cols = grid
    x = jnp.pad(frame.reshape(B, V, rows, cols, D), ((0, 0), (0, 0), (1, 1), (1, 1), (0, 0)))
    shifts = [x[:, :, i:i + rows, j:j + cols] for i in range(3) for j in range(3)]
    return jnp.concatenate(shifts, axis=-1).reshape(B, V, P, 9 * D)


def _embed(params, cfg: ModelConfig, inp: Inputs, grid, domain: int, K: int | None = None):
    """Token embeddings [B, N, D] in packed order, plus per-token noisy flags."""
    dt = jnp.dtype(cfg.dtype)
    B, V, F, P, _ = inp.video.shape
    T = inp.actions.shape[1]
    K = F - T if K is None else K
    xv = inp.video.astype(dt) @ params["proj_in"]["w"].astype(dt) + params["proj_in"]["b"].astype(dt)
    if cfg.view_embedding:
        xv = xv + params["view_embed"].astype(dt)[None, :, None, None, :]
    # Timestep embedding per (view, frame) and per action, added to noisy tokens only.
    temb_v = _time_mlp(params, inp.video_t, cfg).astype(dt)  # [B, V, F, D]
    xv = xv + jnp.where(inp.video_noisy[..., None, None], temb_v[:, :, :, None, :], 0)
    future = jnp.zeros_like(xv[:, :, K:])
    if cfg.anchor_conditioning:  # the 3x3 neighbourhood of the same patch in the last context frame
        future = future + (_neighbourhood(inp.video[:, :, K - 1], grid).astype(dt) @ params["anchor_in"].astype(dt))[:, :, None]
    if cfg.action_to_frames:  # frame K+j: action j and how far actions 0..j moved the robot (clean actions only)
        a = jnp.where(inp.action_noisy[..., None], 0, inp.actions).astype(dt)
        if cfg.action_sum == "pose":  # physical displacement since the last context frame, in the pose's units
            moved = jnp.where(inp.action_noisy[..., None], 0, inp.pose[:, 1:] - inp.pose[:, :1]).astype(dt)
        else:  # models saved before: the running sum of normalised actions
            moved = jnp.cumsum(a, axis=1)
        feats = jnp.concatenate([a, moved], axis=-1) @ params["action_to_frames"].astype(dt)
        future = future + feats[:, None, :, None, :]
    xv = xv.at[:, :, K:].add(future)
    if cfg.pose_conditioning:
        xv = xv + _pose_features(params, inp, K, T, dt)
    if cfg.context_noise:  # the level the context frames were noised with (0 = exactly clean)
        level = jnp.zeros((B,), jnp.float32) if inp.context_level is None else inp.context_level
        emb = _mlp_embed(params["context_noise_embed"], level, cfg).astype(dt)
        xv = xv.at[:, :, :K].add(emb[:, None, None, None, :])
    xa = jnp.einsum("bta,ad->btd", inp.actions.astype(dt), params["action_in"]["w"][domain].astype(dt))
    xa = xa + params["action_in"]["b"][domain].astype(dt) + params["action_modality_embed"].astype(dt)
    temb_a = _time_mlp(params, inp.action_t, cfg).astype(dt)
    xa = xa + jnp.where(inp.action_noisy[..., None], temb_a, 0)
    if cfg.action_reads_frames:  # action j: frame K+j minus frame K-1+j, every view (when both are clean)
        clean = ~inp.video_noisy[:, :, K:] & ~inp.video_noisy[:, :, K - 1:-1]  # [B, V, T]
        diff = jnp.where(clean[..., None, None], inp.video[:, :, K:] - inp.video[:, :, K - 1:-1], 0)
        diff = jnp.moveaxis(diff, 2, 1).reshape(B, T, -1).astype(dt)
        xa = xa + diff @ params["frames_to_action"].astype(dt)
    D = xv.shape[-1]
    x = jnp.concatenate([xv[:, :, :K].reshape(B, -1, D), xv[:, :, K:].reshape(B, -1, D), xa], axis=1)
    return x


def _pose_features(params, inp: Inputs, K: int, T: int, dt):
    """[B, V, F, P, D] additions: absolute (view, token) position embeddings on every video token; the pose
    embedding of frame K-1 (the last context frame) and of future frames K..K+T-1 on their tokens. Future poses are
    integrated from the actions, so they are replaced by ``pose_unknown`` in samples whose actions are targets."""
    if inp.pose is None:
        raise ValueError("a pose_conditioning model needs Inputs.pose [B, T + 1, 7]")
    p = params["pose_in"]
    B, V, F, P, _ = inp.video.shape
    h = jax.nn.silu(inp.pose.astype(jnp.float32) @ p["w1"].astype(jnp.float32) + p["b1"].astype(jnp.float32))
    pe = (h @ p["w2"].astype(jnp.float32) + p["b2"].astype(jnp.float32)).astype(dt)  # [B, T + 1, D]
    known = ~jnp.any(inp.action_noisy, axis=1)  # [B]
    fut = jnp.where(known[:, None, None], pe[:, 1:], params["pose_unknown"].astype(dt))
    per_frame = jnp.concatenate([jnp.zeros((B, K - 1) + pe.shape[2:], dt), pe[:, :1], fut], axis=1)  # [B, F, D]
    return params["token_pos_embed"].astype(dt)[None, :, None] + per_frame[:, None, :, None, :]


def _mlp_embed(p, t, cfg: ModelConfig | None = None):
    """Sinusoid of a noise level through a two-layer MLP (``p``: w1, b1, w2, b2) -> [..., D] float32."""
    if cfg is not None and cfg.layout == "cosmos3":
        e = cosmos3.timestep_embedding(t, p["w1"].shape[0], cfg.timestep_scale)
    else:
        e = layers.timestep_embedding(t, p["w1"].shape[0])
    h = jax.nn.silu(e @ p["w1"].astype(jnp.float32) + p["b1"].astype(jnp.float32))
    return h @ p["w2"].astype(jnp.float32) + p["b2"].astype(jnp.float32)


def _time_mlp(params, t, cfg: ModelConfig | None = None):
    return _mlp_embed(params["time_embed"], t, cfg)


def _block(cfg: ModelConfig, x, p, cos, sin, mask, prefix_kv=None):
    """One pre-norm block. ``prefix_kv``: cached (k, v) of a context prefix that x's tokens also attend to."""
    h = layers.rms_norm(x, p["attn_norm"], cfg.norm_eps)
    q, k, v = layers.qkv(h, p, cos, sin, cfg.norm_eps)
    kv = (k, v)
    if prefix_kv is not None:
        k = jnp.concatenate([prefix_kv[0].astype(k.dtype), k], axis=1)
        v = jnp.concatenate([prefix_kv[1].astype(v.dtype), v], axis=1)
    o = attention_impl.attend(cfg.attention_impl, q, k, v, mask, cfg.attention_block)
    x = x + jnp.einsum("bnhk,hkd->bnd", o, p["wo"].astype(x.dtype))
    h = layers.rms_norm(x, p["mlp_norm"], cfg.norm_eps)
    x = x + layers.swiglu(h, p["w_gate"], p["w_up"], p["w_down"])
    return x, kv


def _run_layers(cfg: ModelConfig, params, x, cos, sin, mask, prefix_kv=None, stack: str = "layers"):
    """lax.scan over the stacked layers (``params[stack]``). Returns the final hidden states and each layer's
    (k, v)."""

    def body(x, layer):
        p, pkv = layer
        return _block(cfg, x, p, cos, sin, mask, pkv)

    if cfg.remat != "none":  # "block": keep only each layer's input; "dots": also its weight matmul outputs
        policy = (jax.checkpoint_policies.nothing_saveable if cfg.remat == "block"
                  else jax.checkpoint_policies.dots_with_no_batch_dims_saveable)
        body = jax.checkpoint(body, policy=policy)
    return jax.lax.scan(body, x, (params[stack], prefix_kv), unroll=not cfg.scan_layers)


def token_noisy(inp: Inputs, P: int, K: int | None = None) -> jax.Array:
    """Per-token noisy flags [B, N] in packed order (context video, future video, actions)."""
    B, V, F = inp.video_noisy.shape
    T = inp.actions.shape[1]
    K = F - T if K is None else K
    per_frame = jnp.broadcast_to(inp.video_noisy[..., None], (B, V, F, P))
    return jnp.concatenate([per_frame[:, :, :K].reshape(B, -1), per_frame[:, :, K:].reshape(B, -1),
                            inp.action_noisy], axis=1)


def _attention_mask(cfg: ModelConfig, noisy: jax.Array, n_ctx: int, q_start: int = 0):
    """Attention mask [B, 1, Nq, N] for queries ``q_start:`` (None = full attention).

    ``context_attention="causal"``: context tokens attend to context only, other clean tokens to clean tokens only,
    noisy tokens to everything. So nothing clean ever depends on a noisy token: the context's keys/values can be
    computed once per rollout chunk, and in inverse mode (every frame clean) those of all video tokens, leaving only
    the action tokens for each sampler step."""
    if cfg.context_attention == "full":
        return None
    if cfg.attention_impl != "dense":  # the same mask as per-token segments: only ever built one tile at a time
        seg = attention.causal_segments(noisy, n_ctx)
        return attention.SegmentMask(seg[:, q_start:], seg, attention.CAUSAL_TABLE)
    n = noisy.shape[1]
    is_ctx = jnp.arange(n) < n_ctx
    q_ctx, q_noisy = is_ctx[q_start:][None, :, None], noisy[:, q_start:, None]
    mask = jnp.where(q_ctx, is_ctx[None, None, :], q_noisy | ~noisy[:, None, :])
    return mask[:, None]


def _outputs(params, cfg: ModelConfig, h, V, T, P, domain, T_video: int | None = None):
    """h: hidden states of the future video then the action tokens, or of the action tokens only (then the video
    outputs are zeros: a video-prefix cache is only used when no video token is a target). ``T_video``: future
    frames when not T (Cosmos3 layout: any number of actions)."""
    B = h.shape[0]
    T_video = T if T_video is None else T_video
    h = layers.rms_norm(h, params["final_norm"], cfg.norm_eps)
    hv, ha = h[:, : h.shape[1] - T], h[:, h.shape[1] - T:]
    dp = params["proj_out"]["w"].shape[1]
    if hv.shape[1] == 0:
        out_v = jnp.zeros((B, V, T_video, P, dp), jnp.float32)
    else:
        out_v = hv @ params["proj_out"]["w"].astype(h.dtype) + params["proj_out"]["b"].astype(h.dtype)
        out_v = out_v.reshape(B, V, T_video, P, dp).astype(jnp.float32)
    out_a = jnp.einsum("btd,da->bta", ha, params["action_out"]["w"][domain].astype(h.dtype))
    out_a = (out_a + params["action_out"]["b"][domain].astype(h.dtype)).astype(jnp.float32)
    return out_v, out_a


def _layout(cfg: ModelConfig, inp: Inputs, context_frames: int | None):
    """(B, V, F, P, T, K): T action tokens, K context frames (F - T unless ``context_frames`` is given, which only
    the Cosmos3 layout allows: there the number of actions is independent of the number of frames)."""
    B, V, F, P, _ = inp.video.shape
    T = inp.actions.shape[1]
    if context_frames is None:
        K = F - T
    else:
        if cfg.layout != "cosmos3" and context_frames != F - T:
            raise ValueError(f"layout {cfg.layout!r} needs context_frames = frames - actions = {F - T}")
        K = context_frames
    if not 0 <= K <= F:
        raise ValueError(f"context frames {K} out of range for {F} frames (pass context_frames)")
    return B, V, F, P, T, K


def _text_prefix(params, cfg: ModelConfig, inp: Inputs, text_kv):
    """The per-layer text keys/values generation tokens attend to (text_pathway configs), else None."""
    if not cfg.text_pathway:
        if text_kv is not None:
            raise ValueError("text_kv given but this config has no text pathway")
        return None
    if cfg.attention_impl in ("context_parallel", "ring"):
        raise NotImplementedError("the text pathway does not run with context parallelism (attention_impl "
                                  f"{cfg.attention_impl!r}); use 'dense', 'blockwise' or 'fused'")
    if text_kv is None:
        text = inp.text
        if text is None and cfg.prompt_ids:  # the config's fixed prompt for every sample
            text = jnp.broadcast_to(jnp.asarray(cfg.prompt_ids, jnp.int32), (inp.video.shape[0], len(cfg.prompt_ids)))
        if text is None:
            raise ValueError("a text_pathway config needs Inputs.text (prompt token ids), text_kv or "
                             "model.prompt_ids")
        text_kv = encode_text(params, cfg, text)
    return text_kv


def _rope(cfg: ModelConfig, inp: Inputs, V, F, grid, T, K, L: int, sl=slice(None)):
    if cfg.layout == "cosmos3":
        if inp.anchor_gap is not None:
            raise ValueError("data.anchor is not wired into the Cosmos3 layout's positions")
        return cosmos3.rope_cos_sin(cfg, cosmos3.positions(cfg, inp.stride, L, V, F, K, grid, T)[:, sl])
    return layers.rope_cos_sin(positions(inp.stride, V, F, grid, T, K, inp.anchor_gap)[:, sl], cfg.head_dim,
                               cfg.rope_axes_dim, cfg.rope_theta)


def _prefix_columns(mask, n: int):
    """Let every query also see ``n`` prefix keys (the text) in front of a [B, 1, Nq, N] mask or a SegmentMask."""
    if mask is None or n == 0:
        return mask
    if isinstance(mask, attention.SegmentMask):
        return attention.with_prefix(mask, n)
    return jnp.concatenate([jnp.ones(mask.shape[:3] + (n,), bool), mask], axis=-1)


def _finish(params, cfg: ModelConfig, inp: Inputs, h, V, T, P, domain, K):
    F = inp.video.shape[2]
    out_v, out_a = _outputs(params, cfg, h, V, T, P, domain, F - K)
    if cfg.layout == "cosmos3":  # Cosmos3 returns zeros at clean (conditioning) tokens
        out_v = jnp.where(inp.video_noisy[:, :, K:, None, None], out_v, 0.0)
        out_a = jnp.where(inp.action_noisy[..., None], out_a, 0.0)
    return out_v, out_a


def _prepare(params, cfg: ModelConfig, inp: Inputs, grid, domain: int, context_frames: int | None, text_kv,
             start: int = 0, stop: int | None = None):
    """What ``apply``, ``encode_context`` and ``apply_cached`` share: the tokens ``start:stop`` (packed order)
    embedded, their rotary tables and their attention mask (keys: every token up to ``stop``, behind the text
    prefix), and the text's keys/values. Returns (x, cos, sin, mask, text_kv, (V, P, T, K))."""
    _, V, F, P, T, K = _layout(cfg, inp, context_frames)
    text_kv = _text_prefix(params, cfg, inp, text_kv)
    L = 0 if text_kv is None else text_kv[0].shape[2]
    x = _embed(params, cfg, inp, grid, domain, K)[:, start:stop]
    if cfg.attention_impl != "dense":
        x = context_parallel.shard_tokens(x)
    cos, sin = _rope(cfg, inp, V, F, grid, T, K, L, slice(start, stop))
    mask = _prefix_columns(_attention_mask(cfg, token_noisy(inp, P, K)[:, :stop], V * K * P, q_start=start), L)
    return x, cos, sin, mask, text_kv, (V, P, T, K)


def apply(params, cfg: ModelConfig, inp: Inputs, grid: tuple[int, int], domain: int = 0, *,
          context_frames: int | None = None, text_kv=None):
    """Raw network outputs for the future-video tokens [B, V, T, P, Dp] and action tokens [B, T, Da].
    (Context-frame outputs are never used, so they are not projected.) See ``flow.predict`` for what the raw
    outputs mean under each ``cfg.prediction``.

    Cosmos3 layout (``cfg.layout="cosmos3"``): ``context_frames`` K may be given (the future frames F - K need not
    equal the number of actions), outputs at clean tokens are zero, and with ``cfg.text_pathway`` the tokens attend
    to the prompt ``inp.text`` (or to precomputed ``text_kv = encode_text(...)``)."""
    x, cos, sin, mask, text_kv, (V, P, T, K) = _prepare(params, cfg, inp, grid, domain, context_frames, text_kv)
    h, _ = _run_layers(cfg, params, x, cos, sin, mask, text_kv)
    return _finish(params, cfg, inp, h[:, V * K * P:], V, T, P, domain, K)


def prefix_length(inp: Inputs, P: int, prefix: str, context_frames: int | None = None) -> int:
    """Tokens in a cacheable prefix: "context" = the context video (exact whenever context_attention="causal"),
    "video" = all video tokens (exact when every frame is clean and every action noisy: inverse mode)."""
    B, V, F = inp.video_noisy.shape
    T = inp.actions.shape[1]
    if prefix == "context":
        return V * (F - T if context_frames is None else context_frames) * P
    if prefix == "video":
        return V * F * P
    raise ValueError(f"prefix must be 'context' or 'video', got {prefix!r}")


def encode_context(params, cfg: ModelConfig, inp: Inputs, grid, domain: int = 0, prefix: str = "context", *,
                   context_frames: int | None = None, text_kv=None, context_kv=None):
    """Per-layer keys/values of a clean prefix (``prefix_length``), [L, B, n_prefix, Hkv, hd] each. Only valid with
    ``context_attention="causal"`` (then clean tokens never see targets, so this is exact). With a text pathway
    the prefix tokens attend to the text, whose keys/values are not part of the result. ``context_kv``: the keys/values
    of the prefix's first tokens, already computed on the same clean tokens (prefix "context", for prefix "video"):
    only the tokens behind them run, and the result holds both."""
    if cfg.context_attention != "causal":
        raise ValueError("context caching needs context_attention='causal'")
    _, _, _, P, _, K = _layout(cfg, inp, context_frames)
    n = prefix_length(inp, P, prefix, K)
    start = 0 if context_kv is None else context_kv[0].shape[2]
    x, cos, sin, mask, text_kv, _ = _prepare(params, cfg, inp, grid, domain, context_frames, text_kv, start, n)
    _, kv = _run_layers(cfg, params, x, cos, sin, mask, _prefix_kv(text_kv, context_kv))
    return kv if context_kv is None else tuple(jnp.concatenate([c.astype(k.dtype), k], axis=2)
                                               for c, k in zip(context_kv, kv))


def _prefix_kv(text_kv, context_kv):
    """The keys/values in front of the tokens a pass runs: the text's, then the cached context's (either may be
    None)."""
    if text_kv is None or context_kv is None:
        return context_kv if text_kv is None else text_kv
    return tuple(jnp.concatenate([t.astype(c.dtype), c], axis=2) for t, c in zip(text_kv, context_kv))


def apply_cached(params, cfg: ModelConfig, inp: Inputs, grid, context_kv, domain: int = 0, *,
                 context_frames: int | None = None, text_kv=None):
    """Same outputs as ``apply`` under causal context attention, computing only the tokens after the cached
    prefix (its length is read off ``context_kv``)."""
    n = context_kv[0].shape[2]
    x, cos, sin, mask, text_kv, (V, P, T, K) = _prepare(params, cfg, inp, grid, domain, context_frames, text_kv,
                                                        start=n)
    h, _ = _run_layers(cfg, params, x, cos, sin, mask, _prefix_kv(text_kv, context_kv))
    return _finish(params, cfg, inp, h, V, T, P, domain, K)


# ----------------------------------------------------------------------------------------------------------------
# The text pathway (Cosmos3 layout; its conventions in cosmos3.py)
# ----------------------------------------------------------------------------------------------------------------
def encode_text(params, cfg: ModelConfig, text: jax.Array):
    """Per-layer keys/values of the prompt tokens ``text`` (int [B, L]) through the understanding pathway:
    ([layers, B, L, Hkv, hd], same) -- the prefix every generation token attends to."""
    if not cfg.text_pathway:
        raise ValueError("this config has no text pathway (text_pathway=False)")
    if cfg.attention_impl in ("context_parallel", "ring"):
        raise NotImplementedError("the text pathway does not run with context parallelism")
    B, L = text.shape
    dt = jnp.dtype(cfg.dtype)
    x = jnp.take(params["embed_tokens"], text, axis=0).astype(dt)
    cos, sin = cosmos3.rope_cos_sin(cfg, jnp.broadcast_to(cosmos3.text_positions(L)[None], (B, L, 3)))
    dense = cfg.attention_impl == "dense"
    causal = jnp.tril(jnp.ones((L, L), bool))[None, None] if dense else attention.causal_mask()
    _, kv = _run_layers(cfg, params, x, cos, sin, causal, stack="text_layers")
    return kv
