"""The bootstrap's resampling: which units (initial conditions, rollouts, episodes) each draw takes, with replacement.

A draw resamples the unit that was sampled -- n units, n picks with replacement -- and a statistic is recomputed on
every draw; its spread is the sampling noise. Every draw comes from ``numpy.random.default_rng(seed)``, so the same
seed gives the same draws, and the numbers a report prints are reproducible. The order in which the generator is
consumed is part of those numbers: these functions draw exactly as the report always has, and changing a call here
(its shape or its order) changes every interval printed since.
"""
from __future__ import annotations

import numpy as np


def indices(n: int, draws: int, seed: int) -> np.ndarray:
    """[draws, n] indices into ``n`` units: row b is draw b's resample of size n with replacement (uniform picks,
    ``Generator.integers``). A statistic that is not a weighted sum over units (a ratio of sums taken per draw,
    ``permanence``) indexes with the rows; one that is, uses :func:`multiplicities`."""
    return np.random.default_rng(seed).integers(0, n, size=(draws, n))


def counts_of(idx: np.ndarray, n: int) -> np.ndarray:
    """Resampled indices [B, m] -> multiplicities [B, n]: how often each of the n units is in each draw."""
    idx = np.asarray(idx)
    w = np.zeros((idx.shape[0], n))
    np.add.at(w, (np.arange(idx.shape[0])[:, None], idx), 1.0)
    return w


def multiplicities(n: int, draws: int, seed: int) -> np.ndarray:
    """[draws, n] counts of each of ``n`` units in ``draws`` resamples of size n with replacement: the
    :func:`indices` of the same seed, counted. A weighted sum with these weights is the statistic on the resample
    (``w @ x`` for a sum over units), vectorised over draws."""
    if n < 1 or draws < 1:
        raise ValueError(f"bootstrap: need n >= 1 units and draws >= 1, got n={n}, draws={draws}")
    return counts_of(indices(n, draws, seed), n)

