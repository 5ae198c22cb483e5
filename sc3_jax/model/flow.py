"""Rectified flow over tokens: noising with per-token noise levels, the loss on noisy tokens only, the Euler sampler.

    x_t = (1 - t) x + t eps,   target velocity v = eps - x,   t = 1 pure noise, t = 0 clean.

Two training-recipe levers (``FlowConfig``, both off by default):
  * ``from_present`` = sigma > 0: a noisy future video token's source is anchor + sigma eps instead of eps (the
    anchor: its view's last context frame, where that frame is clean; ``flow_source``), so
    x_t = (1 - t) x + t (anchor + sigma eps) and v = anchor + sigma eps - x, in the loss and in the sampler alike.
  * ``per_frame_t``: in training each future frame (its views and its action) draws its own t (diffusion forcing).

The network's raw output is read in one of two ways (``ModelConfig.prediction``):
  * "velocity": the output is v directly (Cosmos3 checkpoints).
  * "residual": the output is the clean target minus an anchor (the last context frame of the same view for
    video, zero for actions); v = (x_t - x0_hat) / t. Its loss is the clean-target error ||x0_hat - x||^2
    (the v-loss weighted by t^2, which keeps the small-t end well conditioned). Zero-initialised output
    weights make the untrained model "copy the last frame", the strong baseline a world model must beat.
"""
from __future__ import annotations

import jax
import jax.numpy as jnp

from sc3_jax.model import modes as modes_lib
from sc3_jax.core.config import FlowConfig, ModelConfig
from sc3_jax.model import dit


def noise_inputs(video, actions, stride, video_noisy, action_noisy, t, eps_video, eps_actions, pose=None,
                 context_level=None, anchor_gap=None):
    """Noised model inputs. ``t`` [B] is the sample's noise level, applied to its noisy tokens only; or [B, T] (one
    per future frame, ``FlowConfig.per_frame_t``): future frame i (every view) and action i get ``t[:, i]`` (one
    action per future token frame). ``eps_video``: the flow's source (pure noise, or ``flow_source``'s)."""
    if t.ndim == 1:
        tv = jnp.where(video_noisy, t[:, None, None], 0.0)
        ta = jnp.where(action_noisy, t[:, None], 0.0)
    else:
        F, T = video.shape[2], actions.shape[1]
        if t.shape[1] != T or T > F:
            raise ValueError(f"per-frame noise levels {t.shape} need one action per future token frame (video "
                             f"{video.shape[:3]}, actions {actions.shape[:2]})")
        frame_t = jnp.concatenate([jnp.zeros((t.shape[0], F - T), t.dtype), t], axis=1)  # [B, F], context: 0
        tv = jnp.where(video_noisy, frame_t[:, None, :], 0.0)
        ta = jnp.where(action_noisy, t, 0.0)
    xv = jnp.where(video_noisy[..., None, None], (1 - tv[..., None, None]) * video + tv[..., None, None] * eps_video,
                   video)
    xa = jnp.where(action_noisy[..., None], (1 - ta[..., None]) * actions + ta[..., None] * eps_actions, actions)
    return dit.Inputs(xv, xa, tv, video_noisy, ta, action_noisy, stride, pose=pose, context_level=context_level,
                      anchor_gap=anchor_gap)


def flow_source(video, video_noisy, eps, context_frames: int, from_present: float):
    """The flow's source x_1 for the video tokens: ``eps`` (pure noise) when ``from_present`` is 0 (returned as
    is), else anchor + from_present * eps for the future frames (token frames >= ``context_frames``) of every view
    whose last context frame -- the anchor, ``video[:, :, K - 1]`` as given (the model's residual anchor) -- is
    clean (not ``video_noisy``); eps elsewhere. Only the noisy tokens read it."""
    if not from_present:
        return eps
    K = context_frames
    if K < 1:
        raise ValueError(f"flow.from_present needs a context frame to flow from (context frames {K})")
    anchor = video[:, :, K - 1:K]  # [B, V, 1, P, D]
    future = jnp.arange(video.shape[2]) >= K  # [F]
    use = future[None, None, :] & ~video_noisy[:, :, K - 1:K]  # [B, V, F]
    return jnp.where(use[..., None, None], anchor + from_present * eps, eps)


