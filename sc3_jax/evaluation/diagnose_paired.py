"""``sc3 diagnose --world-model A --against B``: two world models of one robot diagnosed on the same held-out episodes,
their measures compared pair by pair, which is what tells a change to the recipe (a lever) from a seed.

* the dense probe (``diagnose_dense.py``): the same windows with the same sampler key each (the keys are compared:
  results drawn under other seeds are refused); a window pairs where both models located the object;
* the open loop (``tracking.py``): the end-effector, arm and object errors at 1, 2, 4, 8 s and the carried fraction,
  per episode (``per_episode``, kept in every diagnosis' tracking section); an episode pairs where both models
  measured the same items (the same time point, the same real carried steps).

Per measure: each model's mean over the paired items, and A - B, all three pooled over items with 95% percentile
intervals from one bootstrap that resamples *episodes* (clusters: an episode's windows share its frames, so they are
not independent draws), the ratio of resampled sums (``bootstrap.rates``, draws of ``stats.resample``). For errors a
negative A - B favours A. numpy only."""
from __future__ import annotations

import math

import numpy as np

from sc3_jax.evaluation import bootstrap
from sc3_jax.measures.action_following import DRAWS
from sc3_jax.stats import interval, resample

SIDES = ("a", "b", "a_minus_b")
MEASURES = {"end effector": "end-effector error", "arm": "arm position error", "objects": "object position error"}


def check_same_robot(a: str, cfg_a, b: str, cfg_b) -> None:
    """A one-line UserError unless the saved models at ``a`` and ``b`` (configs as evaluated) share the robot facts
    a window means the same under: cameras, image size, data frame rate, control rate, action space."""
    from sc3_jax.core.errors import UserError
    from sc3_jax.model import checkpoint

    def facts(path, cfg):
        r = checkpoint.read_robot(path, cfg)
        return {"views": list(r.views), "image size": list(cfg.data.image_size), "data fps": r.fps,
                "rollout.control_hz": cfg.rollout.control_hz,
                "actions": f"{r.action_space.kind} {r.action_space.dim}-D {list(r.action_space.names)}"}
    fa, fb = facts(a, cfg_a), facts(b, cfg_b)
    diff = [f"{k} {fa[k]} against {fb[k]}" for k in fa if fa[k] != fb[k]]
    if diff:
        raise UserError(f"--against {b}: another robot than --world-model {a}'s ({'; '.join(diff)}): a paired "
                        "comparison needs the same cameras, image size, frame rate, control rate and actions")


def per_episode(tracks, ids) -> list[dict]:
    """The open-loop measures of ``tracking.Tracks`` per episode id: each {"measure", "readout", "time" (None: not
    over time), "units", "episodes": {id: [sum, count]}} (the imagined errors; the carried steps kept, 0 or 1 each)."""
    out = [{"measure": MEASURES[group], "readout": name, "time": label, "units": tracks.units[(group, name)],
            "episodes": {ids[e]: [float(np.sum(v)), len(v)] for e, v in per.items()}}
           for (group, name, label, ref), per in tracks.err.items() if ref == "imagined"]
    out += [{"measure": "carried in imagination", "readout": f"{name}: {view}", "time": None,
             "units": "fraction of real carried steps",
             "episodes": {ids[e]: [float(np.sum(h)), len(h)] for e, h in c["hit"].items()}}
            for (name, view), c in tracks.carried.items()]
    return out


