"""Outcomes read off imagined frames by a benchmark's scorer (the simulated benchmark's perception scorer, passed
in by the command): ``sc3 diagnose``'s offline outcome reproduction (the
open-loop imagined rollout vs the real episode's physics labels, ``meta.labels`` of ``sc3 sim demos``, per object;
where the rollout does not cover the whole episode or no labels exist, vs the perception scorer on the real frames of
the same window instead) and ``sc3 rollout``'s success estimate."""
from __future__ import annotations

import math

import numpy as np

from sc3_jax.stats import resample

BOOTSTRAP_DRAWS = 2000
# objects with physics labels an outcome set needs to be read per category (the gate's outcome set): at 0.75 the binomial
# 95% half-width is ~0.07 with 150 objects (more once episodes' correlation counts), ~0.11 with 60: a set of a few
# dozen objects cannot tell a model at 0.67 from one at the 0.75 gate
MIN_OBJECTS = 150


def no_scorer(views, image_size, weights=None):
    """The outcome scorer when the caller names none: (None, why)."""
    return None, "no outcome scorer for this model's frames (a benchmark's, e.g. the simulated benchmark's perception)"


def episode_objects(meta: dict):
    """(objects, destinations, physics labels or None) from an episode's meta (``sc3 sim demos`` format); (None,
    None, None) when it names no objects."""
    labels = (meta.get("labels") or {}).get("objects")
    if labels:
        return tuple(o["name"] for o in labels), {o["name"]: o["destination"] for o in labels}, labels
    ic = meta.get("initial_condition")
    if ic and "destinations" in ic:
        return tuple(ic["objects"]), dict(ic["destinations"]), None
    return None, None, None


def outcome(scorer, ep, ctx, pred, tgt, valid, steps_in: int) -> dict | None:
    """One open-loop rollout of episode ``ep``: the scorer on its imagined and on its real frames (context ``ctx``
    [V, K, ...], then the ``valid`` steps of ``pred`` / ``tgt``), and the physics labels when the rollout covers all
    ``steps_in`` steps of the episode."""
    from sc3_jax.evaluation.scorers import RolloutView
    objects, dests, physics = episode_objects(ep.meta)
    if objects is None:
        return None
    n = int(valid.sum())
    imagined = np.concatenate([ctx, pred[:, :n]], 1)
    real = np.concatenate([ctx, tgt[:, :n]], 1)
    im = scorer.score(RolloutView(ep.episode_id, imagined, objects, dests))
    re = scorer.score(RolloutView(ep.episode_id, real, objects, dests))
    covered = n >= steps_in
    return {"episode": ep.episode_id, "imagined": im, "real_perception": re,
            "physics": physics if covered else None, "covered": covered}


def _criteria(rows) -> tuple[str, ...]:
    """The criteria of the rows' outcomes, in their order (``metrics.criteria_of``: the first object's)."""
    from sc3_jax.measures.metrics import criteria_of
    return next((criteria_of(o) for r in rows for k in ("physics", "imagined", "real_perception")
                 for o in (r.get(k) or ())), ())


def outcome_section(rows, note, seed: int = 0, draws: int = BOOTSTRAP_DRAWS, names=None) -> dict:
    """Per-criterion agreement of the imagined outcomes with physics and with the scorer on real frames; imagined vs
    physics also per outcome category with intervals (:func:`physics_reproduction`, seeded by ``seed``). ``names``:
    the benchmark's words for its outcome categories (``Benchmark.category_names``), kept in the section for the
    tables (a category not named prints as itself)."""
    from sc3_jax.measures.metrics import outcome_category
    rows = [r for r in rows if r is not None]
    criteria = _criteria(rows)
    category = lambda o: outcome_category({c: o[c] for c in criteria})  # noqa: E731  (sim spells "no failure")
    if not rows:
        return {"available": False, "note": note or "no episode has object labels (meta.labels / "
                                                    "meta.initial_condition)"}

    def agree(a_key, b_key):
        pairs = [(a, b) for r in rows if r[a_key] is not None and r[b_key] is not None
                 for a, b in zip(r[a_key], r[b_key], strict=True)]
        if not pairs:
            return None
        d = {c: float(np.mean([a[c] == b[c] for a, b in pairs])) for c in criteria}
        d["outcome"] = float(np.mean([category(a) == category(b) for a, b in pairs]))
        if len(criteria) > 2:  # the last two together (e.g. lifting and placing: what a gripper's failures move)
            a_, b_ = criteria[-2:]
            d[f"{a_}_and_{b_}"] = float(np.mean([a[a_] == b[a_] and a[b_] == b[b_] for a, b in pairs]))
        d["n_objects"] = len(pairs)
        return d

    vs_physics = agree("imagined", "physics")
    return {"available": True, "n_episodes": len(rows),
            "reference": "physics" if vs_physics else "perception(real frames)",
            "imagined_vs_physics": vs_physics, "imagined_vs_real_perception": agree("imagined", "real_perception"),
            "real_perception_vs_physics": agree("real_perception", "physics"),
            "physics_reproduction": physics_reproduction(rows, seed, draws)} | (
                {"category_names": dict(names)} if names else {})