def noise_context(video, level, key, context_frames: int):
    """Anti-drift augmentation: the first ``context_frames`` frames of every view become (1 - s) x + s eps with
    s = ``level`` [B]; later frames (the targets and any other condition) are returned untouched."""
    K = context_frames
    ctx = video[:, :, :K]
    eps = jax.random.normal(key, ctx.shape, ctx.dtype)
    s = level.astype(ctx.dtype)[:, None, None, None, None]
    return video.at[:, :, :K].set((1 - s) * ctx + s * eps)


def predict(params, cfg: ModelConfig, inp: dit.Inputs, grid, context_kv=None, context_frames: int | None = None):
    """Velocity and clean-target estimates for the future video [B, V, F - K, P, D] and the actions [B, T, Da].
    K = F - T (one action per future frame) unless ``context_frames`` is given (Cosmos3 layout only)."""
    K = inp.video.shape[2] - inp.actions.shape[1] if context_frames is None else context_frames
    if context_kv is None:
        out_v, out_a = dit.apply(params, cfg, inp, grid, context_frames=context_frames)
    else:
        out_v, out_a = dit.apply_cached(params, cfg, inp, grid, context_kv, context_frames=context_frames)
    xt_v, xt_a = inp.video[:, :, K:], inp.actions
    tv = inp.video_t[:, :, K:, None, None]
    ta = inp.action_t[..., None]
    if cfg.prediction == "velocity":
        return (out_v, out_a), (xt_v - tv * out_v, xt_a - ta * out_a)
    x0_v = inp.video[:, :, K - 1: K] + out_v  # anchor: the last (clean) context frame of the same view
    x0_a = out_a
    safe = lambda t: jnp.maximum(t, 1e-6)  # noqa: E731  (clean tokens: velocity unused, avoid 0/0)
    return ((xt_v - x0_v) / safe(tv), (xt_a - x0_a) / safe(ta)), (x0_v, x0_a)


def masked_loss(pred_v, pred_a, target_v, target_a, video_noisy_future, action_noisy, weights=(1.0, 1.0),
                token_weights=None):
    """Per-sample (weighted) mean squared error over noisy tokens only, then the batch mean. Also returns the
    per-sample losses. ``weights``: (video, action) loss weights. ``token_weights`` [B, V, T, N] (None: equal): a
    frame's error is the weighted mean over its N tokens (``moving_token_weights``)."""
    if token_weights is None:
        se_v = jnp.mean(jnp.square(pred_v - target_v), axis=(-2, -1))  # [B, V, T] per frame (mean over its tokens)
    else:
        se_tok = jnp.mean(jnp.square(pred_v - target_v), axis=-1)  # [B, V, T, N]
        w = token_weights.astype(se_tok.dtype)
        se_v = jnp.sum(se_tok * w, axis=-1) / jnp.maximum(jnp.sum(w, axis=-1), 1e-6)
    se_a = jnp.mean(jnp.square(pred_a - target_a), axis=-1)  # [B, T]
    mv, ma = video_noisy_future.astype(jnp.float32), action_noisy.astype(jnp.float32)
    total = weights[0] * jnp.sum(se_v * mv, axis=(1, 2)) + weights[1] * jnp.sum(se_a * ma, axis=1)
    count = jnp.sum(mv, axis=(1, 2)) + jnp.sum(ma, axis=1)
    per_sample = total / jnp.maximum(count, 1.0)
    return jnp.mean(per_sample), per_sample


