"""Paired bootstrap intervals for faithfulness (Pearson r, MMRV) over initial conditions.

A sweep's numbers are means over a few initial conditions per policy, so sampling noise alone moves r by about
+-0.1 at 10 conditions. The interval resamples the *initial conditions* (with replacement), the unit that was
sampled: every policy of a split -- and the evaluator and the real rollouts, which share seeds -- sees the same
resampled set (a paired bootstrap), then the per-(policy, criterion) success rates, r and MMRV are recomputed from
the resampled set. The 95% interval is the 2.5/97.5 percentile of the draws (``nan`` draws -- r of a constant
vector -- are left out and counted).

Data layout (plain numpy, vectorised over draws):

    passes  float [P, n, C]   objects passing criterion c cumulatively, policy p, initial condition i
    counts  float [P, n]      objects scored for (p, i); 0 marks a missing rollout (it then weighs nothing)

    rates(passes, counts, w) = sum_i w[b, i] passes[p, i, c] / sum_i w[b, i] counts[p, i]  -> [B, P, C]

where ``w`` [B, n] are the multiplicities of each initial condition in draw b (``multiplicities``). The
multiplicities come from a ``numpy.random.default_rng(seed)``: the same seed gives the same intervals.
"""
from __future__ import annotations

import numpy as np


def multiplicities(n: int, draws: int, seed: int) -> np.ndarray:
    """[draws, n] counts of each of ``n`` initial conditions in ``draws`` resamples of size n with replacement."""
    if n < 1 or draws < 1:
        raise ValueError(f"bootstrap: need n >= 1 initial conditions and draws >= 1, got n={n}, draws={draws}")
    idx = np.random.default_rng(seed).integers(0, n, size=(draws, n))
    return counts_of(idx, n)


def counts_of(idx: np.ndarray, n: int) -> np.ndarray:
    """Resampled indices [B, n] -> multiplicities [B, n]."""
    idx = np.asarray(idx)
    w = np.zeros((idx.shape[0], n))
    np.add.at(w, (np.arange(idx.shape[0])[:, None], idx), 1.0)
    return w


def rates(passes: np.ndarray, counts: np.ndarray, w: np.ndarray) -> np.ndarray:
    """Success rates [B, P, C] of every draw (see the module docstring); nan where a policy drew no rollout."""
    num = np.einsum("bn,pnc->bpc", w, np.asarray(passes, np.float64))
    den = np.einsum("bn,pn->bp", w, np.asarray(counts, np.float64))[..., None]
    with np.errstate(invalid="ignore", divide="ignore"):
        return np.where(den > 0, num / np.where(den > 0, den, 1.0), np.nan)


def pearson(s: np.ndarray, r: np.ndarray) -> np.ndarray:
    """Pearson r along the last axis, [..., K] x [..., K] -> [...]; nan where either side is constant (as
    ``metrics.pearson``) or has a nan."""
    s, r = np.asarray(s, np.float64), np.asarray(r, np.float64)
    x, y = s - s.mean(-1, keepdims=True), r - r.mean(-1, keepdims=True)
    sxx, syy = (x * x).sum(-1), (y * y).sum(-1)
    const = np.all(s == s[..., :1], -1) | np.all(r == r[..., :1], -1) | (sxx == 0) | (syy == 0)
    with np.errstate(invalid="ignore", divide="ignore"):
        v = (x * y).sum(-1) / np.sqrt(np.where(const, 1.0, sxx * syy))
    return np.where(const | np.isnan(v), np.nan, np.clip(v, -1.0, 1.0))


def mmrv(s: np.ndarray, r: np.ndarray) -> np.ndarray:
    """MMRV along the last axis (``metrics.mmrv``'s definition, sizes from ``r``), [..., K] x [..., K] -> [...];
    nan where an input has a nan."""
    s, r = np.asarray(s, np.float64), np.asarray(r, np.float64)
    violation = (s[..., :, None] > s[..., None, :]) != (r[..., :, None] > r[..., None, :])
    size = np.abs(r[..., :, None] - r[..., None, :])
    out = np.max(np.where(violation, size, 0.0), -1).mean(-1)
    return np.where(np.isnan(s).any(-1) | np.isnan(r).any(-1), np.nan, out)


def interval(draws: np.ndarray, level: float = 0.95) -> dict:
    """Percentile interval of bootstrap draws [B]: {"lo", "hi", "nan_draws"} (nan draws left out; lo/hi are nan when
    every draw is)."""
    d = np.asarray(draws, np.float64)
    ok = d[~np.isnan(d)]
    a = (1.0 - level) / 2.0 * 100.0
    lo, hi = (np.percentile(ok, [a, 100.0 - a]) if len(ok) else (np.nan, np.nan))
    return {"lo": float(lo), "hi": float(hi), "nan_draws": int(len(d) - len(ok))}


def summary(point: float, draws: np.ndarray, level: float = 0.95) -> dict:
    """A point estimate (from the full sample) with the percentile interval of its draws."""
    return {"value": float(point), **interval(draws, level)}
