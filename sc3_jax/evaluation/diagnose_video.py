"""``sc3 diagnose``'s frame checks: pooled PSNR over whole frames and over moving pixels, against the copy-last,
copy-first and temporal-median baselines, one chunk ahead from real context (teacher-forced) and open loop at fixed
horizons (drift). Numpy only; the rollouts that produce the frames run in ``diagnose.py``.

PSNR over a set of frames is the PSNR of their pooled squared error (``10 log10(255^2 n / SSE)``): defined whenever
anything differs (no per-frame inf to drop), frames without moving pixels simply add nothing to the moving-pixel
figure, and baselines and the model are pooled over exactly the same pixels."""
from __future__ import annotations

import math

import numpy as np

from sc3_jax.measures import metrics

PREDICTORS = ("model", "copy_last", "copy_first", "median")


def moving_mask(target: np.ndarray, reference: np.ndarray, threshold: float) -> np.ndarray:
    """uint8 [..., H, W, 3] frames -> bool [..., H, W]: pixels where any channel of ``target`` differs from
    ``reference`` by more than ``threshold`` in [-1, 1] units (one grey level = 1 / 127.5)."""
    d = np.abs(np.asarray(target, np.int16) - np.asarray(reference, np.int16)) / 127.5
    return np.any(d > threshold, axis=-1)


def squared_errors(pred: np.ndarray, target: np.ndarray, mask: np.ndarray) -> np.ndarray:
    """[whole SSE, whole count, moving SSE, moving count] summed over every leading axis (counts in values:
    pixels x channels). ``pred`` may be float (the temporal median) or uint8, on the 0..255 scale."""
    e = (np.asarray(pred, np.float64) - np.asarray(target, np.float64)) ** 2  # [..., H, W, C]
    m = np.asarray(mask, bool)[..., None]
    return np.array([e.sum(), e.size, (e * m).sum(), m.sum() * e.shape[-1]], np.float64)


def psnr_from_sums(sse: float, n: float) -> float:
    """PSNR (dB, 0..255 scale) of a pooled squared error: inf when nothing differs, nan when nothing was counted."""
    if n <= 0:
        return math.nan
    if sse <= 0:
        return math.inf
    return float(metrics.psnr_from_mse(sse / n))


def temporal_median(frames: np.ndarray) -> np.ndarray:
    """uint8 [T, H, W, 3] -> float64 [H, W, 3]: the per-pixel median over time ("erase the arm")."""
    return np.median(np.asarray(frames), axis=0)


class ErrorSums:
    """Pooled squared errors per key (e.g. (view, horizon, predictor))."""

    def __init__(self):
        self.sums: dict[tuple, np.ndarray] = {}
        self.frames: dict[tuple, int] = {}

    def add(self, key: tuple, pred, target, mask):
        self.sums[key] = self.sums.get(key, np.zeros(4)) + squared_errors(pred, target, mask)
        self.frames[key] = self.frames.get(key, 0) + 1

    def psnr(self, key: tuple, region: str) -> float:
        s = self.sums.get(key)
        if s is None:
            return math.nan
        return psnr_from_sums(s[0], s[1]) if region == "whole" else psnr_from_sums(s[2], s[3])

    def moving_fraction(self, key: tuple) -> float:
        s = self.sums.get(key)
        return math.nan if s is None or s[1] == 0 else float(s[3] / s[1])


def tf_starts(eps, spec1, keep: int, stride: int) -> list[tuple[int, int]]:
    """(episode index, start frame) of every teacher-forced chunk: starts every ``keep`` model steps (the open-loop
    chunk cadence) while a whole chunk of targets exists."""
    from sc3_jax.rollout.rollout import max_offline_chunks
    out = []
    for e, ep in enumerate(eps):
        c = 0
        while max_offline_chunks(ep.length, spec1, c * keep * stride) >= 1:
            out.append((e, c * keep * stride))
            c += 1
    if not out:
        raise ValueError("no episode is long enough for one chunk from real context")
    return out


def shuffle_donors(samples, rng) -> list[int]:
    """For each sample the index of another sample whose action chunk it gets: from another episode when there is
    one (else another chunk of the same episode)."""
    ep = np.array([e for e, _ in samples])
    out = []
    for i in range(len(samples)):
        pool = np.flatnonzero(ep != ep[i])
        if not len(pool):
            pool = np.array([j for j in range(len(samples)) if j != i] or [i])
        out.append(int(rng.choice(pool)))
    return out


def add_horizon(sums: ErrorSums, key, pred, target, ctx_last, first, median, thr):
    """One target frame per view: model and baselines into ``sums[(*key, view, predictor)]``."""
    for v in range(target.shape[0]):
        m = moving_mask(target[v], ctx_last[v], thr)
        for p, x in (("model", pred[v]), ("copy_last", ctx_last[v]), ("copy_first", first[v]),
                     ("median", median[v])):
            sums.add((*key, v, p), x, target[v], m)


def add_chunk(sums: ErrorSums, targets, ctx_last, pred, pred_shuffled, first, median, thr):
    """A teacher-forced chunk: every predicted frame (offset i = 1..l'), model, shuffled and baselines."""
    for i in range(targets.shape[1]):
        add_horizon(sums, ("tf", i), pred[:, i], targets[:, i], ctx_last, first, median, thr)
        for v in range(targets.shape[0]):
            sums.add(("tf", i, v, "shuffled"), pred_shuffled[v, i], targets[v, i],
                     moving_mask(targets[v, i], ctx_last[v], thr))


def _region_table(sums: ErrorSums, key, predictors) -> dict:
    return {p: {"whole": sums.psnr((*key, p), "whole"), "moving": sums.psnr((*key, p), "moving")}
            for p in predictors}


def tf_section(sums: ErrorSums, views, horizon_s: float, n: int, u) -> dict:
    """The teacher-forced result: per view, PSNR at the chunk's last frame and the curve over its frames."""
    last = max(k[1] for k in sums.sums)
    out = {"horizon_s": horizon_s, "n_chunks": n, "u_mean": float(np.mean(u)) if u else math.nan, "views": {}}
    for v, name in enumerate(views):
        psnr = _region_table(sums, ("tf", last, v), PREDICTORS + ("shuffled",))
        out["views"][name] = {
            "moving_fraction": sums.moving_fraction(("tf", last, v, "model")), "psnr": psnr,
            "true_minus_shuffled_moving": psnr["model"]["moving"] - psnr["shuffled"]["moving"],
            # per frame offset 1..l' (s = offset / control_hz): the whole chunk's curve
            "curve_moving": {p: [sums.psnr(("tf", i, v, p), "moving") for i in range(last + 1)]
                             for p in PREDICTORS + ("shuffled",)}}
    return out


def drift_section(sums: ErrorSums, views, horizons, steps) -> dict:
    """The open-loop result: per view and horizon, PSNR over the episodes that last that long."""
    out = {"horizons_s": list(horizons), "views": {}}
    for v, name in enumerate(views):
        rows = []
        for hi, h in enumerate(horizons):
            key = ("drift", hi, v, "model")
            n = sums.frames.get(key, 0)  # one frame per episode that lasts this long
            rows.append({"horizon_s": h, "step": steps[hi], "n_episodes": n,
                         "moving_fraction": sums.moving_fraction(key),
                         "psnr": _region_table(sums, ("drift", hi, v), PREDICTORS)})
        out["views"][name] = rows
    return out
