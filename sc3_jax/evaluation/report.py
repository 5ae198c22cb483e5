"""The report of a sweep's results store, whichever sweep wrote it (``sc3 sweep bench`` or ``sc3 sweep episodes``):
every number comes from :func:`compute` (one call, JSON-serialisable), and :func:`render` only formats it (markdown
and HTML tables; for a bench store plots and side-by-side videos, ``report_figures.py``). The numbers of a store of
held-out episodes are ``report_episodes.py``'s; those of a bench store are here:

    from sc3_jax.evaluation.report import compute
    tables = compute("runs/sweep")            # the exact numbers in report.md / report.json

Tables (the paper's): main (split x offline/online: Pearson r, MMRV), early termination (tau: termination rate, r,
MMRV per split), outcome reproduction per category (offline/online), offline PSNR per view, and the perception
scorer's agreement with physics on the real rollouts. Rates are compared only over (policy, seed) cases present in
every mode being compared, so a partial sweep still reports consistent numbers (``cases`` says how many).
"""
from __future__ import annotations

import itertools
import json
import math
from pathlib import Path

import numpy as np

from sc3_jax.core import atomic
from sc3_jax.core.errors import UserError
from sc3_jax.evaluation import (bootstrap, calibrate, diagnose_headline, diagnose_report, intervals, report_episodes,
                                report_figures, report_html)
from sc3_jax.measures import metrics, permanence
from sc3_jax.evaluation.report_html import UNDEFINED, ci
from sc3_jax.evaluation.report_html import fmt as _fmt
from sc3_jax.evaluation.calibrate import object_rows as _object_rows
from sc3_jax.evaluation.merged import open_store
from sc3_jax.evaluation.results import (EVAL_MODES, ResultsStore, criteria_order, paired_frames, seed_blocks,
                                      split_order)
from sc3_jax.core.safe_names import file_name
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





def compute(results, taus=None, draws: int = 2000, seed: int = 0, scene=None, real=None) -> dict:
    """Every number of the report of the store(s) at ``results``, whichever sweep wrote it: a sweep of held-out
    episodes (``report_episodes.compute``; ``real``: its real-outcome sources, None: the sweep's own) or a bench
    sweep (:func:`bench`); ``scene``: the benchmark's object measure (objects kept). ``taus``: other candidate thresholds, read
    from the stored U_chunk (no new rollouts)."""
    roots = [results] if isinstance(results, (str, Path)) else list(results)
    if len(roots) == 1 and report_episodes.is_store(roots[0]):
        return report_episodes.compute(roots[0], real, draws, seed, taus, scene)
    if real:
        raise UserError("--real applies to a sweep of held-out episodes (sc3 sweep episodes); a bench sweep's real "
                        "rollouts are in its store")
    return bench(results, taus, draws, seed, scene)


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


def headline(t: dict) -> str:
    """The answer in one sentence: does the world model rank the policies like the real robot, better than a guess?"""
    f = t["faithfulness"]["physics"]
    mode = next((m for m in ("online", "offline") if m in f), None)
    if mode is None:
        return "No rollouts inside the world model yet: nothing to compare with the real robot."
    split = _splits(t)[-1]  # overall where there are two splits, else the one
    r, m = f[mode]["splits"][split]["pearson"], f[mode]["splits"][split]["mmrv"]
    floor = f["policy_blind"]["splits"][split]["pearson"]
    vs = f[mode].get("vs_floor", {}).get(split, {})
    better = (vs.get("pearson") or {}).get("lo", math.nan) > 0
    where = "" if split == metrics.OVERALL or len(_splits(t)) > 1 else f" ({split.replace('_', ' ')})"
    what = "closed loop" if mode == "online" else "replaying the real actions"
    if not math.isfinite(r["value"]):
        return (f"Cannot tell{where}: r is undefined at these rates (it needs two or more distinct success rates on "
                "each side); add policies or conditions.")
    nums = f"r {ci(r)}, MMRV {ci(m)}"
    guess = f"(its r {ci(floor)}; paired difference {ci(vs.get('pearson'))})"
    if better:
        return (f"Inside the world model ({what}) the policies rank like the real robot{where}: {nums}, better than a "
                f"policy-blind guess {guess}.")
    return (f"Inside the world model ({what}) the ranking agrees with the real robot{where} at {nums}: not "
            f"distinguishable from a policy-blind guess at this many conditions {guess}.")


