"""Seeded degradations of real frames, the ways generated frames differ from rendered ones: soft (blur), patchy
artefacts (noise on random patches, the tokenizer's patch grid) and colour drift (a per-rollout channel gain and
offset). The sweep scores real rollouts on each degraded copy too, so the report shows how far the perception
scorer's agreement with physics holds on frames that look generated.

Every function is pure numpy on uint8 frames [V, T, H, W, 3]; the draw depends only on ``seed`` (the simulator
seed of the rollout), so a resumed sweep degrades identically.
"""
from __future__ import annotations

import numpy as np

PATCH = 8  # pixels: the world model's patch size at 64x64


def blur(frames: np.ndarray, radius: int = 1) -> np.ndarray:
    """Box blur of width 2 * radius + 1 in H and W (edge-padded)."""
    x = np.asarray(frames, np.float32)
    k = 2 * radius + 1
    pad = np.pad(x, [(0, 0)] * (x.ndim - 3) + [(radius, radius), (radius, radius), (0, 0)], mode="edge")
    h, w = x.shape[-3], x.shape[-2]
    out = sum(pad[..., i:i + h, j:j + w, :] for i in range(k) for j in range(k)) / (k * k)
    return np.clip(np.round(out), 0, 255).astype(np.uint8)


def patch_noise(frames: np.ndarray, seed: int, fraction: float = 0.1, sigma: float = 40.0) -> np.ndarray:
    """Gaussian noise (``sigma`` grey levels) on a random ``fraction`` of the PATCH x PATCH patches of every frame."""
    rng = np.random.default_rng([seed, 1])
    x = np.asarray(frames, np.float32)
    *lead, h, w, c = x.shape
    hit = rng.random((*lead, h // PATCH, w // PATCH)) < fraction
    mask = np.repeat(np.repeat(hit, PATCH, -2), PATCH, -1)[..., None]
    mask = np.pad(mask, [(0, 0)] * len(lead) + [(0, h - mask.shape[-3]), (0, w - mask.shape[-2]), (0, 0)])
    x = x + mask * rng.normal(0.0, sigma, x.shape)
    return np.clip(np.round(x), 0, 255).astype(np.uint8)


def colour_shift(frames: np.ndarray, seed: int, gain: float = 0.1, offset: float = 15.0) -> np.ndarray:
    """One random per-channel gain in [1 - gain, 1 + gain] and offset in [-offset, offset] for the whole rollout."""
    rng = np.random.default_rng([seed, 2])
    g = rng.uniform(1 - gain, 1 + gain, 3)
    o = rng.uniform(-offset, offset, 3)
    return np.clip(np.round(np.asarray(frames, np.float32) * g + o), 0, 255).astype(np.uint8)


def all_kinds(frames: np.ndarray, seed: int) -> dict[str, np.ndarray]:
    return {"blur": blur(frames), "patch_noise": patch_noise(frames, seed), "colour_shift": colour_shift(frames, seed)}