def moving_token_weights(clean, K: int, moving_weight: float):
    """[B, V, F - K, N] loss weights of the future tokens of clean video tokens [B, V, F, N, D]: 1 + moving_weight x
    each token's RMS change from the same view's last context frame (token frame K - 1) over the frame's mean change
    (scale-free: latents of any scale; a frame where nothing moves weighs its tokens about equally)."""
    future = clean[:, :, K:].astype(jnp.float32)
    change = jnp.sqrt(jnp.mean(jnp.square(future - clean[:, :, K - 1:K].astype(jnp.float32)), axis=-1))
    rel = change / (jnp.mean(change, axis=-1, keepdims=True) + 1e-6)
    return jax.lax.stop_gradient(1.0 + moving_weight * rel)


def draw_t(rng, batch: int, fcfg: FlowConfig, frames: int | None = None) -> jax.Array:
    """Per-sample noise levels [batch] (or per future frame [batch, frames]), logit-normal, kept inside (0, 1)."""
    shape = (batch,) if frames is None else (batch, frames)
    t = jax.nn.sigmoid(fcfg.t_logit_mean + fcfg.t_logit_std * jax.random.normal(rng, shape))
    return jnp.clip(t, 1e-3, 1.0)


def self_forced_window(params, cfg: ModelConfig, video, actions, stride, rng, grid, fcfg: FlowConfig, shift: int,
                       eligible, pose=None, anchor_gap=None):
    """Self-forced context (anti-drift, as ``noise_context``; RoboWorld's step forcing): in closed loop a chunk's
    context is the model's own earlier prediction, in training it is real. Takes windows extended by ``shift``
    frames -- video [B, V, K + T + shift], actions [B, T + shift], pose [B, T + shift + 1] -- and returns the K + T
    frame training windows (video, actions, pose) and ``picked`` [B]: each ``eligible`` sample is picked with
    probability ``fcfg.self_forcing`` (drawn from ``rng``). An unpicked sample gets its first K + T frames (the
    window as without self-forcing); a picked one the window ``shift`` frames later -- with shift = l
    (rollout.keep_frames), the rollout's next chunk -- whose context is what a rollout would feed it: the last K of
    [real context, the model's prediction of the first ``shift`` future frames], and whose poses are integrated
    through the first chunk's actions, as a rollout's are. That prediction is one forward pass of the whole batch
    (static shapes; selected with ``jnp.where``): one Euler step from the flow's source (``sample``, steps=1: the
    conditional-mean estimate x0 = x_1 - v; x_1 pure noise unless ``fcfg.from_present``), forward dynamics from
    the real context, held constant for autodiff (training learns from it, never through it). Later frames are
    real, so the loss targets stay real frames. With ``anchor_gap`` [B] (data.anchor) token frame 0 is the
    episode's first frame: it stays frame 0 of both windows, and a picked window's gap grows by shift x stride data
    frames, as a rollout's does chunk by chunk.
    Returns (video, actions, pose, anchor_gap, picked)."""
    B = video.shape[0]
    A = 0 if anchor_gap is None else 1  # the anchor's token frame, in front of the context
    T = actions.shape[1] - shift
    F = video.shape[2] - shift
    K = F - T  # context token frames, the anchor's included
    if not 1 <= shift <= T:
        raise ValueError(f"self-forcing shift {shift} must be in [1, T = {T}] (rollout.keep_frames)")
    k_pick, k_pred = jax.random.split(rng)
    picked = eligible & (jax.random.uniform(k_pick, (B,)) < fcfg.self_forcing)
    first = (video[:, :, :F], actions[:, :T], None if pose is None else pose[:, :T + 1], anchor_gap)
    later = (jnp.concatenate([video[:, :, :A], video[:, :, A + shift:shift + F]], axis=2), actions[:, shift:],
             None if pose is None else pose[:, shift:], None if anchor_gap is None else anchor_gap + shift * stride)
    video_noisy, action_noisy = modes_lib.fixed(modes_lib.FD, B, video.shape[1], K, T)
    const = jax.lax.stop_gradient
    predicted, _ = sample(const(params), cfg, *first[:2], stride, video_noisy, action_noisy, k_pred, 1, grid,
                          cache="none", fcfg=fcfg, pose=first[2], anchor_gap=anchor_gap)
    fed = jnp.concatenate([video[:, :, A:K], const(predicted[:, :, K:K + shift])], axis=2)[:, :, -(K - A):]
    later = (later[0].at[:, :, A:K].set(fed.astype(later[0].dtype)),) + later[1:]

    def pick(a, b):
        return None if a is None else jnp.where(picked.reshape((B,) + (1,) * (a.ndim - 1)), b, a)
    return (*(pick(a, b) for a, b in zip(first, later)), picked)


