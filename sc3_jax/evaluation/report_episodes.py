"""The numbers and tables of a sweep of held-out episodes (``ic_sweep.py``), which ``report.render`` writes: the
policies ranked by their imagined success, and -- where real outcomes of the same policies exist (``labels.py``) --
how faithfully the imagined per-policy rates follow the real ones. Every number comes from :func:`compute`
(JSON-serialisable).

Ranking: per policy and criterion the success rate over the evaluation conditions (tau = inf, the whole rollout)
with a 95% bootstrap interval; the conditions are resampled with replacement, one resample per draw for every
policy (paired: all policies were rolled out from the same conditions with the same noise). Policies are ranked by
the rate of ``success`` when the scorer reports it, else by the mean over its criteria; each policy's rank is
recomputed in every draw (``rank_interval``, and ``p_best``: the share of draws where it ranks first, a tie for
first split among those tied).

Against real outcomes (points: policy x criterion, the criteria both sides report), each with a 95% interval:

    online        imagined rates (tau = inf) vs real rates: Pearson r, MMRV (``stats.correlation``, ``rank_violation``)
    online_tau    the same rollouts cut at tau*, chosen on the held-out calibration conditions (highest r against
                  the real rates, ``calibrate.choose_tau``). The real set is one set here (no simulator to draw a
                  second one from), so tau* was chosen against the same real rates it is scored on: read the row as
                  optimistic by the choice among the candidates
    policy_blind  the floor: every policy gets the mean real rate per criterion (``stats.floor.policy_blind``); with a
                  single criterion it is constant, so its r is undefined (nan) and only its MMRV reads
    ceiling       split-half of the real episodes (each policy's own, at random, one split per draw,
                  ``stats.split_half``): how well the real set agrees with itself at half its size (conservative)

Draws resample the imagined conditions (paired across policies) and, independently, each policy's real episodes
(real episodes are other starts, one set per policy). ``vs_floor``: evaluator minus floor on the same draws
(``intervals.difference``): r > 0 and MMRV < 0 favour the world model.
"""
from __future__ import annotations

import math
import os
from pathlib import Path

import numpy as np

from sc3_jax.core import atomic
from sc3_jax.core.errors import UserError
from sc3_jax.evaluation import bootstrap, calibrate, diagnose_headline, diagnose_report, intervals
from sc3_jax.evaluation.report_html import ci, fmt, kept_table
from sc3_jax.evaluation.ic_sweep import KIND, REAL_FILE
from sc3_jax.evaluation.results import ResultsStore
from sc3_jax.stats import floor, interval, resample, split_half

ALL = ["all"]  # one "split": intervals' helpers pool every policy under metrics.OVERALL


def is_store(results: str | Path) -> bool:
    """Whether ``results`` holds a sweep of held-out episodes (``sweep.json`` kind ``initial_conditions``)."""
    p = Path(results) / "sweep.json"
    if not p.is_file():
        return False
    from sc3_jax.core.validate import json_object

    fix = "restore it from a copy of the store"
    cfg = json_object(atomic.read_json(p, fix), str(p), fix)
    if "kind" not in cfg and {"initial_conditions", "conditions"} <= cfg.keys():  # only such a sweep records them
        raise UserError(f"{p}: no \"kind\" (its other fields are a sweep of held-out episodes', which records "
                        f"\"kind\": \"{KIND}\"); restore it from a copy of the store")
    return cfg.get("kind") == KIND


# the fields of an episodes sweep's sweep.json the report reads: name -> (what it must be, its check)
_INT = lambda low: lambda v: isinstance(v, int) and not isinstance(v, bool) and v >= low  # noqa: E731
FIELDS = {"episodes": ("a positive count", _INT(1)), "calibration_episodes": ("a count", _INT(0)),
          "seed0": ("a seed", _INT(0)), "calibration_seed0": ("a seed", _INT(0)),
          "taus": ("a list of thresholds", lambda v: isinstance(v, list)),
          "tau_units": ("'raw' or 'normalised'", lambda v: v in ("raw", "normalised")),
          "world_model": ("the world model's path", lambda v: isinstance(v, str)),
          "initial_conditions": ("the initial conditions' path", lambda v: isinstance(v, str))}