def paired(cells: dict, draws: int = DRAWS, seed: int = 0) -> dict:
    """``cells``: episode -> (sum over A's items, sum over B's same items, item count). {"a", "b", "a_minus_b": each
    {"value", "lo", "hi", "nan_draws"}, "n": items, "episodes"}: pooled means, intervals resampling episodes (one set
    of draws for all three); no interval from a single episode."""
    eps = [e for e, c in cells.items() if c[2] > 0]
    if not eps:
        return {**{s: {"value": math.nan, "lo": math.nan, "hi": math.nan, "nan_draws": 0} for s in SIDES},
                "n": 0, "episodes": 0}
    sa, sb, n = (np.array([cells[e][i] for e in eps], np.float64) for i in range(3))
    sums, counts = np.stack([sa, sb, sa - sb])[..., None], np.stack([n, n, n])  # [3 sides, episodes, 1], [3, episodes]
    point = bootstrap.rates(sums, counts, np.ones((1, len(eps))))[0, :, 0]
    if len(eps) < 2:
        out = {s: {"value": float(point[i]), "lo": math.nan, "hi": math.nan, "nan_draws": 0}
               for i, s in enumerate(SIDES)}
    else:
        d = bootstrap.rates(sums, counts, resample.multiplicities(len(eps), draws, seed))[..., 0]  # [draws, 3]
        out = {s: interval.summary(point[i], d[:, i]) for i, s in enumerate(SIDES)}
    return {**out, "n": int(n.sum()), "episodes": len(eps)}


def compare(ra: dict, rb: dict, draws: int = DRAWS, seed: int = 0) -> dict:
    """The paired comparison of two :func:`diagnose.diagnose` results on the same episodes (A = ``ra``)."""
    from sc3_jax.core.errors import UserError
    from sc3_jax.evaluation.diagnose_report import NOT_RUN_NOTE, ran
    if ra["episodes"] != rb["episodes"]:
        raise UserError(f"{rb['world_model']} was diagnosed on other episodes than {ra['world_model']}: a paired "
                        "comparison needs the same ones (the same --data and --episodes)")
    both = lambda k: k in ra and k in rb and ran(ra[k]) and ran(rb[k])  # noqa: E731
    return {"a": ra["world_model"], "b": rb["world_model"], "data": ra["data"], "episodes": len(ra["episodes"]),
            "draws": draws, "seed": seed,
            "dense": _dense(ra["dense"], rb["dense"], draws, seed) if both("dense") else {"note": NOT_RUN_NOTE},
            "open_loop": _open_loop(ra["tracking"], rb["tracking"], draws, seed) if both("tracking")
            else {"note": NOT_RUN_NOTE}}


def _dense(da: dict, db: dict, draws: int, seed: int) -> dict:
    """Window by window: the same (episode, last context frame), the same key, the object located by both."""
    from sc3_jax.core.errors import UserError
    wa = {(r["episode"], r["from_frame"]): r for r in da["windows"]}
    wb = {(r["episode"], r["from_frame"]): r for r in db["windows"]}
    common = [k for k in wa if k in wb]
    for k in common:
        if wa[k]["key"] != wb[k]["key"]:
            raise UserError(f"window {k[0]} frame {k[1]}: the two diagnoses drew other noise (keys {wa[k]['key']} "
                            f"and {wb[k]['key']}): run both with the same --seed")
    cells: dict = {}  # (measure, time) -> {episode: [sum A, sum B, n]}
    counts: dict = {}  # (measure, time) -> [windows, lost by A, lost by B]
    for k in common:
        ca = {(c["measure"], c["time"]): c["imagined"] for c in wa[k]["carried"]}
        cb = {(c["measure"], c["time"]): c["imagined"] for c in wb[k]["carried"]}
        for mk in [m for m in ca if m in cb]:
            a, b = ca[mk], cb[mk]
            cnt = counts.setdefault(mk, [0, 0, 0])
            cnt[0], cnt[1], cnt[2] = cnt[0] + 1, cnt[1] + (not math.isfinite(a)), cnt[2] + (not math.isfinite(b))
            cell = cells.setdefault(mk, {}).setdefault(k[0], [0.0, 0.0, 0])
            if math.isfinite(a) and math.isfinite(b):
                cell[0], cell[1], cell[2] = cell[0] + a, cell[1] + b, cell[2] + 1
    keys = [(m, t) for m in dict.fromkeys(m for m, _ in cells) for t in da["steps"] if (m, t) in cells]
    rows = [{"measure": m, "time": t, "units": "px", "windows": counts[(m, t)][0],
             "lost": {"a": counts[(m, t)][1], "b": counts[(m, t)][2]}, **paired(cells[(m, t)], draws, seed)}
            for m, t in keys]
    return {"windows_paired": len(common), "windows_a_only": len(wa) - len(common),
            "windows_b_only": len(wb) - len(common), "windows_considered": da["windows_considered"],
            "carry_px": da["carry_px"], "key_seed": da["key_seed"], "rows": rows}