def loss(params, cfg: ModelConfig, video, actions, stride, rng, probs, grid, fcfg: FlowConfig = FlowConfig(),
         context_frames: int | None = None, pose=None, self_forcing_shift: int = 0, anchor_gap=None):
    """The training loss for a batch of clean tokens; modes, noise levels and noise drawn from ``rng``.
    ``context_frames``: see ``predict`` (token frames; default: frames - actions). ``pose``: see ``dit.Inputs``.
    With ``fcfg.self_forcing > 0`` the inputs are windows extended by ``self_forcing_shift`` frames, cut to the
    training windows by ``self_forced_window`` (its picks among forward-dynamics samples) before anything else.
    With ``fcfg.context_noise_max > 0`` the context frames are noised (``noise_context``) next; the targets stay the
    clean frames. ``anchor_gap``: see ``dit.Inputs`` (data.anchor: token frame 0 is the episode's first frame).
    ``fcfg.from_present``: the future video flows from the (context-noised) last context frame plus scaled noise
    (``flow_source``); ``fcfg.per_frame_t``: each future frame and its action draw their own noise level."""
    k_mode, k_t, k_ev, k_ea = jax.random.split(rng, 4)
    picked = None
    if fcfg.self_forcing > 0:
        if context_frames is not None:
            raise ValueError("flow.self_forcing needs one token frame per frame (context_frames None)")
        mode, _ = modes_lib.draw(k_mode, video.shape[0], video.shape[1], probs)  # the same draw as below
        video, actions, pose, anchor_gap, picked = self_forced_window(
            params, cfg, video, actions, stride, jax.random.fold_in(rng, 11), grid, fcfg, self_forcing_shift,
            mode == modes_lib.FD, pose, anchor_gap)
    B, V, F = video.shape[:3]
    T = actions.shape[1]
    K = F - T if context_frames is None else context_frames
    clean = video
    context_level = None
    if fcfg.context_noise_max > 0:
        if not cfg.context_noise:
            raise ValueError("flow.context_noise_max > 0 needs model.context_noise (the model must be told the level)")
        k_cl, k_cn = jax.random.split(jax.random.fold_in(rng, 7))
        context_level = jax.random.uniform(k_cl, (B,), jnp.float32, 0.0, fcfg.context_noise_max)
        video = noise_context(video, context_level, k_cn, K)
    mode, kept = modes_lib.draw(k_mode, B, V, probs)
    video_noisy, action_noisy = modes_lib.masks(mode, kept, V, K, F - K, T)
    if fcfg.per_frame_t:
        if F - K != T:
            raise ValueError(f"flow.per_frame_t needs one action per future token frame ({F - K} future token "
                             f"frames, {T} actions)")
        t = draw_t(k_t, B, fcfg, T)
    else:
        t = draw_t(k_t, B, fcfg)
    eps_v = jax.random.normal(k_ev, video.shape, video.dtype)
    eps_a = jax.random.normal(k_ea, actions.shape, actions.dtype)
    src_v = flow_source(video, video_noisy, eps_v, K, fcfg.from_present)
    inp = noise_inputs(video, actions, stride, video_noisy, action_noisy, t, src_v, eps_a, pose, context_level,
                       anchor_gap)
    (v_v, v_a), (x0_v, x0_a) = predict(params, cfg, inp, grid, context_frames=context_frames)
    if cfg.prediction == "velocity":
        preds, targets = (v_v, v_a), (src_v[:, :, K:] - clean[:, :, K:], eps_a - actions)
    else:
        preds, targets = (x0_v, x0_a), (clean[:, :, K:], actions)
    weights = moving_token_weights(clean, K, fcfg.moving_weight) if fcfg.moving_weight else None
    total, per_sample = masked_loss(*preds, *targets, video_noisy[:, :, K:], action_noisy,
                                    (fcfg.video_loss_weight, fcfg.action_loss_weight), weights)
    metrics = {"loss": total}
    for m, name in enumerate(modes_lib.NAMES):
        sel = (mode == m).astype(jnp.float32)
        metrics[f"loss_{name}"] = jnp.sum(per_sample * sel) / jnp.maximum(jnp.sum(sel), 1.0)
        metrics[f"frac_{name}"] = jnp.mean(sel)
    if picked is not None:  # loss_forward counts these too; this is their share of the batch and their own loss
        sel = picked.astype(jnp.float32)
        metrics["loss_self_forced"] = jnp.sum(per_sample * sel) / jnp.maximum(jnp.sum(sel), 1.0)
        metrics["frac_self_forced"] = jnp.mean(sel)
    return total, metrics


