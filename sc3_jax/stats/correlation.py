"""Pearson correlation between evaluator and real success rates, for one vector pair or a batch of bootstrap draws.

One definition serves both shapes because the report puts a point estimate beside the interval of its draws: were
the two computed by different code, the point could fall outside its own interval by rounding alone.
"""
from __future__ import annotations

import numpy as np


def pearson(evaluator, real) -> np.ndarray:
    """Pearson r along the last axis: [..., K] x [..., K] -> [...] (a numpy scalar for two vectors).

    ``r = sum(x*y) / sqrt(sum(x^2) * sum(y^2))`` with ``x = evaluator - mean(evaluator)``,
    ``y = real - mean(real)`` (SIMPLER's definition, Li et al. 2024), clipped to [-1, 1] against rounding.
    Symmetric in its arguments.

    ``nan`` where either side is constant (all its values exactly equal), without a numpy warning: r is 0/0 there,
    and a constant vector carries no ranking, so no value would be true -- 0 would claim "unrelated", which is wrong
    when both are constant and flattering when a blind evaluator meets varying real rates; +-1 would be invented.
    ``nan`` keeps a table honest and poisons any average it enters (MMRV stays defined and is the number to read
    then). Also ``nan`` where the deviations are not constant but their squares underflow to 0, and where an input
    holds a nan (a bootstrap draw in which a policy drew no rollout): the draw is left out of the interval, counted.

    No input validation: ``metrics.pearson`` checks lengths and finiteness for its callers; bootstrap draws need
    the nan to pass through.
    """
    s, r = np.asarray(evaluator, np.float64), np.asarray(real, np.float64)
    x, y = s - s.mean(-1, keepdims=True), r - r.mean(-1, keepdims=True)
    sxx, syy = (x * x).sum(-1), (y * y).sum(-1)
    # the product under one root, as the formula reads and as every bootstrap interval has been computed
    # (sqrt(sxx) * sqrt(syy) differs in the last bit for about a third of inputs); a product that underflows is
    # undefined, like a zero deviation
    den = sxx * syy
    const = np.all(s == s[..., :1], -1) | np.all(r == r[..., :1], -1) | (sxx == 0) | (syy == 0) | (den == 0)
    with np.errstate(invalid="ignore", divide="ignore"):
        v = (x * y).sum(-1) / np.sqrt(np.where(const, 1.0, den))
    return np.where(const | np.isnan(v), np.nan, np.clip(v, -1.0, 1.0))[()]