def check_fields(cfg: dict, where: Path) -> None:
    """Each field the report reads of sweep.json (``FIELDS``) there and of its kind, else one line naming it (a
    field removed was a KeyError)."""
    for name, (what, ok) in FIELDS.items():
        if name not in cfg or not ok(cfg[name]):
            have = "missing" if name not in cfg else repr(cfg[name])[:60]
            raise UserError(f"{where}: {name} is {have}, expected {what}; restore it from a copy of the store")


def compute(results: str | Path, real: tuple[str, ...] | list[str] | None = None, draws: int = 2000,
            seed: int = 0, taus=None, scene=None) -> dict:
    """Every number of the report of the store at ``results``. ``real``: real-outcome sources (``labels.py``;
    None: those the sweep was given, as its store keeps them, ``real.json``; (): none). ``taus``: other candidate
    thresholds (None: the sweep's). ``scene``: a benchmark's scene measure; with it and the real frames a sweep kept
    (``REAL_FRAMES/POLICY/EPISODE.npz``, as ``sc3 sweep so101`` keeps them), the closed-loop objects kept."""
    from sc3_jax.evaluation import labels

    store = ResultsStore(results)
    if not is_store(results):
        raise UserError(f"{results}: not a sweep of held-out episodes (no sweep.json of kind {KIND!r})")
    cfg = store.config()
    check_fields(cfg, store.root / "sweep.json")
    if taus is not None:
        cfg["taus"] = [str(float(t)) for t in taus]
    own, eps = real is None, None
    if own:  # the outcomes the store keeps: never a path resolved here (the current directory is anyone's)
        saved = Path(results) / REAL_FILE
        real, eps = labels.kept(saved, cfg.get("out")) if os.path.lexists(saved) else ((), None)
    everything = store.records()
    check_against_sweep(cfg, everything, store.root)
    recs = [r for r in everything if r["mode"] == "online"]
    if not recs:
        raise UserError(f"{results}: no rollouts yet (rerun the sweep)")
    names = list(cfg["policy_names"])
    criteria = sorted(recs[0]["outcomes"])
    by = {(r["policy"], r["seed"]): r for r in recs}
    n, c0 = cfg["episodes"], cfg["calibration_seed0"]
    ev_seeds, cal_seeds = list(range(cfg["seed0"], cfg["seed0"] + n)), list(range(c0, c0 + cfg["calibration_episodes"]))
    units = cfg["tau_units"]
    primary = "success" if "success" in criteria else None
    w = resample.multiplicities(n, draws, seed)
    passes, counts = _grid(by, names, ev_seeds, criteria, lambda r: r["outcomes"])
    point, dr = bootstrap.rates(passes, counts, np.ones((1, n))), bootstrap.rates(passes, counts, w)
    out: dict = {"kind": KIND, "config": cfg, "read_from": str(store.root), "criteria": criteria,
                 "ranked_by": primary or f"mean of {criteria}",
                 "conditions": {"evaluation": n, "calibration": len(cal_seeds)},
                 "rollouts": {"evaluation": int(counts.sum()),
                              "calibration": sum((p, s) in by for p in names for s in cal_seeds)},
                 "bootstrap": {"draws": draws, "seed": seed, "level": 0.95,
                               "resampled": "evaluation conditions, paired across policies; real episodes, per "
                                            "policy"},
                 "policies": intervals.ranking(names, criteria, primary, point, dr, counts), "warnings": []}
    if counts.sum() < len(names) * n:
        out["warnings"].append(f"incomplete sweep: {int(counts.sum())} of {len(names) * n} evaluation rollouts so "
                               "far (rerun the sweep to resume); rates are over the rollouts there are")
    out["real"] = None
    if real:
        eps = labels.read(real) if eps is None else eps
        out["real"] = _versus_real(eps, names, criteria, by, ev_seeds, cal_seeds, cfg["taus"], units,
                                   passes, counts, w, draws, seed, out["warnings"])
        out["real"]["sources"], out["real"]["kept"] = list(real), own
    if scene is not None:
        kept = closed_loop_kept(store, [r for r in recs if r["seed"] in ev_seeds], scene, draws, seed)
        if kept:
            out["permanence"] = kept
    out["action_following"] = diagnose_report.beside_sweep(cfg["world_model"])
    return out