def time_grid(steps: int, fcfg: FlowConfig = FlowConfig()) -> jax.Array:
    """``steps + 1`` noise levels from 1 to 0 at equal-probability quantiles of the training distribution of t, so
    every Euler step covers the same share of what the model was trained on (with the default logit-normal(0, 1)
    this is close to SD3's shifted schedule). Uniform spacing would spend the last steps at noise levels a
    high-noise-biased model has rarely seen."""
    u = 1.0 - jnp.arange(steps + 1, dtype=jnp.float32) / steps
    t = jax.nn.sigmoid(fcfg.t_logit_mean + fcfg.t_logit_std * jax.scipy.special.ndtri(u))
    return t.at[0].set(1.0).at[-1].set(0.0)


CACHES = ("auto", "context", "video", "none")


def _context_level(cfg: ModelConfig, batch: int, context_noise: float):
    """The context's noise level [B] the sampler tells a context_noise model (None: the model reads none)."""
    return jnp.full((batch,), context_noise, jnp.float32) if cfg.context_noise else None


def shares_context(cfg: ModelConfig, context_noise: float) -> bool:
    """Whether samplers of the same context see the same context tokens (so may share its keys/values): unless
    each noises it with its own key (a context_noise model sampled at ``context_noise`` > 0)."""
    return not (cfg.context_noise and context_noise > 0)


def context_cache(params, cfg: ModelConfig, video, actions, stride, video_noisy, action_noisy, grid,
                  prefix: str = "context", context_frames: int | None = None, pose=None, context_noise: float = 0.0,
                  anchor_gap=None, context_kv=None):
    """Per-layer keys/values of the clean prefix ``prefix`` of the sampler's inputs (``dit.encode_context``, every
    noise level 0), the context as given; ``context_kv``: the context's, already computed (prefix "video": only the
    frames behind it run). Arguments as ``sample``'s."""
    level = _context_level(cfg, video.shape[0], context_noise)
    clean = dit.Inputs(video, actions, jnp.zeros(video_noisy.shape), video_noisy, jnp.zeros(action_noisy.shape),
                       action_noisy, stride, pose=pose, context_level=level, anchor_gap=anchor_gap)
    return dit.encode_context(params, cfg, clean, grid, prefix=prefix, context_frames=context_frames,
                              context_kv=context_kv)


