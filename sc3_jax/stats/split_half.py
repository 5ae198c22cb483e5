"""The split-half noise ceiling: how well the real data agrees with itself.

Without a second independent real set, split the real data at random into two halves and score one half's rates
against the other's, one random split per bootstrap draw. No evaluator can be expected to track the real rates
better than the real rates track themselves; the estimate is the ceiling at half the data per side, so it is
conservative (lower than at the full size). A split has no full-sample value: the point estimate is the median over
the splits (:func:`point`).

The splits come from ``numpy.random.default_rng(seed)`` in a fixed order (see ``resample``: the order is part of the
printed numbers).
"""
from __future__ import annotations

import numpy as np


def condition_halves(n: int, draws: int, seed: int) -> tuple[np.ndarray, np.ndarray]:
    """Weights (a, b) [draws, n] in {0, 1}: the two halves of a random split of n units (conditions), one split per
    draw, floor(n / 2) units each (one left out when n is odd, so the halves are equal). One split serves every
    policy (paired: each policy was rolled out on the same conditions)."""
    order = np.argsort(np.random.default_rng(seed).random((draws, n)), axis=1)
    a = np.zeros((draws, n))
    np.put_along_axis(a, order[:, :n // 2], 1.0, axis=1)
    b = np.zeros((draws, n))
    np.put_along_axis(b, order[:, n // 2:2 * (n // 2)], 1.0, axis=1)
    return a, b


def group_halves(sizes: list[int], draws: int, seed: int) -> list[tuple[np.ndarray, np.ndarray]]:
    """Per group g of ``sizes[g]`` units (each policy's own real episodes, not shared between policies), the index
    arrays (first, second) [draws, sizes[g] // 2] of its two halves in each draw: a random permutation per group
    and draw, drawn group by group, draw by draw."""
    rng = np.random.default_rng(seed)
    out = []
    for m in sizes:
        h = m // 2
        perms = np.array([rng.permutation(m) for _ in range(draws)], dtype=int).reshape(draws, m)
        out.append((perms[:, :h], perms[:, h:2 * h]))
    return out


def group_half_means(groups: list[np.ndarray], draws: int, seed: int) -> tuple[np.ndarray, np.ndarray]:
    """Means [draws, G, C] of each group's two halves (:func:`group_halves`), ``groups[g]`` its units' values
    [m_g, C] (a policy's real episodes' outcomes): every group has its own split in each draw."""
    a, b = (np.zeros((draws, len(groups), groups[0].shape[1])) for _ in range(2))
    for g, (x, (first, second)) in enumerate(zip(groups, group_halves([len(x) for x in groups], draws, seed))):
        for d in range(draws):  # one mean per draw, as the report's numbers were always made (bit for bit)
            a[d, g], b[d, g] = x[first[d]].mean(0), x[second[d]].mean(0)
    return a, b


def point(draws: np.ndarray) -> float:
    """The ceiling's point estimate: the median of the splits' values [B] (nan ones left out; nan when all are)."""
    d = np.asarray(draws, np.float64)
    ok = d[~np.isnan(d)]
    return float(np.median(ok)) if len(ok) else float("nan")
