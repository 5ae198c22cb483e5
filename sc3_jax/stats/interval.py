"""The percentile interval of bootstrap draws, a point estimate summarised with it, and the Wilson interval of a rate.

The point estimate comes from the full sample, the interval from the draws' percentiles: the percentile bootstrap,
which needs no assumption about the statistic's distribution (r and MMRV are bounded and skewed near their limits).
"""
from __future__ import annotations

import numpy as np


def percentile(draws: np.ndarray, level: float = 0.95) -> dict:
    """{"lo", "hi", "nan_draws"}: the (1 - level) / 2 and (1 + level) / 2 percentiles of bootstrap draws [B].

    ``nan`` draws (r of a constant vector, a rate no rollout was drawn for) are left out and counted, so a reader
    sees how many draws the interval stands on; lo and hi are nan when every draw is."""
    d = np.asarray(draws, np.float64)
    ok = d[~np.isnan(d)]
    a = (1.0 - level) / 2.0 * 100.0
    lo, hi = (np.percentile(ok, [a, 100.0 - a]) if len(ok) else (np.nan, np.nan))
    return {"lo": float(lo), "hi": float(hi), "nan_draws": int(len(d) - len(ok))}


def summary(point: float, draws: np.ndarray, level: float = 0.95) -> dict:
    """{"value", "lo", "hi", "nan_draws"}: a point estimate (from the full sample) with the :func:`percentile`
    interval of its draws."""
    return {"value": float(point), **percentile(draws, level)}


def wilson(successes: int, n: int, level: float = 0.95) -> dict:
    """{"lo", "hi"}: the Wilson score interval of a success rate, ``successes`` of ``n`` Bernoulli trials (within
    [0, 1] and never of zero width at 0 or n successes, unlike the normal approximation). ``n`` = 0: both nan."""
    from statistics import NormalDist

    if n <= 0:
        return {"lo": float("nan"), "hi": float("nan")}
    if not 0 <= successes <= n:
        raise ValueError(f"wilson: {successes} successes of {n} trials")
    z = NormalDist().inv_cdf((1.0 + level) / 2.0)
    p, z2 = successes / n, z * z
    centre = (p + z2 / (2 * n)) / (1 + z2 / n)
    half = z / (1 + z2 / n) * np.sqrt(p * (1 - p) / n + z2 / (4 * n * n))
    return {"lo": float(max(0.0, centre - half)), "hi": float(min(1.0, centre + half))}
