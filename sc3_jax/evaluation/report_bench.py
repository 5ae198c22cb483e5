"""The numbers of a bench sweep's results store (``sc3 sweep bench``), every one from :func:`bench` (one call,
JSON-serialisable); ``report_bench_render.py`` turns them into words and tables, ``report.py`` writes them.

Tables (the paper's): main (split x offline/online: Pearson r, MMRV), early termination (tau: termination rate, r,
MMRV per split), outcome reproduction per category (offline/online), offline PSNR per view, and the perception
scorer's agreement with physics on the real rollouts. Rates are compared only over (policy, seed) cases present in
every mode being compared, so a partial sweep still reports consistent numbers (``cases`` says how many).
"""
from __future__ import annotations

import itertools
import json
from pathlib import Path

import numpy as np

from sc3_jax.core.errors import UserError
from sc3_jax.evaluation import bootstrap, calibrate, diagnose_report, intervals
from sc3_jax.measures import metrics, permanence
from sc3_jax.evaluation.calibrate import object_rows as _object_rows
from sc3_jax.evaluation.merged import open_store
from sc3_jax.evaluation.results import EVAL_MODES, criteria_order, paired_frames, seed_blocks, split_order
from sc3_jax.stats import interval, resample
from sc3_jax.stats.floor import policy_blind


def _policy_blind(real_rates: dict) -> dict:
    """An evaluator that knows each criterion's *average* real success rate in a split but nothing about the
    policies: every policy gets the same rates. Pooling criteria gives it a high r (language is easy for everyone,
    placing hard), which is the floor a world model's r has to be read against. The rule is
    ``stats.floor.policy_blind``'s (one definition); this is its point estimate on ``{split: {(policy, c): rate}}``."""
    out = {}
    for s, r in real_rates.items():
        ps, cs = list(dict.fromkeys(p for p, _ in r)), list(dict.fromkeys(c for _, c in r))
        grid = np.array([[[r.get((p, c), np.nan) for c in cs] for p in ps]])  # [1, P, C]; nan: not measured
        floor = policy_blind(grid, [s] * len(ps))[0]
        out[s] = {(p, c): float(floor[ps.index(p), cs.index(c)]) for (p, c) in r}
    return out


def _faith_rates(ev, re, order=()) -> dict:
    splits = calibrate.ordered(re, order)
    out = metrics.faithfulness(ev, re, splits)
    return {s: out[s] for s in [*splits, metrics.OVERALL] if s in out}


def _rates(rows: list[dict]) -> dict:
    return {s: {f"{p}/{c}": v for (p, c), v in r.items()} for s, r in metrics.success_rates_by_split(rows).items()}


def _agreement(real: dict) -> dict:
    """The perception scorer against physics on real frames, clean and degraded (as generated frames are)."""
    from sc3_jax.evaluation.scorers import agreement
    recs = list(real.values())
    out = {"clean": agreement([r["perception"] for r in recs], [r["objects"] for r in recs])}
    # degraded copies are read on a sample of the real rollouts (SweepConfig.degradations): each kind is scored on
    # the rollouts that have it
    kinds = sorted(set().union(*(r.get("perception_degraded", {}) for r in recs)))
    for k in kinds:
        have = [r for r in recs if k in r.get("perception_degraded", {})]
        out[k] = agreement([r["perception_degraded"][k] for r in have], [r["objects"] for r in have])
    return out


def policy_order(real_records, order=()) -> list[tuple[str, str]]:
    """(policy, split) of every real record, split by split (those of ``order`` first, in its order; the rest by
    name): the order of every grid and table."""
    rank = {s: i for i, s in enumerate(order)}
    return sorted({(r["policy"], r["split"]) for r in real_records},
                  key=lambda x: (rank.get(x[1], len(rank)), x[1], x[0]))


