"""P(best): how often each policy ranks first over bootstrap draws, a tie for first split evenly among those tied.

Counting every tied policy as first would give two policies at 0.00 [0.00, 0.00] "first in 100% of draws" each: the
shares would sum past one and say nothing. Split, they sum to one over the draws where any policy has a score.
"""
from __future__ import annotations

import numpy as np


def p_first(scores: np.ndarray) -> np.ndarray:
    """[P]: the mean over draws of each policy's share of first place in ``scores`` [B, P] (higher is better); the
    policies tied for the top of a draw share it (1/k each); a nan score (no rollout drawn) holds none."""
    s = np.asarray(scores, np.float64)
    ok = ~np.isnan(s)
    best = np.where(ok, s, -np.inf).max(-1, keepdims=True)
    top = ok & (s == best)
    k = top.sum(-1, keepdims=True)
    return (top / np.maximum(k, 1)).mean(0)