def check_against_sweep(cfg: dict, records: list[dict], root: Path) -> None:
    """The records of a store of held-out episodes are of its sweep.json: ``policy_names`` the names its
    ``policies`` give (an edited name would relabel, or silently drop, a policy's rollouts), every record of one of
    them, of a condition it lists (``conditions[seed]``, the episode the record names). One line naming the store
    and the record, else."""
    from sc3_jax.policies.resolve import name_of

    where = root / "sweep.json"
    names, specs, conds = cfg.get("policy_names"), cfg.get("policies"), cfg.get("conditions")
    if not (isinstance(names, list) and all(isinstance(n, str) for n in names) and len(set(names)) == len(names)):
        raise UserError(f"{where}: policy_names is {names!r}, expected the sweep's distinct policy names; restore it")
    if isinstance(specs, list) and all(isinstance(x, str) for x in specs):
        try:
            derived = [name_of(x) for x in specs]
        except ValueError as e:
            raise UserError(f"{where}: policies: {e}; restore it") from None
        if derived != names:
            raise UserError(f"{where}: policy_names {names} are not the names its policies give ({derived}): "
                            "edited? restore it")
    if not (isinstance(conds, list) and all(isinstance(c, str) for c in conds)):
        raise UserError(f"{where}: conditions is {conds!r}, expected the sweep's episode ids; restore it")
    for i, r in enumerate(records, 1):
        problem = None
        if r.get("policy") not in names:
            problem = f"policy {r.get('policy')!r} is none of the sweep's {names}"
        elif not (isinstance(r.get("seed"), int) and 0 <= r["seed"] < len(conds)):
            problem = f"condition {r.get('seed')!r} is none of the sweep's {len(conds)}"
        elif "episode" in r and r["episode"] != conds[r["seed"]]:
            problem = f"episode {r['episode']!r} is not the sweep's condition {r['seed']} ({conds[r['seed']]!r})"
        if problem:
            raise UserError(f"{root}: record {i} ({r.get('id')!r}): {problem} (sweep.json); the record is not of "
                            "this sweep: delete its line or restore the store")


REAL_FRAMES = "real_frames"


def closed_loop_kept(store, recs: list[dict], scene, draws: int, seed: int) -> dict | None:
    """``permanence.summary`` of the online rollouts whose real frames the store keeps (``REAL_FRAMES``); None when
    it keeps none. The times are the kept files' (``at``: model steps after the last context frame, at ``hz``)."""
    from sc3_jax.measures import permanence
    from sc3_jax.core.safe_names import join_inside

    im, re, at, hz, views = [], [], None, None, None
    for r in recs:
        path = join_inside(store.root / REAL_FRAMES, r["policy"], f"{r['episode']}.npz")
        if not path.is_file():
            continue
        with atomic.open_npz(path, "delete it and rerun the sweep to keep it again") as z:
            real, at, hz = z["frames"], [int(k) for k in z["at"]], float(z["hz"])
        imagined = store.load_arrays(r["id"])["frames"]  # [V, 1 + N*l, ...]: index 0 the last context frame
        ok = [i for i, k in enumerate(at) if k < imagined.shape[1]]
        a, b = np.full((real.shape[0], len(at)), np.nan), np.full((real.shape[0], len(at)), np.nan)
        a[:, ok], b[:, ok] = scene(imagined[:, [at[i] for i in ok]]), scene(real[:, ok])
        im.append(a)
        re.append(b)
        views = views or real.shape[0]
    if not im:
        return None
    labels = {label: at.index(k) for label, k in permanence.times(hz).items() if k in at}
    return permanence.summary(np.stack(im), np.stack(re), labels, _view_names(store, views), draws, seed)


