"""The policy-blind floor: the score of an evaluator that knows each criterion's average real success rate in a
split but nothing about the policies, so it gives every policy the same rates.

It is the floor a world model's r and MMRV are read against, and not a low one: pooling criteria gives it a high r
(language following is easy for every policy, placing hard), so "r = 0.8" means little until it beats this guess.
"""
from __future__ import annotations

import warnings

import numpy as np


def policy_blind(rates: np.ndarray, groups: list[str]) -> np.ndarray:
    """Rates [B, P, C] -> the floor's rates [B, P, C]: every policy gets the mean rate of its group's policies
    (``groups[p]``: policy p's split) per criterion and draw, over the policies with a rate (``nanmean``)."""
    out = np.empty_like(rates)
    with warnings.catch_warnings():  # a split with no rollout in a draw (a partial sweep) is nan, said elsewhere
        warnings.simplefilter("ignore", RuntimeWarning)
        for s in set(groups):
            ps = [p for p, x in enumerate(groups) if x == s]
            out[:, ps] = np.nanmean(rates[:, ps], axis=1, keepdims=True)
    return out
