"""The percentile interval of bootstrap draws, and a point estimate summarised with it.

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