def verdict(t: dict) -> list[str]:
    """One line per split: is the online evaluator better than the policy-blind guess (its paired difference's
    interval excludes 0 in the evaluator's favour), on r and on MMRV."""
    online = t["faithfulness"]["physics"].get("online")
    if online is None:
        return ["no online rollouts: nothing to compare with the guess yet"]
    out = []
    for split, d in online["vs_floor"].items():
        if split == metrics.OVERALL and len(online["vs_floor"]) == 2:
            continue  # one split only: "overall" is the same numbers again
        r, m = d["pearson"], d["mmrv"]
        better = [name for name, ok in (("r", r["lo"] > 0), ("MMRV", m["hi"] < 0)) if ok]
        out.append(f"{split}: online r {online['splits'][split]['pearson']['value']:.3f}, paired r - floor "
                   f"{ci(r)}, MMRV - floor {ci(m)}: " +
                   (f"better than a policy-blind guess on {' and '.join(better)}" if better else
                    "not distinguishable from a policy-blind guess at this many conditions"))
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
    """The world model's checkpoint gates, from the ``diagnose.json`` that ``sc3 diagnose --world-model WM --out WM/diagnose.json``
    writes next to it (held-out episodes, not the sweep's rollouts): a sweep of a model that fails them says so."""
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


def _training_data_table(d: dict) -> tuple[str, list[str], list[list[str]]]:
    cats = ("lifted", "placed", "wrong_container", "dropped", "missed")
    rows = [[src, str(v["episodes"]), str(v["objects"])] + [_fmt(v[c] / v["objects"], 2) for c in cats]
            for src, v in d["outcomes"].items()]
    other = ", ".join(f"{k}: {n}" for k, n in d["objects_in_other_container"].items())
    unseen = (f"; swept tasks its data never shows: {', '.join(d['unseen_tasks'])} (out of distribution by "
              "construction: neither their instruction nor their every-object mapping is in the data)"
              if d["unseen_tasks"] else "")
    return (f"The world model's training data. {d['episodes']} episodes, {d['objects']} objects, tasks "
            f"{', '.join(d['tasks'])}; episodes by objects carried into the other container: {other}; every object "
            f"swapped: {d['all_objects_swapped']}{unseen} (the world model's data_stats.json); per-object outcome "
            "shares (placed + wrong_container + dropped + missed = 1).", ["source", "episodes", "objects", *cats],
            rows)


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


# ================================================================================================================
# Rendering
# ================================================================================================================
def _splits(t: dict) -> list[str]:
    """The splits a report shows, in order: with one split, "overall" would repeat its numbers, so it is left out."""
    have = [s for s in [*dict.fromkeys(s for _, s in t["policies"]), metrics.OVERALL]
            if s in t["faithfulness"]["physics"]["policy_blind"]["splits"]]
    return have if len(have) > 2 else [s for s in have if s != metrics.OVERALL] or have


ROW_NAMES = {"offline": "offline", "online": "online (tau = inf)", "online_tau": "online (calibrated tau*)",
             "real_perception": "real, perception-scored", "policy_blind": "policy-blind (floor)",
             "ceiling": "noise ceiling"}
REFERENCES = {"physics": "end to end: imagined (perception) vs real scored by physics",
              "perception": "same instrument: imagined vs real, both scored by perception"}


def _interval_rows(rows: dict, pick, splits) -> list[list[str]]:
    out = []
    for name in ROW_NAMES:
        if name not in rows:
            continue
        cells = [pick(rows[name], s) for s in splits]
        out.append([ROW_NAMES[name]] + [ci(c.get(k) if c else None) for c in cells for k in ("pearson", "mmrv")])
    return out


