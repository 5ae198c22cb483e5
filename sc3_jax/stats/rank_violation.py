"""MMRV, the Mean Maximum Rank Violation (SIMPLER): how badly the evaluator's ranking of the points breaks the real
one, for one vector pair or a batch of bootstrap draws (one definition for both, as ``correlation.pearson``)."""
from __future__ import annotations

import numpy as np


def mmrv(evaluator, real) -> np.ndarray:
    """MMRV along the last axis: [..., K] x [..., K] -> [...] (a numpy scalar for two vectors); lower is better.

    ``MMRV = (1/N) * sum_i max_j |real_i - real_j| * 1[(evaluator_i > evaluator_j) != (real_i > real_j)]``, max over
    all j (j = i never violates; an empty max is 0), SIMPLER's definition (Li et al. 2024).

    NOT symmetric: the *size* of a violation always comes from ``real`` (what a wrong ranking costs is the real gap
    it hides), and ``>`` is strict, so
      * evaluator ties over different real values are violations (at the point whose real value is larger: the
        evaluator failed to rank a real gap), sized by that gap;
      * real ties under different evaluator values are violations of size 0 (they cost nothing);
      * constant evaluator: MMRV = mean(real - min(real)); constant real: 0 whatever the evaluator says.
    A perfect ranking (strictly order-preserving, ties matching) gives 0; the result is at most max(real) -
    min(real), so for success rates it lies in [0, 1]. ``nan`` where an input holds a nan (a bootstrap draw in
    which a policy drew no rollout). No input validation (``metrics.mmrv`` does it for its callers).
    """
    s, r = np.asarray(evaluator, np.float64), np.asarray(real, np.float64)
    violation = (s[..., :, None] > s[..., None, :]) != (r[..., :, None] > r[..., None, :])
    size = np.abs(r[..., :, None] - r[..., None, :])
    out = np.max(np.where(violation, size, 0.0), -1).mean(-1)
    # a comparison with nan is False, which would read as "no violation": say undefined instead
    return np.where(np.isnan(s).any(-1) | np.isnan(r).any(-1), np.nan, out)[()]
