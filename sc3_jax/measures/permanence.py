"""Object permanence: how much of the scene's objects an imagined rollout keeps, per view and over time, against the
real rollout from the same initial condition (``sc3 diagnose``: open loop against the recorded episode; the sweep
report: closed loop against the real rollout of the same condition).

What counts as "the objects" is the benchmark's to say: a *scene measure* maps frames uint8 [V, T, H, W, 3] to the
amount of object in each frame, float [V, T] (the simulated benchmark's counts the pixels of its objects' colours,
``benchmarks/bussing/scorers.object_pixels``; :func:`pixels_of` does it for any list of colours). Measures that need
no benchmark were tried on README command 1's store first (2026-11-28, 42 conditions): the pixels far from the
table's colour, and the frames' gradient energy, both read about 1 (0.8 to 1.6 per view) at every time from 1 to
12 s while the videos show the objects fading -- the containers, the wall and the arm, which do persist, outweigh a
few small objects -- so they would say "kept" where a reader sees the objects go.

``kept`` at a time = the imagined amount summed over rollouts / the real amount summed over the same rollouts: near 1
the objects survive, toward 0 they have faded. Things that moved elsewhere still count (in closed loop the objects
need not be where the real ones are; their presence is measured, not their place). Intervals: a bootstrap over
rollouts. numpy only.
"""
from __future__ import annotations

from collections.abc import Callable, Iterable

import numpy as np

from sc3_jax.stats import resample

SECONDS = (1.0, 2.0, 4.0, 6.0, 12.0)  # the times the report and diagnose read
SceneMeasure = Callable[[np.ndarray], np.ndarray]  # frames uint8 [V, T, H, W, 3] -> amount of object [V, T]


def pixels_of(frames: np.ndarray, colours: np.ndarray, tol: float = 0.07, min_brightness: float = 120.0
              ) -> np.ndarray:
    """Fraction of pixels whose chromaticity (r, g, b over their sum: shading-invariant) lies within ``tol`` of one
    of ``colours`` [K, 3] (any scale), brightness (r + g + b) at least ``min_brightness``: frames [..., H, W, 3] ->
    float [...]."""
    c = np.asarray(colours, np.float32)
    c = c / c.sum(-1, keepdims=True)
    x = np.asarray(frames, np.float32)
    s = x.sum(-1, keepdims=True)
    d = np.linalg.norm((x / np.maximum(s, 1.0))[..., None, :] - c, axis=-1).min(-1)
    return ((d < tol) & (s[..., 0] >= min_brightness)).mean(axis=(-2, -1))


def _kept(im: np.ndarray, re: np.ndarray) -> float:
    den = np.nansum(re)
    return float(np.nansum(im) / den) if den > 0 else float("nan")


def summary(im: np.ndarray, re: np.ndarray, times: dict[str, int], views: list[str], draws: int = 2000,
            seed: int = 0) -> dict:
    """``im``, ``re`` [R, V, n] (rollouts; nan where a rollout has no frame at that index), ``times``: label -> frame
    index. Per label: {"rollouts", "kept": {"all views" and each view: {"value", "lo", "hi"}}} (95%
    bootstrap over rollouts); a time no rollout reaches is left out."""
    im, re = np.asarray(im, float), np.asarray(re, float)
    # each draw as a row of rollout indices: kept is recomputed (nan-aware) on the rollouts it picked
    idx = resample.indices(len(im), draws, seed) if len(im) else np.zeros((0, 0), int)
    out = {}
    for label, k in times.items():
        if k >= im.shape[2]:
            continue
        a, b = im[:, :, k], re[:, :, k]
        ok = ~np.isnan(a).any(1) & ~np.isnan(b).any(1)
        if not ok.any():
            continue
        a, b = np.where(ok[:, None], a, np.nan), np.where(ok[:, None], b, np.nan)
        kept = {}
        for name, cols in [("all views", slice(None))] + [(v, slice(i, i + 1)) for i, v in enumerate(views)]:
            x, y = a[:, cols], b[:, cols]
            boot = [_kept(x[d], y[d]) for d in idx]
            lo, hi = np.nanpercentile(boot, [2.5, 97.5]) if boot else (float("nan"), float("nan"))
            kept[name] = {"value": _kept(x, y), "lo": float(lo), "hi": float(hi)}
        out[label] = {"rollouts": int(ok.sum()), "kept": kept}
    return out


def times(fps: float, seconds: Iterable[float] = SECONDS) -> dict[str, int]:
    """``{"1 s": frame index, ...}`` at ``fps`` frames per second (index 0: the last context frame)."""
    return {f"{s:g} s": int(round(s * fps)) for s in seconds}


def from_pairs(pairs: Iterable[tuple[np.ndarray, np.ndarray]], measure: SceneMeasure, fps: float, views: list[str],
               draws: int = 2000, seed: int = 0) -> dict | None:
    """The summary over (real frames at the model's rate [V, n, ...], imagined frames [V, n', ...]) pairs, read at
    :data:`SECONDS` only (the measure runs on those frames alone); None when there is none."""
    at = times(fps)
    wanted = sorted(set(at.values()))
    measured = [measure_pair(real, imagined, measure, wanted) for real, imagined in pairs]
    if not measured:
        return None
    return summary(np.stack([a for a, _ in measured]), np.stack([b for _, b in measured]),
                   {label: wanted.index(k) for label, k in at.items()}, views, draws, seed)


def measure_pair(real: np.ndarray, imagined: np.ndarray, measure: SceneMeasure, wanted: list[int]
                 ) -> tuple[np.ndarray, np.ndarray]:
    """(imagined, real) amounts [V, len(wanted)] at the frame indices ``wanted`` (nan past either rollout's end)."""
    n = min(real.shape[1], imagined.shape[1])
    ks = [k for k in wanted if k < n]
    a, b = np.full((real.shape[0], len(wanted)), np.nan), np.full((real.shape[0], len(wanted)), np.nan)
    if ks:
        a[:, :len(ks)] = measure(imagined[:, ks])
        b[:, :len(ks)] = measure(real[:, ks])
    return a, b