def bench(results, taus=None, draws: int = 2000, seed: int = 0, scene=None) -> dict:
    """All report numbers from the bench sweep's results store at ``results`` (see the module docstring; several
    stores, or a directory of a sharded sweep's shards, are read as one: ``merged.open_store``). ``taus`` overrides
    the sweep's candidate thresholds (every online record stores U_chunk and the outcomes of every cut, so any
    threshold is evaluated without rolling out again). ``draws`` / ``seed``: the paired bootstrap's. ``scene``: the
    benchmark's scene measure (``permanence.SceneMeasure``): with it, and the frames of real and online rollouts
    kept, how much of the objects the online rollouts keep over time (``permanence``)."""
    store = open_store(results)
    cfg = store.config()
    if taus is not None:
        cfg["taus"] = [str(float(t)) for t in taus]
    units = cfg.get("tau_units", "raw")
    sets = seed_blocks(cfg)
    recs = store.records()
    in_set = {name: set(seeds) for name, seeds in sets.items()}
    by = {(s, m): {(r["policy"], r["seed"]): r for r in recs if r["mode"] == m and r["seed"] in in_set[s]}
          for s in sets for m in EVAL_MODES}
    real = by["evaluation", "real"]
    if not real:
        raise UserError(f"{results}: no real rollouts on the evaluation seeds yet: faithfulness needs the "
                        "simulator's ground truth (run sc3 sweep bench --modes real into this store, or start it with "
                        "--real-from a store of the same protocol)")
    order = split_order(cfg, recs)
    policies = policy_order(real.values(), order)
    criteria = criteria_order(cfg, real.values())
    out: dict = {"config": cfg, "counts": {m: len(by["evaluation", m]) for m in EVAL_MODES},
                 "policies": policies, "criteria": list(criteria),
                 "protocol": {s: {"n": len(v), "seeds": [v[0], v[-1]] if v else [],
                                  "rollouts": {m: len(by[s, m]) for m in EVAL_MODES}} for s, v in sets.items()},
                 "bootstrap": {"draws": draws, "seed": seed, "level": 0.95,
                               "resampled": "evaluation initial conditions, paired across policies and evaluators"}}
    # ground truth, the scorer's agreement with it (clean and degraded frames)
    real_rows = [row for r in real.values() for row in _object_rows(r, r["objects"], criteria)]
    out["rates"] = {"real": _rates(real_rows),
                    "real_perception": _rates([row for r in real.values()
                                               for row in _object_rows(r, r["perception"], criteria)])}
    # every real rollout of the sweep (all three seed blocks are disjoint from the scorer's training seeds): the
    # agreement is a property of the instrument, and the quick protocol's evaluation block alone is ~150 objects
    out["scorer_agreement"] = _agreement({(s, k): r for s in sets for k, r in by[s, "real"].items()})
    # tau: chosen on the calibration block only, then applied once to the evaluation
    calib = calibrate.tau_sweep(by["calibration", "real"], by["calibration", "online"], cfg["taus"], units, order,
                                criteria)
    select = order[0] if order else None
    out["tau"] = {"units": units, "rule": f"max {(select or 'pooled').replace('_', '-')} r on the calibration seeds "
                  "(ties: lower MMRV, then larger tau)", "calibration": calib, "chosen": None}
    if calib:
        out["tau"]["chosen"] = str(calibrate.choose_tau(calib, select))
    # point estimates (metrics.faithfulness on per-object rows), the reproduction table, PSNR
    out["main"], out["reproduction"], out["cases"] = {}, {}, {}
    for mode in ("offline", "online"):
        cases = sorted(set(by["evaluation", mode]) & set(real))
        if not cases:
            continue
        ev = by["evaluation", mode]
        ev_rows = [row for k in cases for row in _object_rows(ev[k], ev[k]["objects"], criteria)]
        re_rows = [row for k in cases for row in _object_rows(real[k], real[k]["objects"], criteria)]
        out["cases"][mode] = len(cases)
        out["rates"][mode] = _rates(ev_rows)
        out["main"][mode] = calibrate.faith(ev_rows, re_rows, order)
        counts = metrics.reproduction_counts(metrics.outcome_categories(re_rows), metrics.outcome_categories(ev_rows),
                                             criteria)
        out["reproduction"][mode] = {c: {"rate": m / n, "reproduced": m, "cases": n} for c, (m, n) in counts.items()}
    real_rates = metrics.success_rates_by_split(real_rows)
    out["baselines"] = {"policy_blind": _faith_rates(_policy_blind(real_rates), real_rates, order)}
    # every evaluator row with paired bootstrap intervals, against physics and against perception-scored real
    out["faithfulness"] = _with_intervals(by, sets, policies, criteria, out["tau"]["chosen"], units, draws, seed)
    out["ranking"] = _ranking(by, policies, criteria, sets["evaluation"], draws, seed)
    if by["evaluation", "online"]:
        online = by["evaluation", "online"]
        # post hoc: on the evaluation seeds
        out["termination"] = calibrate.tau_sweep(real, online, cfg["taus"], units, order, criteria)
        u = np.concatenate([r["u" if units == "normalised" else "u_raw"] for r in online.values()])
        out["u_quantiles"] = {q: float(np.quantile(u, float(q))) for q in ("0.1", "0.5", "0.9")}
    if by["evaluation", "offline"]:
        recs = list(by["evaluation", "offline"].values())
        pv = np.array([r["psnr_view"] for r in recs])
        split = np.array([r["split"] for r in recs])
        # the paper's PSNR table is split in / out of distribution
        out["psnr"] = {**_psnr(pv), "views": _views(cfg["world_model"], pv.shape[1]),
                       "by_split": {s: _psnr(pv[split == s]) for s in calibrate.ordered(set(split), order)}}
    if scene is not None and by["evaluation", "online"]:
        kept = _permanence(store, cfg, by["evaluation", "online"], scene, draws, seed)
        if kept:
            out["permanence"] = kept
    out["diagnose"] = _diagnose_gates(cfg["world_model"])
    out["action_following"] = diagnose_report.beside_sweep(cfg["world_model"])
    out["training_data"] = training_data(cfg["world_model"], {r["task"] for r in real.values()})
    out["read_from"] = str(store.root)  # the directory read (sweep.json's "out" is where the sweep wrote it)
    out["warnings"] = degenerate(policies)
    return out