def tables(t: dict) -> list[tuple[str, list[str], list[list[str]]]]:
    """(title, header, rows) of every table in the report, formatted from :func:`compute`'s output."""
    out = []
    modes = [m for m in ("offline", "online") if m in t["main"]]
    b = t["bootstrap"]
    rows = [[name, str(p["n"]), f"{p['seeds'][0]}-{p['seeds'][1]}" if p["seeds"] else "-",
             ", ".join(f"{m} {k}" for m, k in p["rollouts"].items() if k)] for name, p in t["protocol"].items()]
    out.append(("Protocol: initial conditions per policy and simulator seeds (disjoint blocks).",
                ["set", "n per policy", "seeds", "rollouts"], rows))
    how = (f"value [95% paired bootstrap interval over initial conditions, {b['draws']} draws, seed {b['seed']}]; "
           "r higher is better, MMRV lower")
    splits = _splits(t)
    for ref, what in REFERENCES.items():
        f = t["faithfulness"][ref]
        out.append((f"Faithfulness, {what}. {how}; ceiling: {f['ceiling']['method']}.",
                    ["evaluator"] + [f"{s} {k}" for s in splits for k in ("r", "MMRV")],
                    _interval_rows(f, lambda row, s: row["splits"].get(s), splits)))
    f = t["faithfulness"]["physics"]
    rows = [[ROW_NAMES[name]] + [ci(f[name]["vs_floor"].get(s, {}).get(k)) for s in splits
                                 for k in ("pearson", "mmrv")] for name in ROW_NAMES if "vs_floor" in f.get(name, {})]
    out.append(("Better than a guess? Paired difference to the policy-blind floor, evaluator - floor, on the same "
                f"resampled conditions (vs physics; r > 0 and MMRV < 0 favour the evaluator). {how}",
                ["evaluator"] + [f"{s} {k}" for s in splits for k in ("r", "MMRV")], rows))
    for ref, what in REFERENCES.items():
        f = t["faithfulness"][ref]
        rows = []
        for c in t["criteria"]:
            rows += [[c] + r for r in _interval_rows(f, lambda row, s: row["per_criterion"].get(s, {}).get(c), splits)]
        out.append((f"Per criterion, {what}. Points: the policies of a split. {how}.",
                    ["criterion", "evaluator"] + [f"{s} {k}" for s in splits for k in ("r", "MMRV")], rows))
    tau = t["tau"]
    if tau["calibration"]:
        rows = [[e["tau"] + (" (chosen)" if e["tau"] == tau["chosen"] else "")] +
                [x for s in splits for x in (_fmt(e["termination_rate"].get(s)),
                                                   _fmt(e["faithfulness"].get(s, {}).get("pearson")),
                                                   _fmt(e["faithfulness"].get(s, {}).get("mmrv")))]
                for e in tau["calibration"]]
        n = t["protocol"]["calibration"]["n"]
        out.append((f"tau calibration. On the held-out calibration seeds ({n} per policy, "
                    f"{tau['calibration'][0]['cases']} rollouts; U_chunk in {tau['units']} action units); rule: "
                    f"{tau['rule']}.", ["tau"] + [f"{s} {k}" for s in splits for k in ("term. rate", "r", "MMRV")],
                    rows))
    if "termination" in t:
        rows = []
        for e in t["termination"]:
            row = [e["tau"] + (" (calibrated)" if e["tau"] == tau["chosen"] else "")]
            for split in splits:
                f = e["faithfulness"].get(split)
                row += [_fmt(e["termination_rate"].get(split)), _fmt(f["pearson"]) if f else "-",
                        _fmt(f["mmrv"]) if f else "-"]
            rows.append(row)
        out.append((f"Early termination, every tau (post hoc). On the evaluation seeds, POST HOC: choosing tau from "
                    f"this table tunes on the evaluation; online, U_chunk in {tau['units']} action units, vs physics.",
                    ["tau"] + [f"{s} {k}" for s in splits for k in ("term. rate", "r", "MMRV")], rows))
    rows = [[c] + [(f"{_fmt(t['reproduction'][m][c]['rate'], 2)} ({t['reproduction'][m][c]['reproduced']}/"
                    f"{t['reproduction'][m][c]['cases']})") if c in t["reproduction"].get(m, {}) else "-"
                   for m in modes] for c in metrics.categories(t["criteria"])]
    out.append(("Outcome reproduction per real outcome category (objects)", ["category"] + modes, rows))
    if "psnr" in t:
        p = t["psnr"]
        rows = [[k, str(q["rollouts"])] + [_fmt(x, 2) for x in q["per_view"]] + [_fmt(q["mean"], 2)]
                for k, q in list(p.get("by_split", {}).items()) + [(metrics.OVERALL, p)]]
        out.append(("Offline PSNR (dB, mean over valid frames)", ["split", "rollouts"] + p["views"] + ["mean"], rows))
    if t.get("permanence"):
        out.append(report_html.kept_table(t["permanence"], "online: the online rollouts' frames over the real "
                                                           "rollouts' from the same evaluation conditions"))
    if t.get("training_data"):
        out.append(_training_data_table(t["training_data"]))
    d = t.get("diagnose") or {}
    if d.get("gates") is not None:
        out.append((f"World-model checkpoint gates. `sc3 diagnose` on {d['episodes']} held-out episodes of "
                    f"{Path(str(d['data'])).name} (the world model's diagnose.json).",
                    ["gate", "value", "threshold", "pass"],
                    [[g["gate"], _fmt(g["value"], 2) if g["pass"] is not None else "-", f"{g['threshold']:g}",
                      {True: "PASS", False: "FAIL"}.get(g["pass"], "not run")] for g in d["gates"]]))
    elif d:
        out.append(("World-model checkpoint gates", ["gate", "value", "threshold", "pass"],
                    [["not diagnosed: run `sc3 diagnose --world-model WORLD_MODEL --data HELDOUT --out WORLD_MODEL/diagnose.json`",
                      "-", "-", "-"]]))
    if diagnose_headline.report_table(t.get("action_following")):
        out.append(diagnose_headline.report_table(t["action_following"]))
    a = t["scorer_agreement"]
    out.append(("Perception scorer vs physics. Agreement per criterion on clean frames of every real rollout of the "
                "sweep (evaluation, calibration and ceiling seeds), and on frames degraded the way generated frames "
                "are, of the real rollouts the sweep read degraded (its `degradations`; 'objects' counts them).",
                ["frames"] + list(t["criteria"]) + ["outcome", "objects"],
                [[k] + [_fmt(v[c]) for c in t["criteria"]] + [_fmt(v["outcome"]), str(v["n_objects"])]
                 for k, v in a.items()]))
    rows = []
    for policy, split in t["policies"]:
        row = [policy, split]
        for m in ("real", "real_perception", "offline", "online"):
            r = t["rates"].get(m, {}).get(split, {})
            row.append(" / ".join(_fmt(r.get(f"{policy}/{c}"), 2) for c in t["criteria"]))
        rows.append(row)
    out.append((f"Success rates per policy. {' / '.join(t['criteria']).capitalize()}, cumulative.",
                ["policy", "split", "real", "real (perception)", "offline", "online"], rows))
    return out


