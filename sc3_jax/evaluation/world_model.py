"""Offline checks that a trained world model learned dynamics, each against the baseline it must beat:

  forward dynamics   PSNR of sampled future frames (true actions)  vs  "repeat the last context frame"
  action use         the same with actions shuffled across the batch (must be worse: the model uses its actions)
  inverse dynamics   error of the model's action estimate           vs  predicting the mean action (zero)
                     (normalised units; one sampler step = the model's conditional-mean estimate; a multi-step
                     sample also carries the model's remaining uncertainty as variance: reported as id_sample_mse)
  inpainting         PSNR of the held-out views' future frames      vs  the mean frame of each view
"""
from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np

from sc3_jax.model import flow, modes
from sc3_jax.core.config import Config
from sc3_jax.measures import metrics
from sc3_jax.model.tokenizer import make_tokenizer, to_uint8, window_tokens


def _psnr(pred_u8, true_u8) -> float:
    """PSNR of the pooled squared error over every frame given."""
    return metrics.psnr(pred_u8, true_u8, axis=None)


def make_sampler(cfg: Config, steps: int | None = None):
    tok = make_tokenizer(cfg.model)
    grid = tok.grid(cfg.data.image_size)
    V, K, T = len(cfg.data.views), cfg.data.context_frames, cfg.data.future_frames
    Kt, Tt = window_tokens(tok, K, T)  # token frames (= K, T unless the tokenizer compresses time)

    @jax.jit
    def run(params, frames, actions, stride, rng, mode, kept_view, pose=None):
        """``pose``: the normalised pose condition [B, T + 1, 7] (pose-conditioned models only)."""
        video = tok.encode(frames)
        B = frames.shape[0]
        vn, an = modes.masks(jnp.full((B,), mode), jnp.full((B,), kept_view), V, Kt, Tt, num_actions=T)
        out_v, out_a = flow.sample(params, cfg.model, video, actions, stride, vn, an, rng, steps or cfg.sample.steps,
                                   grid, fcfg=cfg.flow, context_frames=Kt, pose=pose,
                                   context_noise=cfg.sample.context_noise)
        return to_uint8(tok.decode(out_v, cfg.data.image_size)), out_a

    return run


def evaluate(params, cfg: Config, batches, seed: int = 0) -> dict[str, float]:
    """Averages over ``batches`` (pipeline batches of held-out windows: stride 1, recorded actions)."""
    run = make_sampler(cfg)
    run_mean = make_sampler(cfg, steps=1)
    K = cfg.data.context_frames
    rng = jax.random.key(seed)
    acc: dict[str, list[float]] = {}

    def add(k, v):
        acc.setdefault(k, []).append(v)

    for batch in batches:
        frames, actions, stride = batch["frames"], batch["actions"], batch["stride"]
        true_future = frames[:, :, K:]
        rng, k1, k2, k3, k4 = jax.random.split(rng, 5)
        pred, _ = run(params, frames, actions, stride, k1, modes.FD, 0)
        add("fd_psnr", _psnr(np.asarray(pred)[:, :, K:], true_future))
        add("copy_last_psnr", _psnr(np.broadcast_to(frames[:, :, K - 1:K], true_future.shape), true_future))
        shuffled = actions[np.roll(np.arange(len(actions)), 1)]
        pred_s, _ = run(params, frames, shuffled, stride, k1, modes.FD, 0)  # same noise, wrong actions
        add("fd_shuffled_psnr", _psnr(np.asarray(pred_s)[:, :, K:], true_future))
        _, act = run_mean(params, frames, np.zeros_like(actions), stride, k2, modes.ID, 0)
        add("id_mse", float(np.mean((np.asarray(act) - actions) ** 2)))
        _, act = run(params, frames, np.zeros_like(actions), stride, k2, modes.ID, 0)
        add("id_sample_mse", float(np.mean((np.asarray(act) - actions) ** 2)))
        add("mean_action_mse", float(np.mean(actions ** 2)))
        kept = int(jax.random.randint(k3, (), 0, frames.shape[1]))
        pred_c, _ = run(params, frames, actions, stride, k4, modes.CVI, kept)
        others = [v for v in range(frames.shape[1]) if v != kept]
        mean_frame = true_future[:, others].mean(axis=(0, 2), keepdims=True).round().astype(np.uint8)
        add("cvi_psnr", _psnr(np.asarray(pred_c)[:, others, K:], true_future[:, others]))
        add("mean_frame_psnr", _psnr(np.broadcast_to(mean_frame, true_future[:, others].shape),
                                     true_future[:, others]))
    return {k: float(np.mean(v)) for k, v in acc.items()}


def summary(m: dict[str, float]) -> str:
    return "\n".join([
        f"forward dynamics : {m['fd_psnr']:.2f} dB   (repeat last frame {m['copy_last_psnr']:.2f} dB, "
        f"shuffled actions {m['fd_shuffled_psnr']:.2f} dB)",
        f"inverse dynamics : action MSE {m['id_mse']:.3f}, sampled {m['id_sample_mse']:.3f}   "
        f"(mean action {m['mean_action_mse']:.3f})",
        f"inpainting       : {m['cvi_psnr']:.2f} dB   (mean frame {m['mean_frame_psnr']:.2f} dB)",
    ])