def _permanence(store, cfg: dict, online: dict, scene, draws: int, seed: int) -> dict | None:
    """permanence.from_pairs over the evaluation conditions whose real and online frames the store keeps, at the
    model's frame rate (the online frames over the sweep's horizon); None without the frames or the horizon."""
    if not cfg.get("episode_seconds"):
        return None
    rec = next(iter(online.values()))
    fps = rec["frames_per_chunk"] * rec["num_chunks"] / cfg["episode_seconds"]
    got = (paired_frames(store, policy, s, r["stride"]) for (policy, s), r in online.items())
    pairs = ((real[:, at], imagined) for real, imagined, at, _ in filter(None, got))  # one condition's frames at a time
    first = next(pairs, None)
    if first is None:
        return None
    return permanence.from_pairs(itertools.chain([first], pairs), scene, fps,
                                 _views(cfg["world_model"], first[0].shape[0]), draws, seed)


def _ranking(by, policies, criteria, seeds, draws, seed) -> dict:
    """Per split, its policies best first inside the world model (online at tau = inf, else offline), by the rate of
    the last of ``criteria`` (cumulative: an object's success, e.g. placing), with rank intervals and P(best) over the
    same paired draws as the faithfulness rows, and each policy's real rates beside."""
    mode = next((m for m in ("online", "offline") if by["evaluation", m]), None)
    if mode is None:
        return {}
    w, one = resample.multiplicities(len(seeds), draws, seed), np.ones((1, len(seeds)))
    crit = list(criteria)
    ranked_by = crit[-1]
    out = {}
    for split in dict.fromkeys(s for _, s in policies):
        names = [p for p, s in policies if s == split]
        ep, ec = intervals.grid(by["evaluation", mode], names, seeds, crit)
        rows = intervals.ranking(names, crit, ranked_by, bootstrap.rates(ep, ec, one), bootstrap.rates(ep, ec, w), ec)
        rp, rc = intervals.grid(by["evaluation", "real"], names, seeds, crit)
        real_point, real_draws = bootstrap.rates(rp, rc, one), bootstrap.rates(rp, rc, w)
        for row in rows:
            p = names.index(row["policy"])
            row["real"] = {c: interval.summary(float(real_point[0, p, k]), real_draws[:, p, k])
                           for k, c in enumerate(crit)}
        out[split] = {"mode": mode, "ranked_by": ranked_by, "policies": rows}
    return out


