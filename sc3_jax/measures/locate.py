"""Where a thing is in a frame: the centroid of its pixels, and the robot-agnostic arm locator (the pixels that differ
from the episode's temporal median: the median erases what moves, and on a table what moves is mostly the arm).

A locator (``benchmark.Locators``) maps frames uint8 [V, T, H, W, 3] and the views' names to image positions
float [V, T, 2] ((row, col) in pixels), nan where it cannot tell. numpy only."""
from __future__ import annotations

import numpy as np

MIN_PIXELS = 3  # fewer pixels than this say nothing about where a thing is (a 64x64 block is ~10-30 pixels)


def centroid(mask: np.ndarray, min_pixels: int = MIN_PIXELS) -> np.ndarray:
    """(row, col) mean of the True pixels of ``mask`` [..., H, W] -> float [..., 2]; nan with fewer than
    ``min_pixels``."""
    m = np.asarray(mask, bool)
    H, W = m.shape[-2:]
    n = m.sum((-2, -1)).astype(np.float64)
    rows = (m.sum(-1) * np.arange(H)).sum(-1) / np.maximum(n, 1)
    cols = (m.sum(-2) * np.arange(W)).sum(-1) / np.maximum(n, 1)
    out = np.stack([rows, cols], -1)
    out[n < min_pixels] = np.nan
    return out


def colour_mask(frames: np.ndarray, colours: np.ndarray, tol: float = 0.07, min_brightness: float = 120.0
                ) -> np.ndarray:
    """bool [..., H, W]: pixels whose chromaticity (r, g, b over their sum: shading-invariant) lies within ``tol``
    of one of ``colours`` [K, 3], brightness at least ``min_brightness`` (the rule ``permanence.pixels_of``
    counts; here the pixels themselves, to say where they are)."""
    c = np.asarray(colours, np.float32)
    c = c / c.sum(-1, keepdims=True)
    x = np.asarray(frames, np.float32)
    s = x.sum(-1, keepdims=True)
    d = np.linalg.norm((x / np.maximum(s, 1.0))[..., None, :] - c, axis=-1).min(-1)
    return (d < tol) & (s[..., 0] >= min_brightness)


def third_person(views) -> np.ndarray:
    """bool [V]: the views that stay put (a wrist camera moves with the arm, so a position in it is no position)."""
    return np.array(["wrist" not in v for v in views])


def masked_views(positions: np.ndarray, views) -> np.ndarray:
    """``positions`` [V, T, 2] with the wrist views' set to nan."""
    out = np.array(positions, np.float64)
    out[~third_person(views)] = np.nan
    return out


def median_arm(median: np.ndarray, threshold: float, min_pixels: int = MIN_PIXELS):
    """The default arm locator of one episode: the centroid of the pixels whose any channel differs from the
    episode's temporal ``median`` [V, H, W, 3] by more than ``threshold`` ([-1, 1] units), third-person views only."""
    med = np.asarray(median, np.float64)

    def locate(frames: np.ndarray, views) -> np.ndarray:
        diff = np.abs(np.asarray(frames, np.float64) - med[:, None]) / 127.5  # [V, T, H, W, 3]
        return masked_views(centroid(np.any(diff > threshold, -1), min_pixels), views)
    return locate