def _view_names(store, n: int) -> list[str]:
    from sc3_jax.model import checkpoint
    try:
        return list(checkpoint.read_config(store.config()["world_model"]).data.views)[:n]
    except (UserError, OSError, KeyError):  # the world model moved since the sweep: the figures stand without names
        return [f"view {i}" for i in range(n)]


def _grid(by: dict, names: list[str], seeds: list[int], criteria: list[str], pick):
    """(passes [P, n, C], counts [P, n]) of one rollout per (policy, condition); 0 counts: not rolled out yet."""
    passes = np.zeros((len(names), len(seeds), len(criteria)))
    counts = np.zeros((len(names), len(seeds)))
    for p, name in enumerate(names):
        for i, s in enumerate(seeds):
            r = by.get((name, s))
            if r is not None:
                o = pick(r)
                counts[p, i] = 1
                passes[p, i] = [o[c] for c in criteria]
    return passes, counts


def _real_rates(eps, names: list[str], criteria: list[str], draws: int, seed: int):
    """Per policy (in ``names`` order) its real rates [1, P, C] and their draws [B, P, C] (each policy's episodes
    resampled on their own), and the episodes' passes per policy (for the split-half ceiling)."""
    point, dr, per = np.zeros((1, len(names), len(criteria))), np.zeros((draws, len(names), len(criteria))), []
    for p, name in enumerate(names):
        x = np.array([[e.outcomes[c] for c in criteria] for e in eps if e.policy == name], float)  # [m, C]
        wp = resample.multiplicities(len(x), draws, seed + 1 + p)
        point[0, p], dr[:, p] = x.mean(0), wp @ x / wp.sum(1, keepdims=True)
        per.append(x)
    return point, dr, per


def _faith(ev_point, re_point, ev_draws, re_draws) -> dict:
    """r and MMRV over every (policy, criterion) point, with intervals."""
    flat = [x.reshape(len(x), -1) for x in (ev_point, re_point, ev_draws, re_draws)]
    return {"points": int(flat[0].shape[1]),
            **{k: interval.summary(float(fn(flat[0], flat[1])[0]), fn(flat[2], flat[3]))
               for k, fn in intervals.STATISTICS}}