def _open_loop(ta: dict, tb: dict, draws: int, seed: int) -> dict:
    """Episode by episode: the same measure, read-out and time, the same items (count) on both sides."""
    pb = {(r["measure"], r["readout"], r["time"]): r for r in tb.get("per_episode", [])}
    rows = []
    for r in ta.get("per_episode", []):
        other = pb.get((r["measure"], r["readout"], r["time"]))
        if other is None:
            continue
        ea, eb = r["episodes"], other["episodes"]
        cells = {e: [ea[e][0], eb[e][0], ea[e][1]] for e in ea if e in eb and ea[e][1] == eb[e][1] > 0}
        measured = {e for e in ea if ea[e][1]} | {e for e in eb if eb[e][1]}
        rows.append({"measure": r["measure"], "readout": r["readout"], "time": r["time"], "units": r["units"],
                     "unpaired_episodes": len(measured - set(cells)), **paired(cells, draws, seed)})
    return {"rows": rows}


def lines(cmp: dict) -> list[str]:
    """The comparison as markdown: the dense probe's rows, then the open loop's."""
    from sc3_jax.evaluation.diagnose_headline import cell
    L = ["## Paired: A - B on the same episodes and noise", "",
         f"A = {cmp['a']}, B = {cmp['b']}; held-out data {cmp['data']} ({cmp['episodes']} episodes). Each model's "
         "mean over the items both measured, and A - B, with 95% intervals from one bootstrap over episodes "
         f"(an episode's windows resampled together; {cmp['draws']} draws, seed {cmp['seed']}); for errors, A - B < 0 "
         "favours A.", "", "### Dense probe: the object one moment after real context, where the real arm carries it",
         ""]
    d = cmp["dense"]
    if "rows" not in d:
        L.append(d["note"])
    else:
        L += [f"{d['windows_paired']} windows carry an object (>= {d['carry_px']:g} px with the arm) of "
              f"{d['windows_considered']}, each with the same sampler key on both sides (seed {d['key_seed']}, "
              f"episode, frame)" + (f"; {d['windows_a_only']} in A only, {d['windows_b_only']} in B only (other "
                                    "context or chunk lengths)" if d["windows_a_only"] or d["windows_b_only"] else ""),
              "", "| object: view | time | windows (episodes) | A, px | B, px | A - B, px | lost A / B |",
              "|---|---|---|---|---|---|---|"]
        L += [f"| {r['measure']} | {r['time']} | {r['n']} ({r['episodes']}) | {cell(r['a'])} | {cell(r['b'])} | "
              f"{cell(r['a_minus_b'], '{:+.2f}')} | {r['lost']['a']} / {r['lost']['b']} |" for r in d["rows"]]
    L += ["", "### Open loop from the first real frames, recorded actions (one value per episode and time)", ""]
    o = cmp["open_loop"]
    if "rows" not in o:
        L.append(o["note"])
    else:
        L += ["| measure | read-out | time | episodes | A | B | A - B | units |", "|---|---|---|---|---|---|---|---|"]
        for r in o["rows"]:
            fmt = "{:.3f}" if r["units"].startswith(("robot", "fraction")) else "{:.2f}"
            L.append(f"| {r['measure']} | {r['readout']} | {r['time'] or '-'} | {r['episodes']} | {cell(r['a'], fmt)} "
                     f"| {cell(r['b'], fmt)} | {cell(r['a_minus_b'], fmt.replace('{:', '{:+'))} | {r['units']} |")
    return L
