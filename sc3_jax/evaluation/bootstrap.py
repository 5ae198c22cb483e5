"""Success rates of resampled initial conditions: the layout the paired bootstrap of faithfulness is computed in.

A sweep's numbers are means over a few initial conditions per policy, so sampling noise alone moves r by about
+-0.1 at 10 conditions. The interval resamples the *initial conditions* (with replacement), the unit that was
sampled: every policy of a split -- and the evaluator and the real rollouts, which share seeds -- sees the same
resampled set (a paired bootstrap), then the per-(policy, criterion) success rates, r and MMRV are recomputed from
the resampled set. The 95% interval is the 2.5/97.5 percentile of the draws (``nan`` draws -- r of a constant
vector -- are left out and counted). The statistics are ``sc3_jax.stats``' (``correlation``, ``mmrv``,
``interval``); the draws its ``resample.multiplicities``.

Data layout (plain numpy, vectorised over draws):

    passes  float [P, n, C]   objects passing criterion c cumulatively, policy p, initial condition i
    counts  float [P, n]      objects scored for (p, i); 0 marks a missing rollout (it then weighs nothing)

    rates(passes, counts, w) = sum_i w[b, i] passes[p, i, c] / sum_i w[b, i] counts[p, i]  -> [B, P, C]

where ``w`` [B, n] are the multiplicities of each initial condition in draw b (``stats.resample.multiplicities``,
from a ``numpy.random.default_rng(seed)``: the same seed gives the same intervals; all ones for the full sample).
"""
from __future__ import annotations

import numpy as np


def rates(passes: np.ndarray, counts: np.ndarray, w: np.ndarray) -> np.ndarray:
    """Success rates [B, P, C] of every draw (see the module docstring); nan where a policy drew no rollout."""
    num = np.einsum("bn,pnc->bpc", w, np.asarray(passes, np.float64))
    den = np.einsum("bn,pn->bp", w, np.asarray(counts, np.float64))[..., None]
    with np.errstate(invalid="ignore", divide="ignore"):
        return np.where(den > 0, num / np.where(den > 0, den, 1.0), np.nan)
