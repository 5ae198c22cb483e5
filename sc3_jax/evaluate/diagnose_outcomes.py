"""Outcomes read off imagined frames by the perception scorer: ``sc3 diagnose``'s offline outcome reproduction (the
open-loop imagined rollout vs the real episode's physics labels, ``meta.labels`` of ``sc3 sim demos``, per object;
where the rollout does not cover the whole episode or no labels exist, vs the perception scorer on the real frames of
the same window instead) and ``sc3 rollout``'s success estimate."""
from __future__ import annotations

import numpy as np


def perception_scorer(views, image_size, weights: str | None = None):
    """(PerceptionScorer, None), or (None, why not): the scorer reads left/right/wrist frames at 64x64 only.
    ``weights``: perception weights (None: the shipped ones)."""
    if list(views) != ["left", "right", "wrist"] or tuple(image_size) != (64, 64):
        return None, f"the perception scorer reads left/right/wrist at 64x64; this model has {list(views)} at " \
                     f"{tuple(image_size)}"
    from sc3_jax.evaluate import perception
    from sc3_jax.evaluate.scorers import PerceptionScorer
    return PerceptionScorer(perception.load(weights or perception.DEFAULT_WEIGHTS)), None


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
    from sc3_jax.evaluate.scorers import RolloutView
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


def outcome_section(rows, note) -> dict:
    """Per-criterion agreement of the imagined outcomes with physics and with the scorer on real frames."""
    from sc3_jax.evaluate.metrics import CRITERIA, outcome_category
    rows = [r for r in rows if r is not None]
    category = lambda o: outcome_category({c: o[c] for c in CRITERIA})  # noqa: E731  (sim spells "no failure")
    if not rows:
        return {"available": False, "note": note or "no episode has object labels (meta.labels / "
                                                    "meta.initial_condition)"}

    def agree(a_key, b_key):
        pairs = [(a, b) for r in rows if r[a_key] is not None and r[b_key] is not None
                 for a, b in zip(r[a_key], r[b_key], strict=True)]
        if not pairs:
            return None
        d = {c: float(np.mean([a[c] == b[c] for a, b in pairs])) for c in CRITERIA}
        d["outcome"] = float(np.mean([category(a) == category(b) for a, b in pairs]))
        d["lifting_and_placing"] = float(np.mean([a["lifting"] == b["lifting"] and a["placing"] == b["placing"]
                                                  for a, b in pairs]))
        d["n_objects"] = len(pairs)
        return d

    vs_physics = agree("imagined", "physics")
    return {"available": True, "n_episodes": len(rows),
            "reference": "physics" if vs_physics else "perception(real frames)",
            "imagined_vs_physics": vs_physics, "imagined_vs_real_perception": agree("imagined", "real_perception"),
            "real_perception_vs_physics": agree("real_perception", "physics")}


def success_rates(outcomes: list[list[dict]]) -> dict[str, float]:
    """Per criterion the fraction of objects that pass it and every criterion before it (``metrics``' cumulative
    rule), pooled over rollouts; ``n_objects`` how many."""
    from sc3_jax.evaluate.metrics import CRITERIA, cumulative_passes
    objs = [cumulative_passes({c: o[c] for c in CRITERIA}) for row in outcomes for o in row]
    out = {c: float(np.mean([o[c] for o in objs])) if objs else float("nan") for c in CRITERIA}
    out["n_objects"] = len(objs)
    return out
