"""Faithfulness of every evaluator row, each r and MMRV with a paired bootstrap 95% interval (``bootstrap.py``; the
statistics, the floor and the split-half ceiling are ``sc3_jax.stats``').

Rows (evaluators), each compared with a *reference* -- the real rollouts scored by physics (end to end) or by the
perception scorer (the same instrument that scores the imagined rollouts, the paper's protocol of one set of
annotators for both sides):

    offline        the world model replaying the real actions, scored by perception
    online         the policy inside the world model, untruncated (tau = inf)
    online_tau     the same rollouts cut at the calibrated tau* (``calibrate.py``), when the sweep calibrated one
    real_perception  the real rollouts scored by perception (reference physics only): the scorer's own share
                   (each of the rows above also carries ``vs_floor``: its paired difference to the floor)
    policy_blind   every policy gets its split's mean reference rate per criterion: the floor
    ceiling        an independent second set of real rollouts on other seeds, scored like the reference: how well
                   *the simulator itself* agrees with itself at this many conditions (the best any evaluator can
                   expect). Without a second set: the split-half estimate -- the evaluation conditions split at
                   random into halves, one half's rates against the other's, one split per draw -- which is the
                   ceiling at n/2 conditions per side, i.e. conservative (lower than at n).

Pairing: one resample of evaluation initial-condition indices per draw serves every policy, every split, every
evaluator and the reference; a rollout missing on either side of a comparison is left out of both. The second
real set is resampled independently (its seeds are other initial conditions).
"""
from __future__ import annotations

import math

import numpy as np

from sc3_jax.core.errors import UserError
from sc3_jax.evaluation import bootstrap
from sc3_jax.measures import metrics
from sc3_jax.stats import correlation, floor, interval, rank_first, rank_violation, resample, split_half

STATISTICS = (("pearson", correlation.pearson), ("mmrv", rank_violation.mmrv))  # each row's, in table order


def grid(recs: dict, policies: list[str], seeds: list[int], criteria, outcomes=lambda r: r["objects"]):
    """Records keyed (policy, seed) -> (passes [P, n, C] cumulative per criterion of ``criteria``, counts [P, n];
    0 = missing)."""
    passes = np.zeros((len(policies), len(seeds), len(criteria)))
    counts = np.zeros((len(policies), len(seeds)))
    for p, pol in enumerate(policies):
        for i, seed in enumerate(seeds):
            rec = recs.get((pol, seed))
            if rec is None:
                continue
            objs = outcomes(rec)
            counts[p, i] = len(objs)
            for o in objs:
                cum = metrics.cumulative_passes(o, criteria)
                passes[p, i] += [cum[c] for c in criteria]
    return passes, counts


def _points(rates: np.ndarray, split_of: list[str], split: str, criterion: int | None = None) -> np.ndarray:
    """rates [B, P, C] -> the points of one split (all policies for overall) [B, K]."""
    ps = [p for p, s in enumerate(split_of) if split == metrics.OVERALL or s == split]
    x = rates[:, ps]
    return (x if criterion is None else x[..., criterion:criterion + 1]).reshape(len(rates), -1)


def split_order(split_of: list[str]) -> list[str]:
    """The splits of ``split_of`` (each policy's, in the report's order) once each, then the pooled one."""
    return [*dict.fromkeys(s for s in split_of if s != metrics.OVERALL), metrics.OVERALL]