def _versus_real(eps, names, criteria, by, ev_seeds, cal_seeds, taus, units, passes, counts, w, draws, seed,
                 warnings: list[str]) -> dict:
    have = {e.policy for e in eps}
    matched = [p for p in names if p in have]
    if set(names) - have:
        warnings.append(f"no real outcomes for {sorted(set(names) - have)}: left out of r / MMRV (real outcomes name "
                        "policies as --policies NAME=SPEC does)")
    if have - set(names):
        warnings.append(f"real outcomes of {sorted(have - set(names))}, which this sweep did not roll out: ignored")
    labelled = [set(e.outcomes) for e in eps if e.policy in matched]
    shared = [c for c in criteria if labelled and all(c in x for x in labelled)]
    if matched and not shared:
        raise UserError(f"--real: the real labels ({sorted(set().union(*labelled))}) share no criterion with the "
                        f"scorer's ({criteria}); name a scorer criterion as the labels do (e.g. 'success')")
    out: dict = {"episodes": len(eps), "policies": {}, "criteria": shared, "faithfulness": None, "tau": None}
    if not matched:
        warnings.append("no policy of the sweep has real outcomes: nothing to compare")
        return out
    rp, rd, per = _real_rates(eps, matched, shared, draws, seed)
    for p, name in enumerate(matched):
        out["policies"][name] = {"episodes": len(per[p]),
                                 "rates": {c: interval.summary(float(rp[0, p, k]), rd[:, p, k])
                                           for k, c in enumerate(shared)}}
    if len(matched) < 2:
        warnings.append(f"real outcomes for {len(matched)} policy only: r and MMRV compare policies, give at least 2")
        return out
    rows_p = [names.index(p) for p in matched]
    cols = [criteria.index(c) for c in shared]
    n = len(ev_seeds)
    sub = lambda ps, cs: (ps[rows_p][:, :, cols], cs[rows_p])  # noqa: E731  matched policies, shared criteria
    evaluators = {"online": sub(passes, counts)}
    # tau*: on the held-out calibration conditions, against the real rates (see the module docstring)
    cal = _tau_table(by, matched, cal_seeds, shared, taus, units, rp) if cal_seeds else []
    if cal and any(e["cases"] for e in cal):
        tau = calibrate.choose_tau(cal, "overall")
        out["tau"] = {"calibration": cal, "chosen": str(tau), "units": units}
        if math.isfinite(tau):  # tau* = inf: the online row itself
            evaluators["online_tau"] = sub(*_grid(by, names, ev_seeds, criteria,
                                                  lambda r: r["outcomes_by_cut"][str(calibrate.cut(r, tau, units))]))
    floor_p, floor_d = floor.policy_blind(rp, ALL * len(matched)), floor.policy_blind(rd, ALL * len(matched))
    rows = {}
    for name, (ps, cs) in evaluators.items():
        ep, ed = bootstrap.rates(ps, cs, np.ones((1, n))), bootstrap.rates(ps, cs, w)
        rows[name] = _faith(ep, rp, ed, rd)
        rows[name]["vs_floor"] = intervals.difference(ep, floor_p, rp, ed, floor_d, rd, ALL * len(matched)).get(
            "overall")
        if len(matched) >= 3:
            rows[name]["per_criterion"] = {c: _faith(ep[..., k:k + 1], rp[..., k:k + 1], ed[..., k:k + 1],
                                                     rd[..., k:k + 1]) for k, c in enumerate(shared)}
    rows["policy_blind"] = _faith(floor_p, rp, floor_d, rd)
    if min(len(x) for x in per) >= 2:
        a, b = split_half.group_half_means(per, draws, seed + 2)  # rates [B, P, C] of each policy's halves
        ceil = _faith(a[:1], b[:1], a, b)
        for k, fn in intervals.STATISTICS:  # one split has no full-sample value: the median of the splits
            ceil[k]["value"] = split_half.point(fn(a.reshape(draws, -1), b.reshape(draws, -1)))
        ceil["method"] = f"split-half of each policy's real episodes ({min(len(x) for x in per) // 2}+ per half)"
        rows["ceiling"] = ceil
    out["faithfulness"] = rows
    return out


def _tau_table(by, matched, cal_seeds, shared, taus, units, rp) -> list[dict]:
    """Per candidate tau: the calibration conditions' imagined rates, cut at tau, against the real rates."""
    table = []
    m = len(cal_seeds)
    for t in taus:
        tau = calibrate.parse_tau(t)
        ps, cs = _grid(by, matched, cal_seeds, shared, lambda r: r["outcomes_by_cut"][str(calibrate.cut(r, tau,
                                                                                                        units))])
        ev = bootstrap.rates(ps, cs, np.ones((1, m)))
        ok = ~np.isnan(ev).any()
        cut_early = [calibrate.cut(by[k], tau, units) < by[k]["num_chunks"] for k in
                     ((p, s) for p in matched for s in cal_seeds) if k in by]
        table.append({"tau": str(tau), "cases": int(cs.sum()),
                      "termination_rate": float(np.mean(cut_early)) if cut_early else math.nan,
                      "faithfulness": {"overall": {
                          k: float(fn(ev.reshape(1, -1), rp.reshape(1, -1))[0]) if ok else math.nan
                          for k, fn in intervals.STATISTICS}}})
    return table


# ================================================================================================================
# Rendering
# ================================================================================================================
ROWS = {"online": "world model, online (tau = inf)", "online_tau": "world model, online (calibrated tau*)",
        "policy_blind": "policy-blind guess (floor)", "ceiling": "real vs real, split-half (ceiling)"}


