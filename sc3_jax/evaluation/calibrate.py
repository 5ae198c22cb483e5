"""The early-termination threshold tau, chosen the paper's way: on held-out initial conditions, then applied once.

The paper tunes tau "on a held-out subset of 30 trajectories" and adopts the threshold at which in-distribution
faithfulness is best (App. "Early-termination threshold" and "Sweet spot at tau_2 = 0.02"). Here the sweep rolls
out a *calibration* block of initial conditions (simulator seeds disjoint from the evaluation seeds) in the
simulator and in the world model; :func:`choose_tau` reads only that block's results:

    tau* = the candidate with the highest Pearson r on the selection split (calibration rollouts vs the real ones),
           ties broken by lower MMRV there, then by the larger tau (terminate less).

The selection split is the benchmark's first (its in-distribution one: ``results.split_order``), else every split
pooled.

A candidate whose r is nan (a constant side) ranks below every finite r. The evaluation's early-termination table
still lists every candidate, marked post hoc: reading a tau off that table would tune on the evaluation itself.

Every online rollout runs untruncated (tau = inf) and stores the outcomes of the rollout cut after every chunk, so a
candidate tau is a lookup: the kept frames are the chunks before the first with U_chunk > tau (``results.
terminated_at``), U_chunk in the sweep's one unit convention (``RolloutConfig.tau_units``).
"""
from __future__ import annotations

import math

import numpy as np

from sc3_jax.measures import metrics
from sc3_jax.evaluation.results import terminated_at


def parse_tau(t) -> float:
    return math.inf if str(t) in ("inf", "Infinity") else float(t)


def object_rows(rec: dict, objects: list[dict], criteria=None) -> list[dict]:
    """Per-object rows of one rollout record, as ``metrics.success_rates`` takes them: ``criteria`` in their order
    (None: each outcome's own, ``metrics.criteria_of``)."""
    return [{"policy": rec["policy"], "split": rec["split"], "episode": rec["seed"], "object": o["object"],
             **{c: bool(o[c]) for c in (criteria or metrics.criteria_of(o))}} for o in objects]


def cut(rec: dict, tau: float, units: str) -> int:
    """Index into an online record's ``objects_by_cut`` for threshold tau: the first chunk with U > tau (its frames
    and every later chunk's are dropped); ``num_chunks`` when no chunk exceeds tau."""
    u = np.asarray(rec["u"] if units == "normalised" else rec["u_raw"])
    first = int(terminated_at(u[None], tau)[0])
    return len(u) if first < 0 else first


def faith(ev_rows: list[dict], real_rows: list[dict], order=()) -> dict:
    """Point r / MMRV per split (and overall) of two sets of per-object rows; splits in ``order`` (the store's:
    ``results.split_order``), any other by name."""
    re = metrics.success_rates_by_split(real_rows)
    splits = ordered(re, order)
    out = metrics.faithfulness(metrics.success_rates_by_split(ev_rows), re, splits)
    return {s: out[s] for s in [*splits, metrics.OVERALL] if s in out}


def ordered(present, order) -> list:
    """The splits of ``present``: those of ``order`` first, in its order, then the rest by name."""
    return [s for s in order if s in present] + sorted(s for s in present if s not in order)


def tau_sweep(real: dict, online: dict, taus, units: str, order=(), criteria=None) -> list[dict]:
    """For every tau: termination rate per split, r / MMRV of the cut online rollouts against physics, mean chunks
    kept. ``real`` / ``online``: records keyed by (policy, seed); only keys in both are compared. ``order``: the
    splits' (:func:`faith`); ``criteria``: the outcomes' (:func:`object_rows`)."""
    cases = sorted(set(online) & set(real))
    if not cases:
        return []
    re_rows = [row for k in cases for row in object_rows(real[k], real[k]["objects"], criteria)]
    out = []
    for tau in (parse_tau(t) for t in taus):
        cuts = {k: cut(online[k], tau, units) for k in cases}
        ev_rows = [row for k in cases
                   for row in object_rows(online[k], online[k]["objects_by_cut"][cuts[k]], criteria)]
        term = {}
        for split in [*ordered({real[k]["split"] for k in cases}, order), metrics.OVERALL]:
            ks = [k for k in cases if split == metrics.OVERALL or real[k]["split"] == split]
            if ks:
                term[split] = float(np.mean([cuts[k] < online[k]["num_chunks"] for k in ks]))
        out.append({"tau": str(tau), "termination_rate": term, "faithfulness": faith(ev_rows, re_rows, order),
                    "mean_chunks_kept": float(np.mean(list(cuts.values()))), "cases": len(cases)})
    return out


def choose_tau(table: list[dict], split: str | None = None) -> float:
    """tau* from a :func:`tau_sweep` of the *calibration* rollouts (see the module docstring), chosen on ``split``
    (None, or a split the table lacks: every split pooled). Pure: the table is all it reads."""
    if not table:
        raise ValueError("choose_tau: no calibration results (run the sweep with --calibration-episodes N)")

    def key(e):
        f = (e["faithfulness"].get(split) if split is not None else None) or e["faithfulness"][metrics.OVERALL]
        r = f["pearson"]
        return (-math.inf if math.isnan(r) else r, -f["mmrv"], parse_tau(e["tau"]))
    return parse_tau(max(table, key=key)["tau"])
