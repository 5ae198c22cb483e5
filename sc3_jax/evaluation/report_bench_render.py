"""The words of a bench sweep's report, from ``report_bench.bench``'s numbers: its headline and verdict, its tables
(title, header, rows), its method paragraph and its figures (plots and videos, through ``report_figures.py``)."""
from __future__ import annotations

import json
import math
from pathlib import Path

from sc3_jax.evaluation import diagnose_headline, diagnose_report, report_figures, report_html
from sc3_jax.measures import metrics
from sc3_jax.evaluation.report_html import UNDEFINED, ci
from sc3_jax.evaluation.report_html import fmt as _fmt
from sc3_jax.evaluation.results import ResultsStore
from sc3_jax.core.safe_names import file_name


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
                      diagnose_report.word(g)] for g in d["gates"]]))
    elif d:
        out.append(("World-model checkpoint gates", ["gate", "value", "threshold", "pass"],
                    [["not diagnosed: run `sc3 diagnose --world-model WORLD_MODEL --data HELDOUT --out "
                      "WORLD_MODEL/diagnose.json`", "-", "-", "-"]]))
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


def figures(store: ResultsStore, t: dict, stage: Path, videos: int | None):
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