def tables(t: dict) -> list[tuple[str, list[str], list[list[str]]]]:
    """(title, header, rows) of every table of the report."""
    crit, b = t["criteria"], t["bootstrap"]
    how = f"value [95% bootstrap interval, {b['draws']} draws]"
    out = [(f"Ranking inside the world model. {t['conditions']['evaluation']} held-out initial conditions per "
            f"policy, whole rollouts (tau = inf), scored by {t['config']['scorer']}; ranked by {t['ranked_by']}; "
            f"{how}; rank interval and P(best) over the same draws",
            ["rank", "policy", "score", "rank interval", "P(best)"] + crit + ["rollouts"],
            [[str(p["rank"]), p["policy"], ci(p["score"]), f"{p['rank_interval'][0]}-{p['rank_interval'][1]}",
              fmt(p["p_best"], 2)] + [ci(p["rates"][c]) for c in crit] + [str(p["rollouts"])]
             for p in t["policies"]])]
    r = t.get("real")
    if r:
        kept = " (as the store keeps them, real.json)" if r.get("kept") else ""
        out.append((f"Real outcomes. From {', '.join(_source_names(r['sources']))}{kept}, {how}.",
                    ["policy", "episodes"] + r["criteria"],
                    [[p, str(v["episodes"])] + [ci(v["rates"][c]) for c in r["criteria"]]
                     for p, v in r["policies"].items()]))
    if t.get("permanence"):
        out.append(kept_table(t["permanence"], "closed loop: the online rollouts' frames over the real rollouts' "
                                               "from the same conditions"))
    if diagnose_headline.report_table(t.get("action_following")):
        out.append(diagnose_headline.report_table(t["action_following"]))
    if r and r["faithfulness"]:
        f = r["faithfulness"]
        rows = [[ROWS[k], str(f[k]["points"]), ci(f[k]["pearson"]), ci(f[k]["mmrv"]),
                 ci((f[k].get("vs_floor") or {}).get("pearson")), ci((f[k].get("vs_floor") or {}).get("mmrv"))]
                for k in ROWS if k in f]
        out.append((f"Faithfulness. Imagined vs real per-policy rates (points: policy x criterion, {r['criteria']}); "
                    f"{how}; r higher and MMRV lower is better; '- floor': paired difference to the policy-blind "
                    "guess (r > 0, MMRV < 0 favour the world model)",
                    ["evaluator", "points", "r", "MMRV", "r - floor", "MMRV - floor"], rows))
        per = f["online"].get("per_criterion")
        if per:
            out.append(("Per criterion, online (tau = inf). Points are the policies.", ["criterion", "r", "MMRV"],
                        [[c, ci(v["pearson"]), ci(v["mmrv"])] for c, v in per.items()]))
    if r and r.get("tau"):
        tt = r["tau"]
        out.append((f"tau calibration. On the {t['conditions']['calibration']} held-out calibration conditions per "
                    f"policy against the real rates (U_chunk in {tt['units']} action units); chosen: highest r, ties "
                    "lower MMRV, then larger tau. The real set is the one the faithfulness rows are scored on: the "
                    "tau* row is optimistic by this choice", ["tau", "termination rate", "r", "MMRV", "rollouts"],
                    [[e["tau"] + (" (chosen)" if e["tau"] == tt["chosen"] else ""), fmt(e["termination_rate"], 2),
                      fmt(e["faithfulness"]["overall"]["pearson"]), fmt(e["faithfulness"]["overall"]["mmrv"]),
                      str(e["cases"])] for e in tt["calibration"]]))
    return out