def incomplete(t: dict) -> str:
    """A warning line while a swept mode has fewer evaluation rollouts than the protocol's ('' when none is short; a
    world-model mode with none was not asked for)."""
    n = t["protocol"]["evaluation"]["n"] * len(t["policies"])
    short = [f"{m} {t['counts'][m]} of {n}" for m in ("real", "offline", "online") if 0 < t["counts"][m] < n]
    return (f"Incomplete sweep: {', '.join(short)} evaluation rollouts so far (rerun the sweep to resume). Intervals "
            "over a split with a policy that has no rollout yet read nan." if short else "")


def ranking_tables(t: dict) -> list[tuple[str, list[str], list[list[str]]]]:
    """The answer's tables: per split, the policies best first inside the world model, the real rates beside."""
    out = []
    n = t["protocol"]["evaluation"]["n"]
    for split, r in t.get("ranking", {}).items():
        where = f", {split.replace('_', ' ')}" if len(t["ranking"]) > 1 else ""
        rows = [[str(x["rank"]), x["policy"], ci(x["score"]), f"{x['rank_interval'][0]}-{x['rank_interval'][1]}",
                 f"{x['p_best']:.0%}", ci(x["real"][r["ranked_by"]])] for x in r["policies"]]
        out.append((f"Ranking inside the world model{where}. Success ({r['ranked_by']}, the cumulative criterion) of "
                    f"{r['mode']} rollouts on {n} conditions per policy, best first; 95% paired bootstrap intervals, "
                    "rank interval and P(best) over the same draws; real: the simulator on the same conditions.",
                    ["rank", "policy", "imagined success", "rank interval", "P(best)", "real success"], rows))
    return out