def sample(params, cfg: ModelConfig, video, actions, stride, video_noisy, action_noisy, rng, steps: int, grid,
           cache: str = "auto", fcfg: FlowConfig = FlowConfig(), context_frames: int | None = None,
           pose=None, context_noise: float = 0.0, anchor_gap=None, context_kv=None):
    """Euler from t = 1 to t = 0 in ``steps`` Euler steps (``time_grid``); clean tokens held fixed. Returns (video,
    actions) with the noisy positions filled in (the context frames as given, never their noised copy). The noisy
    tokens start at the flow's source: pure noise, or with ``fcfg.from_present`` the noisy future video at the last
    context frame (as the model sees it: context-noised where ``context_noise``) plus scaled noise (``flow_source``).

    ``cache``: which clean prefix's keys/values are computed once and reused by every Euler step (exact only with
    ``context_attention="causal"``): "context" = the context frames, "video" = every frame (only for inverse mode:
    all frames clean, all actions noisy), "none" = no cache (for checks), "auto" = "context" when the model's
    context attention is causal, else "none". ``context_frames``: see ``predict``. ``pose``: see ``dit.Inputs``.
    ``context_noise``: the level the context is noised with (models trained with context noise use a small one at
    inference, as GameNGen does). ``anchor_gap``: see ``dit.Inputs``. ``context_kv``: the context frames' keys/values
    already computed (``context_cache``; only where ``shares_context``), e.g. by a rollout chunk once for its forward
    and inverse samplers: cache "context" reuses them, cache "video" computes only the other frames'."""
    if cache not in CACHES:
        raise ValueError(f"cache {cache!r}: one of {CACHES}")
    K = video.shape[2] - actions.shape[1] if context_frames is None else context_frames
    context_level = _context_level(cfg, video.shape[0], context_noise)
    given = video
    if context_level is not None and context_noise > 0:
        video = noise_context(video, context_level, jax.random.fold_in(rng, 7), K)
    k_v, k_a = jax.random.split(rng)
    source = flow_source(video, video_noisy, jax.random.normal(k_v, video.shape, video.dtype), K, fcfg.from_present)
    video = jnp.where(video_noisy[..., None, None], source, video)
    actions = jnp.where(action_noisy[..., None], jax.random.normal(k_a, actions.shape, actions.dtype), actions)
    if cache == "auto":
        cache = "context" if cfg.context_attention == "causal" else "none"
    if context_kv is not None and (cache == "none" or not shares_context(cfg, context_noise)):
        raise ValueError("context_kv needs a cache and a context the sampler does not noise (shares_context)")
    if cache == "video" or (cache == "context" and context_kv is None):
        context_kv = context_cache(params, cfg, video, actions, stride, video_noisy, action_noisy, grid, cache,
                                   context_frames, pose, context_noise, anchor_gap, context_kv)

    ts = time_grid(steps, fcfg)

    def step(i, carry):
        xv, xa = carry
        t, t_next = ts[i], ts[i + 1]
        inp = dit.Inputs(xv, xa, jnp.where(video_noisy, t, 0.0), video_noisy, jnp.where(action_noisy, t, 0.0),
                         action_noisy, stride, pose=pose, context_level=context_level, anchor_gap=anchor_gap)
        (v_v, v_a), _ = predict(params, cfg, inp, grid, context_kv, context_frames)
        fut = xv[:, :, K:] + (t_next - t) * v_v
        xv = xv.at[:, :, K:].set(jnp.where(video_noisy[:, :, K:, None, None], fut, xv[:, :, K:]))
        xa = jnp.where(action_noisy[..., None], xa + (t_next - t) * v_a, xa)
        return xv, xa

    xv, xa = jax.lax.fori_loop(0, steps, step, (video, actions))
    return xv.at[:, :, :K].set(given[:, :, :K]), xa