def summary(t: dict) -> list[str]:
    """What the numbers say, in a few lines (the command's closing words)."""
    p = t["policies"]
    ranked = "".join((" = " if i and x["rank"] == p[i - 1]["rank"] else " > " if i else "") +
                     f"{x['policy']} {ci(x['score'], 2)}" for i, x in enumerate(p))
    lines = [f"ranking by {t['ranked_by']} inside the world model ({t['conditions']['evaluation']} conditions per "
             f"policy, 95% intervals): {ranked}"]
    tied = [x["policy"] for x in p if x["rank"] == p[0]["rank"]]
    if len(tied) > 1:  # the same score: no first to name (P(best) splits each tied draw among them)
        lines.append(f"{' and '.join(tied)} tie for first at {ci(p[0]['score'], 2)}; first in "
                     + ", ".join(f"{x['p_best']:.0%}" for x in p[:len(tied)]) + " of the bootstrap draws (ties "
                     "split): more conditions (--episodes) may tell them apart")
    elif len(p) > 1:
        lines.append(f"{p[0]['policy']} ranks first in {p[0]['p_best']:.0%} of the bootstrap draws"
                     + ("" if p[0]["score"]["lo"] > p[1]["score"]["hi"] else
                        f"; its interval overlaps {p[1]['policy']}'s: more conditions (--episodes) would tell them "
                        "apart"))
    r = t.get("real")
    if r and r["faithfulness"]:
        f = r["faithfulness"]
        on, fl = f["online"], f["policy_blind"]
        vs = on.get("vs_floor") or {}
        lines.append(f"against the real outcomes ({r['episodes']} episodes): r {ci(on['pearson'])}, MMRV "
                     f"{ci(on['mmrv'])}; policy-blind guess: r {ci(fl['pearson'])}, MMRV {ci(fl['mmrv'])}; paired "
                     f"difference to it: r {ci(vs.get('pearson'))}, MMRV {ci(vs.get('mmrv'))}"
                     + (f"; real vs real (split-half ceiling): r {ci(f['ceiling']['pearson'])}" if "ceiling" in f
                        else ""))
        lines.append(against_floor(vs))
    elif not r:
        lines.append("no real outcomes given (--real): the ranking is the world model's alone, unvalidated")
    return lines + t["warnings"]


def against_floor(vs: dict) -> str:
    """The closing line on the paired differences to the policy-blind guess (r: higher is better; MMRV: lower):
    better where an interval excludes 0 on the good side, worse where it excludes 0 on the bad side."""
    r, m = vs.get("pearson") or {}, vs.get("mmrv") or {}
    better = [k for k, ok in (("r", r.get("lo", math.nan) > 0), ("MMRV", m.get("hi", math.nan) < 0)) if ok]
    worse = [k for k, ok in (("r", r.get("hi", math.nan) < 0), ("MMRV", m.get("lo", math.nan) > 0)) if ok]
    said = []
    if better:
        said.append(f"the world model ranks these policies better than a policy-blind guess on {' and '.join(better)}")
    if worse:
        said.append(f"{'and' if better else 'the world model ranks these policies'} worse than a policy-blind guess "
                    f"on {' and '.join(worse)} (its interval excludes 0 on the wrong side)")
    return "; ".join(said) if said else ("not distinguishable from a policy-blind guess at this many conditions and "
                                         "real episodes (the paired differences' intervals include 0)")


METHOD = ("Each policy acts inside the world model from held-out episodes' first frames and states (closed loop, "
          "the same noise for every policy); the lab's scorer reads each imagined rollout. Policies are ranked by "
          "their imagined success with 95% bootstrap intervals over the conditions; rank interval and P(best) come "
          "from the same draws. Against real outcomes: Pearson r and MMRV over the (policy, criterion) rates, next to "
          "a policy-blind guess (every policy gets the mean real rate: the floor) and a split-half ceiling of the "
          "real episodes. n/a: undefined at these rates (r needs two or more distinct rates on each side).")


def _source_names(sources) -> list[str]:
    """Real-outcome sources by name, not by this machine's path: ``NAME=PATH`` -> ``NAME=basename``."""
    from sc3_jax.evaluation.labels import split_spec

    return [f"{name}={Path(path).name}" if name else Path(path).name for name, path in map(split_spec, sources)]


def verdict(t: dict) -> list[str]:
    """The page's first lines: the verdict against the real outcomes (or that there are none), then the ranking."""
    said = summary(t)
    lines = said[:len(said) - len(t["warnings"])]
    verdict_last = not t.get("real") or bool(t["real"]["faithfulness"])  # summary's last line is then the verdict
    return lines[-1:] + lines[:-1] if verdict_last else lines