def method(t: dict) -> str:
    """The method in one paragraph (the page's "How it is measured")."""
    b, tau = t["bootstrap"], t["tau"]
    return ("Each policy acts from the same initial conditions in the simulator (real) and inside the world model "
            "(online: closed loop; offline: replaying the real actions); a perception scorer reads the imagined "
            "frames, physics the real ones. Faithfulness is Pearson r and MMRV over the (policy, criterion) success "
            "rates of a split, against a policy-blind guess (every policy gets the split's mean real rate per "
            "criterion: the floor) and a second set of real rollouts (the noise ceiling). Intervals are 95% "
            f"percentile intervals of a paired bootstrap over the evaluation conditions ({b['draws']} draws); "
            f"tau (U_chunk in {tau['units']} action units) is chosen on held-out calibration conditions: "
            f"{tau['chosen'] or 'none (no calibration conditions)'}. {UNDEFINED}: undefined at these rates (r needs "
            "two or more distinct rates on each side). Every number is in report.json "
            "(`sc3_jax.evaluation.report.compute`).")


def _parts(t: dict) -> dict:
    """What a report page shows, for either kind of sweep: title, headline lines, warnings, the answer's tables,
    the detail tables, the method paragraph and the facts of the run."""
    if t.get("kind") == report_episodes.KIND:
        cfg, e = t["config"], report_episodes
        return {"title": "Sweep report: held-out episodes", "headlines": e.verdict(t), "warnings": t["warnings"],
                "answer": e.tables(t)[:1], "details": e.tables(t)[1:], "method": e.METHOD,
                "facts": [f"World model {Path(cfg['world_model']).name}, initial conditions "
                          f"{Path(cfg['initial_conditions']).name}; rollouts {t['rollouts']}"]}
    warn = incomplete(t)
    return {"title": "Sweep report: bench", "headlines": [headline(t)],
            "warnings": ([warn] if warn else []) + t.get("warnings", []),
            "answer": ranking_tables(t), "details": tables(t), "method": method(t),
            "facts": ["Rollouts: " + ", ".join(f"{m} {k}" for m, k in t["counts"].items()) + "; compared cases: "
                      + ", ".join(f"{m} {k}" for m, k in t["cases"].items())]}


def markdown(t: dict) -> str:
    p = _parts(t)
    head = "".join(f"**{h}**\n\n" for h in p["headlines"][:1]) + "".join(f"{h}\n\n" for h in p["headlines"][1:])
    parts = [f"# {p['title']}\n\n{head}" + "".join(f"**{w}**\n\n" for w in p["warnings"])]
    parts += [report_html.markdown_table(*x) for x in p["answer"] + p["details"]]
    parts.append(f"## How it is measured\n\n{p['method']} Results: `{Path(t['read_from']).name}`. "
                 + " ".join(f"{f}." for f in p["facts"]) + "\n")
    return "\n".join(parts)