def compare(ev_point, re_point, ev_draws, re_draws, split_of: list[str], point_from_draws: bool = False,
            criteria=()) -> dict:
    """r and MMRV with intervals, per split (all criteria pooled) and per (split, criterion of ``criteria``).

    ev/re_point [1, P, C] (the full sample), ev/re_draws [B, P, C]. ``point_from_draws``: the value is the median
    of the draws (the split-half ceiling has no single full-sample value)."""
    out: dict = {"splits": {}, "per_criterion": {}}
    for split in split_order(split_of):
        for c in (None,) + tuple(range(len(criteria))):
            pts = [_points(x, split_of, split, c) for x in (ev_point, re_point, ev_draws, re_draws)]
            if pts[0].shape[1] < 2:
                continue
            cell = {"n": int(pts[0].shape[1])}
            for name, fn in STATISTICS:
                draws = fn(pts[2], pts[3])
                point = split_half.point(draws) if point_from_draws else float(fn(pts[0], pts[1])[0])
                cell[name] = interval.summary(point, draws)
            if c is None:
                out["splits"][split] = cell
            else:
                out["per_criterion"].setdefault(split, {})[criteria[c]] = cell
    return out


def difference(a_point, b_point, re_point, a_draws, b_draws, re_draws, split_of: list[str]) -> dict:
    """Paired difference of two evaluators per split (all criteria pooled): r(a) - r(b) and MMRV(a) - MMRV(b), each
    against the reference, all on the very same resample of conditions in every draw. Rates [1 or B, P, C]."""
    out = {}
    for split in split_order(split_of):
        pts = [_points(x, split_of, split) for x in (a_point, b_point, re_point, a_draws, b_draws, re_draws)]
        if pts[0].shape[1] < 2:
            continue
        out[split] = {name: interval.summary(float(fn(pts[0], pts[2])[0] - fn(pts[1], pts[2])[0]),
                                             fn(pts[3], pts[5]) - fn(pts[4], pts[5]))
                      for name, fn in STATISTICS}
    return out


def versus_floor(ev_point, re_point, ev_draws, re_draws, split_of: list[str]) -> dict:
    """Paired difference to the policy-blind floor (:func:`difference`): r > 0 and MMRV < 0 favour the evaluator.

    Reading an evaluator's interval against the floor's (the acceptance rule "lower bound above the floor's upper
    bound") ignores that both come from the same real rollouts; the paired difference does not, so it is the
    sharper test of "better than a guess". The floor is this comparison's: from the reference rates of the cases the
    evaluator is compared on (the floor row's own when nothing is missing)."""
    return difference(ev_point, floor.policy_blind(re_point, split_of), re_point, ev_draws,
                      floor.policy_blind(re_draws, split_of), re_draws, split_of)


def versus(reference, a, b, split_of: list[str], draws: int, seed: int) -> dict:
    """Paired difference of evaluator grids ``a`` - ``b`` (e.g. an ablation and the full recipe, swept against one
    real set), each (passes, counts) on the reference's seeds: a case missing on any of the three sides is left out
    of all three, and one resample per draw serves all (the multiplicities of :func:`evaluator_rows`)."""
    both = (reference[1] > 0) & (a[1] > 0) & (b[1] > 0)
    w, one = resample.multiplicities(both.shape[1], draws, seed), np.ones((1, both.shape[1]))
    masked = [(p * both[..., None], c * both) for p, c in (a, b, reference)]
    return difference(*[bootstrap.rates(p, c, one) for p, c in masked],
                      *[bootstrap.rates(p, c, w) for p, c in masked], split_of)