def physics_reproduction(rows, seed: int = 0, draws: int = BOOTSTRAP_DRAWS) -> dict | None:
    """Imagined vs physics with 95% intervals, from the rows whose rollout covered the episode (None: none did).

    Per physics outcome category (``metrics.outcome_category``): its objects and the fraction whose imagined
    category is the same; the same agreement over every object and per criterion; the confusion table (physics
    category -> imagined category -> objects). Intervals: percentile bootstrap resampling *episodes* (the objects of
    one episode share its rollout, so they are not independent draws), one set of ``draws`` resamplings shared by
    every figure, seeded; None with fewer than 2 episodes (nothing to resample)."""
    from sc3_jax.measures.metrics import categories, outcome_category
    rows = [r for r in rows if r is not None and r["physics"] is not None]
    if not rows:
        return None
    criteria = _criteria(rows)
    cats = categories(criteria)
    category = lambda o: outcome_category({c: o[c] for c in criteria})  # noqa: E731  (sim spells "no failure")
    pairs = [[(a, b) for a, b in zip(r["imagined"], r["physics"], strict=True)] for r in rows]  # per episode
    E = len(rows)
    # weights[d, e]: how often resampling d draws episode e (E draws with replacement)
    weights = resample.multiplicities(E, draws, seed) if E >= 2 else None

    def stat(hit, keep=lambda im, ph: True) -> dict:
        """Fraction of the kept (imagined, physics) objects where ``hit``, with its interval."""
        num = np.array([sum(bool(hit(im, ph)) for im, ph in ep if keep(im, ph)) for ep in pairs], np.float64)
        den = np.array([sum(bool(keep(im, ph)) for im, ph in ep) for ep in pairs], np.float64)
        n = int(den.sum())
        out = {"n_objects": n, "agreement": float(num.sum() / n) if n else math.nan, "ci95": None}
        if weights is not None and n:
            with np.errstate(invalid="ignore", divide="ignore"):
                boot = (weights @ num) / (weights @ den)  # nan where a resampling holds none of these objects
            boot = boot[np.isfinite(boot)]
            if len(boot):
                out["ci95"] = [float(x) for x in np.percentile(boot, [2.5, 97.5])]
        return out

    confusion = {c: {k: 0 for k in cats} for c in cats}
    for ep in pairs:
        for im, ph in ep:
            confusion[category(ph)][category(im)] += 1
    n = sum(len(ep) for ep in pairs)
    return {"n_episodes": E, "n_objects": n, "draws": draws if weights is not None else 0, "seed": seed,
            "enough_objects": n >= MIN_OBJECTS, "min_objects": MIN_OBJECTS,
            "outcome": stat(lambda im, ph: category(im) == category(ph)),
            "criteria": {c: stat(lambda im, ph, c=c: im[c] == ph[c]) for c in criteria},
            "categories": {c: stat(lambda im, ph: category(im) == category(ph), lambda im, ph, c=c: category(ph) == c)
                           for c in cats},
            "confusion": confusion}


def success_rates(outcomes: list[list[dict]]) -> dict[str, float]:
    """Per criterion the fraction of objects that pass it and every criterion before it (``metrics``' cumulative
    rule), pooled over rollouts; ``n_objects`` how many."""
    from sc3_jax.measures.metrics import criteria_of, cumulative_passes
    criteria = next((criteria_of(o) for row in outcomes for o in row), ())
    objs = [cumulative_passes({c: o[c] for c in criteria}) for row in outcomes for o in row]
    out = {c: float(np.mean([o[c] for o in objs])) if objs else float("nan") for c in criteria}
    out["n_objects"] = len(objs)
    return out