def closing_lines(t: dict) -> list[str]:
    """What the numbers say in a few lines: the sweep commands' closing words."""
    if t.get("kind") == report_episodes.KIND:
        return report_episodes.summary(t)
    title, header, rows = next(x for x in tables(t) if x[0].startswith("Faithfulness, end to end"))
    return [report_html.markdown_table(title, header, rows)] + verdict(t) + t.get("warnings", [])


def render(results, out: str | Path | None = None, videos: int | None = None, taus=None, draws: int = 2000,
           scene=None, real=None) -> Path:
    """Write report.md, report.html and report.json (and, for a bench sweep, plots, a filmstrip and a video per
    policy: ``videos`` at most) to ``out`` (None: the first store's report/); returns report.md. Every file is
    written to a staging directory and moved into ``out`` only once all of them exist (report.md last), so a failure
    (a damaged frames file, an unwritable ``out``) or a kill leaves the previous report as it was."""
    from sc3_jax.core.validate import out_dir

    roots = [results] if isinstance(results, (str, Path)) else list(results)
    # a store is someone else's data: its report/ linked elsewhere would have the report overwrite what it points at
    out = out_dir(out if out is not None else Path(roots[0]) / "report", "--out" if out is not None else
                  "the report directory", links=False)
    t = compute(results, taus, draws, scene=scene, real=real)
    with atomic.staged(out, last=("report.md",)) as stage:
        (stage / "report.json").write_text(json.dumps(t, indent=1))
        figures, vids = ([], []) if t.get("kind") == report_episodes.KIND else \
            _figures(open_store(results), t, stage, videos)
        md = markdown(t)
        md += "".join(f"\n![{caption}]({name})\n" for name, caption in figures)
        if vids:
            md += "\n## Real | online (| offline) (rows: views)\n\n" + "".join(f"* [{v}]({v})\n" for v in vids)
        elif videos:
            md += ("\n(No videos: no policy has real and online frames of its first evaluation condition in this "
                   "store's rollouts/ (an archived store, or a sweep of held-out episodes, keeps no real frames), or "
                   "the world model's config.json, which gives the frames' rate, is not where the sweep read it.)\n")
        (stage / "report.md").write_text(md)
        p = _parts(t)
        (stage / "report.html").write_text(report_html.page(
            p["title"], p["headlines"], p["answer"], figures, vids, p["method"], p["details"], p["warnings"],
            [f"Results: {Path(t['read_from']).name}"] + p["facts"]))
    return out / "report.md"


def _figures(store: ResultsStore, t: dict, stage: Path, videos: int | None):
    """A bench report's pictures, written into ``stage``: (figures [(file, caption)], videos [file])."""
    figures = []
    if t.get("ranking"):
        report_figures.scatter(t, stage / "correlation.png", _splits(t)[-1])
        figures.append(("correlation.png", "Imagined against real success per policy and criterion (95% intervals); "
                                           "the dotted diagonal is perfect agreement, grey x the policy-blind guess."))
    seed = t["config"]["seed0"]
    for policy, _ in t["policies"]:  # a filmstrip per policy: cheap to keep, shows what the model imagines
        name = file_name(f"filmstrip_{policy}_{seed}", ".png")  # a policy name from the store: no path of its own
        if report_figures.filmstrip(store, policy, seed, stage / name):
            figures.append((name, f"{policy}, condition {seed}: real (upper) and imagined (lower) frames per view"))
    if "termination" in t:
        report_figures.u_plot(store, t, stage / "u_chunk.png")
        figures.append(("u_chunk.png", "U_chunk per chunk, every policy (median and quartiles over the evaluation "
                                       "conditions); dashed: the candidate taus."))
    c = Path(t["config"]["world_model"]) / "config.json"  # the online frames' rate: the model's (no video without it)
    vids, hz = [], json.loads(c.read_text()).get("rollout", {}).get("control_hz") if c.exists() else None
    for policy, _ in t["policies"]:
        if videos is not None and len(vids) >= videos:
            break
        name = file_name(f"{policy}_{seed}", ".mp4")
        if hz and report_figures.side_by_side(store, policy, seed, stage / name, hz):
            vids.append(name)
    return figures, vids