def evaluator_rows(reference, evaluators: dict, split_of: list[str], draws: int, seed: int,
                   ceiling=None, extra_vs_reference: dict | None = None, criteria=()) -> dict:
    """Every evaluator row against one reference (see the module docstring).

    reference: (passes, counts) of the real rollouts on the evaluation seeds, scored by the reference instrument;
    evaluators: {name: (passes, counts)} on the same seeds; ceiling: (passes, counts) of the second real set scored
    by the same instrument, or None (split-half); extra_vs_reference: more rows compared like evaluators;
    criteria: the names of the rates' last axis (each row's per-criterion cells)."""
    rp, rc = reference
    n = rc.shape[1]
    w = resample.multiplicities(n, draws, seed)
    one = np.ones((1, n))
    rows = {}
    for name, (ep, ec) in {**evaluators, **(extra_vs_reference or {})}.items():
        both = (ec > 0) & (rc > 0)
        if not both.any():
            continue
        # a case missing on either side leaves both: its passes as well as its counts (else rates exceed 1)
        (epm, ecm), (rpm, rcm) = ((x * both[..., None], c * both) for x, c in ((ep, ec), (rp, rc)))
        rates = [bootstrap.rates(epm, ecm, one), bootstrap.rates(rpm, rcm, one),
                 bootstrap.rates(epm, ecm, w), bootstrap.rates(rpm, rcm, w)]
        rows[name] = compare(*rates, split_of, criteria=criteria)
        rows[name]["vs_floor"] = versus_floor(*rates, split_of)
    re_point, re_draws = bootstrap.rates(rp, rc, one), bootstrap.rates(rp, rc, w)
    rows["policy_blind"] = compare(floor.policy_blind(re_point, split_of), re_point,
                                   floor.policy_blind(re_draws, split_of), re_draws, split_of, criteria=criteria)
    if ceiling is not None:
        cp, cc = ceiling
        w2 = resample.multiplicities(cc.shape[1], draws, seed + 1)
        rows["ceiling"] = compare(bootstrap.rates(cp, cc, np.ones((1, cc.shape[1]))), re_point,
                                  bootstrap.rates(cp, cc, w2), re_draws, split_of, criteria=criteria)
        rows["ceiling"]["method"] = f"second real set, {cc.shape[1]} conditions per policy"
    else:
        if n < 2:
            raise UserError("the split-half noise ceiling needs at least 2 evaluation conditions per policy; sweep "
                            "more (--episodes) or a second real set (--ceiling-episodes)")
        a, b = (bootstrap.rates(rp, rc, h) for h in split_half.condition_halves(n, draws, seed + 2))
        rows["ceiling"] = compare(a[:1], b[:1], a, b, split_of, point_from_draws=True, criteria=criteria)
        rows["ceiling"]["method"] = f"split-half: {n // 2} vs {n // 2} evaluation conditions (conservative)"
    return rows


def score(rates: np.ndarray, criteria: list[str], primary: str | None) -> np.ndarray:
    """[..., P, C] -> the ranking score [..., P]: the ``primary`` criterion's rate, else the mean over criteria."""
    return rates[..., list(criteria).index(primary)] if primary else np.nanmean(rates, -1)


def ranking(names, criteria, primary, point, draws, counts) -> list[dict]:
    """Policies best first by ``score``: each with its score and rates (95% intervals), its rank (ties share one),
    the interval of its rank over the bootstrap draws, and P(best) (the share of draws in which it ranks first, a tie
    for first split among those tied: ``stats.rank_first``).
    ``point`` [1, P, C] and ``draws`` [B, P, C] rates (``bootstrap.rates``), ``counts`` [P, n] rollouts."""
    point_score, sdraws = score(point[0], criteria, primary), score(draws, criteria, primary)  # [P], [B, P]
    with np.errstate(invalid="ignore"):
        ranks = 1 + (sdraws[:, None, :] > sdraws[:, :, None]).sum(-1)  # [B, P]: 1 + policies scoring higher
    key = np.nan_to_num(point_score, nan=-1.0)  # a policy without rollouts yet ranks last
    best = rank_first.p_first(sdraws)  # a tie for first is split, not counted as each one's win
    order = sorted(range(len(names)), key=lambda p: (-key[p], names[p]))
    out = []
    for p in order:
        lo, hi = np.percentile(ranks[:, p], [2.5, 97.5])
        out.append({"policy": names[p], "rank": int(1 + (key > key[p]).sum()),
                    "rollouts": int(counts[p].sum()), "score": interval.summary(float(point_score[p]), sdraws[:, p]),
                    "rank_interval": [int(lo), int(math.ceil(hi))], "p_best": float(best[p]),
                    "rates": {c: interval.summary(float(point[0, p, k]), draws[:, p, k])
                              for k, c in enumerate(criteria)}})
    return out