def distill_loss(params, teacher_params, cfg: ModelConfig, video, actions, stride, rng, probs, grid,
                 fcfg: FlowConfig = FlowConfig(), teacher_cfg: ModelConfig | None = None,
                 teacher_fcfg: FlowConfig | None = None, context_frames: int | None = None, pose=None,
                 context_noise: float = 0.0):
    """Progressive distillation of the sampler (Salimans & Ho 2022, on rectified flow): the student (``params``)
    learns to produce in ONE Euler step what the teacher (``teacher_params``, frozen) produces in
    ``fcfg.distill_steps``, from the same noise, context noise and conditions. Both go through ``sample`` itself --
    one key, so one noise draw, and the path a rollout takes (context noise at the inference level
    ``context_noise``, pose conditioning, anchor, context cache) -- and the loss is ``masked_loss`` between the two
    samples over each sample's noisy tokens, modes drawn from ``probs`` as in ``loss``. Video targets are the
    teacher's ``distill_steps``-step sample; action targets (inverse dynamics) its 1-step read, the step count the
    sweep re-reads actions with (``SweepConfig.inverse_steps``), so U_chunk -- and the tau calibrated on it -- keep
    the teacher's meaning. With residual prediction the student's one step is its clean estimate x0_hat, so the
    loss is on the flow loss's scale. ``teacher_cfg`` / ``teacher_fcfg``: the teacher's model (its compute dtype)
    and its time grid (default: the student's); both must flow from the same source (``from_present``). Metrics:
    the loss, per mode, and ``loss_teacher_1step`` / ``loss_forward_teacher_1step``: the same loss for the
    teacher's own 1-step sample, where the student starts (a student below it samples closer to the teacher's
    ``distill_steps`` steps than the teacher does in one)."""
    teacher_cfg = cfg if teacher_cfg is None else teacher_cfg
    teacher_fcfg = fcfg if teacher_fcfg is None else teacher_fcfg
    if teacher_fcfg.from_present != fcfg.from_present:
        raise ValueError(f"flow.from_present: the teacher's {teacher_fcfg.from_present} and the student's "
                         f"{fcfg.from_present} differ; both must sample from the same source")
    B, V, F = video.shape[:3]
    T = actions.shape[1]
    K = F - T if context_frames is None else context_frames
    k_mode, k_sample = jax.random.split(rng)
    mode, kept = modes_lib.draw(k_mode, B, V, probs)
    video_noisy, action_noisy = modes_lib.masks(mode, kept, V, K, F - K, T)
    const = jax.lax.stop_gradient

    def run(p, c, fc, steps):
        return sample(p, c, video, actions, stride, video_noisy, action_noisy, k_sample, steps, grid, cache="auto",
                      fcfg=fc, context_frames=context_frames, pose=pose, context_noise=context_noise)

    one_v, one_a = (const(x) for x in run(const(teacher_params), teacher_cfg, teacher_fcfg, 1))
    target_v = one_v if fcfg.distill_steps == 1 else \
        const(run(const(teacher_params), teacher_cfg, teacher_fcfg, fcfg.distill_steps)[0])
    student_v, student_a = run(params, cfg, fcfg, 1)
    masks = (video_noisy[:, :, K:], action_noisy, (fcfg.video_loss_weight, fcfg.action_loss_weight))
    total, per_sample = masked_loss(student_v[:, :, K:], student_a, target_v[:, :, K:], one_a, *masks)
    base, base_per_sample = masked_loss(one_v[:, :, K:], one_a, target_v[:, :, K:], one_a, *masks)
    metrics = {"loss": total, "loss_teacher_1step": base}
    for m, name in enumerate(modes_lib.NAMES):
        sel = (mode == m).astype(jnp.float32)
        metrics[f"loss_{name}"] = jnp.sum(per_sample * sel) / jnp.maximum(jnp.sum(sel), 1.0)
        metrics[f"frac_{name}"] = jnp.mean(sel)
    fd = (mode == modes_lib.FD).astype(jnp.float32)
    metrics["loss_forward_teacher_1step"] = jnp.sum(base_per_sample * fd) / jnp.maximum(jnp.sum(fd), 1.0)
    return total, metrics