def degenerate(policies: list[tuple[str, str]]) -> list[str]:
    """Warnings for statistics that cannot mean anything with these (policy, split) pairs: with fewer than 2
    policies in a split every policy-blind guess is exact and r / MMRV compare one policy's criteria only."""
    out = []
    for split in dict.fromkeys(s for _, s in policies):
        n = sum(s == split for _, s in policies)
        if n == 1:
            out.append(f"{split}: one policy only, so the policy-blind floor equals the real rates and floor, ceiling "
                       "and every r / MMRV there rank criteria, not policies: evaluate at least 2 policies per split")
    return out


def _psnr(pv: np.ndarray) -> dict:
    """Mean offline PSNR per view and over views of the rollouts' ``psnr_view`` rows [rollouts, views]."""
    return {"per_view": [float(x) for x in np.nanmean(pv, 0)], "mean": float(np.nanmean(pv)), "rollouts": len(pv)}


def _views(world_model: str, n: int) -> list[str]:
    """The camera names of ``psnr_view``'s columns: the world model's views, in its order (``view i`` if the
    model has moved or names a different count)."""
    path = Path(world_model) / "config.json"
    # the JSON alone: checkpoint.read_config would also validate (and import) the whole model config
    views = json.loads(path.read_text()).get("data", {}).get("views", []) if path.exists() else []
    return list(views) if len(views) == n else [f"view {i}" for i in range(n)]


def _diagnose_gates(world_model: str) -> dict:
    """The world model's checkpoint gates, from the ``diagnose.json`` that ``sc3 diagnose --world-model WM --out
    WM/diagnose.json`` writes next to it (held-out episodes, not the sweep's rollouts): a sweep of a model that fails
    them says so."""
    from sc3_jax.evaluation import diagnose
    path = Path(world_model) / "diagnose.json"
    if not path.exists():
        return {"path": str(path), "gates": None}
    res = diagnose.load_result(path)
    return {"path": str(path), "data": res.get("data"), "episodes": len(res.get("episodes", [])),
            "gates": res["gates"]}


def training_data(world_model: str, swept_tasks) -> dict | None:
    """What the world model was trained on, from the ``data_stats.json`` shipped beside it (`sc3 sim demos-stats`'
    JSON of its training store): the per-object outcome mix per data source, and which swept tasks its data never
    shows (their rows are out of distribution by construction). None when the model ships no such file."""
    path = Path(world_model) / "data_stats.json"
    if not path.exists():
        return None
    d = json.loads(path.read_text())
    o = d["outcomes"]
    return {"path": str(path), "episodes": d["episodes"], "objects": d["objects"], "tasks": sorted(d["tasks"]),
            "outcomes": {**o["sources"], "all": o["all"]},
            "objects_in_other_container": d.get("objects_in_other_container", {}),
            "all_objects_swapped": d.get("all_objects_swapped"),
            "unseen_tasks": sorted(set(swept_tasks) - set(d["tasks"]))}


def _with_intervals(by, sets, policies, criteria, chosen_tau, units, draws, seed) -> dict:
    names, split_of = [p for p, _ in policies], [s for _, s in policies]
    seeds = sets["evaluation"]
    real = by["evaluation", "real"]
    g = lambda recs, key="objects", s=seeds: intervals.grid(recs, names, s, criteria, lambda r: r[key])  # noqa: E731
    evaluators = {m: g(by["evaluation", m]) for m in ("offline", "online") if by["evaluation", m]}
    if chosen_tau is not None and by["evaluation", "online"]:
        tau = calibrate.parse_tau(chosen_tau)
        evaluators["online_tau"] = intervals.grid(by["evaluation", "online"], names, seeds, criteria,
                                                  lambda r: r["objects_by_cut"][calibrate.cut(r, tau, units)])
    second = by["ceiling", "real"]
    out = {}
    for ref, key in (("physics", "objects"), ("perception", "perception")):
        extra = {"real_perception": g(real, "perception")} if ref == "physics" else {}
        ceiling = g(second, key, sets["ceiling"]) if second else None
        out[ref] = intervals.evaluator_rows(g(real, key), evaluators, split_of, draws, seed, ceiling, extra, criteria)
    return out
