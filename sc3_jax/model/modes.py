"""The three training modes as per-sample token masks (not the sweep's evaluation modes real / offline / online,
``evaluation/results.py``). A training mode is only a choice of which token groups are noisy:

    forward dynamics (FD):       future frames of every view noisy; context frames and actions clean
    cross-view inpainting (CVI): future frames of every view but one randomly kept view noisy
    inverse dynamics (ID):       actions noisy; every frame clean

Modes are drawn per sample inside the jitted step with ``jnp.where`` on masks, so one batch mixes modes and one
compiled step serves all of them.
"""
from __future__ import annotations

import jax
import jax.numpy as jnp

FD, CVI, ID = 0, 1, 2
NAMES = ("forward", "inpaint", "inverse")


def without(probs, *removed: int) -> tuple[float, float, float]:
    """Mode probabilities with the ``removed`` modes at zero and the others in their original ratio (the paper's
    ablations remove a mode and keep the rest as they were, whatever the base config's mixture)."""
    p = [0.0 if i in removed else float(x) for i, x in enumerate(probs)]
    total = sum(p)
    if total <= 0:
        raise ValueError(f"no training mode left in {tuple(probs)} without modes {removed}")
    return tuple(x / total for x in p)


def draw(rng: jax.Array, batch: int, num_views: int, probs) -> tuple[jax.Array, jax.Array]:
    """Per-sample mode ids [B] drawn with ``probs`` (FD, CVI, ID) and the view kept clean under CVI [B]."""
    k_mode, k_view = jax.random.split(rng)
    p = jnp.asarray(probs, jnp.float32)
    mode = jax.random.choice(k_mode, 3, (batch,), p=p / p.sum())
    kept_view = jax.random.randint(k_view, (batch,), 0, num_views)
    return mode.astype(jnp.int32), kept_view.astype(jnp.int32)


def masks(mode: jax.Array, kept_view: jax.Array, num_views: int, context_frames: int, future_frames: int,
          num_actions: int | None = None):
    """Noisy-token masks: video [B, V, K+T] and actions [B, A] (True = noisy target, False = clean condition).
    A = T (one action per future frame) unless ``num_actions`` says otherwise (time-compressed latents: the
    Cosmos3 layout has ``time_compression`` actions per future token frame)."""
    B = mode.shape[0]
    is_future = jnp.arange(context_frames + future_frames) >= context_frames  # [F]
    view = jnp.arange(num_views)
    fd = mode[:, None, None] == FD
    cvi = (mode[:, None, None] == CVI) & (view[None, :, None] != kept_view[:, None, None])
    video_noisy = (fd | cvi) & is_future[None, None, :]
    action_noisy = jnp.broadcast_to((mode == ID)[:, None], (B, future_frames if num_actions is None else num_actions))
    return video_noisy, action_noisy


def fixed(mode: int, batch: int, num_views: int, context_frames: int, future_frames: int, kept_view: int = 0,
          num_actions: int | None = None):
    """Masks for every sample in one given mode (sampling, evaluation)."""
    return masks(jnp.full((batch,), mode, jnp.int32), jnp.full((batch,), kept_view, jnp.int32), num_views,
                 context_frames, future_frames, num_actions)
